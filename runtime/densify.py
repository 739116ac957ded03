"""Densification of sparse depth: the interpolation every depth table compares against, and the base that the
relative depth network corrects (``models.ditnet``, ``runtime.network``).

Numpy and scipy only, so that the runtime computes the same fill as training without torch.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DEFAULT_FILL_M", "interpolate_sparse", "network_fill"]

#: Fill [m] of an image without samples: the relative network's input then carries no scale (models.blocks).
DEFAULT_FILL_M = 2.0


def interpolate_sparse(sparse: np.ndarray) -> np.ndarray:
    """Linear interpolation of the samples over their Delaunay triangulation, nearest sample outside the hull.

    Every depth table compares the network against this: a network with sparse input has to beat what its own
    input gives without it. The result is linear in the sample depths (the fill of ``2 * sparse`` is twice the
    fill of ``sparse``) and equals the samples at sampled pixels.

    Args:
        sparse: (H, W) float [m], 0 = no sample.

    Returns:
        (H, W) float32 [m]; all zeros when there is no sample, the constant when there is one.

    >>> s = np.zeros((3, 5), np.float32); s[1, 0], s[1, 4] = 1.0, 3.0
    >>> interpolate_sparse(s)[1].tolist()  # two points: no hull, nearest
    [1.0, 1.0, 1.0, 3.0, 3.0]
    >>> s = np.zeros((3, 3), np.float32); s[0, 0], s[0, 2], s[2, 0], s[2, 2] = 1.0, 1.0, 3.0, 3.0
    >>> interpolate_sparse(s)[1].tolist()  # rows 0 and 2 bound the hull, row 1 halfway
    [2.0, 2.0, 2.0]
    """
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import Delaunay, QhullError, cKDTree

    sparse = np.asarray(sparse)
    if sparse.ndim != 2:
        raise ValueError(f"sparse must be (H, W), got shape {sparse.shape}")
    h, w = sparse.shape
    v, u = np.nonzero(sparse > 0)
    if len(u) == 0:
        return np.zeros((h, w), np.float32)
    vals = sparse[v, u].astype(np.float64)
    if len(u) == 1:
        return np.full((h, w), vals[0], np.float32)
    pts = np.stack([u, v], axis=1).astype(np.float64)
    gv, gu = np.mgrid[0:h, 0:w]
    grid = np.stack([gu.ravel(), gv.ravel()], axis=1).astype(np.float64)
    out = np.full(h * w, np.nan)
    if len(u) >= 3:
        try:
            out = LinearNDInterpolator(Delaunay(pts), vals)(grid)
        except QhullError:  # all points on a line: nearest everywhere
            pass
    hole = ~np.isfinite(out)
    if hole.any():
        out[hole] = vals[cKDTree(pts).query(grid[hole])[1]]
    return out.reshape(h, w).astype(np.float32)


def network_fill(sparse: np.ndarray) -> np.ndarray:
    """The relative network's ``fill`` input: :func:`interpolate_sparse`, or ``DEFAULT_FILL_M`` without samples."""
    sparse = np.asarray(sparse)
    if not (sparse > 0).any():
        return np.full(sparse.shape, DEFAULT_FILL_M, np.float32)
    return interpolate_sparse(sparse)
