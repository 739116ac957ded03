"""Where an ATE gap between systems comes from, on one sequence of ``bench_peers``: error over time, scale per
time window, drift over short horizons (translation, yaw, tilt) and an IMU-only propagation as the floor a
visual-inertial system must beat.

    python -m benchmarks.peers.diagnose --data outputs/peers/seq --sequence flight_s0 \\
        --run dit-slam-sparse=outputs/peers/runs/flight_s0/dit-slam-sparse_run0 \\
        --run orbslam3-mono=outputs/peers/runs/flight_s0/orbslam3-mono_run0 \\
        --out benchmarks/results/peers_diagnosis_flight_s0.json

``--run LABEL=DIR`` (repeatable): ``DIR/trajectory.txt`` of a run; the label's part before ``:`` names the system
(``benchmarks.peers.scoring.SYSTEMS``, which decides body or camera poses), ``LABEL=DIR/FILE.txt`` another file of
the run (``orbslam3-mono:online=DIR/trajectory_online.txt``). Every trajectory is compared in the *camera*
frame (``T_w_b T_b_c`` for the inertial systems) so that lever arms do not differ between systems.

Per trajectory: the Sim(3) ATE over all its frames and over the frames every trajectory has (the common time
window), the median error in 3 s bins after that Sim(3) alignment, the Sim(3) scale and ATE fitted on each 6 s
window alone (a scale that changes between windows cannot be removed by one Sim(3): scale drift), and the error of
the relative motion over 1 s and 5 s (translation after the global scale; yaw about gravity and tilt, in
degrees). The IMU-only row propagates ``imu0`` from the ground-truth state (pose, velocity, biases) at each start
over the same horizons: what the IMU alone gives, the floor for the visual part.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from benchmarks.peers import scoring

BIN_S = 3.0
WINDOW_S = 6.0
HORIZONS_S = (1.0, 5.0)


def umeyama(P: np.ndarray, Q: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` minimising ``sum |s R P_i + t - Q_i|^2`` (Umeyama 1991); P, Q (N, 3), N >= 3."""
    P, Q = np.asarray(P, np.float64), np.asarray(Q, np.float64)
    if P.shape != Q.shape or P.ndim != 2 or P.shape[0] < 3:
        raise ValueError(f"umeyama needs two (N, 3) arrays with N >= 3, got {P.shape} and {Q.shape}")
    mp, mq = P.mean(0), Q.mean(0)
    X, Y = P - mp, Q - mq
    U, D, Vt = np.linalg.svd(Y.T @ X / len(P))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / (X**2).sum(1).mean()) if with_scale else 1.0
    return s, R, mq - s * R @ mp


def aligned_error(P: np.ndarray, Q: np.ndarray, with_scale: bool = True) -> tuple[np.ndarray, float]:
    """Per-point error after the best Sim(3) (or SE(3)) alignment of P onto Q, and the scale."""
    s, R, t = umeyama(P, Q, with_scale)
    return np.linalg.norm(s * P @ R.T + t - Q, axis=1), s


def rmse(e) -> float:
    e = np.asarray(e, np.float64)
    return float(np.sqrt(np.mean(e**2))) if e.size else math.nan


