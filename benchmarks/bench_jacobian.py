"""Accuracy of the finite-difference code Jacobian (Eq. 17) against torch autograd: paper Fig. 6 (a), (b).

For every validation frame and test code (the zero code and draws from N(0, 0.5^2 I)) the reference is
``torch.autograd.functional.jacobian(vectorize=True, strategy="forward-mode")`` of the torch decoder (exact to
float32 round-off; the default reverse mode gives the same numbers but vmaps over all H*W cotangents and does
not fit in memory at 224x224), evaluated on the conditioning features that ONNX Runtime's ``prior.onnx``
produced for the frame: reference and finite differences differentiate the same function of the code (the
ORT/torch decoder parity is ~1e-6 m). The finite differences go through the runtime's ONNX path:

* (a) all code dimensions perturbed by the same delta: ``KeyframeDepth.jacobian(code, delta=delta)``, i.e.
  ``J[:, :, i] = (F(c + delta e_i) - F(c)) / delta`` with the nominal and the C perturbed codes in one batch;
* (b) one dimension ``i`` at a time, its delta swept, the other C - 1 fixed at ``--fixed-delta`` (1e-2): the
  same batch built with per-dimension steps by :func:`fd_jacobian`. The curve of dimension ``i`` is the error
  of column ``i``; the error of the whole Jacobian is recorded too. (In eval mode the rows of a batch do not
  interact, so column ``i`` depends only on its own step; ``rows_independent_max_abs`` checks that.)

Errors per (frame, code): mean, 99th percentile and max over pixels (and dimensions) of
``|J_fd - J_autograd|`` in metres per unit code, and the mean relative to ``mean |J_autograd|``. Forward
differences err by about ``delta/2 |d2F/dc2|`` (truncation, plus kinks of ReLU / max layers crossed by the
step) and by about ``eps_float32 |F| / delta`` (round-off): a V in log-log with its minimum in between.

Usage::

    python benchmarks/bench_jacobian.py                        # stand-in net, synthetic validation frames
    python benchmarks/bench_jacobian.py --model models/default --ckpt RUN/checkpoints/best.ckpt --data ROOT

Prints tables, reports where the error is smallest, and writes ``jacobian.json`` + ``jacobian_delta.png``
into ``--out`` (default ``benchmarks/results/``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks import common


def fd_jacobian(
    dn, features: dict[str, np.ndarray], code: np.ndarray, deltas: np.ndarray, nominal_in_batch: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Forward-difference Jacobian (Eq. 17) through ONNX Runtime with one step per code dimension.

    The same computation as ``KeyframeDepth.jacobian`` (nominal + C perturbed codes in one decoder batch, each
    column divided by the step actually taken in float32) but with ``deltas[i]`` for dimension ``i``.

    Args:
        dn: a ``runtime.network.DepthNetwork``.
        features: the keyframe's decoder features (``KeyframeDepth.features``).
        code: (C,) float32 code.
        deltas: (C,) steps (> 0).

    Returns:
        depth (H, W) [m] at ``code`` and J (H, W, C) [m per unit code].
    """
    code = np.asarray(code, np.float32).reshape(-1)
    deltas = np.asarray(deltas, np.float32).reshape(-1)
    C = code.size
    if deltas.shape != (C,) or not (deltas > 0).all():
        raise ValueError(f"deltas must be {C} positive steps, got {deltas}")
    perturbed = np.repeat(code[None], C, 0) + np.diag(deltas)  # (C, C) float32
    if nominal_in_batch:
        out = dn.decode(np.concatenate([code[None], perturbed]), features)
        nominal, moved = out[0], out[1:]
    else:
        nominal, moved = dn.decode(code[None], features)[0], dn.decode(perturbed, features)
    step = (perturbed[np.arange(C), np.arange(C)] - code).astype(np.float32)
    J = ((moved - nominal[None]) / step[:, None, None]).transpose(1, 2, 0)  # (H, W, C)
    return nominal, np.ascontiguousarray(J)


