"""Sparse depth from FAST corners (paper Sec. 6.1).

A SLAM front end knows metric depth only at tracked corners. To train and evaluate the ``*s`` modalities the
same way, corners are detected with FAST (``cv2.FastFeatureDetector``) on the network-size grey image and the
ground-truth depth is read there:

* training: a random number of corners in ``train_num`` (a random subset when more are found) with
  ``N(0, noise_std)`` noise [m] added, the paper's std being 0.1 m; noisy values are clamped to at least
  ``MIN_SPARSE_DEPTH`` so that a sample never reads as "no sample" (0).
* evaluation: exactly ``num_eval`` (125, as in the paper) corners without noise. When the image has fewer
  corners with valid depth, random valid pixels fill up to ``num_eval`` (``fill=True``, the default) so that
  every image gets the same count; fewer than ``num_eval`` samples are returned only when the image has fewer
  valid pixels.

SLAM-like input (optional): ``outlier_frac`` (training) or ``eval_outlier_frac`` (evaluation) of the samples get
a wrong depth (the true one times ``exp(U(-1, 1))``, a mis-triangulated map point), and at evaluation
``eval_noise_std`` adds noise as in training. In training, a share ``clean_frac`` of the frames keeps its points
exact (no noise, no outliers), so that the network learns to tell reliable points from noisy ones instead of
distrusting every point.

Corners without valid ground truth (depth 0) are never sampled. The sparse channel is a float32 (H, W) map in
metres with 0 everywhere except at sampled pixels. Randomness comes only from the ``rng`` argument, so a
sample is reproducible from its seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from runtime.densify import interpolate_sparse

__all__ = ["SparseConfig", "fast_corners", "interpolate_sparse", "sample_sparse_depth", "MIN_SPARSE_DEPTH"]

#: Smallest sparse depth [m] written after adding noise (0 means "no sample").
MIN_SPARSE_DEPTH = 1e-3


@dataclass(frozen=True)
class SparseConfig:
    """How sparse depth is sampled.

    Attributes:
        num_eval: samples per image at evaluation (paper: 125).
        train_num: (min, max) number of corners drawn uniformly per training image.
        noise_std: std of the Gaussian noise added in training [m] (paper: 0.1).
        fast_threshold: FAST intensity threshold (grey levels, 0-255).
        fill: at evaluation, fill up with random valid pixels when there are fewer than ``num_eval`` corners.
        outlier_frac: fraction of training samples whose depth is multiplied by ``exp(U(-1, 1))``.
        eval_noise_std: std of the Gaussian noise added at evaluation [m] (the paper's protocol: 0).
        eval_outlier_frac: ``outlier_frac`` at evaluation (the paper's protocol: 0).
        clean_frac: probability that a training frame's samples get no noise and no outliers.
    """

    num_eval: int = 125
    train_num: tuple[int, int] = (50, 200)
    noise_std: float = 0.1
    fast_threshold: int = 10
    fill: bool = True
    outlier_frac: float = 0.0
    eval_noise_std: float = 0.0
    eval_outlier_frac: float = 0.0
    clean_frac: float = 0.0

    def __post_init__(self) -> None:
        lo, hi = self.train_num
        if self.num_eval < 0 or lo < 0 or hi < lo:
            raise ValueError(f"bad sparse counts num_eval={self.num_eval}, train_num={self.train_num}")
        if self.noise_std < 0 or self.eval_noise_std < 0:
            raise ValueError(f"noise_std={self.noise_std}, eval_noise_std={self.eval_noise_std} must be >= 0")
        if not all(0 <= f <= 1 for f in (self.outlier_frac, self.eval_outlier_frac, self.clean_frac)):
            raise ValueError(
                f"outlier_frac={self.outlier_frac}, eval_outlier_frac={self.eval_outlier_frac}, "
                f"clean_frac={self.clean_frac} not in [0, 1]"
            )
        if not 0 < self.fast_threshold < 256:
            raise ValueError(f"fast_threshold={self.fast_threshold} must be in 1..255")


def fast_corners(gray: np.ndarray, threshold: int = 10, nonmax: bool = True) -> np.ndarray:
    """FAST-9 corners of a uint8 grey image.

    Args:
        gray: (H, W) uint8 image.
        threshold: FAST intensity threshold.
        nonmax: non-maximum suppression.

    Returns:
        (N, 2) int64 pixel coordinates ``(u, v)`` = (column, row), in detection order.

    >>> img = cv2.GaussianBlur(np.pad(np.full((16, 16), 255, np.uint8), 8), (3, 3), 0)  # a bright square
    >>> fast_corners(img).tolist()  # its four corners
    [[9, 9], [22, 9], [9, 22], [22, 22]]
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray must be (H, W) uint8, got shape {gray.shape} dtype {gray.dtype}")
    det = cv2.FastFeatureDetector_create(threshold=int(threshold), nonmaxSuppression=bool(nonmax))
    kps = det.detect(gray, None)
    if not kps:
        return np.zeros((0, 2), np.int64)
    uv = np.rint(cv2.KeyPoint_convert(kps)).astype(np.int64)  # (N, 2) float -> int (FAST gives integers)
    return uv


def sample_sparse_depth(
    gray: np.ndarray,
    depth: np.ndarray,
    rng: np.random.Generator,
    train: bool,
    cfg: SparseConfig = SparseConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Sample sparse depth at FAST corners.

    Args:
        gray: (H, W) uint8 grey image (the network input, after augmentation).
        depth: (H, W) float32 ground-truth depth [m], 0 = invalid, on the same pixel grid.
        rng: the sample's random generator.
        train: training (random count, noise) or evaluation (exactly ``cfg.num_eval``, no noise).
        cfg: sampling parameters.

    Returns:
        ``sparse`` (H, W) float32 [m] (0 = no sample) and ``uv`` (K, 2) int64 sampled pixels (u, v).

    >>> g = cv2.GaussianBlur(np.pad(np.full((20, 20), 200, np.uint8), 10), (3, 3), 0)  # 4 corners
    >>> d = np.full((40, 40), 2.0, np.float32)
    >>> s, uv = sample_sparse_depth(g, d, np.random.default_rng(0), train=False)
    >>> len(uv), float(s[uv[:, 1], uv[:, 0]].min()), int((s > 0).sum())
    (125, 2.0, 125)
    """
    if depth.shape != gray.shape:
        raise ValueError(f"depth has shape {depth.shape}, gray has {gray.shape}")
    h, w = depth.shape
    uv = fast_corners(gray, cfg.fast_threshold)
    if len(uv):
        uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)]
        uv = uv[depth[uv[:, 1], uv[:, 0]] > 0]
    if train:
        k = int(rng.integers(cfg.train_num[0], cfg.train_num[1] + 1))
        if len(uv) > k:
            uv = uv[np.sort(rng.choice(len(uv), size=k, replace=False))]
    else:
        k = cfg.num_eval
        if len(uv) > k:
            uv = uv[np.sort(rng.choice(len(uv), size=k, replace=False))]
        elif len(uv) < k and cfg.fill:
            valid = depth.reshape(-1) > 0
            valid[uv[:, 1] * w + uv[:, 0]] = False  # not twice the same pixel
            cand = np.flatnonzero(valid)
            extra = cand[np.sort(rng.choice(len(cand), size=min(k - len(uv), len(cand)), replace=False))]
            uv = np.concatenate([uv, np.stack([extra % w, extra // w], axis=1)], axis=0)
    values = depth[uv[:, 1], uv[:, 0]].astype(np.float32)
    outliers = cfg.outlier_frac if train else cfg.eval_outlier_frac
    noise = cfg.noise_std if train else cfg.eval_noise_std
    if train and cfg.clean_frac > 0 and rng.random() < cfg.clean_frac:
        outliers = noise = 0.0
    if outliers > 0 and len(uv):
        bad = rng.random(len(uv)) < outliers
        values = np.where(bad, values * np.exp(rng.uniform(-1.0, 1.0, len(uv))), values).astype(np.float32)
    if noise > 0 and len(uv):
        values = np.maximum(values + rng.normal(0.0, noise, len(uv)).astype(np.float32), MIN_SPARSE_DEPTH)
    sparse = np.zeros((h, w), np.float32)
    sparse[uv[:, 1], uv[:, 0]] = values
    return sparse, uv
