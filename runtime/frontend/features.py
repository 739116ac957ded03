"""Corner detection spread over the image by grid bucketing.

Three detectors are offered (``fast``, ``gftt`` = Shi-Tomasi, ``orb``); ``benchmarks/bench_slam.py --detectors``
measures their time and track quality (figures in ``reports/ablations.md``); FAST is the default, the cheapest
with the longest tracks. Its threshold is absolute, so a bare wall's sensor noise yields no corners (GFTT's
quality level is relative to the image's best corner and needs the ``min_eig`` floor for that). Detection runs on
the raw (distorted) image; the tracker undistorts the points.

Spread: every cell of the grid gets an equal share of ``max_features``; the share a cell's tracks already fill is
not detected again. A cell left with fewer than ``min_per_cell`` features (a low-contrast region of a real scene)
is searched again with the lower ``fast_threshold_low`` (ORB-SLAM's two FAST thresholds, 20 and 7), and its best
``min_per_cell`` corners come before any other cell's surplus when the total is capped.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class FeatureConfig:
    """Feature detection settings (pixels of the raw camera image)."""

    detector: str = "fast"  # fast | gftt | orb (fast: measured cheapest with the longest tracks, see module doc)
    max_features: int = 180  # total tracked features to maintain
    grid_cols: int = 6  # bucketing grid
    grid_rows: int = 4
    min_distance: int = 20  # px between features (new vs new and new vs tracked)
    quality_level: float = 0.01  # gftt: relative corner quality
    min_eig: float = 5e-4  # gftt: absolute floor on the corner's min eigenvalue (a bare wall's noise: ~3e-5)
    fast_threshold: int = 15  # fast: intensity threshold
    fast_threshold_low: int = 7  # fast: threshold of the second search in cells left under min_per_cell
    min_per_cell: int = 2  # features (tracked + new) each grid cell should hold; 0: no per-cell minimum
    border: int = 12  # px ignored at the image border (KLT windows)


def _cells(pts: np.ndarray, width: int, height: int, cols: int, rows: int) -> np.ndarray:
    """Grid cell index (row-major) of pixels (N, 2)."""
    cx = np.clip((pts[:, 0] * cols / width).astype(np.int64), 0, cols - 1)
    cy = np.clip((pts[:, 1] * rows / height).astype(np.int64), 0, rows - 1)
    return cy * cols + cx


def _bucket(
    pts: np.ndarray, score: np.ndarray, width: int, height: int, cols: int, rows: int, quota: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the best points per grid cell, at most ``quota[cell]`` each (vectorised), and each kept
    point's rank in its cell (0 = the cell's best).

    Args:
        pts: (N, 2) pixels; score: (N,) higher is better; quota: (rows * cols,) int.
    """
    if pts.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    cell = _cells(pts, width, height, cols, rows)
    order = np.lexsort((-score, cell))  # by cell, then best first
    cs = cell[order]
    first = np.searchsorted(cs, cs, "left")  # start of each point's cell run
    rank = np.arange(cs.size) - first
    keep = rank < quota[cs]
    return order[keep], rank[keep]