def autograd_jacobian(net, feats, code: np.ndarray) -> np.ndarray:
    """``torch.autograd.functional.jacobian(vectorize=True)`` of ``code -> depth`` (H, W, C) [m per unit
    code].

    Forward mode (C = 8 tangents in one vmapped pass). The default reverse mode would vmap over all H*W
    cotangents at once: at 224x224 that is 50176 batched backward passes and did not fit in 24 GB.
    """
    import torch

    def f(c):
        return net.decoder(c[None], *feats)[0, 0]

    return (
        torch.autograd.functional.jacobian(f, torch.from_numpy(code), vectorize=True, strategy="forward-mode")
        .detach()
        .numpy()
    )


def delta_grid(lo: float, hi: float, per_decade: int) -> np.ndarray:
    """Log grid from ``lo`` to ``hi`` with ``per_decade`` points per decade (exact powers of ten included)."""
    if not (0 < lo < hi) or per_decade < 1:
        raise ValueError(f"need 0 < lo < hi and per_decade >= 1, got {lo}, {hi}, {per_decade}")
    n = int(round(np.log10(hi / lo) * per_decade)) + 1
    return np.logspace(np.log10(lo), np.log10(hi), n)


def sweep(
    bm: common.BenchModel,
    frames: list[common.Frame],
    codes: list[tuple[str, np.ndarray]],
    deltas: np.ndarray,
    fixed_delta: float,
    per_dim: bool = True,
    threads: int = 2,
    log=print,
) -> dict:
    """Run sweeps (a) and (b) over frames x codes; return the raw per-pair errors [P, ...] and timings."""
    import torch

    from runtime.network import DepthNetwork, SessionConfig

    dn = DepthNetwork(bm.model_dir, SessionConfig(threads=threads))
    C, K = dn.code_dim, len(deltas)
    P = len(frames) * len(codes)
    a_mean, a_max, a_p99 = np.zeros((P, K)), np.zeros((P, K)), np.zeros((P, K))
    a_col = np.zeros((P, C, K))
    b_col, b_full = np.zeros((P, C, K)), np.zeros((P, C, K))
    scale, scale_col, depth_mean = np.zeros(P), np.zeros((P, C)), np.zeros(P)
    rows_independent = 0.0
    t_ad, t_fd = 0.0, 0.0
    pairs = []
    p = 0
    for frame in frames:
        kf = dn.prior(frame.image, frame.sparse)
        feats = [torch.from_numpy(kf.features[n]) for n in dn.feature_names]
        for code_name, code in codes:
            t0 = time.perf_counter()
            J_ad = autograd_jacobian(bm.net, feats, code)
            t_ad += time.perf_counter() - t0
            scale[p] = np.abs(J_ad).mean()
            scale_col[p] = np.abs(J_ad).mean(axis=(0, 1))
            t0 = time.perf_counter()
            J_a = []
            for k, d in enumerate(deltas):
                depth, J = kf.jacobian(code, delta=float(d))
                err = np.abs(J - J_ad)
                a_mean[p, k], a_max[p, k], a_p99[p, k] = err.mean(), err.max(), np.quantile(err, 0.99)
                a_col[p, :, k] = err.mean(axis=(0, 1))
                J_a.append(J)
            depth_mean[p] = float(depth.mean())
            if per_dim:
                for i in range(C):
                    for k, d in enumerate(deltas):
                        steps = np.full(C, fixed_delta, np.float32)
                        steps[i] = d
                        _, J = fd_jacobian(dn, kf.features, code, steps)
                        err = np.abs(J - J_ad)
                        b_col[p, i, k] = err[:, :, i].mean()
                        b_full[p, i, k] = err.mean()
                        rows_independent = max(
                            rows_independent, float(np.abs(J[:, :, i] - J_a[k][:, :, i]).max())
                        )
            t_fd += time.perf_counter() - t0
            pairs.append(
                {
                    "frame": frame.name,
                    "code": code_name,
                    "mean_abs_J": float(scale[p]),
                    "mean_depth_m": depth_mean[p],
                }
            )
            log(
                f"  {frame.name:28s} code {code_name:14s} mean|J| {scale[p]:.3g} m  "
                f"err(a) at {fixed_delta:g}: {a_mean[p, np.argmin(np.abs(deltas - fixed_delta))]:.3g} m"
            )
            p += 1
    return {
        "pairs": pairs,
        "a_mean": a_mean,
        "a_max": a_max,
        "a_p99": a_p99,
        "depth_mean": depth_mean,
        "a_col": a_col,
        "b_col": b_col,
        "b_full": b_full,
        "scale": scale,
        "scale_col": scale_col,
        "rows_independent": rows_independent,
        "time_autograd_s": t_ad,
        "time_fd_s": t_fd,
        "decoder_calls": dn.decoder_calls,
    }


