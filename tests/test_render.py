"""The point-cloud renderer (runtime/render.py): known footprints and depths, z-buffer, look-at, alignment."""

import numpy as np
import pytest

from runtime.geometry import Camera, inv_T, make_T, so3_exp
from runtime.render import align_se3, look_at, map_views, project_points, render_points

CAM = Camera(50.0, 50.0, 49.5, 39.5, 100, 80)  # pixel centres at integers; u = 49.5 + 50 x / z


def _plane(z: float, u_range, v_range, per_px: int = 2) -> np.ndarray:
    """Camera-frame points at depth z whose projections fill pixels u_range x v_range (inclusive), several
    points per pixel spread inside it (offsets within +-0.4 px)."""
    off = (np.arange(per_px) + 0.5) / per_px * 0.8 - 0.4
    u = (np.arange(u_range[0], u_range[1] + 1)[:, None] + off).ravel()
    v = (np.arange(v_range[0], v_range[1] + 1)[:, None] + off).ravel()
    uu, vv = np.meshgrid(u, v)
    x = (uu.ravel() - CAM.cx) / CAM.fx * z
    y = (vv.ravel() - CAM.cy) / CAM.fy * z
    return np.stack([x, y, np.full(x.size, z)], 1)


def test_plane_at_known_depth_renders_to_its_pixel_footprint():
    pts = _plane(2.0, (20, 79), (10, 69))
    r = render_points(pts, np.eye(4), CAM)
    expect = np.zeros((80, 100), bool)
    expect[10:70, 20:80] = True
    np.testing.assert_array_equal(r.mask, expect)
    np.testing.assert_allclose(r.depth[expect], 2.0, atol=1e-6)
    assert (r.depth[~expect] == 0).all() and (r.index[~expect] == -1).all() and r.rgb is None
    # every covered pixel shows a point that projects into it
    uv, z, ok = project_points(pts[r.index[expect]], np.eye(4), CAM)
    vv, uu = np.nonzero(expect)
    assert ok.all() and np.abs(uv[:, 0] - uu).max() <= 0.5 and np.abs(uv[:, 1] - vv).max() <= 0.5
    # a splat radius of 1 grows the footprint by one pixel on every side
    r1 = render_points(pts, np.eye(4), CAM, radius=1)
    grown = np.zeros((80, 100), bool)
    grown[9:71, 19:81] = True
    np.testing.assert_array_equal(r1.mask, grown)
    np.testing.assert_allclose(r1.depth[grown], 2.0, atol=1e-6)


def test_wall_seen_through_look_at_has_its_distance_as_depth():
    # a wall x = 3 (world, z up), camera at the origin looking along +x: image right = world -y
    T_w_c = look_at([0.0, 0.0, 0.0], [3.0, 0.0, 0.0])
    y, zz = np.meshgrid(np.linspace(-0.59, 0.59, 119), np.linspace(-0.29, 0.29, 59))
    wall = np.stack([np.full(y.size, 3.0), y.ravel(), zz.ravel()], 1)
    r = render_points(wall, T_w_c, CAM)
    # u = cx + fx (-y) / 3: y in [-0.59, 0.59] -> u in [39.67, 59.33] -> pixel columns 40..59;
    # v = cy + fy (-z) / 3: z in [-0.29, 0.29] -> v in [34.67, 44.33] -> rows 35..44
    expect = np.zeros((80, 100), bool)
    expect[35:45, 40:60] = True
    np.testing.assert_array_equal(r.mask, expect)
    np.testing.assert_allclose(r.depth[r.mask], 3.0, atol=1e-9)
    # a point at world y > 0 lands left of the centre (image x points to world -y), z > 0 above it
    uv, z, ok = project_points(np.array([[3.0, 0.5, 0.2]]), T_w_c, CAM)
    assert ok[0] and z[0] == pytest.approx(3.0)
    np.testing.assert_allclose(uv[0], [CAM.cx - 50 * 0.5 / 3, CAM.cy - 50 * 0.2 / 3])


