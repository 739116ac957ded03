"""The time offsets between a sequence's camera and its ground truth, from the motion the images show.

``dit-sim imu`` synthesises the IMU from the ground truth, so the IMU runs on the ground truth's clock. When the
recording's camera and ground truth disagree by ``d`` (an image stamped ``t`` was taken when the ground truth
reads ``t + d``), the completed sequence carries a camera-IMU offset that the source's real IMU may not have had.
This module measures it; ``benchmarks/bench_time_offset.py`` reports it for a sequence. ``dit-sim imu`` does not
apply it: on MH_05, putting the ground truth on the camera clock did not lower the ATE (reports/ablations.md).

Rotation and position are estimated separately: a recorded ground truth can fuse sources with different delays
(MH_05's positions come from a laser tracker). Between images the camera's relative motion is taken from tracked
corners (KLT, undistorted, essential matrix with RANSAC). The rotation offset compares the images' relative
rotations (consecutive images, carried into the body frame with the camera's extrinsic rotation) with the ground
truth's over the same interval shifted by ``d``; the position offset compares the direction of the camera's motion
(images two apart) with the ground truth's displacement shifted by ``d``, its rotations at the image times. Each
offset minimises the trimmed mean (80 %) of the angles over a 2 ms grid, refined by a least-squares parabola near
the best point.

Measured (``python benchmarks/bench_time_offset.py``): realistic synthetic ``flight`` seed 0, camera and ground
truth consistent by construction: rotation +1.8 ms, position -4.5 ms; the same with its positions delayed by
20 ms: position +15.5 ms (moved by 20.0 ms). MH_05 excerpt: rotation -0.1 ms, position +17.7 ms.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from runtime.geometry import Camera
from runtime.io.euroc import _imread


@dataclass
class OffsetEstimate:
    """``offset_s``: ground-truth time minus camera time of the same instant; ``pairs`` image pairs used;
    ``residual_deg`` the trimmed mean (80 %) of the pairs' angles (rotation disagreement, or motion-direction angle)
    at the offset, ``residual_zero_deg`` at zero."""

    offset_s: float
    pairs: int
    residual_deg: float
    residual_zero_deg: float

    def as_dict(self) -> dict:
        return {
            "offset_s": round(self.offset_s, 5),
            "pairs": self.pairs,
            "residual_deg": round(self.residual_deg, 4),
            "residual_zero_deg": round(self.residual_zero_deg, 4),
        }


@dataclass
class RelativeMotions:
    """Camera motion between images ``idx`` and ``idx + step``: rotation ``R_c1_c2`` (K, 3, 3) and the unit
    direction ``t_c1`` (K, 3) of the second camera's centre in the first camera's frame."""

    idx: np.ndarray
    step: int
    R_c1_c2: np.ndarray
    t_c1: np.ndarray


def relative_motions(
    imgs: list[np.ndarray], camera: Camera, step: int = 1, max_corners: int = 400, min_inliers: int = 30
) -> RelativeMotions:
    """Relative camera motions between grey images ``step`` apart (KLT corners, undistorted, essential matrix
    with RANSAC); pairs with fewer than ``min_inliers`` inliers are left out."""
    Rs, ts, idx = [], [], []
    for i in range(len(imgs) - step):
        a, b = imgs[i], imgs[i + step]
        p0 = cv2.goodFeaturesToTrack(a, max_corners, 0.01, 10)
        if p0 is None or len(p0) < min_inliers:
            continue
        p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(21, 21), maxLevel=3)
        ok = st.ravel() == 1
        if ok.sum() < min_inliers:
            continue
        x0 = camera.pixel_to_normalized(p0.reshape(-1, 2)[ok])
        x1 = camera.pixel_to_normalized(p1.reshape(-1, 2)[ok])
        E, inl = cv2.findEssentialMat(x0, x1, np.eye(3), cv2.RANSAC, 0.999, 0.5 / camera.fx)
        if E is None or E.shape != (3, 3) or int(inl.sum()) < min_inliers:
            continue
        _, R, t, _ = cv2.recoverPose(E, x0, x1, np.eye(3), mask=inl.copy())
        Rs.append(R.T)  # recoverPose: x_c2 = R x_c1 + t, so R_c1_c2 = R^T
        ts.append((-R.T @ t).ravel())  # the second centre in the first frame, unit length
        idx.append(i)
    return RelativeMotions(
        np.array(idx, dtype=np.int64), step, np.array(Rs).reshape(-1, 3, 3), np.array(ts).reshape(-1, 3)
    )


def _minimise(cost: Callable[[float], float], max_s: float, step_s: float, half_width_s: float) -> float:
    """The minimiser of ``cost`` on a grid over ``[-max_s, max_s]``, refined by the vertex of a least-squares
    parabola through the grid points within ``half_width_s`` of the best one."""
    grid = np.arange(-max_s, max_s + 0.5 * step_s, step_s)
    c = np.array([cost(d) for d in grid])
    k = int(np.argmin(c))
    near = np.abs(grid - grid[k]) <= half_width_s + 1e-12
    a2, a1, _ = np.polyfit(grid[near] - grid[k], c[near], 2)
    best = float(grid[k])
    if a2 > 0:
        best += float(np.clip(-a1 / (2 * a2), -half_width_s, half_width_s))
    return best


def _trimmed_mean(x: np.ndarray, keep: float = 0.8) -> float:
    """Mean of the smallest ``keep`` fraction (the essential matrix's rare wrong solutions left out)."""
    x = np.sort(np.asarray(x))
    return float(x[: max(1, int(keep * x.size))].mean())


def rotation_offset(
    t_s: np.ndarray,
    mo: RelativeMotions,
    R_b_c: np.ndarray,
    rotation: Callable[[np.ndarray], np.ndarray],
    max_s: float = 0.1,
) -> OffsetEstimate:
    """The offset ``d`` for which the ground truth's rotation ``rotation(t + d)`` ((N, 3, 3) ``R_w_b``) best
    explains the images' relative rotations; ``t_s`` (N,) are the image times."""
    if mo.idx.size < 10:
        raise ValueError(f"{mo.idx.size} image pairs with a motion: too few to estimate a time offset")
    R_b = R_b_c @ mo.R_c1_c2 @ R_b_c.T
    t1, t2 = t_s[mo.idx], t_s[mo.idx + mo.step]

    def cost(d: float) -> float:
        R_gt = np.swapaxes(rotation(t1 + d), -1, -2) @ rotation(t2 + d)
        dR = np.swapaxes(R_gt, -1, -2) @ R_b
        cos = np.clip((np.trace(dR, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
        return _trimmed_mean(np.degrees(np.arccos(cos)))

    best = _minimise(cost, max_s, 0.002, 0.01)
    return OffsetEstimate(best, int(mo.idx.size), cost(best), cost(0.0))


def position_offset(
    t_s: np.ndarray,
    mo: RelativeMotions,
    T_b_c: np.ndarray,
    rotation: Callable[[np.ndarray], np.ndarray],
    position: Callable[[np.ndarray], np.ndarray],
    max_s: float = 0.1,
) -> OffsetEstimate:
    """The offset ``d`` for which the ground truth's positions ``position(t + d)`` (N, 3), with its rotations at
    the image times, best explain the directions of the camera's motion between images."""
    if mo.idx.size < 10:
        raise ValueError(f"{mo.idx.size} image pairs with a motion: too few to estimate a time offset")
    t1, t2 = t_s[mo.idx], t_s[mo.idx + mo.step]
    R1, R2 = rotation(t1), rotation(t2)
    R_bc, p_bc = T_b_c[:3, :3], T_b_c[:3, 3]
    R_w_c1 = R1 @ R_bc

    def cost(d: float) -> float:
        c1 = position(t1 + d) + R1 @ p_bc
        c2 = position(t2 + d) + R2 @ p_bc
        dc = np.einsum("nji,nj->ni", R_w_c1, c2 - c1)
        dc /= np.maximum(np.linalg.norm(dc, axis=1, keepdims=True), 1e-12)
        return _trimmed_mean(np.degrees(np.arccos(np.clip(np.sum(dc * mo.t_c1, 1), -1.0, 1.0))))

    best = _minimise(cost, max_s, 0.002, 0.02)
    return OffsetEstimate(best, int(mo.idx.size), cost(best), cost(0.0))


def estimate_time_offsets(
    images: list[Path],
    frame_ts_ns: np.ndarray,
    camera: Camera,
    T_b_c: np.ndarray,
    rotation: Callable[[np.ndarray], np.ndarray],
    position: Callable[[np.ndarray], np.ndarray],
    t0_ns: int,
    max_s: float = 0.1,
) -> dict[str, OffsetEstimate]:
    """The ground truth's rotation and position offsets to the camera clock (module docstring).

    Args:
        images: image files in time order; frame_ts_ns: their timestamps (ns).
        camera: the camera model (distortion included); T_b_c: (4, 4) camera-to-body.
        rotation, position: the ground truth's ``R_w_b`` (N, 3, 3) and ``p_w_b`` (N, 3) at times [s] after
            ``t0_ns``.
        max_s: the largest offset searched (either sign).

    Returns:
        ``{"rotation": ..., "position": ...}``: the ground truth read at ``t + offset`` matches image time ``t``.
    """
    T_b_c = np.asarray(T_b_c, np.float64)
    t_s = (np.asarray(frame_ts_ns, np.int64) - int(t0_ns)) * 1e-9
    imgs = [_imread(p, cv2.IMREAD_GRAYSCALE) for p in images]
    rot = rotation_offset(t_s, relative_motions(imgs, camera, step=1), T_b_c[:3, :3], rotation, max_s)
    pos = position_offset(t_s, relative_motions(imgs, camera, step=2), T_b_c, rotation, position, max_s)
    return {"rotation": rot, "position": pos}
