"""Keyframe selection by rotation-compensated parallax, tracked ratio and time."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass
class KeyframeConfig:
    """When a frame becomes a keyframe (any of the triggers, once ``min_interval_s`` has passed)."""

    # sparse 35 px: 1.5x frames/s at the same ATE as 18; dense 18 px: 35 cost it +9.1 +- 6.7 mm (reports/ablations.md)
    min_parallax_px: float = 35.0  # median rotation-compensated displacement since the last keyframe (sparse system)
    dense_min_parallax_px: float = 18.0  # the same trigger for the dense system (its depth codes want the keyframes)
    min_tracked_ratio: float = 0.6  # fraction of the last keyframe's tracks still tracked
    min_landmarks: int = 25  # tracked landmarks below this -> new keyframe (to triangulate more)
    max_interval_s: float = 0.5  # a keyframe at least this often (bounds the preintegration)
    min_interval_s: float = 0.09  # never two keyframes closer than this

    def for_system(self, dense: bool) -> KeyframeConfig:
        """The triggers the sparse (``dense=False``) or the dense system uses: the dense one its own parallax."""
        return replace(self, min_parallax_px=self.dense_min_parallax_px) if dense else self


def rotation_compensated_parallax(
    xn_kf: np.ndarray, xn_cur: np.ndarray, R_ccur_ckf: np.ndarray, focal: float
) -> np.ndarray:
    """Per-track parallax [px] after removing the rotation between the keyframe and the current camera.

    Args:
        xn_kf, xn_cur: (N, 2) normalised coordinates of the same tracks in the keyframe and the current frame.
        R_ccur_ckf: (3, 3) rotation from the keyframe camera to the current camera.
        focal: px.
    """
    if xn_kf.shape[0] == 0:
        return np.zeros(0)
    f = np.concatenate([xn_kf, np.ones((xn_kf.shape[0], 1))], 1) @ R_ccur_ckf.T
    z = np.where(np.abs(f[:, 2]) > 1e-6, f[:, 2], 1e-6)
    return np.linalg.norm(f[:, :2] / z[:, None] - xn_cur, axis=1) * focal


class KeyframeSelector:
    """Stateless decisions; the caller passes what it knows about the last keyframe."""

    def __init__(self, cfg: KeyframeConfig | None = None) -> None:
        self.cfg = cfg or KeyframeConfig()

    def decide(
        self,
        dt_s: float,
        n_kf_tracks: int,
        n_common: int,
        parallax_px: float,
        n_landmarks: int,
        still: bool = False,
        n_tracks: int | None = None,
    ) -> tuple[bool, str]:
        """Whether the current frame is a keyframe, and why.

        Args:
            dt_s: seconds since the last keyframe.
            n_kf_tracks: tracks the last keyframe had.
            n_common: of those, still tracked now.
            parallax_px: median rotation-compensated parallax of the common tracks.
            n_landmarks: tracked tracks that are landmarks.
            still: the sensor is at rest (only the time trigger applies).
            n_tracks: tracks in the current frame (default ``n_common``); "few landmarks" needs enough of
            them.
        """
        c = self.cfg
        n_tracks = n_common if n_tracks is None else n_tracks
        if dt_s < c.min_interval_s:
            return False, ""
        if dt_s >= c.max_interval_s:
            return True, "time"
        if still:
            return False, ""
        if parallax_px >= c.min_parallax_px:
            return True, "parallax"
        if n_kf_tracks >= c.min_landmarks and n_common < c.min_tracked_ratio * n_kf_tracks:
            return True, "tracked_ratio"
        if (
            n_landmarks < c.min_landmarks and n_tracks >= 2 * c.min_landmarks
        ):  # only if there is something to map
            return True, "few_landmarks"
        return False, ""
