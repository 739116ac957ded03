"""Sampling of the depth consistency pixels (Sec. 5.2, Fig. 4) against its specification."""

import numpy as np
import pytest

from runtime.dense.sampling import (
    allocate_samples,
    cell_edges,
    cell_feature_counts,
    cell_index,
    reversed_weights,
    sample_consistency_pixels,
)

W, H = 224, 224


def features_in_cells(per_cell, seed=0):
    """Feature points with the given count per cell (row-major 3 x 3)."""
    rng = np.random.default_rng(seed)
    ex, ey = cell_edges(W, 3), cell_edges(H, 3)
    pts = []
    for lidx, n in enumerate(per_cell):
        r, c = divmod(lidx, 3)
        pts.append(np.stack([rng.integers(ex[c], ex[c + 1], n), rng.integers(ey[r], ey[r + 1], n)], -1))
    return np.concatenate(pts).astype(np.float64)


def test_cells_are_row_major_and_cover_the_image():
    assert cell_edges(224, 3).tolist() == [0, 75, 149, 224]
    uv = np.array([[0, 0], [74, 0], [75, 0], [223, 0], [0, 149], [223, 223], [-1, 5], [5, 224], [np.nan, 3]])
    assert cell_index(uv, W, H).tolist() == [0, 0, 1, 2, 6, 8, -1, -1, -1]
    counts = cell_feature_counts(features_in_cells([5, 0, 2, 0, 9, 0, 0, 1, 3]), W, H)
    assert counts.tolist() == [5, 0, 2, 0, 9, 0, 0, 1, 3]


def test_weights_sum_to_one_and_order_is_reversed():
    counts = np.array([5, 0, 2, 7, 9, 4, 1, 3, 6])  # distinct counts: no ties
    q, g = reversed_weights(counts)
    assert q.sum() == pytest.approx(1.0) and g.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(q, counts / counts.sum())
    # the cell with the most features gets the smallest q, the emptiest the largest, and so on in order
    assert np.argsort(g).tolist() == np.argsort(q)[::-1].tolist()
    np.testing.assert_allclose(np.sort(g), np.sort(q))  # the same values, reassigned
    assert g[4] == pytest.approx(q.min()) and g[1] == pytest.approx(q.max())


def test_hand_example_and_ties():
    q, g = reversed_weights(np.array([6, 3, 1, 0]))
    np.testing.assert_allclose(q, [0.6, 0.3, 0.1, 0.0])
    np.testing.assert_allclose(g, [0.0, 0.1, 0.3, 0.6])
    # equal counts get equal weights (they share what they receive); the sum stays 1
    q, g = reversed_weights(np.array([4, 4, 2, 0, 0, 0, 0, 0, 0]))
    assert g.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(g[:2], 0.0)  # the two richest cells receive the two smallest q (0 and 0)
    np.testing.assert_allclose(g[2], 0.0)  # third-richest receives the third smallest q, also 0
    np.testing.assert_allclose(g[3:], 1 / 6)  # the six empty cells share 0.4 + 0.4 + 0.2
    # no features: uniform
    q, g = reversed_weights(np.zeros(9))
    np.testing.assert_allclose(q, 1 / 9)
    np.testing.assert_allclose(g, 1 / 9)
    with pytest.raises(ValueError, match="non-negative"):
        reversed_weights(np.array([1, -1, 0]))


def test_allocation_sums_exactly():
    g = np.array([0.5, 0.25, 0.125, 0.125])
    assert allocate_samples(g, 8).tolist() == [4, 2, 1, 1]
    n = allocate_samples(np.full(9, 1 / 9), 600)
    assert n.sum() == 600 and n.max() - n.min() <= 1
    with pytest.raises(ValueError, match="sum to 1"):
        allocate_samples(np.array([0.5, 0.2]), 10)


def test_samples_per_cell_follow_gamma_and_lie_in_their_cell():
    per_cell = [40, 0, 10, 5, 60, 0, 0, 2, 20]
    s = sample_consistency_pixels(features_in_cells(per_cell), W, H, 600, rng=1)
    assert s.uv.shape == (600, 2) and s.cell.shape == (600,)
    assert s.counts.tolist() == per_cell
    np.testing.assert_array_equal(np.bincount(s.cell, minlength=9), s.n_per_cell)
    np.testing.assert_array_equal(cell_index(s.uv, W, H), s.cell)  # every sample in its cell
    assert np.all(np.abs(s.n_per_cell - s.gamma * 600) < 1.0)
    assert np.all(s.uv == np.round(s.uv))  # integer pixels
    # featureless cells get more samples than any cell with features; the richest cell the fewest
    empty = np.array(per_cell) == 0
    assert s.n_per_cell[empty].min() > s.n_per_cell[~empty].max()
    assert s.n_per_cell[4] == s.n_per_cell.min()
    # no duplicates within a cell when the cell has enough pixels
    assert np.unique(s.uv, axis=0).shape[0] == 600


def test_deterministic_by_seed_and_margin():
    f = features_in_cells([3, 0, 0, 8, 1, 0, 0, 0, 2])
    a = sample_consistency_pixels(f, W, H, 300, rng=7)
    b = sample_consistency_pixels(f, W, H, 300, rng=7)
    c = sample_consistency_pixels(f, W, H, 300, rng=8)
    np.testing.assert_array_equal(a.uv, b.uv)
    assert not np.array_equal(a.uv, c.uv)
    np.testing.assert_array_equal(a.n_per_cell, c.n_per_cell)  # only the pixels differ
    m = sample_consistency_pixels(f, W, H, 300, rng=7, margin=10)
    assert m.uv.min() >= 10 and m.uv.max() <= W - 11
    gen = np.random.default_rng(3)
    d = sample_consistency_pixels(f, W, H, 50, rng=gen)
    assert d.uv.shape == (50, 2)


def test_features_outside_are_ignored_and_small_images():
    f = np.array([[-5.0, 3.0], [W + 2.0, 10.0], [10.0, 10.0]])
    s = sample_consistency_pixels(f, W, H, 90, rng=0)
    assert s.counts.sum() == 1 and s.n_per_cell[0] == 0 and s.n_per_cell.sum() == 90
    # a tiny image: cells smaller than their sample count draw with replacement
    t = sample_consistency_pixels(np.zeros((0, 2)), 6, 6, 90, rng=0)
    assert t.uv.shape == (90, 2) and np.all(cell_index(t.uv, 6, 6) == t.cell)
    with pytest.raises(ValueError, match="smaller"):
        sample_consistency_pixels(f, 2, 2, 10)
