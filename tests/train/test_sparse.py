"""FAST sparse-depth sampling: counts, values, noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from train.sparse import MIN_SPARSE_DEPTH, SparseConfig, fast_corners, sample_sparse_depth


def _textured(h=96, w=128, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.uint8), (3, 3), 0)
    depth = (1.0 + rng.random((h, w)) * 3.0).astype(np.float32)
    return img, depth


def test_eval_exactly_125_noise_free_at_corners():
    img, depth = _textured()
    corners = {tuple(c) for c in fast_corners(img).tolist()}
    assert len(corners) > 125
    sparse, uv = sample_sparse_depth(img, depth, np.random.default_rng(1), train=False)
    assert len(uv) == 125 and int((sparse > 0).sum()) == 125
    np.testing.assert_array_equal(sparse[uv[:, 1], uv[:, 0]], depth[uv[:, 1], uv[:, 0]])
    assert {tuple(c) for c in uv.tolist()} <= corners
    # deterministic for a given generator seed
    sparse2, _ = sample_sparse_depth(img, depth, np.random.default_rng(1), train=False)
    np.testing.assert_array_equal(sparse, sparse2)


def test_eval_fills_up_with_valid_pixels_and_skips_invalid():
    img = cv2.GaussianBlur(np.pad(np.full((20, 20), 200, np.uint8), 20), (3, 3), 0)  # 4 corners only
    depth = np.full(img.shape, 2.5, np.float32)
    depth[:, :10] = 0.0  # invalid band
    sparse, uv = sample_sparse_depth(img, depth, np.random.default_rng(0), train=False)
    assert len(fast_corners(img)) == 4
    assert len(uv) == 125 and int((sparse > 0).sum()) == 125  # 4 corners + 121 random valid pixels
    assert (uv[:, 0] >= 10).all() and np.all(sparse[uv[:, 1], uv[:, 0]] == 2.5)
    # without fill: only the corners
    _, uv = sample_sparse_depth(img, depth, np.random.default_rng(0), train=False, cfg=SparseConfig(fill=False))
    assert len(uv) == 4
    # fewer valid pixels than 125: all of them
    depth[:] = 0.0
    depth[5, :30] = 1.0
    _, uv = sample_sparse_depth(img, depth, np.random.default_rng(0), train=False)
    assert len(uv) == 30


def test_train_random_subset_with_noise_std_0p1():
    img, depth = _textured(192, 256)
    depth[:] = 3.0
    cfg = SparseConfig(train_num=(60, 120))
    noise, counts = [], []
    for s in range(20):
        sparse, uv = sample_sparse_depth(img, depth, np.random.default_rng(s), train=True, cfg=cfg)
        counts.append(len(uv))
        noise.append(sparse[uv[:, 1], uv[:, 0]] - 3.0)
    noise = np.concatenate(noise)
    assert all(60 <= c <= 120 for c in counts) and len(set(counts)) > 5
    assert noise.std() == pytest.approx(0.1, rel=0.1)
    assert abs(noise.mean()) < 0.02
    # noisy values stay positive (0 means "no sample")
    depth[:] = 0.05
    sparse, uv = sample_sparse_depth(img, depth, np.random.default_rng(0), train=True, cfg=cfg)
    assert sparse[uv[:, 1], uv[:, 0]].min() >= MIN_SPARSE_DEPTH


def test_bad_inputs():
    img, depth = _textured()
    with pytest.raises(ValueError, match="depth has shape"):
        sample_sparse_depth(img, depth[:, :5], np.random.default_rng(0), train=False)
    with pytest.raises(ValueError, match="uint8"):
        fast_corners(img.astype(np.float32))
    with pytest.raises(ValueError, match="train_num"):
        SparseConfig(train_num=(5, 2))


def test_interpolate_sparse_known_answers():
    from train.sparse import interpolate_sparse

    # a plane d = 1 + 0.1 u + 0.05 v sampled at scattered pixels is reproduced inside the hull
    rng = np.random.default_rng(0)
    h, w = 40, 50
    s = np.zeros((h, w), np.float32)
    u, v = rng.integers(0, w, 60), rng.integers(0, h, 60)
    s[v, u] = 1 + 0.1 * u + 0.05 * v
    cu, cv = np.array([0, w - 1, 0, w - 1]), np.array([0, 0, h - 1, h - 1])
    s[cv, cu] = 1 + 0.1 * cu + 0.05 * cv  # the corners: the hull is the whole image
    gv, gu = np.mgrid[0:h, 0:w]
    np.testing.assert_allclose(interpolate_sparse(s), 1 + 0.1 * gu + 0.05 * gv, rtol=1e-5)
    # outside the hull: the nearest sample; no sample: zeros; one sample: constant
    s = np.zeros((10, 10), np.float32)
    s[2, 2], s[2, 5], s[5, 2] = 1.0, 2.0, 3.0
    out = interpolate_sparse(s)
    assert out[9, 9] in (2.0, 3.0) and out[0, 0] == 1.0 and out[2, 3] == pytest.approx(1 + 1 / 3, rel=1e-5)
    assert not interpolate_sparse(np.zeros((4, 4), np.float32)).any()
    one = np.zeros((4, 4), np.float32)
    one[1, 1] = 2.5
    assert (interpolate_sparse(one) == 2.5).all()


def test_slam_like_eval_noise_and_outliers():
    g = np.zeros((64, 64), np.uint8)
    d = np.full((64, 64), 4.0, np.float32)
    cfg = SparseConfig(num_eval=200, eval_noise_std=0.0, eval_outlier_frac=0.5, outlier_frac=0.0)
    s, uv = sample_sparse_depth(g, d, np.random.default_rng(0), False, cfg)
    vals = s[uv[:, 1], uv[:, 0]]
    bad = np.abs(vals - 4.0) > 1e-6
    assert 0.35 < bad.mean() < 0.65  # about half moved ...
    assert vals.min() >= 4.0 / np.e - 1e-5 and vals.max() <= 4.0 * np.e + 1e-5  # ... by a factor within e^(+-1)
    cfg = SparseConfig(num_eval=200, eval_noise_std=0.1)
    s, uv = sample_sparse_depth(g, d, np.random.default_rng(0), False, cfg)
    assert 0.07 < float(np.std(s[uv[:, 1], uv[:, 0]])) < 0.13
    with pytest.raises(ValueError, match="outlier_frac"):
        SparseConfig(outlier_frac=1.5)


def test_clean_frac_keeps_a_share_of_training_frames_exact():
    g = np.random.default_rng(1).integers(0, 256, (64, 64)).astype(np.uint8)  # texture: many FAST corners
    d = np.full((64, 64), 4.0, np.float32)

    def exact_frames(clean_frac: float) -> list[bool]:
        cfg = SparseConfig(train_num=(40, 40), noise_std=0.1, outlier_frac=0.05, clean_frac=clean_frac)
        out = []
        for seed in range(200):
            s, uv = sample_sparse_depth(g, d, np.random.default_rng(seed), True, cfg)
            assert len(uv) == 40
            out.append(bool(np.all(s[uv[:, 1], uv[:, 0]] == 4.0)))
        return out

    assert not any(exact_frames(0.0))  # every frame noisy
    assert all(exact_frames(1.0))
    assert 0.4 < np.mean(exact_frames(0.5)) < 0.6
    with pytest.raises(ValueError, match="clean_frac"):
        SparseConfig(clean_frac=-0.1)
