"""The IMU-only coast of a ``whitewall`` sequence: what it allows, and where a run's ATE comes from.

While the camera sees nothing but the bare wall, a monocular system has only the IMU between two visual fixes.

* :func:`oracle_coast` smooths keyframe states over the coast with GTSAM (``CombinedImuFactor`` on the
  sequence's IMU) between exact end states, optionally with an exact camera-to-wall distance at every keyframe
  (:func:`wall_distance_factor`): a bound on what any system can do there.
* :func:`run_segments` splits a run's ATE into the parts before, over and after the coast, and measures how
  far apart the two sides' own alignments put the relocalised pose.

``benchmarks/bench_coast.py`` drives both over a set of runs and prints the tables. Never imports torch.
"""

from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from runtime.backend.factors import custom_factor
from runtime.backend.imu import ImuStream, integrate, make_bias, preintegration_params
from runtime.eval import interpolate_poses
from runtime.geometry import from_pose3, ns_to_s, rotation_angle, skew, to_pose3
from runtime.io.euroc import read_euroc
from runtime.io.tum import read_tum
from runtime.render import align_se3

__all__ = ["ORACLES", "coast_interval", "oracle_coast", "wall_distance_factor", "run_segments", "coast_row"]

#: The oracles of :func:`oracle_coast`: the exact end pose (what a relocalisation's PnP gives), pose and
#: velocity (what the tracking after it gives), and the latter with a perfect wall-distance sensor added.
ORACLES = ("end pose", "end pose+vel", "+ wall distance")


def coast_interval(seq_root: Path, sparse_run: Path | None, widen: float) -> tuple[int, int, str]:
    """(t_lost, t_regained) [ns] of the blank stretch and where it came from.

    From the longest "visual tracking lost" / "regained" pair of events in ``sparse_run``'s ``metrics.json``;
    without one, the sequence's white-wall hold (``sim_info.json``) widened by ``widen`` seconds.
    """
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
    gt = seq.gt
    n = max(2, int(round(ns_to_s(t1 - t0) / dt_kf)) + 1)
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
    graph.add(gtsam.PriorFactorPose3(X(0), to_pose3(T[0]), tight(6, 1e-3)))
    graph.add(gtsam.PriorFactorVector(V(0), v[0], tight(3, 1e-3)))
    graph.add(gtsam.PriorFactorConstantBias(B(0), make_bias(bias0), tight(6, 1e-4)))
    graph.add(gtsam.PriorFactorPose3(X(n - 1), to_pose3(T[-1]), tight(6, 1e-3)))
    if mode != "end pose":
        graph.add(gtsam.PriorFactorVector(V(n - 1), v[-1], tight(3, 1e-3)))
    for k in range(n - 1):
        pim = gtsam.PreintegratedCombinedMeasurements(params, make_bias(bias0))
        integrate(pim, *imu.segment(int(ts[k]), int(ts[k + 1])))
        graph.add(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim))
    if mode == "+ wall distance":
        t_b_c = seq.T_b_c[:3, 3]
        for k in range(1, n - 1):
            distance = wall_x - (T[k][:3, :3] @ t_b_c + T[k][:3, 3])[0]
            graph.add(wall_distance_factor(X(k), distance, wall_x, t_b_c))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    return np.array([from_pose3(result.atPose3(X(k)))[:3, 3] - T[k][:3, 3] for k in range(n)])


def wall_distance_factor(key, distance: float, wall_x: float, t_b_c: np.ndarray, sigma: float = 0.01):
    """Measured camera-to-wall distance ``wall_x - x(p_w_c)`` [m] for the pose ``T_w_b`` at ``key`` (one row).

    Args:
        key: the ``X(k)`` key (Pose3 ``T_w_b``).
        distance: the measurement [m]; wall_x: the wall, the plane ``x = wall_x`` of the world [m].
        t_b_c: (3,) camera position in the body frame [m]; sigma: the measurement's sigma [m].
    """

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
    row = {"seed": seed, "t0_s": ns_to_s(t0 - seq.gt.ts[0]), "t1_s": ns_to_s(t1 - seq.gt.ts[0]), "source": source}
    for mode in ORACLES:
        e = oracle_coast(seq, t0, t1, mode, dt_kf, wall_x)
        row[mode] = float(np.sqrt(np.mean(np.sum(e**2, 1))))
        row[f"{mode} per axis"] = np.sqrt(np.mean(e**2, 0)).tolist()
    row["runs"] = {m: run_segments(seq, d, t0, t1) for m, d in runs.items() if (d / "trajectory.txt").is_file()}
    return row
