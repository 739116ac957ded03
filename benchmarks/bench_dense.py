"""Ablation of the tight coupling (the shape of the paper's Table 3): sparse vs dense with Eq. 13 only vs
dense with Eq. 13 + 14, on synthetic ``textured`` and ``whitewall`` sequences (sim/), with the shipped depth
model, and the same dense system fed the rendered ground-truth depth instead of the network's prior (the
upper bound of what a better network could buy: ``dense_gt_eq13_14``).

    python benchmarks/bench_dense.py                              # 60 s, seeds 0 1 2 (the issue's setting)
    python benchmarks/bench_dense.py --duration 30 --seeds 0      # smaller (whitewall needs >= 24 s)
    python benchmarks/bench_dense.py --scale 0.5 --set n_consis=200   # half-resolution images
    python benchmarks/bench_dense.py --presets whitewall --slam-set backend.window_size=8   # a runtime key
    python benchmarks/bench_dense.py --modes dense_eq13_14 --model outputs/export/my_model   # another network
    python benchmarks/bench_dense.py --presets --sequences data/mh05_s0 data/mh05_s1 --modes sparse dense_eq14
        # existing folders (e.g. `dit-sim imu` output of the MH_05 excerpt): a trailing _s<N> is the seed

Per run: ATE (SE3 RMSE, m), FPS (frames / wall time of the whole run, one process, runs one after another),
and for the dense runs the depth metrics of Table 2 on the keyframes that held a code, against the rendered
ground truth (``mav0/depth0``) at network resolution: (a) the sparse map points, (b) the network prior at
c = 0, (c) the window's optimised code, (d) the map's code (refined at fixed poses, ``runtime.dense.refine``; the
depth the dense map is made of), and the reference (i): the network's own sparse input interpolated
(``runtime.densify.interpolate_sparse``), which a network with sparse input has to beat. The machine is shared
and noisy: compare FPS as ratios within one invocation.
The bars: per dense mode and sequence, the paired ATE difference against sparse over the seeds (mean and standard
error; frames/s as the ratio of runs of one seed, which follow each other), frames/s >= 20, and (c) and (d) below
(b).
Prints one table (mean over seeds per preset and mode, plus per-run rows) and writes ``bench_dense.json``,
after every run too (``"complete": false`` until the end): an interrupted invocation keeps its finished runs, and
the same command with ``--resume`` runs only the missing ones.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_slam import apply_override, make_config
from benchmarks.common import REPO, resumable_rows, slam_machine, write_json
from runtime.dense import DenseConfig
from runtime.diagnostics.oracle_depth import oracle_depth_source
from runtime.io.euroc import read_euroc
from runtime.run import run_sequence

MODES = {
    "sparse": None,
    "dense_eq13": {"use_depth_residual": True, "use_consistency": False},
    "dense_eq13_14": {"use_depth_residual": True, "use_consistency": True},
    # the network with Eq. 14 only (not in the default run): Eq. 13 ties a landmark to the depth the network was
    # given at that landmark's pixel, a prior on its earlier estimate
    "dense_eq14": {"use_depth_residual": False, "use_consistency": True},
    # the upper bound: Eq. 13 + 14 with the rendered depth in place of the network's prior
    # (runtime.diagnostics.oracle_depth); what a perfect depth network would buy on the same sequences. Its rows
    # use the Laplace sigma sqrt(2) * oracle_b: the rendered depth has no correlated error field to inflate for.
    "dense_gt_eq13_14": {
        "use_depth_residual": True,
        "use_consistency": True,
        "factors": {"sigma_per_b": float(np.sqrt(2.0))},
    },
    # the upper bound with one residual at a time: which of the two moves the trajectory (not in the default run)
    "dense_gt_eq13": {
        "use_depth_residual": True,
        "use_consistency": False,
        "factors": {"sigma_per_b": float(np.sqrt(2.0))},
    },
    "dense_gt_eq14": {
        "use_depth_residual": False,
        "use_consistency": True,
        "factors": {"sigma_per_b": float(np.sqrt(2.0))},
    },
}
#: modes that run on the rendered depth (runtime.diagnostics.oracle_depth) instead of the network's prior
GROUND_TRUTH_MODES = ("dense_gt_eq13_14", "dense_gt_eq13", "dense_gt_eq14")
ORACLE_B = 0.02  # m, Laplace scale of the rendered depth
DEFAULT_MODES = ("sparse", "dense_eq13", "dense_eq13_14", "dense_gt_eq13_14")


def sequence(data: Path, preset: str, duration: float, seed: int, scale: float) -> Path:
    """Render (once) and return the sequence root."""
    from sim.euroc import write_euroc_sequence

    root = data / f"euroc_{preset}_{duration:g}s_s{seed}_x{scale:g}"
    if (root / "mav0" / "cam0" / "data.csv").is_file() and (root / "mav0" / "depth0" / "data.csv").is_file():
        return root
    t0 = time.perf_counter()
    out = Path(
        write_euroc_sequence(root, preset, duration=duration, seed=seed, imu_noise=True, progress=False, scale=scale)
    )
    print(f"bench_dense: rendered {out} in {time.perf_counter() - t0:.0f} s", flush=True)
    return out


#: DenseConfig keys that a mode decides (which residuals); ``--set`` changes the others
MODE_KEYS = ("use_depth_residual", "use_consistency")


def dense_config(mode: str, sets: list[str]) -> DenseConfig | None:
    """The ``DenseConfig`` of a mode (None for ``sparse``): the mode's keys over ``sets`` ("key=value" overrides of
    the other keys, as ``--set``; dotted for the nested ones, ``factors.min_sigma=0.01``) over the package
    defaults; per-keyframe maps are not saved unless set."""
    base = MODES[mode]
    if base is None:
        return None
    d = json.loads(json.dumps(base))
    for s in sets:
        k, sep, v = s.partition("=")
        if not sep:
            raise SystemExit(f"bench_dense: --set needs key=value, got {s!r}")
        apply_override(d, k, v)
    d.update({k: base[k] for k in MODE_KEYS})  # the mode decides the residuals
    d.setdefault("save_maps", False)
    return DenseConfig.from_dict(d)


def run_mode(seq, run_dir, mode: str, sets=(), slam_cfg=None, model_dir=None) -> dict:
    """One run of ``mode`` on ``seq`` into ``run_dir`` (``sets``: as ``--set``); returns its metrics."""
    return run_sequence(
        seq,
        run_dir,
        slam_cfg,
        progress=False,
        plot=False,
        dense=dense_config(mode, list(sets)),
        model_dir=model_dir,
        depth_source=oracle_depth_source(seq.depth, ORACLE_B) if mode in GROUND_TRUTH_MODES else None,
    )


def model_identity(model_dir: str | None) -> dict:
    """The network the dense modes use: its folder and the SHA-256 of its ONNX files (checked readable here).

    Raises:
        runtime.network.ModelError: the folder lacks the exported files or its manifest does not match them.
    """
    import hashlib

    from runtime.network import DepthNetwork, default_model_dir

    d = Path(model_dir) if model_dir is not None else default_model_dir()
    DepthNetwork(d)  # the same checks as the SLAM run (files, manifest, input/output shapes)
    return {
        "dir": str(d),
        "shipped": model_dir is None,
        "sha256": {f: hashlib.sha256((d / f).read_bytes()).hexdigest() for f in ("prior.onnx", "decoder.onnx")},
    }


def named_sequence(path: str) -> tuple[str, int, Path]:
    """``(name, seed, root)`` of an existing sequence folder given to ``--sequences``: a trailing ``_s<N>`` of its
    name is the seed (``euroc_flight_30s_s2`` -> ``("euroc_flight_30s", 2)``), else the seed is 0."""
    root = Path(path)
    if not (root / "mav0" / "cam0" / "data.csv").is_file():
        raise SystemExit(f"bench_dense: {root} is not an EuRoC-layout sequence (no mav0/cam0/data.csv)")
    m = re.fullmatch(r"(.+)_s(\d+)", root.name)
    return (m.group(1), int(m.group(2)), root) if m else (root.name, 0, root)


def run_row(preset: str, seed: int, mode: str, m: dict) -> dict:
    """One row of the table from a run's ``metrics.json`` dict ``m``: ATE [m], FPS, keyframes, decoder runs, the
    drift found at a relocalisation [m] and the depth metrics of (a) sparse points, (b) prior, (c) optimised,
    (d) the map's codes and (i) the reference: the network's sparse input interpolated."""
    dm = m.get("depth_metrics") or {}
    r = {
        "preset": preset,
        "seed": seed,
        "mode": mode,
        "ate": m.get("ate_se3_rmse_m", float("nan")),
        "fps": m["fps"],
        "keyframes": m["keyframes"],
        "decoder_calls": m.get("decoder_calls", 0),
        "timing_dense_ms_per_frame": m.get("timing_dense_ms_per_frame"),
        "peak_rss_mb": m.get("peak_rss_mb"),  # the run's own peak (runtime.run resets it at each run's start)
        "later_jobs_at_last_frame": m.get("dense_later_jobs_at_last_frame"),  # the network thread's backlog
        # dead-reckoning drift found by the relocalisation after a loss of visual tracking (whitewall)
        "reloc_drift_m": max((r["drift_m"] for r in m.get("relocalisations") or []), default=float("nan")),
    }
    for stage, key in (("sparse", "a"), ("prior", "b"), ("optimised", "c"), ("map", "d"), ("interpolated", "i")):
        s = dm.get(stage) or {}
        r[f"rmse_{key}"] = s.get("rmse", float("nan"))
        r[f"absrel_{key}"] = s.get("abs_rel", float("nan"))
        r[f"delta1_{key}"] = s.get("delta1", float("nan"))
    return r


COLS = (
    *("ate", "fps", "rmse_a", "rmse_b", "rmse_c", "rmse_d", "rmse_i"),
    *("absrel_b", "absrel_c", "absrel_i", "delta1_b", "delta1_c"),
)


def fmt_table(rows: list[dict], per_run: bool = True) -> str:
    head = (
        f"{'preset':10s} {'mode':14s} {'seeds':>5s} {'ATE m':>8s} {'FPS':>6s} {'RMSE(a)':>8s} "
        f"{'RMSE(b)':>8s} {'RMSE(c)':>8s} {'RMSE(d)':>8s} {'RMSE(i)':>8s} {'AbsRel b':>8s} {'AbsRel c':>8s} "
        f"{'AbsRel i':>8s} {'d1 b':>6s} {'d1 c':>6s}"
    )
    lines = [head, "-" * len(head)]
    groups = {}
    for r in rows:
        groups.setdefault((r["preset"], r["mode"]), []).append(r)
    for (preset, mode), rs in groups.items():
        mean = {
            c: float(np.nanmean([r[c] for r in rs])) if any(np.isfinite(r[c]) for r in rs) else float("nan")
            for c in COLS
        }
        lines.append(
            f"{preset:10s} {mode:14s} {len(rs):5d} {mean['ate']:8.4f} {mean['fps']:6.1f} "
            f"{mean['rmse_a']:8.3f} {mean['rmse_b']:8.3f} {mean['rmse_c']:8.3f} {mean['rmse_d']:8.3f} "
            f"{mean['rmse_i']:8.3f} {mean['absrel_b']:8.3f} {mean['absrel_c']:8.3f} {mean['absrel_i']:8.3f} "
            f"{mean['delta1_b']:6.3f} {mean['delta1_c']:6.3f}"
        )
    if per_run:
        lines.append("per run:")
        for r in rows:
            lines.append(
                f"  {r['preset']:10s} {r['mode']:14s} seed {r['seed']}: ATE {r['ate']:.4f} m, "
                f"{r['fps']:.1f} FPS, RMSE a/b/c/d/i {r['rmse_a']:.3f}/{r['rmse_b']:.3f}/{r['rmse_c']:.3f}/"
                f"{r['rmse_d']:.3f}/{r['rmse_i']:.3f} m, "
                f"decoder runs {r['decoder_calls']}, drift at relocalisation {r['reloc_drift_m']:.3f} m"
                + (f", peak memory {r['peak_rss_mb']:.0f} MiB" if r.get("peak_rss_mb") else "")
                + (f", {r['later_jobs_at_last_frame']} later jobs left" if r.get("later_jobs_at_last_frame") else "")
            )
    return "\n".join(lines)


def bars(rows: list[dict]) -> dict:
    """The dense-by-default issue's quality bars per sequence, for the modes that ran: the depth residuals' paired
    ATE difference against sparse (mean <= 0), frames/s >= 20 on every seed, the window's optimised codes and the
    map's codes better than c = 0."""

    def mean(preset, mode, col):
        v = [r[col] for r in rows if r["preset"] == preset and r["mode"] == mode and np.isfinite(r[col])]
        return float(np.mean(v)) if v else float("nan")

    out = {}
    for preset in sorted({r["preset"] for r in rows}):
        modes = {r["mode"] for r in rows if r["preset"] == preset}
        for mode in sorted(modes - {"sparse"} - set(GROUND_TRUTH_MODES)):
            b, c, d = mean(preset, mode, "rmse_b"), mean(preset, mode, "rmse_c"), mean(preset, mode, "rmse_d")
            if np.isfinite(b):
                out[f"{preset}_{mode}_rmse_c_lt_b"] = {"prior": b, "optimised": c, "met": bool(c < b)}
            if np.isfinite(b) and np.isfinite(d):
                out[f"{preset}_{mode}_rmse_d_lt_b"] = {"prior": b, "map": d, "met": bool(d < b)}
            f = min(r["fps"] for r in rows if r["preset"] == preset and r["mode"] == mode)
            out[f"{preset}_{mode}_fps_ge_20"] = {"fps_min": f, "met": bool(f >= 20)}
            if "sparse" in modes:
                out[f"{preset}_{mode}_minus_sparse"] = paired(rows, preset, mode, "sparse")
    return out


