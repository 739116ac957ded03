"""Warnings for camera images that look wrong: almost black, saturated, or a suspicious bit depth.

The reader (:mod:`runtime.io.euroc`) converts every image to 8-bit grey with OpenCV, which keeps the high byte
of a 16-bit PNG: 12-bit data stored in 16-bit PNGs (values below 4096) then reads as almost black, and the
system runs without visual constraints. :class:`ImageCheck` looks at a sample of the frames and says so once
per kind of problem (logged at WARNING and kept in ``metrics.json``'s ``image_warnings``).

>>> import numpy as np
>>> chk = ImageCheck()
>>> chk.look(0, np.full((48, 64), 2, np.uint8))[0].split(":")[0]
'frame 0'
>>> chk.kinds()
['dark']
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

DARK_P99 = 12  # grey levels: the 99th percentile below this is an almost black image
SATURATED_FRACTION = 0.5  # more pixels than this at 255: saturated
EVERY = 20  # look at every EVERY-th frame (and the first)
BIT12_MAX = 4096  # a 16-bit image whose maximum is below this holds at most 12-bit data


class ImageCheck:
    """Looks at every ``EVERY``-th image; each kind of problem is reported once (``warnings``)."""

    def __init__(self) -> None:
        self.warnings: list[str] = []
        self._seen: set[str] = set()

    def kinds(self) -> list[str]:
        return sorted(self._seen)

    def _warn(self, kind: str, msg: str) -> list[str]:
        if kind in self._seen:
            return []
        self._seen.add(kind)
        self.warnings.append(msg)
        log.warning("%s", msg)
        return [msg]

    def look(self, i: int, img: np.ndarray, seq=None) -> list[str]:
        """Check frame ``i``'s decoded 8-bit image (and, for the first frame, the file's bit depth).

        Returns:
            The new warnings (empty when the image looks fine or the problem was reported before).
        """
        if i % EVERY:
            return []
        out: list[str] = []
        if i == 0 and seq is not None:
            out += self._bit_depth(seq)
        a = np.asarray(img)
        if a.size == 0:
            return out
        p99 = float(np.percentile(a, 99))
        if p99 < DARK_P99:
            out += self._warn(
                "dark",
                f"frame {i}: the image is almost black (99th percentile {p99:.0f} of 255): no features can be "
                "tracked; check the exposure or the bit depth of the images",
            )
        sat = float(np.mean(a >= 255))
        if sat > SATURATED_FRACTION:
            out += self._warn("saturated", f"frame {i}: {100 * sat:.0f}% of the pixels are saturated (255)")
        return out

    def _bit_depth(self, seq) -> list[str]:
        paths = getattr(seq, "frame_paths", None)
        if not paths:
            return []
        import cv2

        path = Path(paths[0])
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16:
            return []
        mx = int(raw.max())
        if mx < BIT12_MAX:
            return self._warn(
                "bit_depth",
                f"{path}: 16-bit PNG whose maximum is {mx} (< {BIT12_MAX}: 12-bit or less data?); it reads as "
                f"8-bit with a maximum of {mx >> 8}: rescale the images to the full 16-bit range",
            )
        return []
