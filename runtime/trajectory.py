"""Per-frame records of the SLAM system and the trajectory of every frame filled in from the keyframes.

Only keyframes are optimised; a frame between keyframes keeps its pose relative to its reference keyframe (as
DROID-SLAM's ``PoseTrajectoryFiller`` does), composed with that keyframe's final estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.geometry import blend_poses, inv_T


@dataclass
class FrameRecord:
    """What the system decided for one frame after initialisation."""

    ts: int
    frame_idx: int
    ref_kf: int  # keyframe the pose is stored relative to
    T_rel: np.ndarray  # (4, 4) T_kf_b: pose relative to the reference keyframe at the time
    T_online: np.ndarray  # (4, 4) causal estimate T_w_b
    is_kf: bool
    status: str  # tracking | coasting | building | no_image | still | init | imu_backfill (see :func:`frame_status`)
    T_created: np.ndarray | None = None  # keyframes: the pose they entered the window with (before LM)
    segment: int = 0  # trajectory segment: a new one (in a new frame) after each re-initialisation from scratch
    imu_s: float = 0.0  # imu_backfill: seconds of IMU integrated back from the start's first posed frame


#: statuses whose pose comes from the IMU alone
IMU_ONLY = ("coasting", "building", "no_image", "imu_backfill")


def frame_status(records: list[FrameRecord]) -> tuple[list[str], np.ndarray]:
    """Each record's status and the seconds its pose rests on the IMU alone (in the records' order).

    ``tracking``, ``still`` (at rest), ``init`` (posed by the start's own window): 0. ``coasting`` (too few tracked
    landmarks), ``building`` (after a start, before visual tracking is acquired) and ``no_image``: the time since the
    last frame with a visual pose. ``imu_backfill``: a frame kept from before the start (or a restart's window), posed
    by integrating the IMU back from the start's first posed frame; the time to it."""
    status = [r.status for r in records]
    imu_s = np.zeros(len(records))
    last_visual = None
    for i, r in enumerate(records):
        if r.status == "imu_backfill":
            imu_s[i] = r.imu_s
        elif r.status in IMU_ONLY:
            imu_s[i] = (r.ts - last_visual) * 1e-9 if last_visual is not None else 0.0
        else:
            last_visual = r.ts
    return status, imu_s


def fill_trajectory(records: list[FrameRecord], history: dict, mode: str = "refined") -> tuple[np.ndarray, np.ndarray]:
    """Poses of every recorded frame: ts (N,) ns, T_w_b (N, 4, 4).

    ``refined``: keyframes take their final estimates (``history``: ``kf_id -> (ts, T_w_b)``); a frame between
    keyframes ``a`` and ``b`` takes its pose relative to each (as estimated online) composed with their final
    estimates, blended by time (position linearly, rotation by slerp), so the trajectory stays continuous across
    keyframes even where the window later moved them (a relocalisation's correction, a coasted stretch).
    ``online``: the estimates as they were when each frame was processed.
    """
    ts = np.array([r.ts for r in records], dtype=np.int64)
    if mode == "online":
        return ts, np.array([r.T_online for r in records]).reshape(-1, 4, 4)
    kf_recs = [r for r in records if r.is_kf and r.ref_kf in history]
    kf_ts = np.array([r.ts for r in kf_recs], dtype=np.int64)
    out = []
    for r in records:
        if r.ref_kf not in history:
            out.append(r.T_online)
            continue
        T_a = history[r.ref_kf][1] @ r.T_rel
        i = int(np.searchsorted(kf_ts, r.ts, "right"))
        nb = kf_recs[i] if i < len(kf_recs) else None
        if r.is_kf or nb is None or nb.T_created is None:
            out.append(T_a)
            continue
        T_b = history[nb.ref_kf][1] @ inv_T(nb.T_created) @ r.T_online
        t_a = history[r.ref_kf][0]
        out.append(blend_poses(T_a, T_b, float(np.clip((r.ts - t_a) / max(nb.ts - t_a, 1), 0.0, 1.0))))
    return ts, np.array(out).reshape(-1, 4, 4)