def yaw_tilt_deg(R_err: np.ndarray) -> tuple[float, float]:
    """A world-frame rotation error split into the rotation about the world z axis (gravity; yaw) and the rest
    (tilt), in degrees: ``R_err = Rz(yaw) @ R_tilt`` with ``R_tilt`` free of a z component (swing-twist)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R_err).as_quat()  # x y z w
    twist = np.array([0.0, 0.0, q[2], q[3]])
    n = np.linalg.norm(twist)
    if n < 1e-12:  # a pure 180 deg tilt
        return 0.0, 180.0
    twist /= n
    yaw = 2.0 * math.degrees(math.atan2(twist[2], twist[3]))
    yaw = (yaw + 180.0) % 360.0 - 180.0
    tilt = Rotation.from_quat(twist).inv() * Rotation.from_quat(q)
    return yaw, math.degrees(tilt.magnitude())


def relative_drift(ts: np.ndarray, T: np.ndarray, ref: np.ndarray, horizon_s: float, scale: float) -> np.ndarray:
    """For each frame i with a frame j ``horizon_s`` later (within 30 ms): rows ``[t_i, translation error [m],
    distance [m], |yaw| [deg], tilt [deg]]`` of the motion i -> j, the estimate anchored on the reference at i
    (``scale`` multiplies the estimated translation: the global Sim(3) scale)."""
    t = (np.asarray(ts, np.int64) - int(ts[0])) * 1e-9
    j = np.searchsorted(t, t + horizon_s - 0.03)
    rows = []
    for i in range(len(t)):
        if j[i] >= len(t) or abs(t[j[i]] - t[i] - horizon_s) > 0.03:
            continue
        dE = np.linalg.inv(T[i]) @ T[j[i]]
        dG = np.linalg.inv(ref[i]) @ ref[j[i]]
        et = np.linalg.norm(ref[i, :3, :3] @ (scale * dE[:3, 3] - dG[:3, 3]))
        R_err = ref[i, :3, :3] @ dE[:3, :3] @ dG[:3, :3].T @ ref[i, :3, :3].T  # world frame, anchored at i
        yaw, tilt = yaw_tilt_deg(R_err)
        rows.append([t[i], et, np.linalg.norm(dG[:3, 3]), abs(yaw), tilt])
    return np.asarray(rows).reshape(-1, 5)


def _binned(t: np.ndarray, v: np.ndarray, width: float, stat=np.median) -> list:
    edges = np.arange(0.0, float(t.max()) + width, width) if t.size else np.zeros(0)
    return [[float(a), float(stat(v[(t >= a) & (t < a + width)]))] for a in edges if np.any((t >= a) & (t < a + width))]


def trajectory_report(ts, T, ref, t0: int, common: tuple[int, int]) -> dict:
    """The diagnosis of one trajectory ``T`` (camera poses) against ``ref`` (camera ground truth) at ``ts``."""
    P, Q = T[:, :3, 3], ref[:, :3, 3]
    t = (np.asarray(ts, np.int64) - t0) * 1e-9
    e, s = aligned_error(P, Q)
    e_se3, _ = aligned_error(P, Q, with_scale=False)
    inside = (ts >= common[0]) & (ts <= common[1])
    e_common, _ = aligned_error(P[inside], Q[inside])
    windows = []
    for a in np.arange(0.0, float(t.max()), WINDOW_S):
        w = (t >= a) & (t < a + WINDOW_S)
        if w.sum() >= 10:
            ew, sw = aligned_error(P[w], Q[w])
            windows.append({"t_s": float(a), "sim3_scale": sw, "scale_rel": sw / s, "ate_m": rmse(ew)})
    rep = {
        "frames": int(len(ts)),
        "first_pose_s": float(t[0]),
        "ate_sim3_m": rmse(e),
        "ate_se3_m": rmse(e_se3),
        "sim3_scale": s,
        "ate_sim3_common_m": rmse(e_common),
        "error_bins_m": _binned(t, e, BIN_S),
        "windows": windows,
        "window_scale_spread": float(np.ptp([w["scale_rel"] for w in windows])) if windows else math.nan,
        "window_ate_median_m": float(np.median([w["ate_m"] for w in windows])) if windows else math.nan,
    }
    for h in HORIZONS_S:
        d = relative_drift(ts, T, ref, h, s)
        key = f"{h:g}s"
        rep[f"drift_{key}"] = {
            "trans_rmse_m": rmse(d[:, 1]),
            "trans_pct_of_distance": float(100 * np.median(d[:, 1] / np.maximum(d[:, 2], 1e-3))) if len(d) else None,
            "yaw_median_deg": float(np.median(d[:, 3])) if len(d) else None,
            "tilt_median_deg": float(np.median(d[:, 4])) if len(d) else None,
            "trans_bins_m": _binned(d[:, 0], d[:, 1], BIN_S) if len(d) else [],
        }
    return rep


def imu_only_drift(seq, horizon_s: float, step_s: float = 0.5) -> np.ndarray:
    """IMU-only propagation from the ground-truth state (pose, velocity, biases) at starts ``step_s`` apart over
    ``horizon_s``: rows as :func:`relative_drift` (camera frame, gravity along the world z axis)."""
    from runtime.backend.imu import ImuStream, propagate

    imu = ImuStream.from_sequence(seq)
    gt = seq.gt
    T_b_c = np.asarray(seq.T_b_c, np.float64)
    h = int(round(horizon_s * 1e9))
    rows = []
    t0 = int(seq.frame_ts[0])
    for start in np.arange(max(int(gt.ts[0]), imu.t_start), min(int(gt.ts[-1]), imu.t_end) - h, int(step_s * 1e9)):
        i = int(np.searchsorted(gt.ts, start))
        j = int(np.searchsorted(gt.ts, int(gt.ts[i]) + h))
        if j >= len(gt.ts):
            break
        g, a, dt = imu.segment(int(gt.ts[i]), int(gt.ts[j]))
        R, p, v = propagate(gt.T_w_b[i, :3, :3], gt.p_w_b[i], gt.v_w[i], g, a, dt, gt.bg[i], gt.ba[i])
        T_end = np.eye(4)
        T_end[:3, :3], T_end[:3, 3] = R, p
        est = np.stack([gt.T_w_b[i] @ T_b_c, T_end @ T_b_c])
        ref = np.stack([gt.T_w_b[i] @ T_b_c, gt.T_w_b[j] @ T_b_c])
        d = relative_drift(np.array([gt.ts[i], gt.ts[j]]), est, ref, (gt.ts[j] - gt.ts[i]) * 1e-9, 1.0)
        if len(d):
            d[:, 0] = (gt.ts[i] - t0) * 1e-9
            rows.append(d[0])
    return np.asarray(rows).reshape(-1, 5)


def _load(label: str, path: Path, seq) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from runtime.geometry import interpolate_poses
    from runtime.io.tum import read_tum

    f = path / "trajectory.txt" if path.is_dir() else path
    if not f.is_file() or f.stat().st_size == 0:
        raise FileNotFoundError(f"{f}: no trajectory for '{label}'")
    ts, T = read_tum(f)
    system = label.split(":")[0]
    if scoring.reference_frame(system) == "body":
        T = T @ np.asarray(seq.T_b_c, np.float64)
    ref, inside = interpolate_poses(ts, seq.gt.ts, seq.gt.T_w_b @ np.asarray(seq.T_b_c, np.float64))
    return np.asarray(ts, np.int64)[inside], T[inside], ref


def diagnose(seq_dir: Path, runs: dict[str, Path]) -> dict:
    """The report of every run (label -> folder or trajectory file) on the sequence ``seq_dir``, plus the
    IMU-only propagation's drift."""
    from runtime.io.euroc import read_euroc

    seq = read_euroc(seq_dir)
    t0 = int(seq.frame_ts[0])
    loaded = {k: _load(k, Path(p), seq) for k, p in runs.items()}
    common = (max(int(v[0][0]) for v in loaded.values()), min(int(v[0][-1]) for v in loaded.values()))
    out = {
        "sequence": str(seq_dir),
        "frames": len(seq),
        "path_length_m": float(np.linalg.norm(np.diff(seq.gt.p_w_b, axis=0), axis=1).sum()),
        "common_window_s": [(common[0] - t0) * 1e-9, (common[1] - t0) * 1e-9],
        "runs": {k: str(p) for k, p in runs.items()},
        "systems": {k: trajectory_report(*v, t0, common) for k, v in loaded.items()},
    }
    imu = {}
    for h in HORIZONS_S:
        d = imu_only_drift(seq, h)
        imu[f"drift_{h:g}s"] = {
            "trans_rmse_m": rmse(d[:, 1]),
            "trans_median_m": float(np.median(d[:, 1])) if len(d) else None,
            "yaw_median_deg": float(np.median(d[:, 3])) if len(d) else None,
            "tilt_median_deg": float(np.median(d[:, 4])) if len(d) else None,
        }
    out["imu_only"] = imu
    return out