def test_z_buffer_keeps_the_nearest_point_and_its_colour():
    far = _plane(2.0, (10, 89), (10, 69))
    near = _plane(1.0, (40, 59), (30, 49))
    pts = np.concatenate([far, near])
    rgb = np.zeros((len(pts), 3), np.uint8)
    rgb[: len(far)] = (255, 0, 0)
    rgb[len(far) :] = (0, 0, 255)
    for order in (slice(None), slice(None, None, -1)):  # independent of the order of the points
        r = render_points(pts[order], np.eye(4), CAM, rgb=rgb[order], background=7)
        inner = np.zeros((80, 100), bool)
        inner[30:50, 40:60] = True
        np.testing.assert_allclose(r.depth[inner], 1.0)
        np.testing.assert_allclose(r.depth[r.mask & ~inner], 2.0)
        assert (r.rgb[inner] == (0, 0, 255)).all() and (r.rgb[r.mask & ~inner] == (255, 0, 0)).all()
        assert (r.rgb[~r.mask] == 7).all()


def test_points_behind_or_outside_are_dropped():
    pts = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.01], [100.0, 0.0, 1.0], [0.0, 0.0, 1.0], [np.nan, 0, 1]])
    _, _, ok = project_points(pts, np.eye(4), CAM)
    assert ok.tolist() == [False, False, False, True, False]
    r = render_points(pts, np.eye(4), CAM, radius=2)
    assert set(np.unique(r.index)) == {-1, 3} and r.mask.sum() == 25


def test_look_at_known_answer_and_errors():
    T = look_at([1.0, 2.0, 3.0], [1.0, 5.0, 3.0])  # looking along +y: image right = +x, image down = -z
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 0, 0], [0, 0, -1])
    with pytest.raises(ValueError, match="coincide"):
        look_at([1, 1, 1], [1, 1, 1])
    with pytest.raises(ValueError, match="rgb has shape"):
        render_points(np.zeros((3, 3)), np.eye(4), CAM, rgb=np.zeros((2, 3)))


def test_align_se3_recovers_a_known_rigid_transform():
    rng = np.random.default_rng(0)
    n = 200
    ts = 10**9 + np.arange(n, dtype=np.int64) * 50_000_000
    gt = np.tile(np.eye(4), (n, 1, 1))
    t = np.arange(n) * 0.05
    gt[:, :3, 3] = np.stack([np.cos(t), np.sin(1.7 * t), 0.2 * np.sin(0.5 * t)], 1)
    gt[:, :3, :3] = so3_exp(np.stack([0.1 * t, 0.0 * t, 0.3 * t], 1))
    G = make_T(so3_exp(np.array([0.1, -0.2, 1.1])), [2.0, -1.0, 0.3])  # T_gt_est
    est = inv_T(G) @ gt
    est[:, :3, 3] += 1e-4 * rng.standard_normal((n, 3))
    T = align_se3(ts[::2], est[::2], ts, gt)
    np.testing.assert_allclose(T, G, atol=2e-4)
    with pytest.raises(ValueError, match="within the ground truth"):
        align_se3(ts[:2], est[:2], ts, gt)


def test_map_views_frame_the_map_and_draw_the_trajectory():
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-2, 2, (4000, 2)), np.zeros(4000)]  # a 4 m floor, green
    rgb = np.tile([[20, 200, 20]], (4000, 1)).astype(np.uint8)
    traj = np.c_[np.linspace(-1.5, 1.5, 50), np.zeros(50), np.full(50, 1.0)]  # a line 1 m above it
    img = map_views(floor, rgb, traj, size=(160, 120))
    assert img.shape == (120, 320, 3) and img.dtype == np.uint8
    for view in (img[:, :160], img[:, 160:]):
        green = (view[..., 1] == 200) & (view[..., 0] == 20)
        red = (view[..., 0] > 150) & (view[..., 1] < 100)
        assert 0.1 < green.mean() < 0.95  # the floor fills much of the view, not all of it
        assert red.sum() > 30  # the trajectory is drawn
    top = img[:, :160]
    cols = np.nonzero(((top[..., 0] > 150) & (top[..., 1] < 100)).any(0))[0]
    assert cols.max() - cols.min() > 40  # the trajectory runs along world x: across the top view
    assert map_views(np.zeros((0, 3)), None, None, size=(40, 30)).shape == (30, 80, 3)  # empty map: blank views


