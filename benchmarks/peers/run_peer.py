"""Run one peer on one EuRoC-layout sequence, in a process of its own (``bench_peers`` measures its CPU time).

    python -m benchmarks.peers.run_peer --system orbslam3-mono --sequence DIR --out DIR --vocab ORBVOC
    python -m benchmarks.peers.run_peer --system orbslam3-mono-inertial --sequence DIR --out DIR --vocab ORBVOC
    python -m benchmarks.peers.run_peer --system cuvslam-mono --sequence DIR --out DIR

Writes ``OUT/trajectory.txt`` (TUM, seconds; ``T_w_c`` for monocular systems, ``T_w_b`` for inertial ones, see
``benchmarks.peers.scoring``) and ``OUT/result.json`` (frames, frames with a pose, losses, resets, the wall and
CPU time of the frame loop). Frames are fed as fast as the peer takes them (no real-time pacing), images decoded
inside the loop as ``dit-slam`` does. Needs the extra ``peers`` (``pyorbslam3``, ``dim_odom``).

Timestamps given to ORB-SLAM3 are seconds since the first frame: its EuRoC trajectory writer prints
``1e9 * t`` with 6 significant digits, which erases the frame spacing of absolute (1.7e9 s) stamps. The
written trajectory is mapped back to the frames' own nanosecond stamps.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.peers.settings import cuvslam_camera, read_setup, write_orbslam3_settings


def _frames(seq: Path) -> tuple[np.ndarray, list[Path]]:
    rows = [ln.split(",") for ln in (seq / "mav0" / "cam0" / "data.csv").read_text().splitlines()]
    rows = [r for r in rows if r and r[0].strip() and not r[0].startswith("#")]
    ts = np.array([int(r[0]) for r in rows], dtype=np.int64)
    paths = [seq / "mav0" / "cam0" / "data" / r[1].strip() for r in rows]
    return ts, paths


def _imu(seq: Path) -> tuple[np.ndarray, np.ndarray]:
    """imu0 rows: ts (M,) ns and (M, 6) ``[gx, gy, gz, ax, ay, az]`` (EuRoC's column order)."""
    a = np.loadtxt(seq / "mav0" / "imu0" / "data.csv", delimiter=",", comments="#", dtype=np.float64)
    lines = (seq / "mav0" / "imu0" / "data.csv").read_text().splitlines()
    ts = np.array([int(ln.split(",", 1)[0]) for ln in lines if ln.strip() and not ln.startswith("#")], np.int64)
    return ts, a[:, 1:7]


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


def _write_tum(path: Path, ts_ns: np.ndarray, T: np.ndarray) -> None:
    with path.open("w") as f:
        for t, M in zip(ts_ns, T, strict=True):
            q = _quat_xyzw(M[:3, :3])
            p = M[:3, 3]
            f.write(f"{int(t) // 10**9}.{int(t) % 10**9:09d} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} ")
            f.write(f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


def _read_euroc_traj(path: Path, t0_ns: int, frame_ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ORB-SLAM3's ``SaveTrajectoryEuRoC`` output (``1e9*t tx ty tz qx qy qz qw``, t = our rebased seconds),
    matched to the nearest frame stamp."""
    from scipy.spatial.transform import Rotation

    if not path.is_file() or path.stat().st_size == 0:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    a = np.atleast_2d(np.loadtxt(path))
    t = t0_ns + np.round(a[:, 0]).astype(np.int64)
    j = np.clip(np.searchsorted(frame_ts, t), 1, len(frame_ts) - 1)
    j = np.where(np.abs(frame_ts[j - 1] - t) <= np.abs(frame_ts[j] - t), j - 1, j)
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, 3] = a[:, 1:4]
    T[:, :3, :3] = Rotation.from_quat(a[:, 4:8]).as_matrix()
    ts, keep = np.unique(frame_ts[j], return_index=True)
    return ts, T[keep]


def run_orbslam3(seq: Path, out: Path, inertial: bool, vocab: Path, imu_noise_scale: float, pace: float = 0.0) -> dict:
    """``pace`` > 0: at least that many wall seconds per frame (sleeping after the track call), so that ORB-SLAM3's
    local mapping and IMU initialisation threads keep up with tracking on a loaded machine."""
    import cv2
    import pyorbslam3 as pos

    settings = write_orbslam3_settings(seq, out / "orbslam3.yaml", inertial, imu_noise_scale=imu_noise_scale)
    ts, paths = _frames(seq)
    t0 = int(ts[0])
    if inertial:
        its, imu = _imu(seq)
        chunk_rows = np.column_stack([(its - t0) * 1e-9, imu])  # [t, gx, gy, gz, ax, ay, az], rebased seconds
    sensor = pos.Sensor.IMU_MONOCULAR if inertial else pos.Sensor.MONOCULAR
    slam = pos.Slam(str(vocab), str(settings), sensor, use_viewer=False)
    states: dict[str, int] = {}
    online_ts, online_T = [], []
    losses = 0
    resets = 0
    was_ok = False
    seen_ok = False
    last_imu = 0
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i, (t, p) in enumerate(zip(ts, paths, strict=True)):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(f"{p}: unreadable image")
        ts_s = (int(t) - t0) * 1e-9
        if inertial:
            k = int(np.searchsorted(its, t, side="right"))
            r = slam.track_monocular(img, ts_s, imu=chunk_rows[last_imu:k])
            last_imu = k
        else:
            r = slam.track_monocular(img, ts_s)
        if pace > 0:
            time.sleep(max(0.0, pace - (time.perf_counter() - wall0) + i * pace))
        name = str(r.state).split(".")[-1]
        states[name] = states.get(name, 0) + 1
        if r.pose_valid and r.pose_wc is not None:
            online_ts.append(int(t))
            online_T.append(np.asarray(r.pose_wc, dtype=np.float64))
        ok = name in ("OK", "OK_KLT")
        if was_ok and name == "LOST":
            losses += 1
        if seen_ok and name == "NOT_INITIALIZED" and was_ok:
            resets += 1
        if ok:
            seen_ok = True
        was_ok = ok or (was_ok and name == "RECENTLY_LOST")
    slam.shutdown()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    slam.save_trajectory_euroc(str(out / "orbslam3_euroc.txt"))
    fts, fT = _read_euroc_traj(out / "orbslam3_euroc.txt", t0, ts)
    online_T = np.asarray(online_T).reshape(-1, 4, 4)
    if inertial and len(online_T):  # pose_wc is the camera; the body (IMU) is T_w_c T_c_b
        setup = read_setup(seq)
        online_T = online_T @ np.linalg.inv(setup.T_b_c)
    _write_tum(out / "trajectory_online.txt", np.asarray(online_ts, np.int64), online_T)
    _write_tum(out / "trajectory.txt", fts, fT)
    return {
        "frames": len(ts),
        "frames_with_pose": int(len(fts)),
        "frames_with_pose_online": int(len(online_ts)),
        "states": states,
        "losses": losses,
        "resets": resets,
        "wall_s": wall,
        "cpu_s": cpu,
        "trajectory": "final (SaveTrajectoryEuRoC: frames of the largest map, after the final optimisation)",
        "imu_noise_scale": imu_noise_scale if inertial else None,
    }


def _ident_tf(parent, child):
    return ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))


def run_cuvslam(seq: Path, out: Path) -> dict:
    import cv2
    import dim_odom
    from scipy.spatial.transform import Rotation

    cam = cuvslam_camera(read_setup(seq))
    ts, paths = _frames(seq)
    # the rig frame is the camera itself (identity mount): the output is the camera's pose, T_w_c
    tracker = dim_odom.CuvslamOdometry({"camera_mode": "mono", "use_gpu": False}, tf=_ident_tf)
    K = [cam["fx"], 0.0, cam["cx"], 0.0, cam["fy"], cam["cy"], 0.0, 0.0, 1.0]
    tracker.handle_camera_info(
        dim_odom.CameraModel(int(ts[0]), "cam0", cam["width"], cam["height"], [*cam["coeffs"], 0.0], K)
    )
    est_ts, est_T = [], []
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for t, p in zip(ts, paths, strict=True):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(f"{p}: unreadable image")
        h, w = img.shape
        e = tracker.handle_image(dim_odom.ImageFrame(int(t), "cam0", w, h, "mono8", w, img.tobytes()))
        # monocular cuVSLAM answers the identity until it has initialised: those frames have no pose yet
        if e is not None and (est_ts or np.any(np.asarray(e.translation) != 0.0)):
            M = np.eye(4)
            M[:3, 3] = e.translation
            M[:3, :3] = Rotation.from_quat(e.rotation_xyzw).as_matrix()
            est_ts.append(int(t))
            est_T.append(M)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    tracker.report()
    _write_tum(out / "trajectory.txt", np.asarray(est_ts, np.int64), np.asarray(est_T).reshape(-1, 4, 4))
    return {
        "frames": len(ts),
        "frames_with_pose": len(est_ts),
        "losses": None,
        "resets": None,
        "wall_s": wall,
        "cpu_s": cpu,
        "trajectory": "online (per-frame odometry, use_gpu=False)",
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--system", required=True, choices=["orbslam3-mono", "orbslam3-mono-inertial", "cuvslam-mono"])
    ap.add_argument("--sequence", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--vocab", help="ORB vocabulary (DBoW2 text) for ORB-SLAM3")
    ap.add_argument("--imu-noise-scale", type=float, default=1.0)
    ap.add_argument("--pace", type=float, default=0.0, help="ORB-SLAM3: minimum wall seconds per frame (0: none)")
    a = ap.parse_args(argv)
    seq, out = Path(a.sequence), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if a.system.startswith("orbslam3"):
        if not a.vocab or not Path(a.vocab).is_file():
            raise SystemExit(f"run_peer: --vocab must name an ORB vocabulary file, got {a.vocab!r}")
        res = run_orbslam3(seq, out, a.system.endswith("inertial"), Path(a.vocab), a.imu_noise_scale, a.pace)
        res["pace_s"] = a.pace
    else:
        res = run_cuvslam(seq, out)
    res["system"] = a.system
    (out / "result.json").write_text(json.dumps(res, indent=2))
    print(json.dumps(res), flush=True)
    return res


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