def paired(rows: list[dict], preset: str, mode: str, ref: str) -> dict:
    """Paired difference of ``mode`` against ``ref`` over the seeds both ran on ``preset``: mean ATE difference
    [m] with its standard error, and the mean frames/s ratio (runs of one seed follow each other)."""
    by = {(r["mode"], r["seed"]): r for r in rows if r["preset"] == preset}
    seeds = sorted(s for (m, s) in by if m == mode and (ref, s) in by)
    d = np.array([by[mode, s]["ate"] - by[ref, s]["ate"] for s in seeds])
    ratio = np.array([by[mode, s]["fps"] / by[ref, s]["fps"] for s in seeds])
    se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan")
    return {  # numbers only (notebook 03 formats every value but "met")
        "n_seeds": len(seeds),
        "ate_diff_mean": float(d.mean()) if d.size else float("nan"),
        "ate_diff_se": se,
        "fps_ratio_mean": float(ratio.mean()) if ratio.size else float("nan"),
        "met": bool(d.size and d.mean() <= 0),
    }


def _row_key(row: dict) -> tuple[str, int, str]:
    return row["preset"], int(row["seed"]), row["mode"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="*", default=["textured", "whitewall"])
    ap.add_argument(
        "--sequences",
        nargs="*",
        default=[],
        help="existing EuRoC-layout folders to run as well (e.g. dit-sim imu output of the MH_05 excerpt); a "
        "trailing _s<N> of a folder's name is its seed",
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--scale", type=float, default=1.0, help="image scale of the rendered sequences")
    ap.add_argument("--modes", nargs="+", default=list(DEFAULT_MODES), choices=list(MODES))
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        help="DenseConfig overrides key=value for every dense mode (not the keys a mode decides: "
        + ", ".join(MODE_KEYS)
        + ")",
    )
    ap.add_argument(
        "--slam-set",
        nargs="*",
        default=[],
        help="SlamConfig overrides key=value (conf/slam/runtime keys, e.g. backend.window_size=8)",
    )
    ap.add_argument(
        "--model",
        default=None,
        help="exported network folder (prior.onnx, decoder.onnx, manifest.json) for the dense modes; default: the "
        "shipped model",
    )
    ap.add_argument("--data", default=str(REPO / "data" / "sim" / "bench_dense"), help="sequence cache folder")
    ap.add_argument("--out", default=str(REPO / "outputs" / "bench_dense"))
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the runs of an earlier invocation with the same arguments (its bench_dense.json in --out) and "
        "run only the missing ones",
    )
    args = ap.parse_args(argv)
    run_args = {k: v for k, v in vars(args).items() if k != "resume"}
    slam_cfg = make_config("default", args.slam_set)  # a bad override fails here, before any rendering
    model = model_identity(args.model)  # so does a missing or malformed model folder
    logging.basicConfig(level=logging.ERROR)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    machine = slam_machine(data="synthetic (sim/)")
    done = resumable_rows(out / "bench_dense.json", run_args, machine, _row_key) if args.resume else {}
    rows = []
    res = {
        "machine": machine,
        "args": run_args,
        "model": model,
        "columns": (
            "ATE SE3 RMSE [m]; depth RMSE [m] of (a) sparse map points, (b) prior c=0, (c) optimised code (the "
            "window's), (d) map code (refined at fixed poses), (i) the network's sparse input interpolated (reference)"
        ),
        "complete": False,
        "rows": rows,
    }
    jobs = [(preset, seed, None) for preset in args.presets for seed in args.seeds]
    jobs += [named_sequence(p) for p in args.sequences]
    for preset, seed, given in jobs:
        root = given
        for mode in args.modes:
            if (preset, seed, mode) in done:
                rows.append(done[preset, seed, mode])
                print(f"bench_dense: {preset} seed {seed} {mode}: kept from the earlier invocation", flush=True)
                continue
            root = root or sequence(Path(args.data), preset, args.duration, seed, args.scale)
            t0 = time.perf_counter()
            seq = read_euroc(root)
            m = run_mode(seq, out / f"{preset}_s{seed}_{mode}", mode, args.set, slam_cfg, args.model)
            rows.append(run_row(preset, seed, mode, m))
            r = rows[-1]
            print(
                f"bench_dense: {preset} seed {seed} {mode}: ATE {r['ate']:.4f} m, {r['fps']:.1f} FPS, "
                f"RMSE a/b/c/i {r['rmse_a']:.3f}/{r['rmse_b']:.3f}/{r['rmse_c']:.3f}/{r['rmse_i']:.3f} "
                f"({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
            write_json(out / "bench_dense.json", res)  # an interruption loses only the run in progress
    table = fmt_table(rows)
    b = bars(rows)
    print(table)
    print("bars:")
    for k, v in b.items():
        print(f"  {k}: {v}")
    res.update(complete=True, bars=b, table=table)
    write_json(out / "bench_dense.json", res)
    print(f"bench_dense: wrote {out / 'bench_dense.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
