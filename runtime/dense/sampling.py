"""Pixel sampling for the depth consistency residual (Sec. 5.2, Fig. 4).

The keyframe image is divided into ``3 x 3`` cells (row-major, cell ``l = row * 3 + col``). With ``f_l`` the
number of 2D feature points in cell ``l``:

* ``q_l = f_l / sum(f)``: the normalised feature distribution (``sum q = 1``; uniform ``1/9`` without
  features);
* ``gamma``: the *reversed* queue: the cells sorted by ``q`` get the ``q`` values in the opposite order, so
  the cell with the most features receives the smallest ``q`` and the emptiest cell the largest
  (``gamma[order[i]] = q[order[L-1-i]]`` with ``order = argsort(q)``; ``sum gamma = 1``). Cells with equal
  ``q`` share the mean of the values they receive (the paper leaves ties open; this keeps equal cells equal
  and the assignment independent of the cell numbering);
* ``n_l = gamma_l * N_consis`` pixels, rounded by largest remainder so that ``sum n = N_consis``, drawn
  uniformly (integer pixels, without replacement while the cell has enough pixels) in cell ``l`` with a
  seeded generator.

Featureless cells therefore get more samples: depth consistency constrains the regions that the
feature-based residuals do not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "CellSamples",
    "cell_edges",
    "cell_index",
    "cell_feature_counts",
    "reversed_weights",
    "allocate_samples",
    "sample_consistency_pixels",
]


@dataclass
class CellSamples:
    """Result of :func:`sample_consistency_pixels`.

    Attributes:
        uv: (N, 2) float64 sampled pixels ``(u, v)`` (integer-valued), image coordinates of the sampled image.
        cell: (N,) int cell index of each sample (row-major).
        counts: (L,) features per cell; q: (L,) normalised counts; gamma: (L,) reversed weights;
        n_per_cell: (L,) samples per cell.
    """

    uv: np.ndarray
    cell: np.ndarray
    counts: np.ndarray
    q: np.ndarray
    gamma: np.ndarray
    n_per_cell: np.ndarray


def cell_edges(size: int, n: int) -> np.ndarray:
    """Integer pixel edges (n + 1,) splitting ``size`` pixels into ``n`` near-equal cells.

    >>> cell_edges(224, 3).tolist()
    [0, 75, 149, 224]
    """
    if size < n or n < 1:
        raise ValueError(f"cannot split {size} pixels into {n} cells")
    return np.round(np.linspace(0, size, n + 1)).astype(np.int64)


def cell_index(uv: np.ndarray, width: int, height: int, grid: tuple[int, int] = (3, 3)) -> np.ndarray:
    """Cell (row-major, ``grid = (rows, cols)``) of each pixel (N, 2); -1 outside ``[-0.5, size - 0.5)``."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    rows, cols = grid
    ex, ey = cell_edges(width, cols), cell_edges(height, rows)
    # pixel centre u covers [u - 0.5, u + 0.5): the pixel column is round(u)
    with np.errstate(invalid="ignore"):
        px = np.floor(uv[:, 0] + 0.5)
        py = np.floor(uv[:, 1] + 0.5)
        ok = np.isfinite(px) & np.isfinite(py) & (px >= 0) & (py >= 0) & (px < width) & (py < height)
    cx = np.searchsorted(ex, np.where(ok, px, 0), side="right") - 1
    cy = np.searchsorted(ey, np.where(ok, py, 0), side="right") - 1
    return np.where(ok, cy * cols + cx, -1)


def cell_feature_counts(
    features_uv: np.ndarray, width: int, height: int, grid: tuple[int, int] = (3, 3)
) -> np.ndarray:
    """Number of feature points per cell (L,) = (rows * cols,); points outside the image are ignored."""
    cells = cell_index(features_uv, width, height, grid)
    return np.bincount(cells[cells >= 0], minlength=grid[0] * grid[1]).astype(np.int64)


