"""Local dense map helpers: back-projection, uncertainty filter, voxels, saved maps, depth metrics (the fused map
of a run is tested in test_fusion.py)."""

import cv2
import numpy as np
import pytest

from runtime.dense.config import DenseMapConfig
from runtime.dense.map import (
    backproject,
    depth_metrics,
    gt_depth_to_network,
    mean_metrics,
    save_keyframe_maps,
    sparse_depth_image,
    uncertainty_mask,
    voxel_downsample,
)
from runtime.geometry import Camera, NetworkMapping
from tests.runtime.synth import EUROC_CAM

H, W = 48, 64


def test_backproject_known_answer():
    cam = Camera(2.0, 2.0, 1.0, 1.0, 3, 3)
    p, uv = backproject(np.full((3, 3), 2.0), cam)
    assert p.shape == (9, 3)
    np.testing.assert_allclose(p[0], [-1.0, -1.0, 2.0])
    np.testing.assert_allclose(p[-1], [1.0, 1.0, 2.0])
    np.testing.assert_allclose(uv[-1], [2.0, 2.0])
    d = np.full((3, 3), 2.0)
    d[1, 1] = 0.0
    assert backproject(d, cam)[0].shape == (8, 3)  # 0 = invalid
    assert backproject(np.full((3, 3), 2.0), cam, stride=2)[0].shape == (4, 3)
    with pytest.raises(ValueError, match="4x3"):
        backproject(np.ones((3, 4)), cam)


def test_uncertainty_filter():
    d = np.full((H, W), 2.0)
    B = np.full((H, W), 0.05)
    B[:, : W // 2] = 0.5  # left half unreliable
    d[0, 0] = 20.0  # out of range
    m = uncertainty_mask(d, B, DenseMapConfig(max_rel_uncertainty=0.1))
    assert m.sum() == H * (W - W // 2)
    m = uncertainty_mask(d, B, DenseMapConfig(max_uncertainty=0.6, max_rel_uncertainty=None))
    assert m.sum() == H * W - 1
    m = uncertainty_mask(d, B, DenseMapConfig(max_uncertainty=0.04, max_rel_uncertainty=None))
    assert m.sum() == 0


def test_voxel_downsample_hand_values():
    p = np.array([[0.01, 0.0, 0.0], [0.03, 0.02, 0.0], [0.5, 0.0, 0.0], [-0.01, 0.0, 0.0]])
    c = np.array([[10, 20, 30], [30, 40, 50], [0, 0, 0], [255, 255, 255]], np.uint8)
    out, col = voxel_downsample(p, 0.1, c)
    np.testing.assert_allclose(out, [[-0.01, 0.0, 0.0], [0.02, 0.01, 0.0], [0.5, 0.0, 0.0]])
    np.testing.assert_array_equal(col, [[255, 255, 255], [20, 30, 40], [0, 0, 0]])
    same, _ = voxel_downsample(p, 0.0)
    np.testing.assert_array_equal(same, p)


def test_save_keyframe_maps_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    d = rng.uniform(0.5, 6.0, (H, W)).astype(np.float32)
    B = rng.uniform(0.01, 0.3, (H, W)).astype(np.float32)
    paths = save_keyframe_maps(tmp_path / "kf", "kf_000012", d, B)
    assert [p.name for p in paths] == ["kf_000012.npz", "kf_000012_depth.png", "kf_000012_uncertainty.png"]
    z = np.load(paths[0])
    np.testing.assert_array_equal(z["depth"], d)
    np.testing.assert_array_equal(z["uncertainty"], B)
    png = cv2.imread(str(paths[1]), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16
    np.testing.assert_allclose(png / 5000.0, d, atol=1e-4)


def test_gt_depth_to_network():
    # no distortion and a 1:1 mapping: unchanged
    cam = Camera(50.0, 50.0, 31.5, 23.5, W, H)
    g = np.random.default_rng(0).uniform(1, 4, (H, W)).astype(np.float32)
    g[3, 4] = 0.0
    np.testing.assert_array_equal(gt_depth_to_network(g, cam, NetworkMapping.fit(W, H, W, H)), g)
    # EuRoC distortion + 752x480 -> 224x224: a constant map stays constant where valid, nearest keeps values
    m = NetworkMapping.fit(EUROC_CAM.width, EUROC_CAM.height, 224, 224)
    g = np.full((EUROC_CAM.height, EUROC_CAM.width), 2.5, np.float32)
    g[:, :376] = 1.5
    out = gt_depth_to_network(g, EUROC_CAM, m)
    assert out.shape == (224, 224)
    assert set(np.unique(out).tolist()) <= {0.0, 1.5, 2.5}
    assert (out > 0).mean() > 0.9
    with pytest.raises(ValueError, match="camera"):
        gt_depth_to_network(np.ones((10, 10)), EUROC_CAM, m)


def test_sparse_depth_image():
    uv = np.array([[1.2, 2.4], [0.8, 1.6], [5.0, 5.0], [-1.0, 0.0], [3.0, 3.0]])
    z = np.array([2.0, 1.5, -1.0, 3.0, 4.0])
    s = sparse_depth_image(uv, z, (6, 6))
    assert s.dtype == np.float32 and s[2, 1] == 1.5  # two points on one pixel: the closer wins
    assert s[3, 3] == 4.0 and s[5, 5] == 0.0 and np.count_nonzero(s) == 2


def test_depth_metrics_hand_values():
    p = np.array([[1.0, 2.0], [4.5, 9.0]])
    g = np.array([[1.0, 1.0], [5.0, 0.0]])
    m = depth_metrics(p, g)
    assert m["n"] == 3 and m["coverage"] == 1.0
    assert m["rmse"] == pytest.approx(np.sqrt((0 + 1 + 0.25) / 3))
    assert m["mae"] == pytest.approx(0.5)
    assert m["abs_rel"] == pytest.approx((0 + 1 + 0.1) / 3)
    assert m["irmse"] == pytest.approx(np.sqrt((0 + 0.25 + (1 / 4.5 - 0.2) ** 2) / 3))
    assert m["delta1"] == pytest.approx(2 / 3)  # ratios 1, 2, 1.11
    assert m["delta2"] == pytest.approx(2 / 3)  # 2 > 1.5625
    assert m["delta3"] == pytest.approx(2 / 3)  # 2 > 1.25^3 = 1.953 as well
    assert depth_metrics(np.array([1.9]), np.array([1.0]))["delta3"] == 1.0  # 1.9 < 1.953
    # a sparse prediction: only pixels with a value count, coverage says how many
    sp = np.array([[1.1, 0.0], [0.0, 3.0]])
    m = depth_metrics(sp, g)
    assert m["n"] == 1 and m["coverage"] == pytest.approx(1 / 3) and m["rmse"] == pytest.approx(0.1)
    m = depth_metrics(sp, g, mask=np.array([[False, True], [True, True]]))
    assert m["n"] == 0 and np.isnan(m["rmse"])
    agg = mean_metrics([depth_metrics(p, g), depth_metrics(sp, g), m])
    assert agg["images"] == 2 and agg["n"] == 4
    assert agg["rmse"] == pytest.approx((np.sqrt(1.25 / 3) + 0.1) / 2)
    with pytest.raises(ValueError, match="shape"):
        depth_metrics(p, g[:1])