def _min_distance_filter(
    pts: np.ndarray, score: np.ndarray, min_dist: float, shape: tuple[int, int]
) -> np.ndarray:
    """Greedy non-maximum suppression on an occupancy grid of cell ``min_dist`` (vectorised per cell)."""
    if pts.shape[0] == 0 or min_dist <= 1:
        return np.arange(pts.shape[0])
    h, w = shape
    gc = int(np.ceil(w / min_dist))
    gx = (pts[:, 0] // min_dist).astype(np.int64)
    gy = (pts[:, 1] // min_dist).astype(np.int64)
    cell = gy * gc + gx
    order = np.lexsort((-score, cell))
    cs = cell[order]
    first = np.r_[True, cs[1:] != cs[:-1]]
    return order[first]


class FeatureDetector:
    """Detect new corners away from already tracked ones, bucketed over a grid."""

    def __init__(self, width: int, height: int, cfg: FeatureConfig | None = None) -> None:
        self.cfg = cfg = cfg or FeatureConfig()
        if cfg.detector not in ("gftt", "fast", "orb"):
            raise ValueError(f"feature detector {cfg.detector!r} is not one of gftt, fast, orb")
        self.width, self.height = int(width), int(height)
        n_cells = cfg.grid_cols * cfg.grid_rows
        self.per_cell = int(np.ceil(cfg.max_features / n_cells))
        self._border_mask = np.zeros((self.height, self.width), np.uint8)
        b = cfg.border
        self._border_mask[b : self.height - b, b : self.width - b] = 255
        if cfg.detector == "fast":
            self._det = cv2.FastFeatureDetector_create(threshold=cfg.fast_threshold, nonmaxSuppression=True)
            self._det_low = cv2.FastFeatureDetector_create(threshold=cfg.fast_threshold_low, nonmaxSuppression=True)
        elif cfg.detector == "orb":
            self._det = cv2.ORB_create(
                nfeatures=10 * cfg.max_features, edgeThreshold=max(b, 16), fastThreshold=10
            )
        else:
            self._det = None

    def detect(self, image: np.ndarray, existing: np.ndarray | None = None) -> np.ndarray:
        """New features for the image.

        Args:
            image: (H, W) uint8 grey.
            existing: (M, 2) pixels of features already tracked (they count towards each cell's quota and
                block a disk of ``min_distance`` around them).

        Returns:
            (K, 2) float32 pixel positions of new features, ``K <= max_features - M``.
        """
        c = self.cfg
        if image.shape[:2] != (self.height, self.width):
            raise ValueError(
                f"image is {image.shape[1]}x{image.shape[0]}, detector expects {self.width}x{self.height}"
            )
        existing = (
            np.zeros((0, 2)) if existing is None else np.asarray(existing, dtype=np.float64).reshape(-1, 2)
        )
        n_want = c.max_features - existing.shape[0]
        if n_want <= 0:
            return np.zeros((0, 2), np.float32)
        mask = self._border_mask.copy()
        for x, y in existing.astype(np.int32):  # ~200 disks; cv2.circle is ~1 us each
            cv2.circle(mask, (int(x), int(y)), c.min_distance, 0, -1)
        if c.detector == "gftt":
            pts = cv2.goodFeaturesToTrack(
                image,
                maxCorners=4 * c.max_features,
                qualityLevel=c.quality_level,
                minDistance=c.min_distance,
                mask=mask,
                blockSize=3,
            )
            if pts is None:
                return np.zeros((0, 2), np.float32)
            pts = pts.reshape(-1, 2).astype(np.float64)
            score = -np.arange(pts.shape[0], dtype=np.float64)  # returned best first
            if c.min_eig > 0:  # the quality level is relative: on a textureless image it accepts noise
                ev = cv2.cornerMinEigenVal(image, 3)
                strong = ev[pts[:, 1].astype(np.int64), pts[:, 0].astype(np.int64)] >= c.min_eig
                pts, score = pts[strong], score[strong]
        else:
            kps = self._det.detect(image, mask)
            if not kps:
                return np.zeros((0, 2), np.float32)
            pts = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2)
            score = np.array([k.response for k in kps], dtype=np.float64)
            keep = _min_distance_filter(pts, score, c.min_distance, image.shape[:2])
            pts, score = pts[keep], score[keep]
        # quotas: per-cell target minus tracked features already in the cell
        n_cells = c.grid_cols * c.grid_rows
        have = np.bincount(_cells(existing, self.width, self.height, c.grid_cols, c.grid_rows), minlength=n_cells)
        quota = np.maximum(self.per_cell - have, 0)
        sel, rank = _bucket(pts, score, self.width, self.height, c.grid_cols, c.grid_rows, quota)
        pts, score = pts[sel], score[sel]
        cell = _cells(pts, self.width, self.height, c.grid_cols, c.grid_rows)
        first = rank < np.maximum(c.min_per_cell - have, 0)[cell]  # a cell's share of its minimum
        if c.min_per_cell > 0 and c.detector == "fast" and c.fast_threshold_low < c.fast_threshold:
            lp, ls = self._weak_cells(image, mask, have + np.bincount(cell, minlength=n_cells), pts)
            pts, score = np.concatenate([pts, lp]), np.concatenate([score, ls])
            first = np.concatenate([first, np.ones(lp.shape[0], bool)])
        # a weak cell's minimum first, then the best of the rest
        order = np.lexsort((-score, ~first))[:n_want]
        return pts[order].astype(np.float32)

    def _weak_cells(
        self, image: np.ndarray, mask: np.ndarray, count: np.ndarray, taken: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """FAST at ``fast_threshold_low`` in the cells holding fewer than ``min_per_cell`` features (each cell's
        image alone); ``(points (K, 2), scores (K,))`` away from ``taken`` (new points of the first search)."""
        c = self.cfg
        weak = np.nonzero(count < c.min_per_cell)[0]
        if weak.size == 0:
            return np.zeros((0, 2)), np.zeros(0)
        mask = mask.copy()
        for x, y in taken.astype(np.int32):
            cv2.circle(mask, (int(x), int(y)), c.min_distance, 0, -1)
        out_p, out_s = [], []
        for cell in weak.tolist():
            r, q = divmod(cell, c.grid_cols)
            x0, x1 = q * self.width // c.grid_cols, (q + 1) * self.width // c.grid_cols
            y0, y1 = r * self.height // c.grid_rows, (r + 1) * self.height // c.grid_rows
            kps = self._det_low.detect(image[y0:y1, x0:x1], mask[y0:y1, x0:x1])
            if not kps:
                continue
            p = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2) + (x0, y0)
            sc = np.array([k.response for k in kps], dtype=np.float64)
            keep = _min_distance_filter(p, sc, c.min_distance, image.shape[:2])
            keep = keep[np.argsort(-sc[keep])][: c.min_per_cell - int(count[cell])]
            out_p.append(p[keep])
            out_s.append(sc[keep])
        if not out_p:
            return np.zeros((0, 2)), np.zeros(0)
        return np.concatenate(out_p), np.concatenate(out_s)
