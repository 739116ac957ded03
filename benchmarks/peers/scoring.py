"""One scoring for every system of ``bench_peers``: the same ``evo`` call, the alignment chosen by the system's kind.

* A monocular system (no IMU) knows neither scale nor gravity, and it estimates the *camera*: its trajectory is
  aligned with Sim(3) to the camera-frame ground truth ``T_w_c = T_w_b T_b_c``.
* An inertial system estimates the *body* (IMU) pose with metric scale and gravity: aligned with SE(3) and, as a
  second row, with Sim(3), to the body-frame ground truth (EuRoC's ``state_groundtruth_estimate0``).

Both go through :func:`runtime.eval.trajectory_metrics` (the evo call ``dit-slam`` itself reports), with the
ground truth interpolated at the estimate's timestamps. Only numpy and evo: tested without the peers installed.
"""

from __future__ import annotations

import math

import numpy as np

from runtime.eval import trajectory_metrics

__all__ = ["SYSTEMS", "alignments", "reference_frame", "reference_poses", "score", "tracked_fraction", "median_range"]

#: system name -> whether it uses the IMU (the row names of ``benchmarks/results/peers.json``).
SYSTEMS = {
    "dit-slam-sparse": True,
    "dit-slam-dense": True,
    "orbslam3-mono": False,
    "orbslam3-mono-inertial": True,
    "cuvslam-mono": False,
}


def _inertial(system: str) -> bool:
    if system not in SYSTEMS:
        raise KeyError(f"unknown system '{system}' (known: {', '.join(SYSTEMS)})")
    return SYSTEMS[system]


def alignments(system: str) -> tuple[str, ...]:
    """The alignments a system is scored with: ``("se3", "sim3")`` for inertial ones, ``("sim3",)`` otherwise."""
    return ("se3", "sim3") if _inertial(system) else ("sim3",)


def reference_frame(system: str) -> str:
    """``"body"`` for inertial systems (their trajectory is ``T_w_b``), ``"camera"`` for monocular ones."""
    return "body" if _inertial(system) else "camera"


def reference_poses(gt_T_w_b: np.ndarray, T_b_c: np.ndarray, frame: str) -> np.ndarray:
    """The ground truth in ``frame``: ``T_w_b`` as given (``"body"``) or ``T_w_b @ T_b_c`` (``"camera"``)."""
    gt_T_w_b = np.asarray(gt_T_w_b, dtype=np.float64)
    if frame == "body":
        return gt_T_w_b
    if frame == "camera":
        return gt_T_w_b @ np.asarray(T_b_c, dtype=np.float64)
    raise ValueError(f"frame must be 'body' or 'camera', got {frame!r}")


def tracked_fraction(n_posed: int, n_frames: int) -> float:
    """Frames with a pose over the frames of the sequence (0 for an empty sequence)."""
    return float(n_posed) / n_frames if n_frames > 0 else 0.0


def score(
    system: str, est_ts: np.ndarray, est_T: np.ndarray, gt_ts: np.ndarray, gt_T_w_b: np.ndarray, T_b_c: np.ndarray
) -> dict[str, dict]:
    """ATE of one run: ``{alignment: {"ate_m", "scale", "eval_frames", "rpe_trans_m"}}`` for each alignment of
    ``system``. ``est_T`` are ``T_w_b`` for inertial systems and ``T_w_c`` for monocular ones; timestamps in ns.
    With fewer than 3 poses in the ground truth's span every alignment gets ``ate_m = nan``."""
    ref = reference_poses(gt_T_w_b, T_b_c, reference_frame(system))
    est_ts = np.asarray(est_ts, dtype=np.int64)
    out: dict[str, dict] = {}
    try:
        m = trajectory_metrics(est_ts, np.asarray(est_T, dtype=np.float64).reshape(-1, 4, 4), gt_ts, ref)
    except ValueError:  # too few poses inside the ground truth's span
        m = None
    for a in alignments(system):
        if m is None:
            out[a] = {"ate_m": math.nan, "scale": math.nan, "eval_frames": 0, "rpe_trans_m": math.nan}
            continue
        out[a] = {
            "ate_m": m[f"ate_{a}_rmse_m"],
            "scale": m["sim3_scale"] if a == "sim3" else 1.0,
            "eval_frames": m["eval_frames"],
            "rpe_trans_m": m["rpe_trans_rmse_m"],
        }
    return out


def median_range(values) -> tuple[float, float, float]:
    """Median, minimum and maximum of the finite values (all nan when none is finite)."""
    v = sorted(float(x) for x in values if isinstance(x, (int, float)) and math.isfinite(float(x)))
    if not v:
        return math.nan, math.nan, math.nan
    n = len(v)
    med = v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])
    return med, v[0], v[-1]
