"""Reader of RGB-D frame folders in the 3DMatch / tsdf-fusion layout (SUN3D fragments, RealSense captures).

A folder holds, per frame ``NNNNNN``:

* ``frame-NNNNNN.color.jpg`` (or ``.png``): RGB image,
* ``frame-NNNNNN.depth.png``: uint16 depth in **millimetres**, 0 = invalid, registered to the colour image,
* ``frame-NNNNNN.pose.txt``: 4x4 camera-to-world ``T_w_c`` (whitespace-separated rows),

and one intrinsics file, ``camera-intrinsics.txt`` or ``intrinsics.K.txt``: the 3x3 matrix ``K``.

Returned images are RGB (H, W, 3) uint8, depth (H, W) float32 metres with 0 = invalid, poses float64 4x4.

>>> folder = RgbdFolder("../shared/data/rgbd_real/realsense_box")   # doctest: +SKIP
>>> rgb, depth = folder[0]                                          # doctest: +SKIP
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

__all__ = ["INTRINSICS_FILES", "RgbdFolder", "RgbdFormatError", "read_rgbd_frame"]

#: Intrinsics file names looked for, in order.
INTRINSICS_FILES = ("camera-intrinsics.txt", "intrinsics.K.txt")
#: Depth PNG unit [m].
DEPTH_UNIT_M = 1e-3

_FRAME = re.compile(r"^frame-(\d+)\.color\.(jpg|png)$")


class RgbdFormatError(ValueError):
    """A frame folder that is missing a file or holds a malformed one; the message names the file."""


def _read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as e:
        raise RgbdFormatError(f"{path}: cannot read a {shape[0]}x{shape[1]} matrix: {e}") from e
    if m.shape != shape or not np.isfinite(m).all():
        raise RgbdFormatError(f"{path}: expected a finite {shape[0]}x{shape[1]} matrix, got shape {m.shape}")
    return m


def read_rgbd_frame(color: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One frame from its colour file: ``(rgb (H, W, 3) uint8, depth (H, W) float32 [m], T_w_c or None)``."""
    color = Path(color)
    m = _FRAME.match(color.name)
    if m is None:
        raise RgbdFormatError(f"{color}: not a frame-NNNNNN.color.jpg|png file")
    stem = color.parent / f"frame-{m.group(1)}"
    bgr = cv2.imread(str(color), cv2.IMREAD_COLOR)
    if bgr is None:
        raise RgbdFormatError(f"{color}: cannot decode the image")
    dpath = Path(f"{stem}.depth.png")
    raw = cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise RgbdFormatError(f"{dpath}: missing or not an image")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise RgbdFormatError(f"{dpath}: expected single-channel uint16 millimetres, got {raw.dtype} {raw.shape}")
    if raw.shape != bgr.shape[:2]:
        raise RgbdFormatError(f"{dpath}: depth is {raw.shape}, colour is {bgr.shape[:2]} (not registered)")
    ppath = Path(f"{stem}.pose.txt")
    pose = _read_matrix(ppath, (4, 4)) if ppath.is_file() else None
    return bgr[..., ::-1].copy(), raw.astype(np.float32) * np.float32(DEPTH_UNIT_M), pose


class RgbdFolder:
    """The frames of one folder, in frame-number order; ``folder[i] -> (rgb, depth)`` like the NYU readers.

    Attributes:
        root: the folder.
        K: (3, 3) float64 intrinsics of the colour (= depth) image.
        frames: colour file of every frame.
    """

    def __init__(self, root: str | Path, limit: int | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise RgbdFormatError(f"{self.root}: no such folder")
        frames = [p for p in self.root.iterdir() if _FRAME.match(p.name)]
        if not frames:
            raise RgbdFormatError(f"{self.root}: no frame-NNNNNN.color.jpg|png files")
        self.frames = sorted(frames, key=lambda p: int(_FRAME.match(p.name).group(1)))
        if limit is not None:
            self.frames = self.frames[: int(limit)]
        kfile = next((self.root / n for n in INTRINSICS_FILES if (self.root / n).is_file()), None)
        if kfile is None:
            raise RgbdFormatError(f"{self.root}: no intrinsics file ({' or '.join(INTRINSICS_FILES)})")
        self.K = _read_matrix(kfile, (3, 3))

    @property
    def name(self) -> str:
        return self.root.name

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        rgb, depth, _ = read_rgbd_frame(self.frames[i])
        return rgb, depth

    def pose(self, i: int) -> np.ndarray | None:
        """``T_w_c`` (4, 4) of frame ``i``, or None when the frame has no pose file."""
        m = _FRAME.match(self.frames[i].name)
        ppath = self.root / f"frame-{m.group(1)}.pose.txt"
        return _read_matrix(ppath, (4, 4)) if ppath.is_file() else None
