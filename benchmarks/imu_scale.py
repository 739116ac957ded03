"""How well a sequence's IMU fixes the metric scale of its true trajectory: the profile likelihood of the scale.

    python benchmarks/imu_scale.py --sequences DIR [DIR ...] [--segment 5] [--raise 1 5 10] [--out F.json]
    python benchmarks/imu_scale.py --runs RUN_DIR [RUN_DIR ...] [--raise 10] [--out F.json]

Each DIR is an EuRoC-layout sequence with an IMU and a ground truth (e.g. ``dit-sim imu`` completions of the MH_05
excerpt). The ground truth's poses every ``--step`` frames are held fixed with their positions multiplied by a
scale ``s``; the velocities and the biases (the runtime's ``CombinedImuFactor`` between the poses, its bias random
walk, a loose prior on the first bias) are optimised. The IMU's error at that optimum, as a function of ``s``, is the
profile: its minimum ``s*`` is the scale that the IMU prefers for the true shape, and its curvature gives a standard
deviation. That is what an estimator with perfect vision (shape and rotations exact, scale free) could get from the
IMU alone, over the whole sequence and over consecutive ``--segment`` second pieces, with the white-noise densities
of ``imu0/sensor.yaml`` raised by each ``--raise`` (as ``imu.max_noise_scale`` raises them; the raise changes the
standard deviation, hardly ``s*``). An exact IMU gives ``s* = 1``; how far ``s*`` strays from 1 on a noisy one is the
scale error that its noise allows. The bias random walk must be the stated one: it lets the bias take up the small
misfit of the runtime's sample hold (each sample held over the next period); with a walk near zero the scale takes it
(1.06 on the fast synthetic path of ``tests/benchmarks/test_imu_scale.py`` with near-exact samples, stated as
such, and a walk of 1e-12). Prints a table and writes JSON.

``--runs`` asks the same of an estimate: each RUN_DIR is a ``dit-slam`` output (``keyframes.txt``, and
``metrics.json`` naming the sequence). The profile is taken over the run's keyframe poses as they are (``ours``),
with their rotations replaced by the truth's (``true_R``), and with their positions replaced by the truth's brought
into the run's frame at the run's scale (``true_p``: the best Sim(3) of the estimate onto the truth, inverted),
beside the run's Sim(3) scale ``s`` (truth = ``s`` x estimate). An estimator that used the IMU's scale information
fully would leave ``s`` near the truth's own ``s*``; where ``true_p``'s ``s*`` is near ``s`` but ``ours`` is near 1,
the IMU would correct the run's scale if its positions had the true shape, and agrees with the wrong scale given
the shape the run has.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import slam_machine, write_json

__all__ = ["scale_profile", "profile_sequence", "profile_run", "main"]


def scale_profile(seq, ts: np.ndarray, T_w_b: np.ndarray, noise_raise: float = 1.0, imu=None) -> tuple[float, float]:
    """``(s*, sd)``: the scale of ``T_w_b``'s positions (N, 4, 4) at ``ts`` (N,) ns that ``seq``'s IMU prefers,
    and its standard deviation from the profile's curvature (``nan`` when the profile is flat). ``imu``: ``seq``'s
    :class:`runtime.backend.imu.ImuStream` when the caller has it (built here otherwise)."""
    import gtsam
    from scipy.optimize import minimize_scalar

    from runtime.backend.imu import ImuStream, integrate, make_bias, preintegration_params

    if ts.size < 3:
        raise ValueError(f"{ts.size} poses: a scale profile needs at least 3")
    X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
    imu = ImuStream.from_sequence(seq) if imu is None else imu
    params = preintegration_params(seq.imu, scales=(noise_raise, noise_raise))
    zero = make_bias(np.zeros(6))
    pims = []
    for a, b in zip(ts[:-1], ts[1:], strict=True):
        pim = gtsam.PreintegratedCombinedMeasurements(params, zero)
        integrate(pim, *imu.segment(int(a), int(b)))
        pims.append(pim)
    t_s = (ts - ts[0]) * 1e-9
    fix = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    bias_prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.5] * 3 + [0.1] * 3))  # accel, gyro: loose
    lp = gtsam.LevenbergMarquardtParams()
    lp.setMaxIterations(50)
    lp.setRelativeErrorTol(1e-10)

    def error(s: float) -> float:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        p = T_w_b[:, :3, 3] * s
        vel = np.gradient(p, t_s, axis=0)
        for n in range(ts.size):
            pose = gtsam.Pose3(gtsam.Rot3(T_w_b[n, :3, :3]), p[n])
            values.insert(X(n), pose)
            values.insert(V(n), vel[n])
            values.insert(B(n), zero)
            graph.add(gtsam.PriorFactorPose3(X(n), pose, fix))
            if n:
                graph.add(gtsam.CombinedImuFactor(X(n - 1), V(n - 1), X(n), V(n), B(n - 1), B(n), pims[n - 1]))
        graph.add(gtsam.PriorFactorConstantBias(B(0), zero, bias_prior))
        return float(graph.error(gtsam.LevenbergMarquardtOptimizer(graph, values, lp).optimize()))

    best = minimize_scalar(error, bounds=(0.7, 1.4), method="bounded", options={"xatol": 1e-5})
    s, h = float(best.x), 2e-3
    curv = (error(s + h) - 2.0 * best.fun + error(s - h)) / h**2  # graph error = chi2 / 2
    return s, float(1.0 / np.sqrt(curv)) if curv > 0 else float("nan")


def profile_sequence(root: Path, segment_s: float, raises: list[float], step: int = 5) -> dict:
    """The scale profile of ``root``'s ground truth over the whole sequence and over ``segment_s`` pieces."""
    from runtime.backend.imu import ImuStream
    from runtime.io.euroc import read_euroc

    seq = read_euroc(root)
    if seq.gt is None:
        raise ValueError(f"{root} has no ground truth")
    ts = seq.frame_ts[seq.gt.covers(seq.frame_ts)][::step]
    ts = ts[(ts >= seq.imu_ts[0]) & (ts <= seq.imu_ts[-1])]
    T = seq.gt_pose_at(ts)
    imu = ImuStream.from_sequence(seq)  # one stream for every profile
    t_s = (ts - ts[0]) * 1e-9
    out = {"poses": int(ts.size), "duration_s": float(t_s[-1]), "raises": {}}
    for r in raises:
        row = {"whole": scale_profile(seq, ts, T, r, imu), "segments": []}
        for a in np.arange(0.0, t_s[-1] - 0.5 * segment_s, segment_s):
            m = (t_s >= a) & (t_s <= a + segment_s)
            if m.sum() >= 3:
                row["segments"].append([float(a), *scale_profile(seq, ts[m], T[m], r, imu)])
        out["raises"][f"x{r:g}"] = row
    return out