def summarise(raw: dict, deltas: np.ndarray, fixed_delta: float, per_dim: bool) -> dict:
    """Average the per-pair errors over (frame, code) pairs and find the best steps."""
    a_mean, a_max, a_p99, scale = raw["a_mean"], raw["a_max"], raw["a_p99"], raw["scale"]
    rel = a_mean / scale[:, None]
    all_dims = {
        "mean_abs": a_mean.mean(0),  # (K,) m per unit code
        "max_abs": a_max.max(0),
        "p99_abs": a_p99.mean(0),  # 99th percentile over pixels and dimensions, averaged over pairs
        # float32 round-off guide: eps32 * mean depth / delta (the FD error where round-off dominates)
        "roundoff_guide": np.finfo(np.float32).eps * raw["depth_mean"].mean() / deltas,
        "rel_mean": rel.mean(0),  # mean |J_fd - J_ad| / mean |J_ad|
        "mean_abs_pair_min": a_mean.min(0),
        "mean_abs_pair_max": a_mean.max(0),
        "mean_abs_per_dim": raw["a_col"].mean(0),  # (C, K)
    }
    k_best = int(np.argmin(all_dims["mean_abs"]))
    k_fixed = int(np.argmin(np.abs(np.log(deltas / fixed_delta))))
    best = {
        "all_dims": {
            "delta": float(deltas[k_best]),
            "mean_abs": float(all_dims["mean_abs"][k_best]),
            "rel_mean": float(all_dims["rel_mean"][k_best]),
            "max_abs": float(all_dims["max_abs"][k_best]),
            "pairs_with_same_argmin": int((np.argmin(a_mean, 1) == k_best).sum()),
        },
        "at_fixed_delta": {
            "delta": float(deltas[k_fixed]),
            "mean_abs": float(all_dims["mean_abs"][k_fixed]),
            "rel_mean": float(all_dims["rel_mean"][k_fixed]),
            "max_abs": float(all_dims["max_abs"][k_fixed]),
            "over_best": float(all_dims["mean_abs"][k_fixed] / all_dims["mean_abs"][k_best]),
        },
    }
    out = {"all_dims": all_dims, "best": best}
    if per_dim:
        col = raw["b_col"].mean(0)  # (C, K)
        col_rel = (raw["b_col"] / raw["scale_col"][:, :, None]).mean(0)
        out["per_dim"] = {
            "fixed_delta": fixed_delta,
            "mean_abs": col,
            "rel_mean": col_rel,
            "mean_abs_full_J": raw["b_full"].mean(0),
            "rows_independent_max_abs": raw["rows_independent"],
        }
        best["per_dim"] = [
            {
                "dim": i,
                "delta": float(deltas[int(np.argmin(col[i]))]),
                "mean_abs": float(col[i].min()),
                "rel_mean": float(col_rel[i, int(np.argmin(col[i]))]),
            }
            for i in range(col.shape[0])
        ]
    return out


