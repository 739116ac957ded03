"""Trajectory evaluation with ``evo`` (ATE after SE(3) / Sim(3) alignment, RPE) and the top-view plot.

The ground truth is interpolated at the estimate's timestamps (linear position, slerp rotation), so estimates
and
reference pair exactly; ``evo`` then aligns (Umeyama) and computes the statistics. Both trajectories are body
poses ``T_w_b`` (EuRoC's ground truth is the body/IMU frame).
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np

from runtime.geometry import interpolate_poses, ns_to_s

log = logging.getLogger(__name__)

MAX_TUM_SECONDS = 1e11  # a TUM time beyond this (year 5138) is not seconds: nanoseconds written as seconds?
OFFSET_WARN_S = 0.02  # a best time offset at least this large (and clearly better) is reported as a warning
SCALE_PIECE_S = 5.0  # [s] pieces of the trajectory whose Sim(3) scale is reported (scale drift)
SCALE_MIN_SPREAD_M = 0.1  # [m] a piece whose true positions spread less than this gets no scale (ill-defined)


def _traj(ts_ns: np.ndarray, T: np.ndarray):
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(poses_se3=list(np.asarray(T, dtype=np.float64)), timestamps=ns_to_s(np.asarray(ts_ns)))


def trajectory_metrics(
    est_ts: np.ndarray,
    est_T: np.ndarray,
    gt_ts: np.ndarray,
    gt_T: np.ndarray,
    rpe_delta_s: float = 1.0,
    return_aligned: bool = False,
) -> dict:
    """ATE (SE(3) and Sim(3) alignment) and RPE of an estimate against ground truth, computed by ``evo``.

    Args:
        est_ts: (N,) ns; est_T: (N, 4, 4) estimated ``T_w_b``.
        gt_ts: (K,) ns; gt_T: (K, 4, 4) ground-truth ``T_w_b``.
        rpe_delta_s: RPE pair spacing [s] (converted to frames at the estimate's median rate).
        return_aligned: add ``"aligned_se3"``: (N', 3) SE(3)-aligned estimate positions (N' evaluated frames).

    Returns:
        ``{"ate_se3_rmse_m", "ate_se3_mean_m", "ate_se3_max_m", "ate_sim3_rmse_m", "sim3_scale",
        "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "rpe_delta_frames", "eval_frames", "path_length_m"}``.
    """
    from evo.core import metrics

    est_ts = np.asarray(est_ts, dtype=np.int64)
    est_T = np.asarray(est_T, dtype=np.float64)
    if est_T.shape != (est_ts.size, 4, 4):
        raise ValueError(f"estimate has {est_ts.size} timestamps but poses of shape {est_T.shape}")
    ref_T, inside = interpolate_poses(est_ts, gt_ts, gt_T)
    if inside.sum() < 3:
        span = f"{ns_to_s(est_ts[0]):.3f}..{ns_to_s(est_ts[-1]):.3f} s" if est_ts.size else "empty"
        raise ValueError(
            f"only {int(inside.sum())} estimated poses lie within the ground truth's time range (estimate "
            f"{span}, ground truth {ns_to_s(gt_ts[0]):.3f}..{ns_to_s(gt_ts[-1]):.3f} s; same clock and unit?)"
        )
    ts = est_ts[inside]
    est = _traj(ts, est_T[inside])
    ref = _traj(ts, ref_T[inside])
    out: dict = {"eval_frames": int(ts.size), "path_length_m": float(ref.path_length)}

    est_se3 = copy.deepcopy(est)
    est_se3.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_se3))
    st = ape.get_all_statistics()
    out.update(
        ate_se3_rmse_m=st["rmse"],
        ate_se3_mean_m=st["mean"],
        ate_se3_median_m=st["median"],
        ate_se3_max_m=st["max"],
    )

    est_sim3 = copy.deepcopy(est)
    _, _, s = est_sim3.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_sim3))
    out.update(ate_sim3_rmse_m=ape.get_statistic(metrics.StatisticsType.rmse), sim3_scale=float(s))

    rate = 1.0 / np.median(ns_to_s(np.diff(ts))) if ts.size > 1 else 1.0
    delta = max(1, int(round(rpe_delta_s * rate)))
    out["rpe_delta_frames"] = delta
    if ts.size > delta + 1:
        rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta, metrics.Unit.frames, all_pairs=True)
        rpe_t.process_data((ref, est))
        rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta, metrics.Unit.frames, all_pairs=True)
        rpe_r.process_data((ref, est))
        out.update(
            rpe_trans_rmse_m=rpe_t.get_statistic(metrics.StatisticsType.rmse),
            rpe_rot_rmse_deg=rpe_r.get_statistic(metrics.StatisticsType.rmse),
        )
    else:
        out.update(rpe_trans_rmse_m=float("nan"), rpe_rot_rmse_deg=float("nan"))
    out = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in out.items()}
    out["scale_by_piece"] = scale_by_piece(ts, np.asarray(est.positions_xyz), np.asarray(ref.positions_xyz))
    if return_aligned:
        out["aligned_se3"] = np.asarray(est_se3.positions_xyz)
        out["reference"] = np.asarray(ref.positions_xyz)
    return out


def scale_by_piece(
    ts_ns: np.ndarray, est_xyz: np.ndarray, ref_xyz: np.ndarray, piece_s: float = SCALE_PIECE_S
) -> list[float | None]:
    """The Sim(3) scale of each ``piece_s`` piece of a trajectory, each piece aligned alone (truth = scale x
    estimate, as ``sim3_scale``): a monocular system's scale drift, which one scale for the whole run hides.

    On MH_05 the runs that end 2-3 % long are 5-8 % long over their first 5 s and near 1 after 20 s
    (reports/ablations.md). A piece with fewer than 3 poses, whose true positions spread less than
    ``SCALE_MIN_SPREAD_M`` (RMS about their mean; a hover), or whose alignment is degenerate (a straight line, or
    an estimate that does not move: evo's Umeyama refuses a cross-covariance of rank under 2), gets None.

    Args:
        ts_ns: (N,) ns; est_xyz, ref_xyz: (N, 3) estimated and true positions at those times.

    Returns:
        One scale per piece from the first stamp on, in time order.
    """
    from evo.core.geometry import GeometryException, umeyama_alignment

    t = ns_to_s(np.asarray(ts_ns, np.int64) - int(ts_ns[0])) if len(ts_ns) else np.zeros(0)
    out: list[float | None] = []
    for k in range(int(np.ceil((t[-1] + 1e-9) / piece_s)) if t.size else 0):
        m = (t >= k * piece_s) & (t < (k + 1) * piece_s)
        ref = ref_xyz[m]
        if m.sum() < 3 or np.sqrt(np.mean(np.sum((ref - ref.mean(0)) ** 2, 1))) < SCALE_MIN_SPREAD_M:
            out.append(None)
            continue
        try:
            _, _, c = umeyama_alignment(est_xyz[m].T, ref.T, with_scale=True)
        except GeometryException:
            out.append(None)
            continue
        out.append(round(float(c), 4) if np.isfinite(c) else None)
    return out


def plot_top_view(
    path: str | Path,
    est_ts: np.ndarray,
    est_T: np.ndarray,
    gt_ts: np.ndarray | None,
    gt_T: np.ndarray | None,
    title: str = "",
    imu_only: np.ndarray | None = None,
) -> Path:
    """Top view (x-y) of the estimate (SE(3)-aligned to the ground truth when given) and the ground truth;
    ``imu_only`` (N,) bool marks the poses that rest on the IMU alone (``frames.csv``: coasting, building, no image,
    before a start), drawn as orange dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=110)
    est_p = np.asarray(est_T)[:, :3, 3]
    label = "estimate"
    if gt_T is not None and len(gt_ts) > 1:
        ax.plot(gt_T[:, 0, 3], gt_T[:, 1, 3], "k-", lw=1.2, label="ground truth")
        try:
            m = trajectory_metrics(est_ts, est_T, gt_ts, gt_T, return_aligned=True)
            est_p = m["aligned_se3"]
            label = f"estimate (SE3-aligned, ATE {100 * m['ate_se3_rmse_m']:.1f} cm)"
        except ValueError as e:
            log.warning("plot: no alignment (%s)", e)
    ax.plot(est_p[:, 0], est_p[:, 1], "-", color="tab:red", lw=1.0, label=label)
    ax.plot(est_p[:1, 0], est_p[:1, 1], "o", color="tab:red", ms=4)
    if imu_only is not None:
        imu_only = np.asarray(imu_only, dtype=bool)
        if imu_only.shape != (len(est_p),):
            raise ValueError(f"imu_only has shape {imu_only.shape}, the estimate {len(est_p)} poses")
        if imu_only.any():
            n = int(imu_only.sum())
            ax.plot(*est_p[imu_only, :2].T, ".", color="tab:orange", ms=3, label=f"IMU alone ({n} poses)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def load_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM file, an EuRoC ``state_groundtruth_estimate0/data.csv`` or sequence folder -> (ts, T)."""
    from runtime.io.euroc import read_groundtruth
    from runtime.io.tum import read_tum

    p = Path(path)
    if p.is_dir():
        for cand in (
            p / "mav0" / "state_groundtruth_estimate0" / "data.csv",
            p / "state_groundtruth_estimate0" / "data.csv",
            p / "data.csv",
        ):
            if cand.is_file():
                gt = read_groundtruth(cand)
                return gt.ts, gt.T_w_b
        raise FileNotFoundError(f"{p}: no state_groundtruth_estimate0/data.csv inside")
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such trajectory file")
    if p.suffix == ".csv":
        gt = read_groundtruth(p)
        return gt.ts, gt.T_w_b
    _check_tum_seconds(p)
    return read_tum(p)


def _check_tum_seconds(p: Path) -> None:
    """Refuse a TUM file whose first timestamp cannot be seconds (e.g. EuRoC nanoseconds)."""
    with open(p) as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                t = float(line.replace(",", " ").split()[0])
            except ValueError:
                return  # the reader names the bad line
            if abs(t) > MAX_TUM_SECONDS:
                raise ValueError(
                    f"{p}:{n}: timestamp {line.split()[0]} is not in seconds (nanoseconds?); TUM files hold "
                    "seconds: divide the first column by 1e9"
                )
            return


def _umeyama_rmse(a: np.ndarray, b: np.ndarray) -> float:
    """RMSE of positions ``a`` (N, 3) after the best rigid (SE(3)) alignment onto ``b`` (N, 3)."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((b - cb).T @ (a - ca))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    return float(np.sqrt(np.mean(np.sum((b - (a - ca) @ R.T - cb) ** 2, 1))))


def best_time_offset(
    est_ts: np.ndarray, est_T: np.ndarray, gt_ts: np.ndarray, gt_T: np.ndarray, max_s: float = 1.0
) -> dict:
    """The time offset ``d`` [s] for which the estimate at ``t`` best matches the ground truth at ``t + d``.

    Searches ``|d| <= max_s`` on a 20 ms grid, then 2 ms around the best, by the SE(3)-aligned position RMSE.

    Returns:
        ``{"time_offset_s", "ate_se3_rmse_at_offset_m", "ate_se3_rmse_at_zero_m"}``, or ``{}`` when fewer than
        3 poses overlap the ground truth.
    """
    est_ts = np.asarray(est_ts, np.int64)
    p_est = np.asarray(est_T, np.float64)[:, :3, 3]

    def rmse(d: float) -> float:
        ref, inside = interpolate_poses(est_ts + int(round(d * 1e9)), gt_ts, gt_T)
        return _umeyama_rmse(p_est[inside], ref[inside, :3, 3]) if inside.sum() >= 3 else float("inf")

    zero = rmse(0.0)
    if not np.isfinite(zero):
        return {}
    grid = np.arange(-max_s, max_s + 1e-9, 0.02)
    best = float(grid[int(np.argmin([rmse(d) for d in grid]))])
    fine = np.arange(best - 0.02, best + 0.02 + 1e-9, 0.002)
    errs = [rmse(d) for d in fine]
    best = float(fine[int(np.argmin(errs))])
    return {
        "time_offset_s": round(best, 4),
        "ate_se3_rmse_at_offset_m": float(min(errs)),
        "ate_se3_rmse_at_zero_m": zero,
    }


def evaluation_warnings(m: dict, n_est: int) -> list[str]:
    """Warnings for metrics ``m`` of an estimate of ``n_est`` poses: dropped poses, a time offset."""
    out = []
    dropped = n_est - int(m.get("eval_frames", n_est))
    if dropped:
        out.append(
            f"{dropped} of {n_est} estimated poses lie outside the ground truth's time range and were not evaluated"
        )
    d = m.get("time_offset_s")
    if d is not None and abs(d) >= OFFSET_WARN_S and m["ate_se3_rmse_at_offset_m"] < 0.8 * m["ate_se3_rmse_at_zero_m"]:
        out.append(
            f"the estimate matches the ground truth best {d:+.3f} s later (ATE {m['ate_se3_rmse_at_offset_m']:.4f} m "
            f"there against {m['ate_se3_rmse_at_zero_m']:.4f} m): are the clocks offset?"
        )
    return out