def test_depth_panels_share_one_colour_scale_per_row():
    """``keyframe_depth.png``: the panels of a row side by side. Known answers: a depth linear in the pixels,
    sampled at the four corners, interpolates to itself, so the "points interpolated", "network depth" and "true
    depth" panels are the same pixels (one colour scale per row); no value is black; no true depth, no panel."""
    from runtime.render import depth_panels

    h, w, k = 12, 10, 4
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    depth = 1.0 + 0.2 * u + 0.1 * v
    sparse = np.zeros_like(depth)
    for r, c in ((0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1)):
        sparse[r, c] = depth[r, c]
    image = (16 * v + u).astype(np.uint8)
    row = {"image": image, "sparse": sparse, "depth": depth, "uncertainty": np.full((h, w), 0.1), "gt": depth}
    pic = depth_panels([row, dict(row, title="second")], min_width=40)
    band = 18
    assert pic.shape == (2 * (band + h * k), 5 * w * k, 3) and pic.dtype == np.uint8
    panel = [pic[band + 24 : band + h * k, i * w * k : (i + 1) * w * k] for i in range(5)]  # below the labels
    assert np.array_equal(panel[1], panel[2]) and np.array_equal(panel[2], panel[4])
    assert np.abs(panel[2].astype(int) - panel[3]).max() > 50  # the uncertainty has its own scale
    holes = dict(row, depth=np.where(u > 5, 0.0, depth), gt=None)
    pic = depth_panels([holes], min_width=40)
    assert pic.shape == (band + h * k, 4 * w * k, 3)  # no true depth: four panels
    assert (pic[-1, 2 * w * k + 6 * k : 3 * w * k] == 0).all()  # no depth there: black
    with pytest.raises(ValueError, match="every array"):
        depth_panels([dict(row, gt=depth[:-1])])
    with pytest.raises(ValueError, match="no rows"):
        depth_panels([])


def test_rendering_in_chunks_gives_the_same_picture(monkeypatch):
    """The points go through the z-buffer in chunks (``RENDER_CHUNK``): any chunk size gives the same depth,
    colours and winning point at every pixel, ties to the lower index included (points repeated at one place)."""
    import runtime.render as render

    rng = np.random.default_rng(3)
    pts = np.concatenate([_plane(2.0, (0, 99), (0, 79), per_px=1), rng.uniform([-1, -1, 0.5], [1, 1, 4], (3000, 3))])
    pts = np.concatenate([pts, pts[rng.integers(0, len(pts), 500)]])  # exact ties in depth, later indices
    rgb = rng.integers(0, 255, (len(pts), 3), dtype=np.uint8)
    T_w_c = make_T(so3_exp(np.array([0.05, -0.1, 0.02])), np.array([0.1, 0.0, -0.2]))
    whole = render_points(pts, T_w_c, CAM, rgb=rgb, radius=1)
    for chunk in (1000, 997, 7):
        monkeypatch.setattr(render, "RENDER_CHUNK", chunk)
        r = render_points(pts, T_w_c, CAM, rgb=rgb, radius=1)
        np.testing.assert_array_equal(r.index, whole.index)
        np.testing.assert_array_equal(r.depth, whole.depth)
        np.testing.assert_array_equal(r.rgb, whole.rgb)
    assert whole.mask.sum() > 0.8 * whole.mask.size
