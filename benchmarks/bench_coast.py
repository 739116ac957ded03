"""What decides the ``whitewall`` ATE: the IMU-only coast in front of the bare wall, and how the trajectory after
the relocalisation ties back to the one before it.

    python benchmarks/bench_dense.py --presets whitewall      # the runs (once)
    python benchmarks/bench_coast.py                          # seeds 0 1 2, 60 s, the same folders

While the camera sees nothing but the bare wall, no visual residual constrains the motion: a monocular system
is left with the IMU between two visual fixes, and depth on a blank plane could at best add the distance to it
(its normal component), if the depth followed the distance. Two tables:

**Oracles** (what the coast allows). Per sequence the script smooths keyframe states every ``--dt-kf`` seconds
over the coast with GTSAM (``CombinedImuFactor`` on the sequence's noisy IMU, bias random walk included) from
the ground-truth state at the loss (pose, velocity, biases), and at the regain:

* ``end pose``: the ground-truth pose only (what a relocalisation's PnP gives);
* ``end pose+vel``: pose and velocity (what the tracking after the relocalisation gives);
* ``+ wall distance``: the latter plus the exact camera-to-wall distance at every keyframe (a perfect depth
  sensor on the wall, 1 cm sigma).

It prints their position RMSE over the coast [mm] in the ground-truth frame.

**Runs** (where each run's ATE comes from). For every run folder of the sequence (``bench_dense``'s modes): the
ATE (SE(3) alignment of the whole trajectory, positions), the RMSE before, over and after the coast under that
alignment, the RMSE of the part before and of the part after the coast each aligned on its own, and the
disagreement of those two alignments at the last coasted pose (the relocalisation): how far apart [mm] and how
much rotated [deg] the two parts' frames are. A large jump with small one-sided errors means that the ATE is
set by the tie between the two parts, not by the coast.

The coast interval comes from the sparse run's events ("visual tracking lost" / "regained"); without a run, from
the sequence's white-wall hold widened by ``--widen`` seconds. Writes ``bench_coast.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.common import cpu_model  # noqa: E402
from runtime.backend.imu import ImuStream, integrate, make_bias, preintegration_params  # noqa: E402
from runtime.geometry import from_pose3, rotation_angle, to_pose3  # noqa: E402
from runtime.io.euroc import read_euroc  # noqa: E402
from runtime.io.tum import read_tum  # noqa: E402

NS = 1e-9
ORACLES = ("end pose", "end pose+vel", "+ wall distance")


def coast_interval(seq_root: Path, sparse_run: Path | None, widen: float) -> tuple[int, int, str]:
    """(t_lost, t_regained) [ns] of the blank stretch and where it came from."""
    if sparse_run is not None and (sparse_run / "metrics.json").is_file():
        ev = json.loads((sparse_run / "metrics.json").read_text()).get("events") or []
        spans, lost = [], None  # (lost, regained) pairs; the longest is the blank stretch
        for t, msg in ev:
            if msg.startswith("visual tracking lost"):
                lost = t
            elif msg.startswith("visual tracking regained") and lost is not None:
                spans.append((lost, t))
                lost = None
        if spans:
            a, b = max(spans, key=lambda s: s[1] - s[0])
            return int(round(a * 1e9)), int(round(b * 1e9)), "sparse run's events"
    info = json.loads((seq_root / "sim_info.json").read_text())
    w0, w1 = info["whitewall_window_ns"]
    return int(w0 - widen * 1e9), int(w1 + widen * 1e9), f"white-wall hold +- {widen:g} s"


def oracle_coast(seq, t0: int, t1: int, mode: str, dt_kf: float = 0.4, wall_x: float | None = None) -> np.ndarray:
    """Position errors (K, 3) [m] of keyframes every ``dt_kf`` over ``[t0, t1]`` smoothed over the IMU from exact
    end states (``mode`` one of :data:`ORACLES`; the wall is the plane ``x = wall_x`` of the world)."""
    import gtsam
    from gtsam.symbol_shorthand import B, V, X

    gt = seq.gt
    n = max(2, int(round((t1 - t0) * NS / dt_kf)) + 1)
    grid = np.linspace(t0, t1, n).astype(np.int64)
    idx = np.clip(np.searchsorted(gt.ts, grid), 0, len(gt) - 1)  # ground-truth samples (200 Hz) at the grid
    ts, T, v = gt.ts[idx], gt.T_w_b[idx], gt.v_w[idx]
    bias0 = np.concatenate([gt.ba[idx[0]], gt.bg[idx[0]]])
    params = preintegration_params(seq.imu)
    imu = ImuStream.from_sequence(seq)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    tight = gtsam.noiseModel.Isotropic.Sigma
    for k in range(n):
        values.insert(X(k), to_pose3(T[k]))
        values.insert(V(k), v[k])
        values.insert(B(k), make_bias(bias0))
    graph.push_back(gtsam.PriorFactorPose3(X(0), to_pose3(T[0]), tight(6, 1e-3)))
    graph.push_back(gtsam.PriorFactorVector(V(0), v[0], tight(3, 1e-3)))
    graph.push_back(gtsam.PriorFactorConstantBias(B(0), make_bias(bias0), tight(6, 1e-4)))
    graph.push_back(gtsam.PriorFactorPose3(X(n - 1), to_pose3(T[-1]), tight(6, 1e-3)))
    if mode != "end pose":
        graph.push_back(gtsam.PriorFactorVector(V(n - 1), v[-1], tight(3, 1e-3)))
    for k in range(n - 1):
        pim = gtsam.PreintegratedCombinedMeasurements(params, make_bias(bias0))
        integrate(pim, *imu.segment(int(ts[k]), int(ts[k + 1])))
        graph.push_back(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim))
    if mode == "+ wall distance":
        t_b_c = seq.T_b_c[:3, 3]
        for k in range(1, n - 1):
            graph.push_back(_wall_factor(X(k), wall_x - (T[k][:3, :3] @ t_b_c + T[k][:3, 3])[0], wall_x, t_b_c))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    return np.array([from_pose3(result.atPose3(X(k)))[:3, 3] - T[k][:3, 3] for k in range(n)])


def _wall_factor(key, distance: float, wall_x: float, t_b_c: np.ndarray, sigma: float = 0.01):
    """Measured camera-to-wall distance ``wall_x - x(p_w_c)`` for the pose ``T_w_b`` at ``key`` (one row)."""
    import gtsam

    from runtime.backend.factors import custom_factor
    from runtime.geometry import skew

    def error(values, want_jacobians):
        P = values.atPose3(key).matrix()
        R = P[:3, :3]
        p_c = R @ t_b_c + P[:3, 3]
        r = np.array([wall_x - p_c[0] - distance])
        if not want_jacobians:
            return r, None
        # retract: R Exp(w), p + R v  ->  dp_c = -R [t_b_c]x w + R v
        return r, [-np.concatenate([-(R @ skew(t_b_c))[0], R[0]])[None, :]]

    return custom_factor(gtsam.noiseModel.Isotropic.Sigma(1, sigma), [key], error, [6])


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def run_segments(seq, run: Path, t0: int, t1: int) -> dict:
    """Where a run's ATE comes from: errors [m] before ``t0``, over ``[t0, t1]`` and after ``t1`` under the SE(3)
    alignment of the whole trajectory, each side aligned on its own, and the disagreement of the two one-sided
    alignments at the last pose of the coast (positions in the ground-truth frame).

    Returns:
        ``{"ate", "pre", "coast", "post", "pre_only", "post_only", "jump_m", "jump_deg"}``.
    """
    from runtime.eval import interpolate_poses
    from runtime.render import align_se3

    ts, T = read_tum(run / "trajectory.txt")
    inside = seq.gt.covers(ts)
    ts, T = ts[inside], T[inside]
    ref = interpolate_poses(ts, seq.gt.ts, seq.gt.T_w_b)[0][:, :3, 3]
    p = T[:, :3, 3]

    def errors(sel: np.ndarray, A: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p[sel] @ A[:3, :3].T + A[:3, 3] - ref[sel], axis=1)

    every = np.ones(len(ts), bool)
    pre, coast, post = ts < t0, (ts >= t0) & (ts <= t1), ts > t1
    A = align_se3(ts, T, seq.gt.ts, seq.gt.T_w_b)
    e = errors(every, A)
    out = {"ate": _rms(e), "pre": _rms(e[pre]), "coast": _rms(e[coast]), "post": _rms(e[post])}
    if pre.sum() < 3 or post.sum() < 3 or not coast.any():
        return out | {
            "pre_only": float("nan"),
            "post_only": float("nan"),
            "jump_m": float("nan"),
            "jump_deg": float("nan"),
        }
    Aa = align_se3(ts[pre], T[pre], seq.gt.ts, seq.gt.T_w_b)
    Ab = align_se3(ts[post], T[post], seq.gt.ts, seq.gt.T_w_b)
    q = p[coast][-1]
    return out | {
        "pre_only": _rms(errors(pre, Aa)),
        "post_only": _rms(errors(post, Ab)),
        "jump_m": float(np.linalg.norm((Aa[:3, :3] @ q + Aa[:3, 3]) - (Ab[:3, :3] @ q + Ab[:3, 3]))),
        "jump_deg": float(np.degrees(rotation_angle(Aa[:3, :3].T @ Ab[:3, :3]))),
    }


def coast_row(root: Path, seed: int, runs: dict[str, Path], dt_kf: float = 0.4, widen: float = 2.0) -> dict:
    """One whitewall sequence: the coast interval (from ``runs["sparse"]``'s events when there is one), the
    oracles' coast RMSE [m] (and per axis) and :func:`run_segments` of every run (``mode -> run folder``) that
    wrote a trajectory."""
    seq = read_euroc(root)
    wall_x = float(json.loads((root / "sim_info.json").read_text())["room_size_m"][0])
    t0, t1, source = coast_interval(root, runs.get("sparse"), widen)
    row = {"seed": seed, "t0_s": (t0 - seq.gt.ts[0]) * NS, "t1_s": (t1 - seq.gt.ts[0]) * NS, "source": source}
    for mode in ORACLES:
        e = oracle_coast(seq, t0, t1, mode, dt_kf, wall_x)
        row[mode] = float(np.sqrt(np.mean(np.sum(e**2, 1))))
        row[f"{mode} per axis"] = np.sqrt(np.mean(e**2, 0)).tolist()
    row["runs"] = {m: run_segments(seq, d, t0, t1) for m, d in runs.items() if (d / "trajectory.txt").is_file()}
    return row


SEGMENTS = ("ate", "pre", "coast", "post", "pre_only", "post_only", "jump_m")


def fmt_tables(rows: list[dict]) -> str:
    """The oracle table (coast RMSE [mm]) and the per-run segment table (mm, deg)."""
    head = f"{'seed':>4s} {'coast [s]':>13s} " + " ".join(f"{c:>16s}" for c in ORACLES)
    lines = ["position RMSE over the coast [mm], keyframes smoothed over the IMU from exact end states", head]
    for r in rows:
        cells = " ".join(f"{1e3 * r[c]:16.1f}" for c in ORACLES)
        lines.append(f"{r['seed']:4d} {r['t0_s']:6.2f}-{r['t1_s']:6.2f} {cells}")
    lines.append(f"{'mean':>4s} {'':13s} " + " ".join(f"{1e3 * np.mean([r[c] for r in rows]):16.1f}" for c in ORACLES))
    runs = sorted({m for r in rows for m in r["runs"]})
    if runs:
        lines += [
            "",
            "runs [mm]: ATE, then RMSE before / over / after the coast (whole alignment), each side aligned",
            "alone, and the two sides' alignments apart at the relocalisation (jump)",
        ]
        head = f"{'seed':>4s} {'run':18s} " + " ".join(f"{c:>9s}" for c in SEGMENTS) + f" {'jump deg':>9s}"
        lines.append(head)
        for mode in runs:
            got = [r["runs"][mode] for r in rows if mode in r["runs"]]
            for r in rows:
                if mode in r["runs"]:
                    s = r["runs"][mode]
                    cells = " ".join(f"{1e3 * s[c]:9.1f}" for c in SEGMENTS)
                    lines.append(f"{r['seed']:4d} {mode:18s} {cells} {s['jump_deg']:9.3f}")
            cells = " ".join(f"{1e3 * np.nanmean([s[c] for s in got]):9.1f}" for c in SEGMENTS)
            lines.append(f"{'mean':>4s} {mode:18s} {cells} {np.nanmean([s['jump_deg'] for s in got]):9.3f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--data", default=str(ROOT / "data" / "sim" / "bench_dense"), help="bench_dense's sequences")
    ap.add_argument("--runs", default=str(ROOT / "outputs" / "bench_dense"), help="bench_dense's run folders")
    ap.add_argument("--dt-kf", type=float, default=0.4, help="keyframe spacing of the oracle coasts [s]")
    ap.add_argument("--widen", type=float, default=2.0, help="coast = the hold widened by this, without runs [s]")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "bench_coast"))
    args = ap.parse_args(argv)
    rows = []
    for seed in args.seeds:
        root = Path(args.data) / f"euroc_whitewall_{args.duration:g}s_s{seed}_x{args.scale:g}"
        if not (root / "mav0").is_dir():
            raise SystemExit(f"bench_coast: no sequence {root}; run benchmarks/bench_dense.py --presets whitewall")
        runs = {run.name.split("_", 2)[2]: run for run in sorted(Path(args.runs).glob(f"whitewall_s{seed}_*"))}
        rows.append(coast_row(root, seed, runs, args.dt_kf, args.widen))
        print(f"bench_coast: seed {seed} done ({rows[-1]['source']})", flush=True)
    table = fmt_tables(rows)
    print(table)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = {
        "machine": {"cpu": cpu_model(), "platform": platform.platform(), "data": "synthetic (sim/)"},
        "args": vars(args),
        "rows": rows,
        "table": table,
    }
    (out / "bench_coast.json").write_text(json.dumps(res, indent=2, default=float))
    print(f"bench_coast: wrote {out / 'bench_coast.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
