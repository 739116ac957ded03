"""Ray caster: known answers, parity with a brute-force float64 slab test, the white wall."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.geometry import Camera, make_T
from sim.euroc import EUROC_CAM0, EUROC_T_B_C0, simulate_sequence
from sim.render import Renderer, camera_rays
from sim.scenes import make_scene, scene_from_boxes
from sim.trajectory import R_LEVEL, euler_to_R_w_c


def test_depth_known_answer():
    """Room [0, 10]^3 seen from (1, 5, 5) along +x, a box face 1 m ahead: depth min(9, 5/|x|, 5/|y|) or 1."""
    scene = scene_from_boxes([10.0, 10.0, 10.0], [[2.0, 4.5, 4.5]], [[2.5, 5.5, 5.5]], albedo=0.5)
    cam = Camera(20.0, 20.0, 39.5, 29.5, 80, 60)  # wide pinhole: walls, floor, ceiling and the box in view
    T_w_c = make_T(R_LEVEL, [1.0, 5.0, 5.0])  # optical axis along world +x
    img, depth = Renderer(scene, cam).render(T_w_c)
    v, u = np.mgrid[0:60, 0:80]
    x, y = (u - 39.5) / 20.0, (v - 29.5) / 20.0  # ray [x, y, 1] -> world direction (1, -x, -y)
    with np.errstate(divide="ignore"):
        room = np.minimum(9.0, np.minimum(5.0 / np.abs(x), 5.0 / np.abs(y)))
    on_box = (np.abs(x) <= 0.5) & (np.abs(y) <= 0.5)  # the face x = 2 spans y, z in [4.5, 5.5]
    expect = np.where(on_box, 1.0, room)
    np.testing.assert_allclose(depth, expect, rtol=1e-6)
    assert on_box.sum() == 400 and np.isclose(depth, 9.0).sum() > 50
    np.testing.assert_array_equal(img, np.full_like(img, 128))  # albedo 0.5, shade 1, no noise


def _brute_force(scene, T_w_c, xn, yn):
    """Nearest hit by a float64 slab test against all boxes (independent of the renderer's culling)."""
    d = np.stack([xn, yn, np.ones_like(xn)], -1).astype(np.float64) @ T_w_c[:3, :3].T
    o = T_w_c[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (scene.lo[:, None, :] - o) / d[None]
        t2 = (scene.hi[:, None, :] - o) / d[None]
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    near, far = tmin.max(-1), tmax.min(-1)
    room = far[0]
    hit = (near[1:] <= far[1:]) & (near[1:] > 0)
    box = np.where(hit, near[1:], np.inf).min(0) if scene.n_boxes > 1 else np.inf
    return np.minimum(room, box)


@pytest.mark.parametrize("seed", [0, 1])
def test_culled_render_matches_brute_force(seed):
    scene = make_scene(seed, "textured")
    cam = EUROC_CAM0
    r = Renderer(scene, cam)
    xn, yn = camera_rays(cam)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, xn.size, 3000)
    for _ in range(4):
        p = scene.free_lo + rng.uniform(0, 1, 3) * (scene.free_hi - scene.free_lo)
        R = euler_to_R_w_c(*(np.array([v]) for v in (rng.uniform(-np.pi, np.pi), rng.normal(0, 0.3), 0.1)))[0]
        T = make_T(R, p)
        depth, face = r.trace(T)
        ref = _brute_force(scene, T, xn.reshape(-1)[idx], yn.reshape(-1)[idx])
        got = depth.reshape(-1)[idx]
        rel = np.abs(got - ref) / ref
        assert np.mean(rel < 1e-4) > 0.995 and np.median(rel) < 1e-5
        assert face.min() >= 0 and face.max() < 6 * scene.n_boxes


def test_camera_rays_invert_projection():
    xn, yn = camera_rays(EUROC_CAM0)
    uv, ok = EUROC_CAM0.project(np.stack([xn, yn, np.ones_like(xn)], -1))
    v, u = np.mgrid[0:480, 0:752]
    assert ok.all()
    assert np.abs(uv - np.stack([u, v], -1)).max() < 1e-3


def _flat_fraction(img, thr=8.0):
    g = img.astype(np.float32)
    gx = np.abs(g[1:-1, 2:] - g[1:-1, :-2]) / 2
    gy = np.abs(g[2:, 1:-1] - g[:-2, 1:-1]) / 2
    return float(np.mean(np.maximum(gx, gy) < thr))


def test_whitewall_window_is_textureless():
    import cv2

    d = simulate_sequence("whitewall", 26.0, 4, imu_noise=False)
    w0, w1 = d.window
    assert w1 - w0 >= 5.0
    r = Renderer(d.scene, EUROC_CAM0)
    rng = np.random.default_rng(0)
    fast = cv2.FastFeatureDetector_create(20)

    def frame(t):
        k = int(round(t / 0.005))
        return r.render(d.T_w_b(k) @ EUROC_T_B_C0, rng, 1.0)[0]

    for t in np.linspace(w0, w1, 4):
        img = frame(t)
        assert _flat_fraction(img) > 0.9  # most pixels: near-zero gradient
        assert len(fast.detect(img)) < 50
    for t in (3.0, d.trajectory.duration - 0.5):  # before and after: textured
        assert len(fast.detect(frame(t))) > 200


def test_scene_is_deterministic_and_free_region_is_clear():
    a, b, c = make_scene(3), make_scene(3), make_scene(4)
    np.testing.assert_array_equal(a.lo, b.lo)
    np.testing.assert_array_equal(a.atlas.data, b.atlas.data)
    assert a.lo.shape != c.lo.shape or not np.array_equal(a.lo, c.lo)
    # corners of the free region keep the clearance to every box and wall
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    for s in (a, c, make_scene(5, "whitewall")):
        pts = s.free_lo + corners * (s.free_hi - s.free_lo)
        grid = s.free_lo + np.random.default_rng(0).uniform(0, 1, (2000, 3)) * (s.free_hi - s.free_lo)
        assert s.min_distance(np.concatenate([pts, grid])).min() >= s.clearance - 1e-9
