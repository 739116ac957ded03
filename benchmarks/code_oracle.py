"""How much can an exported model's depth code correct? The best code for each frame, fitted to its true depth.

    python benchmarks/code_oracle.py --model runtime/assets/default_model --real ../shared/data/rgbd_real
        [--sim-val 40] [--radius 0 5.66] [--iters 12] [--limit N] [--out F.json]

The paper's G-S protocol (125 FAST points with their true depth, no noise), on the frame sets of ``dit-eval
depth``. For each frame the decoder's code is fitted to the frame's true depth by Levenberg-Marquardt on the
exported decoder and its finite-difference Jacobian (the SLAM system's ``KeyframeDepth.depth`` / ``.jacobian``),
starting at c = 0: a step is taken only when it lowers the squared depth error over the pixels with ground truth.
``--radius R`` keeps the code inside the ball ``|c| <= R`` (each step projected onto it; 0 = no bound). A unit
Gaussian code lies within ``2 sqrt(C)`` (5.66 for C = 8) with probability above 0.9999, so that radius asks what
the code can do without leaving the CVAE prior's typical set.

The fitted code is an oracle: it uses the ground truth, which neither the posterior of training nor SLAM's
optimisation sees. Its RMSE is therefore a floor for what any code, whoever chooses it, can give this decoder:
- a posterior mean can beat c = 0 by at most the oracle's margin;
- SLAM's optimised codes can move the depth at most that far from the prior.

Per set it prints and writes the RMSE (the mean of the per-image RMSEs, as ``dit-eval depth``) at c = 0, of the
best code within each radius, and of the interpolation of the same sparse points, and the best codes' median norm.
"""

from __future__ import annotations

import argparse

import numpy as np


def best_code(prior, gt: np.ndarray, radius: float = 0.0, iters: int = 12) -> tuple[np.ndarray, list[float]]:
    """The code whose decoded depth is closest to ``gt`` in squared error (projected Levenberg-Marquardt).

    Args:
        prior: a :class:`runtime.network.KeyframeDepth` (``.depth(code)``, ``.jacobian(code)``).
        gt: (H, W) true depth [m] at network size, 0 = no ground truth.
        radius: keep ``|code| <= radius`` (0: unbounded).
        iters: Jacobian evaluations.

    Returns:
        ``(code (C,) float32, sse)``: the code and the squared error [m^2] after each iteration (``sse[0]`` at
        c = 0), never increasing.
    """
    valid = gt > 0
    if not valid.any():
        raise ValueError("best_code: the ground truth has no valid pixel")
    code = np.zeros(prior.net.code_dim, np.float32)

    def sse(c: np.ndarray) -> float:
        return float((((gt - prior.depth(c))[valid]) ** 2).sum())

    def project(c: np.ndarray) -> np.ndarray:
        n = float(np.linalg.norm(c))
        return (c * (radius / n) if radius > 0 and n > radius else c).astype(np.float32)

    history, lam = [sse(code)], None
    eye = np.eye(code.size)
    for _ in range(iters):
        depth, J = prior.jacobian(code)
        r = (gt - depth)[valid].astype(np.float64)
        Jv = J[valid].astype(np.float64)
        H, g = Jv.T @ Jv, Jv.T @ r
        if lam is None:
            lam = 1e-3 * float(np.trace(H)) / code.size + 1e-12
        for _ in range(8):  # raise the damping until a step lowers the error
            cand = project(code + np.linalg.solve(H + lam * eye, g))
            e = sse(cand)
            if e < history[-1]:
                code, lam = cand, lam / 3.0
                break
            lam *= 10.0
        else:
            history.append(history[-1])
            break
        history.append(e)
    return code, history


def _rmse(pred: np.ndarray, gt: np.ndarray) -> float:
    """RMSE [m] over the pixels with ground truth (``gt > 0``), as ``train.metrics`` computes it per image."""
    valid = gt > 0
    return float(np.sqrt(np.mean((pred[valid] - gt[valid]) ** 2)))


def evaluate(net, sets: dict, radii=(0.0,), iters: int = 12) -> dict:
    """RMSE at c = 0, of the best code within each radius, and of the interpolation, per frame set."""
    from train.sparse import interpolate_sparse

    out = {}
    zero = np.zeros(net.code_dim, np.float32)
    for name, ds in sets.items():
        sq = {"c=0": [], "interpolation": []}
        norms = {r: [] for r in radii}
        for i in range(len(ds)):
            item = ds[i]
            image, gt = np.asarray(item["image"]), np.asarray(item["depth"])[0]
            sparse = image[-1] if net.uses_sparse else None
            prior = net.prior(image[0], sparse)
            valid = gt > 0
            if not valid.any():
                continue
            sq["c=0"].append(_rmse(prior.depth(zero), gt))
            if sparse is not None:
                sq["interpolation"].append(_rmse(interpolate_sparse(sparse), gt))
            for r in radii:
                code, _ = best_code(prior, gt, r, iters)
                sq.setdefault(f"best code, |c| <= {r:g}" if r > 0 else "best code, unbounded", []).append(
                    _rmse(prior.depth(code), gt)
                )
                norms[r].append(float(np.linalg.norm(code)))
        rmse = {k: float(np.mean(v)) for k, v in sq.items() if v}
        out[name] = {
            "frames": len(ds),
            "rmse_m": rmse,
            "best_over_zero": {k: rmse[k] / rmse["c=0"] for k in rmse if k.startswith("best code")},
            "code_norm_median": {f"{r:g}": float(np.median(v)) for r, v in norms.items()},
        }
    return out


def main(argv: list[str] | None = None) -> dict:
    from benchmarks.common import gs_protocol_sets, machine_info, write_json
    from runtime.network import DepthNetwork, default_model_dir

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(default_model_dir()), help="exported model directory")
    ap.add_argument("--real", default=None, help="RGB-D frame folders in the rgbd_real layout (or one folder)")
    ap.add_argument("--sim-val", type=int, default=0, help="fresh realistic synthetic rooms (seed 1000)")
    ap.add_argument("--radius", type=float, nargs="+", default=[0.0], help="code-norm bounds (0: none)")
    ap.add_argument("--iters", type=int, default=12, help="Jacobian evaluations per frame")
    ap.add_argument("--limit", type=int, default=None, help="first N frames of each set")
    ap.add_argument("--out", default=None, help="JSON path")
    args = ap.parse_args(argv)
    if any(r < 0 for r in args.radius) or args.iters < 1:
        raise SystemExit("code_oracle: --radius must be >= 0 and --iters >= 1")
    net = DepthNetwork(args.model)
    res = evaluate(net, gs_protocol_sets(net, args.real, args.sim_val, args.limit), tuple(args.radius), args.iters)
    for name, r in res.items():
        print(f"\n{name}: {r['frames']} frames")
        print("| depth | RMSE [m] | over c = 0 |")
        print("|---|---|---|")
        for k, v in r["rmse_m"].items():
            print(f"| {k} | {v:.4f} | {v / r['rmse_m']['c=0']:.3f} |")
        print("median |code| of the best code: " + ", ".join(f"{k}: {v:.2f}" for k, v in r["code_norm_median"].items()))
    doc = {
        "model": str(args.model),
        "protocol": "gs",
        "radius": args.radius,
        "iters": args.iters,
        "sets": res,
        "machine": machine_info(),
    }
    if args.out:
        print(f"wrote {write_json(args.out, doc)}")
    return doc


if __name__ == "__main__":
    main()
