"""Augmentation invariants: depth / s, alignment under scale, rotation and flip; colour, grey, identity."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.densify import network_fill
from runtime.geometry import NetworkMapping
from train.augment import AugmentConfig, FrameTransform, affine_matrix, color_jitter, to_gray

H, W = 120, 160  # frame size for the tests (4:3 like NYU)


def _frame(seed=0):
    rng = np.random.default_rng(seed)
    rgb = (rng.random((H, W, 3)) * 255).astype(np.uint8)
    depth = np.full((H, W), 2.0, np.float32)
    return rgb, depth


def _marked(u=100, v=40):
    """Black image with a white 3x3 mark at (u, v); depth 2 m with 5 m at the mark."""
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[v - 1 : v + 2, u - 1 : u + 2] = 255
    depth = np.full((H, W), 2.0, np.float32)
    depth[v - 1 : v + 2, u - 1 : u + 2] = 5.0
    return rgb, depth


def test_scale_divides_depth_by_s():
    rgb, depth = _frame()
    tf = FrameTransform(64, 64, "rgb", train=True, augment=AugmentConfig(rotation_deg=0.0))
    seen = []
    for seed in range(6):
        out = tf(rgb, depth, np.random.default_rng(seed))
        s = float(out["params"][0])
        d = out["depth"][0]
        assert 1.0 <= s <= 1.5
        np.testing.assert_allclose(d[d > 0], 2.0 / s, rtol=1e-6)
        assert (d > 0).all()  # no rotation: the zoomed crop stays inside the frame
        seen.append(s)
    assert max(seen) - min(seen) > 0.1


@pytest.mark.parametrize("seed", range(8))
def test_mark_moves_consistently_in_image_and_depth(seed):
    rgb, depth = _marked()
    tf = FrameTransform(64, 64, "rgb", train=True, augment=AugmentConfig(color_jitter=0.0, scale=(1.0, 1.5)))
    out = tf(rgb, depth, np.random.default_rng(seed))
    s, angle, flip = (float(x) for x in out["params"][:3])
    # where the affine map sends the mark's centre
    m = NetworkMapping.fit(W, H, 64, 64)
    A = affine_matrix((H, W), (64, 64), m.scale * s, angle, bool(flip))
    u, v = A @ np.array([100.0, 40.0, 1.0])
    img = out["image"].sum(0)
    vi, ui = np.unravel_index(np.argmax(img), img.shape)
    d = out["depth"][0]
    vd, ud = np.nonzero(d > 4.0 / s)
    assert len(ud) > 0
    assert abs(ui - u) <= 1.0 and abs(vi - v) <= 1.0
    assert abs(ud.mean() - u) <= 1.0 and abs(vd.mean() - v) <= 1.0
    np.testing.assert_allclose(d[vd, ud], 5.0 / s, rtol=1e-6)


def test_flip_mirrors_and_rotation_turns():
    rgb, depth = _marked(u=110, v=60)  # right of centre, on the centre row
    out_f = FrameTransform(64, 64, "rgb", True, AugmentConfig((1.0, 1.0), 0.0, 0.0, 1.0))(
        rgb, depth, np.random.default_rng(0)
    )
    out_n = FrameTransform(64, 64, "rgb", True, AugmentConfig((1.0, 1.0), 0.0, 0.0, 0.0))(
        rgb, depth, np.random.default_rng(0)
    )
    _, un = np.nonzero(out_n["depth"][0] > 4)
    _, uf = np.nonzero(out_f["depth"][0] > 4)
    assert un.mean() > 40 and uf.mean() < 24
    assert un.mean() + uf.mean() == pytest.approx(63.0, abs=1.0)  # mirror about the centre column 31.5
    # a mark on the right of the centre rotated by +alpha moves down (y down, clockwise on screen)
    A = affine_matrix((H, W), (64, 64), 0.4, 10.0)
    assert (A @ [110.0, 59.5, 1.0])[1] > (A @ [79.5, 59.5, 1.0])[1]


def test_identity_training_transform_equals_validation_mapping():
    rgb, depth = _frame(1)
    depth = depth + np.linspace(0, 1, W, dtype=np.float32)[None]  # smooth ramp
    ident = AugmentConfig(scale=(1.0, 1.0), rotation_deg=0.0, color_jitter=0.0, hflip_p=0.0)
    tr = FrameTransform(64, 64, "rgb", True, ident)(rgb, depth, np.random.default_rng(0))
    va = FrameTransform(64, 64, "rgb", False)(rgb, depth, np.random.default_rng(0))
    np.testing.assert_array_equal(va["params"][:6], [1, 0, 0, 1, 1, 1])
    np.testing.assert_allclose(tr["depth"], va["depth"], atol=0.01)  # nearest samples of a smooth ramp
    assert np.abs(tr["image"] - va["image"]).mean() < 0.03
    # validation = resize + centre crop of runtime.geometry.NetworkMapping
    m = NetworkMapping.fit(W, H, 64, 64)
    np.testing.assert_array_equal(va["depth"][0], m.image_to_network(depth, nearest=True))


def test_color_jitter_definitions():
    x = np.array([[[0.2, 0.4, 0.6], [0.6, 0.4, 0.2]]], np.float32)  # (1, 2, 3), grey 0.3980 and 0.4020
    np.testing.assert_allclose(color_jitter(x, 1.2, 1.0, 1.0), x * 1.2, rtol=1e-6)
    m = to_gray(x).mean()
    np.testing.assert_allclose(color_jitter(x, 1.0, 0.8, 1.0), (x - m) * 0.8 + m, rtol=1e-5)
    g = to_gray(x)[..., None]
    np.testing.assert_allclose(color_jitter(x, 1.0, 1.0, 1.2), (x - g) * 1.2 + g, rtol=1e-5)
    # saturation keeps the grey level; the output stays in [0, 1]
    np.testing.assert_allclose(to_gray(color_jitter(x, 1.0, 1.0, 0.8)), to_gray(x), rtol=1e-5)
    assert color_jitter(np.ones((2, 2, 3), np.float32), 1.2, 1.2, 1.2).max() == 1.0


def test_grey_converts_after_jitter_and_channels_per_modality():
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[...] = (200, 100, 50)
    depth = np.full((H, W), 2.0, np.float32)
    aug = AugmentConfig(scale=(1.0, 1.0), rotation_deg=0.0, color_jitter=0.2, hflip_p=0.0)
    out = FrameTransform(32, 32, "gray", True, aug)(rgb, depth, np.random.default_rng(3))
    b, c, s = out["params"][3:6]
    want = to_gray(color_jitter(rgb[:1, :1].astype(np.float32) / 255, b, c, s))[0, 0]
    np.testing.assert_allclose(out["image"][0], want, atol=1e-5)
    assert not np.isclose(want, to_gray(rgb[:1, :1].astype(np.float32) / 255)[0, 0], atol=1e-3)
    for mod, cin in (("rgb", 3), ("rgbs", 4), ("gray", 1), ("grays", 2)):
        o = FrameTransform(32, 32, mod, False)(*_frame(), np.random.default_rng(0))
        assert o["image"].shape == (cin, 32, 32) and o["image"].dtype == np.float32
        assert o["depth"].shape == (1, 32, 32)
        img = o["image"][: 3 if mod.startswith("rgb") else 1]
        assert 0.0 <= img.min() <= img.max() <= 1.0
        if mod.endswith("s"):
            assert int((o["image"][-1] > 0).sum()) == 125 == int(o["params"][-1])


def test_bad_inputs():
    with pytest.raises(ValueError, match="modality"):
        FrameTransform(32, 32, "depth", False)
    tf = FrameTransform(32, 32, "rgb", False)
    with pytest.raises(ValueError, match="uint8"):
        tf(np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), np.random.default_rng(0))
    with pytest.raises(ValueError, match="depth has shape"):
        tf(np.zeros((H, W, 3), np.uint8), np.zeros((H, W + 1), np.float32), np.random.default_rng(0))


def test_fill_is_the_interpolation_of_the_sparse_channel():
    rng = np.random.default_rng(5)
    rgb, _ = _frame(5)
    depth = rng.uniform(1.0, 6.0, (H, W)).astype(np.float32)  # varied depth: a fill that is not constant
    for train in (True, False):
        out = FrameTransform(64, 64, "grays", train=train, with_fill=True)(rgb, depth, np.random.default_rng(3))
        assert out["fill"].shape == (1, 64, 64) and out["fill"].dtype == np.float32
        assert (out["image"][-1] > 0).sum() >= 20
        np.testing.assert_array_equal(out["fill"][0], network_fill(out["image"][-1]))
        assert out["fill"].std() > 0.1
    assert "fill" not in FrameTransform(64, 64, "grays", train=True)(rgb, depth, np.random.default_rng(3))
    assert "fill" not in FrameTransform(64, 64, "gray", train=True, with_fill=True)(rgb, depth, rng)