def print_report(res: dict) -> None:
    print(f"{res['sequence']}: common window {res['common_window_s'][0]:.2f}-{res['common_window_s'][1]:.2f} s")
    head = f"{'run':28s} {'ATE sim3':>9s} {'common':>8s} {'scale':>7s} {'win ATE':>8s} {'win scale spread':>16s}"
    print(head + "".join(f" {'drift ' + f'{h:g}s':>11s} {'yaw':>6s}" for h in HORIZONS_S))
    for k, r in res["systems"].items():
        line = (
            f"{k:28s} {1e3 * r['ate_sim3_m']:7.1f}mm {1e3 * r['ate_sim3_common_m']:6.1f}mm {r['sim3_scale']:7.4f} "
            f"{1e3 * r['window_ate_median_m']:6.1f}mm {100 * r['window_scale_spread']:15.1f}%"
        )
        for h in HORIZONS_S:
            d = r[f"drift_{h:g}s"]
            line += f" {1e3 * d['trans_rmse_m']:9.1f}mm {d['yaw_median_deg']:6.3f}"
        print(line)
    line = f"{'IMU only (from ground truth)':28s} {'':>9s} {'':>8s} {'':>7s} {'':>8s} {'':>16s}"
    for h in HORIZONS_S:
        d = res["imu_only"][f"drift_{h:g}s"]
        line += f" {1e3 * d['trans_rmse_m']:9.1f}mm {d['yaw_median_deg']:6.3f}"
    print(line)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="bench_peers --data folder")
    ap.add_argument("--sequence", required=True)
    ap.add_argument("--run", action="append", required=True, metavar="LABEL=DIR", help="a run to diagnose")
    ap.add_argument("--out", help="JSON to write")
    a = ap.parse_args(argv)
    runs = {}
    for r in a.run:
        label, sep, path = r.partition("=")
        if not sep:
            raise SystemExit(f"diagnose: --run needs LABEL=DIR, got {r!r}")
        scoring.alignments(label.split(":")[0])  # KeyError for an unknown system
        runs[label] = Path(path)
    res = diagnose(Path(a.data) / a.sequence, runs)
    res["command"] = "python -m benchmarks.peers.diagnose " + " ".join(argv if argv is not None else sys.argv[1:])
    print_report(res)
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))
        print(f"wrote {a.out}")
    return res


if __name__ == "__main__":
    main()