def profile_run(run: Path, raises: list[float]) -> dict:
    """The scale profile of a ``dit-slam`` run's keyframes: as estimated, with the true rotations, and with the
    true positions at the run's scale (module docstring)."""
    import json

    from benchmarks.peers.diagnose import umeyama
    from runtime.backend.imu import ImuStream
    from runtime.io.euroc import read_euroc
    from runtime.io.tum import read_tum

    metrics = json.loads((run / "metrics.json").read_text())
    seq = read_euroc(metrics["sequence"])
    if seq.gt is None:
        raise ValueError(f"{run}: its sequence has no ground truth")
    ts, T = read_tum(run / "keyframes.txt")
    keep = seq.gt.covers(ts) & (ts >= seq.imu_ts[0]) & (ts <= seq.imu_ts[-1])
    ts, T = ts[keep], T[keep]
    G = seq.gt_pose_at(ts)
    s, R, t = umeyama(T[:, :3, 3], G[:, :3, 3])  # truth = s R estimate + t
    true_R, true_p = T.copy(), T.copy()
    true_R[:, :3, :3] = np.einsum("ij,njk->nik", R.T, G[:, :3, :3])  # the truth's rotations in the run's frame
    true_p[:, :3, 3] = (G[:, :3, 3] - t) @ R / s
    imu = ImuStream.from_sequence(seq)
    out = {"sequence": str(seq.root), "keyframes": int(ts.size), "sim3_scale": s, "raises": {}}
    out |= {k: metrics[k] for k in ("ate_se3_rmse_m", "ate_sim3_rmse_m") if k in metrics}  # the run's, as it wrote them
    for r in raises:
        out["raises"][f"x{r:g}"] = {
            name: scale_profile(seq, ts, M, r, imu) for name, M in (("ours", T), ("true_R", true_R), ("true_p", true_p))
        } | {"truth": scale_profile(seq, ts, G, r, imu)}
    return out