def plot(path: Path, deltas: np.ndarray, summary: dict, fixed_delta: float, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per_dim = "per_dim" in summary
    fig, axes = plt.subplots(1, 2 if per_dim else 1, figsize=(12 if per_dim else 6.5, 4.6), squeeze=False)
    ax = axes[0, 0]
    a = summary["all_dims"]
    ax.fill_between(
        deltas,
        a["mean_abs_pair_min"],
        a["mean_abs_pair_max"],
        alpha=0.2,
        color="C0",
        label="mean abs, range over frames x codes",
    )
    ax.loglog(deltas, a["mean_abs"], "o-", color="C0", label="mean abs error")
    ax.loglog(deltas, a["max_abs"], "s--", color="C3", ms=4, label="max abs error")
    ax.loglog(deltas, a["p99_abs"], "^--", color="C1", ms=4, label="99th percentile abs error")
    ax.loglog(deltas, a["roundoff_guide"], ":", color="grey", label="eps_float32 * mean depth / delta")
    b = summary["best"]["all_dims"]
    ax.axvline(fixed_delta, color="grey", ls=":", lw=1)
    ax.plot([b["delta"]], [b["mean_abs"]], "*", color="k", ms=12, label=f"minimum at delta={b['delta']:.2g}")
    ax.set_ylim(bottom=0.3 * float(np.min(a["mean_abs_pair_min"])))
    ax.set(
        xlabel="delta (all dimensions)",
        ylabel="|J_fd - J_autograd| [m per unit code]",
        title="(a) same delta for all code dimensions",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best", framealpha=0.6)
    if per_dim:
        ax = axes[0, 1]
        col = summary["per_dim"]["mean_abs"]
        for i in range(col.shape[0]):
            ax.loglog(deltas, col[i], "o-", ms=3, label=f"dim {i}")
        ax.axvline(fixed_delta, color="grey", ls=":", lw=1)
        ax.set(
            xlabel=f"delta of one dimension (others at {fixed_delta:g})",
            ylabel="mean |J_fd - J_autograd| of that column",
            title="(b) one dimension at a time",
        )
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def tables(deltas: np.ndarray, summary: dict) -> str:
    a = summary["all_dims"]
    rows = [
        [f"{d:.2g}", a["mean_abs"][k], 100 * a["rel_mean"][k], a["p99_abs"][k], a["max_abs"][k]]
        for k, d in enumerate(deltas)
    ]
    text = "(a) all dimensions perturbed by delta; errors in m per unit code\n"
    text += common.markdown_table(
        ["delta", "mean abs err", "mean rel err %", "p99 abs err", "max abs err"], rows
    )
    if "per_dim" in summary:
        col = summary["per_dim"]["mean_abs"]
        fixed = summary["per_dim"]["fixed_delta"]
        text += f"\n\n(b) mean abs err of column i, dimension i at delta, others at {fixed:g}\n"
        rows = [[f"{d:.2g}", *col[:, k]] for k, d in enumerate(deltas)]
        text += common.markdown_table(["delta", *[f"dim {i}" for i in range(col.shape[0])]], rows)
    return text


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--model", type=Path, default=None, help="exported model dir (prior.onnx, decoder.onnx, manifest)"
    )
    p.add_argument(
        "--ckpt", type=Path, default=None, help="checkpoint with the same weights (torch reference)"
    )
    p.add_argument(
        "--data", type=Path, default=None, help="NYU-layout root with val/; default: synthetic frames"
    )
    p.add_argument("--frames", type=int, default=4, help="validation frames")
    p.add_argument(
        "--random-codes", type=int, default=2, help="codes drawn from N(0, 0.5^2) besides the zero code"
    )
    p.add_argument("--delta-min", type=float, default=1e-5)
    p.add_argument("--delta-max", type=float, default=1.0)
    p.add_argument("--per-decade", type=int, default=2, help="grid points per decade of delta")
    p.add_argument("--fixed-delta", type=float, default=1e-2, help="step of the other dimensions in (b)")
    p.add_argument("--no-per-dim", dest="per_dim", action="store_false", help="skip sweep (b)")
    p.add_argument("--modality", default="grays", help="stand-in net only")
    p.add_argument("--height", type=int, default=224, help="stand-in net only")
    p.add_argument("--width", type=int, default=224, help="stand-in net only")
    p.add_argument("--width-mult", type=float, default=0.25, help="stand-in net only")
    p.add_argument(
        "--standin-dir", type=Path, default=None, help="where the stand-in is exported (default: cache)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch and ORT intra-op threads (<= cores)")
    p.add_argument("--out", type=Path, default=common.RESULTS, help="output folder for JSON and PNG")
    p.add_argument("--no-plot", dest="plot", action="store_false")
    args = p.parse_args(argv)
    if args.frames < 1 or args.random_codes < 0 or args.threads < 1:
        p.error(
            f"need frames >= 1, random-codes >= 0, threads >= 1 (got {args.frames}, {args.random_codes}, "
            f"{args.threads})"
        )
    if not args.delta_min <= args.fixed_delta <= args.delta_max:
        p.error(f"--fixed-delta {args.fixed_delta} outside [{args.delta_min}, {args.delta_max}]")

    import torch

    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    bm, root = common.model_and_val_data(args, args.frames, "bench_jacobian")
    synthetic = (root / "sim_info.json").is_file()
    frames = common.val_frames(root, bm.modality, bm.height, bm.width, args.frames, seed=args.seed)
    codes = common.bench_codes(bm.code_dim, args.random_codes, seed=args.seed)
    deltas = delta_grid(args.delta_min, args.delta_max, args.per_decade)
    print(f"model: {bm.description}")
    print(
        f"data: {len(frames)} {'SYNTHETIC (dit-sim)' if synthetic else ''} validation frames from {root}; "
        f"codes: {', '.join(n for n, _ in codes)}; {len(deltas)} deltas {deltas[0]:.0e}..{deltas[-1]:.0e}"
    )
    raw = sweep(bm, frames, codes, deltas, args.fixed_delta, args.per_dim, args.threads)
    summary = summarise(raw, deltas, args.fixed_delta, args.per_dim)
    machine = common.machine_info(torch_threads=args.threads, ort_threads=args.threads)
    result = {
        "benchmark": "jacobian",
        "figure": "paper Fig. 6 (a) all dimensions, (b) one dimension at a time",
        "model": bm.summary(),
        "data": {
            "root": str(root),
            "synthetic": synthetic,
            "frames": [f.name for f in frames],
            "codes": {n: c.tolist() for n, c in codes},
            "preprocess": "NetworkMapping resize+crop, grey BT.601, 125 uniform GT samples "
            "(export.checkpoint.validation_inputs)",
        },
        "reference": "torch.autograd.functional.jacobian(vectorize=True, strategy='forward-mode') of the "
        "torch decoder on the ORT prior features",
        "fd": "ONNX Runtime forward differences (runtime.network, nominal in the batch, float32 step taken)",
        "unit": "m per unit code",
        "deltas": deltas,
        "pairs": raw["pairs"],
        "mean_abs_J": float(raw["scale"].mean()),
        "sweep_all_dims": summary["all_dims"],
        "sweep_per_dim": summary.get("per_dim"),
        "best": summary["best"],
        "per_pair_mean_abs_all_dims": raw["a_mean"],
        "timing_s": {
            "autograd": raw["time_autograd_s"],
            "fd_sweeps": raw["time_fd_s"],
            "total": time.perf_counter() - t_start,
            "decoder_calls": raw["decoder_calls"],
        },
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "machine": machine,
    }
    title = (
        f"FD Jacobian (Eq. 17, ONNX Runtime) vs torch autograd - {bm.source} model "
        f"{bm.modality} {bm.height}x{bm.width}, {len(frames)} {'synthetic ' if synthetic else ''}frames "
        f"x {len(codes)} codes"
    )
    if args.plot:
        result["png"] = str(plot(args.out / "jacobian_delta.png", deltas, summary, args.fixed_delta, title))
    json_path = common.write_json(args.out / "jacobian.json", result)

    print()
    print(tables(deltas, summary))
    b, f = summary["best"]["all_dims"], summary["best"]["at_fixed_delta"]
    n_pairs = len(raw["pairs"])
    print(f"\nmean |J_autograd| = {result['mean_abs_J']:.3g} m/unit code over {n_pairs} (frame, code) pairs")
    print(
        f"(a) smallest mean error at delta = {b['delta']:.2g}: {b['mean_abs']:.3g} m "
        f"({100 * b['rel_mean']:.2g} % of mean |J|; argmin shared by {b['pairs_with_same_argmin']}/{n_pairs} "
        f"pairs); at delta = {f['delta']:.2g}: {f['mean_abs']:.3g} m ({100 * f['rel_mean']:.2g} %), "
        f"{f['over_best']:.2f}x the minimum"
    )
    if args.per_dim:
        per = summary["best"]["per_dim"]
        print("(b) best delta per dimension: " + ", ".join(f"{q['dim']}: {q['delta']:.2g}" for q in per))
        print(
            f"    rows of a batch independent: max |column i (b) - column i (a)| = "
            f"{summary['per_dim']['rows_independent_max_abs']:.2g}"
        )
    print(
        f"model: {bm.source}; data: {'synthetic' if synthetic else 'given'} ({root}); machine: "
        f"{common.describe_machine(machine)}; {result['timing_s']['total']:.0f} s"
    )
    print(f"wrote {json_path}" + (f" and {result['png']}" if args.plot else ""))
    return result


if __name__ == "__main__":
    main()
