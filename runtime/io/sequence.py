"""Open whatever a user has as one sequence: an EuRoC ASL folder or a ROS bag, with an optional calibration
folder, and fisheye lenses seen through a pinhole view.

``open_sequence`` returns an object with the attributes of :class:`runtime.io.euroc.EurocSequence` that the
runtime reads (``camera``, ``T_b_c``, ``cam_rate_hz``, ``frame_ts``, ``image(i)``, ``imu_ts``, ``gyro``,
``accel``, ``imu``, ``gt``, ``has_depth``, ``depth(i)``, ``root``).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np

from runtime.geometry import Camera
from runtime.io.bag import BagTopics, is_bag, read_bag
from runtime.io.calib import read_calibration
from runtime.io.euroc import read_euroc

log = logging.getLogger(__name__)

__all__ = ["open_sequence", "CameraView", "PinholeView", "StartView"]


class CameraView:
    """A sequence seen with another camera model (e.g. the intrinsics ``dit-slam`` refined, :mod:`runtime.calibration`)
    and, with ``time_offset_ns``, its camera's stamps moved onto the IMU's clock (the image stamped ``t`` was taken
    at ``t + time_offset_ns``); every other attribute is the wrapped sequence's (images and depth by index)."""

    def __init__(self, seq, camera: Camera, time_offset_ns: int = 0) -> None:
        self.seq = seq
        self.camera = camera
        self.time_offset_ns = int(time_offset_ns)
        if self.time_offset_ns:
            self.frame_ts = np.asarray(seq.frame_ts, dtype=np.int64) + np.int64(self.time_offset_ns)

    def __getattr__(self, name):
        return getattr(self.seq, name)

    def __len__(self) -> int:
        return len(self.seq)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.seq!r})"


class PinholeView(CameraView):
    """A fisheye sequence seen through the pinhole camera with the same ``K`` (images resampled with
    :meth:`runtime.geometry.Camera.undistort_image`; rays beyond the fisheye's image are black).

    The tracking front end and the network take pinhole (or radial-tangential) images; an equidistant lens is
    undistorted once per frame here. Every other attribute is the wrapped sequence's.
    """

    def __init__(self, seq):
        if not seq.camera.is_fisheye:
            raise ValueError(f"PinholeView is for fisheye cameras, got model {seq.camera.model!r}")
        super().__init__(seq, seq.camera.pinhole())
        self.fisheye: Camera = seq.camera

    def image(self, i: int) -> np.ndarray:
        return self.fisheye.undistort_image(self.seq.image(i))

    def depth(self, i: int) -> np.ndarray | None:
        d = self.seq.depth(i)
        return None if d is None else self.fisheye.undistort_image(d, interpolation=cv2.INTER_NEAREST)


class StartView:
    """The sequence as a recording started ``start_s`` seconds after its first frame: its frames from the first one
    stamped at or after that time, and its IMU samples from just after the last frame it leaves out (a recording
    started there has none earlier). Frames, images and depth are indexed from that frame; the ground truth stays
    whole, and every other attribute is the wrapped sequence's.

    Raises:
        ValueError: ``start_s`` negative or not finite, or leaving fewer than two frames.
    """

    def __init__(self, seq, start_s: float) -> None:
        start_s = float(start_s)
        ts = np.asarray(seq.frame_ts, dtype=np.int64)
        if not (np.isfinite(start_s) and start_s >= 0):
            raise ValueError(f"start_s={start_s:g}: expected seconds >= 0 from the sequence's first frame")
        k = int(np.searchsorted(ts, ts[0] + round(start_s * 1e9), "left")) if ts.size else 0
        if ts.size - k < 2:
            span = (ts[-1] - ts[0]) * 1e-9 if ts.size else 0.0
            raise ValueError(
                f"start_s={start_s:g}: leaves {max(ts.size - k, 0)} of the sequence's {ts.size} frames "
                f"({span:.2f} s from the first to the last); need at least 2"
            )
        self.seq, self.start_s, self.start_index = seq, start_s, k
        self.frame_ts = ts[k:]
        paths = getattr(seq, "frame_paths", None)
        if paths is not None:
            self.frame_paths = list(paths)[k:]
        imu_ts = np.asarray(seq.imu_ts, dtype=np.int64)
        j = int(np.searchsorted(imu_ts, ts[k - 1], "right")) if k > 0 else 0
        self.imu_ts, self.gyro, self.accel = imu_ts[j:], np.asarray(seq.gyro)[j:], np.asarray(seq.accel)[j:]

    def image(self, i: int) -> np.ndarray:
        return self.seq.image(self._index(i))

    def depth(self, i: int) -> np.ndarray | None:
        return self.seq.depth(self._index(i))

    def _index(self, i: int) -> int:
        i = int(i)
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range: {len(self)} frames from {self.start_s:g} s")
        return i + self.start_index

    def __getattr__(self, name):
        return getattr(self.seq, name)

    def __len__(self) -> int:
        return int(self.frame_ts.size)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.seq!r}, start_s={self.start_s:g})"


def open_sequence(
    path: str | Path,
    calib: str | Path | None = None,
    topics: BagTopics | None = None,
    pinhole_view: bool = True,
):
    """Open an ASL folder (``mav0`` inside) or a bag (``.bag`` file, ROS2 folder, ``.db3`` / ``.mcap``).

    Args:
        path: the sequence.
        calib: calibration folder (EuRoC ``sensor.yaml`` files or Kalibr's ``camchain.yaml`` + ``imu.yaml``);
            needed for a bag, and replaces an ASL folder's own ``sensor.yaml`` calibration when given.
        topics: the bag's topics (default: EuRoC's names, or the calibration's Kalibr ``rostopic``).
        pinhole_view: wrap a fisheye sequence in :class:`PinholeView` (what the SLAM system runs on).

    Raises:
        ValueError: a bag without ``calib``; the readers' format errors (naming file, key or topic).
    """
    path = Path(path).expanduser()
    if is_bag(path):
        if calib is None:
            raise ValueError(f"{path}: a bag carries no calibration; give calib=DIR (EuRoC sensor.yaml or Kalibr)")
        seq = read_bag(path, calib, topics)
    else:
        seq = read_euroc(path)
        if calib is not None:
            cal = read_calibration(calib)
            seq = dataclasses.replace(
                seq, camera=cal.camera, T_b_c=cal.T_b_c, imu=cal.imu, cam_rate_hz=cal.cam_rate_hz or seq.cam_rate_hz
            )
            if cal.time_shift_ns:
                seq.frame_ts = seq.frame_ts + np.int64(cal.time_shift_ns)
            log.info("calibration from %s", cal.source)
    if pinhole_view and seq.camera.is_fisheye:
        log.info("fisheye camera: running on its pinhole view (same K)")
        return PinholeView(seq)
    return seq