def _main_runs(args) -> dict:
    rows = {}
    print("| run | raise | Sim(3) scale s | s*: ours | true rotations | true positions | truth |")
    print("|---|---|---|---|---|---|---|")
    for r in args.runs:
        row = rows[str(r)] = profile_run(Path(r), args.raises)
        for key, v in row["raises"].items():
            cells = " | ".join(f"{v[k][0]:.4f} ± {v[k][1]:.4f}" for k in ("ours", "true_R", "true_p", "truth"))
            print(f"| {r} | {key} | {row['sim3_scale']:.4f} | {cells} |", flush=True)
    return {"runs": args.runs, "rows": rows}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--sequences", nargs="+", help="EuRoC-layout folders with an IMU and ground truth")
    what.add_argument("--runs", nargs="+", help="dit-slam output folders: profile their keyframes instead")
    ap.add_argument("--segment", type=float, default=5.0, help="length of the pieces [s]")
    ap.add_argument("--raise", dest="raises", type=float, nargs="+", default=[1.0, 5.0, 10.0])
    ap.add_argument("--step", type=int, default=5, help="a pose every STEP frames")
    ap.add_argument("--out", default=None, help="JSON path")
    args = ap.parse_args(argv)
    if args.runs:
        for r in args.runs:
            if not (Path(r) / "keyframes.txt").is_file() or not (Path(r) / "metrics.json").is_file():
                sys.exit(f"imu_scale: {r} has no keyframes.txt or metrics.json (not a dit-slam output folder)")
        doc = _main_runs(args) | {"machine": slam_machine()}
        if args.out:
            print(f"wrote {write_json(args.out, doc)}")
        return doc
    for s in args.sequences:
        if not (Path(s) / "mav0" / "imu0").is_dir() or not (Path(s) / "mav0" / "state_groundtruth_estimate0").is_dir():
            sys.exit(f"imu_scale: {s} has no mav0/imu0 or mav0/state_groundtruth_estimate0")
    rows = {}
    print(
        f"| sequence | raise | whole: s* ± sd | {args.segment:g} s pieces: s* min - max | pieces: RMS of s* - 1 | sd |"
    )
    print("|---|---|---|---|---|---|")
    for s in args.sequences:
        r = rows[Path(s).name] = profile_sequence(Path(s), args.segment, args.raises, args.step)
        for key, v in r["raises"].items():
            seg = np.array([x[1] for x in v["segments"]])
            sd = np.array([x[2] for x in v["segments"]])
            rms = float(np.sqrt(np.mean((seg - 1.0) ** 2)))
            v["segments_rms"] = rms
            print(
                f"| {Path(s).name} | {key} | {v['whole'][0]:.4f} ± {v['whole'][1]:.4f} | "
                f"{seg.min():.3f} - {seg.max():.3f} | {rms:.4f} | {np.median(sd):.4f} |",
                flush=True,
            )
    doc = {"sequences": args.sequences, "segment_s": args.segment, "step": args.step, "machine": slam_machine()}
    doc["rows"] = rows
    if args.out:
        print(f"wrote {write_json(args.out, doc)}")
    return doc


if __name__ == "__main__":
    main()