def reversed_weights(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(q, gamma)`` from feature counts per cell (see the module docstring).

    >>> q, g = reversed_weights(np.array([6, 3, 1, 0]))
    >>> q.tolist(), g.tolist()
    ([0.6, 0.3, 0.1, 0.0], [0.0, 0.1, 0.3, 0.6])
    """
    counts = np.asarray(counts, dtype=np.float64).reshape(-1)
    if counts.size == 0 or np.any(counts < 0) or not np.all(np.isfinite(counts)):
        raise ValueError(f"counts must be finite, non-negative and non-empty, got {counts}")
    total = counts.sum()
    q = counts / total if total > 0 else np.full(counts.size, 1.0 / counts.size)
    order = np.argsort(q, kind="stable")  # ascending
    gamma = np.empty_like(q)
    gamma[order] = q[order][::-1]  # smallest q receives the largest value
    # ties: cells with equal q share the mean of what they received
    uniq, inv = np.unique(q, return_inverse=True)
    if uniq.size < q.size:
        gamma = (np.bincount(inv, weights=gamma) / np.bincount(inv))[inv]
    return q, gamma


def allocate_samples(gamma: np.ndarray, n_total: int) -> np.ndarray:
    """Integer samples per cell ``~ gamma * n_total`` summing to ``n_total`` (largest remainder; ties by
    cell index)."""
    gamma = np.asarray(gamma, dtype=np.float64)
    if n_total < 0:
        raise ValueError(f"n_total={n_total}: must be >= 0")
    if not np.isclose(gamma.sum(), 1.0) or np.any(gamma < 0):
        raise ValueError(f"gamma must be non-negative and sum to 1, got {gamma}")
    raw = gamma * n_total
    n = np.floor(raw + 1e-9).astype(np.int64)
    short = int(n_total - n.sum())
    if short > 0:
        rem = raw - n
        n[np.argsort(-rem, kind="stable")[:short]] += 1
    return n


def sample_consistency_pixels(
    features_uv: np.ndarray,
    width: int,
    height: int,
    n_total: int,
    rng: np.random.Generator | int | None = 0,
    grid: tuple[int, int] = (3, 3),
    margin: int = 0,
) -> CellSamples:
    """Pixels for the depth consistency residual of one keyframe (Sec. 5.2).

    Args:
        features_uv: (F, 2) feature points ``(u, v)`` in the same image as the samples (e.g. network pixels).
        width, height: image size [px].
        n_total: ``N_consis``, total number of samples.
        rng: ``numpy.random.Generator`` or seed (deterministic for a given seed).
        grid: (rows, cols) of cells, the paper's 3 x 3.
        margin: pixels near the image border that are never sampled (cells keep their nominal extent).

    Returns:
        :class:`CellSamples` with exactly ``n_total`` samples.

    >>> s = sample_consistency_pixels(np.array([[10.0, 10.0]] * 5), 90, 90, 90, rng=0)
    >>> int(s.n_per_cell[0]), int(s.n_per_cell.sum())   # the only cell with features gets nothing
    (0, 90)
    """
    width, height, n_total, margin = int(width), int(height), int(n_total), int(margin)
    if width < grid[1] or height < grid[0]:
        raise ValueError(f"image {width}x{height} is smaller than the {grid} grid")
    if margin < 0 or 2 * margin >= min(width, height):
        raise ValueError(f"margin={margin} leaves no pixel in a {width}x{height} image")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    counts = cell_feature_counts(
        np.asarray(features_uv, dtype=np.float64).reshape(-1, 2), width, height, grid
    )
    q, gamma = reversed_weights(counts)
    n_cell = allocate_samples(gamma, n_total)
    ex, ey = cell_edges(width, grid[1]), cell_edges(height, grid[0])
    uvs, cells = [], []
    for lidx in np.nonzero(n_cell)[0]:  # at most 9 cells: the pixel draws inside are vectorised
        r, c = divmod(int(lidx), grid[1])
        u0, u1 = max(ex[c], margin), min(ex[c + 1], width - margin)
        v0, v1 = max(ey[r], margin), min(ey[r + 1], height - margin)
        if u1 <= u0 or v1 <= v0:  # the margin ate this cell: sample the nearest valid strip instead
            u0, u1 = (
                min(max(ex[c], margin), width - margin - 1),
                max(min(ex[c + 1], width - margin), margin + 1),
            )
            v0, v1 = (
                min(max(ey[r], margin), height - margin - 1),
                max(min(ey[r + 1], height - margin), margin + 1),
            )
        w, h = u1 - u0, v1 - v0
        k = int(n_cell[lidx])
        flat = gen.choice(w * h, size=k, replace=k > w * h)
        uvs.append(np.stack([u0 + flat % w, v0 + flat // w], -1).astype(np.float64))
        cells.append(np.full(k, lidx, dtype=np.int64))
    uv = np.concatenate(uvs) if uvs else np.zeros((0, 2))
    cell = np.concatenate(cells) if cells else np.zeros(0, np.int64)
    return CellSamples(uv, cell, counts, q, gamma, n_cell)
