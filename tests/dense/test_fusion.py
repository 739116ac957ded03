"""Fused dense map (runtime.dense.fusion): known answers on planes, the 1 / B^2 weights, integration once per
keyframe (also through DenseMapper), the PLY with normals, and the accuracy / completeness metric."""

from collections import defaultdict
from concurrent.futures import Future

import numpy as np
import pytest

from runtime.dense import DenseConfig, DenseMapper
from runtime.dense.config import DenseMapConfig
from runtime.dense.fusion import FINEST_VOXEL, VoxelMap, depth_normals, surface_metrics, write_fused_map
from runtime.dense.mapper import _KfDense, _Stats
from runtime.dense.tsdf import TsdfVolume
from runtime.geometry import Camera, inv_T
from runtime.io.ply import read_ply, read_ply_normals, read_ply_vertex
from tests.dense.fakes import T_B_C, body_pose, network_K, plane_depth

H, W = 48, 64
K = network_K(H, W)
CAM = Camera(*K, W, H)


def _tilted_plane():
    """A camera turned 0.5 rad (yaw) towards the wall x_w = 3: its depth map and T_w_c."""
    T_w_b = body_pose((0.0, 0.0, 0.5), (0.2, -0.1, 0.3))
    return plane_depth(T_w_b, K, (H, W), 3.0), T_w_b @ T_B_C


def test_two_identical_depth_maps_of_a_plane_give_points_on_it_with_its_normal():
    depth, T_w_c = _tilted_plane()
    m = VoxelMap(0.02)
    cfg = DenseMapConfig(max_rel_uncertainty=None)
    n1 = m.integrate(0, depth, T_w_c, CAM, cfg=cfg)
    n2 = m.integrate(1, depth, T_w_c, CAM, cfg=cfg)
    assert n1 == n2 == H * W
    xyz, rgb, nrm, count = m.points()
    assert len(xyz) > 500 and (count == 2).all()  # every voxel seen by both keyframes
    np.testing.assert_allclose(xyz[:, 0], 3.0, atol=1e-9)  # on the wall x_w = 3
    has = np.linalg.norm(nrm, axis=1) > 0
    assert has.mean() > 0.9  # only the border pixels have no normal
    # the wall's normal, facing the camera (which is at x = 0.2 < 3): -x
    np.testing.assert_allclose(nrm[has], np.tile([-1.0, 0.0, 0.0], (int(has.sum()), 1)), atol=1e-9)
    assert (rgb == 128).all()  # no image: grey


def test_two_keyframes_from_different_poses_fuse_onto_the_wall_they_see():
    """Two keyframes at different poses see the wall x_w = 3 with exact depth maps and grey images."""
    Ts = [body_pose((0.0, 0.0, 0.1), (0.0, 0.0, 0.0)), body_pose((0.0, 0.05, -0.1), (0.3, 0.4, 0.1))]
    depths = [plane_depth(T, K, (H, W), 3.0) for T in Ts]
    grey = [np.full((H, W), 100, np.uint8), np.full((H, W), 200, np.uint8)]
    cfg = DenseMapConfig(voxel=0.0, max_rel_uncertainty=None)
    m = VoxelMap.from_config(cfg)  # voxel 0: the finest map; pixels are > 5 cm apart on the wall
    assert m.voxel == FINEST_VOXEL
    assert m.integrate(0, depths[0], Ts[0] @ T_B_C, CAM, image=grey[0], cfg=cfg) == H * W
    xyz0, rgb0, _, _ = m.points()
    assert len(xyz0) == H * W and (rgb0 == 100).all()  # one voxel a pixel, the grey image's value in r, g, b
    assert m.integrate(1, depths[1], Ts[1] @ T_B_C, CAM, image=grey[1], cfg=cfg) == H * W
    xyz, rgb, _, count = m.points()
    assert count.sum() == 2 * H * W and rgb.shape == xyz.shape and rgb.dtype == np.uint8
    np.testing.assert_allclose(xyz[:, 0], 3.0, atol=1e-9)  # every fused point on the wall
    assert set(np.unique(rgb[count == 1]).tolist()) == {100, 200}
    # the fused map spans what the cameras see: the first camera's centre ray hits the wall in its centre
    T_w_c = Ts[0] @ T_B_C
    ray = T_w_c[:3, 2]
    hit = T_w_c[:3, 3] + ray * (3.0 - T_w_c[0, 3]) / ray[0]
    assert np.min(np.linalg.norm(xyz - hit, axis=1)) < 0.05
    # coarser voxels average more points: fewer of them, still on the plane
    coarse = VoxelMap(0.1)
    for k in range(2):
        coarse.integrate(k, depths[k], Ts[k] @ T_B_C, CAM, image=grey[k], cfg=cfg)
    xyz_v, _, _, _ = coarse.points()
    assert 10 < len(xyz_v) < len(xyz)
    np.testing.assert_allclose(xyz_v[:, 0], 3.0, atol=1e-9)


def test_the_uncertainty_filter_drops_the_unreliable_half_of_a_keyframe():
    d = np.full((H, W), 2.0)
    B = np.full((H, W), 0.05)
    B[:, : W // 2] = 0.5  # left half unreliable: B / depth = 0.25 > 0.1 (the default max_rel_uncertainty)
    d[0, 0] = 20.0  # out of range
    m = VoxelMap.from_config(DenseMapConfig(voxel=0.0))
    T_w_c = body_pose() @ T_B_C
    assert m.integrate(0, d, T_w_c, CAM, uncertainty=B, cfg=DenseMapConfig(voxel=0.0)) == H * (W - W // 2)
    xyz, _, _, _ = m.points()
    assert len(xyz) == H * (W - W // 2)
    p_c = xyz @ inv_T(T_w_c)[:3, :3].T + inv_T(T_w_c)[:3, 3]
    u = CAM.fx * p_c[:, 0] / p_c[:, 2] + CAM.cx
    assert np.rint(u).min() == W // 2  # only the right half's pixels are in the map
    np.testing.assert_allclose(p_c[:, 2], 2.0, atol=1e-9)


def test_depth_normals_are_undefined_across_a_depth_jump_and_on_the_border():
    d = np.full((H, W), 2.0)
    d[:, W // 2 :] = 4.0  # an occlusion edge
    n = depth_normals(d, CAM)
    ok = np.isfinite(n).all(-1)
    assert not ok[:, W // 2 - 1 : W // 2 + 1].any()  # the two columns at the jump
    assert not ok[0].any() and not ok[:, 0].any()
    np.testing.assert_allclose(n[ok], np.tile([0.0, 0.0, -1.0], (int(ok.sum()), 1)), atol=1e-12)


def test_a_voxel_seen_with_a_small_and_a_large_uncertainty_lies_near_the_small_one():
    m = VoxelMap(1.0)  # one voxel holds the whole view of a fronto-parallel plane
    cam = Camera(4.0, 4.0, 1.5, 1.5, 4, 4)
    eye = np.eye(4)
    m.integrate(0, np.full((4, 4), 2.30), eye, cam, uncertainty=np.full((4, 4), 0.01))  # weight 1e4
    m.integrate(1, np.full((4, 4), 2.40), eye, cam, uncertainty=np.full((4, 4), 0.1))  # weight 1e2
    xyz, _, _, count = m.points()
    z = xyz[count == 2, 2]
    assert z.size > 0
    np.testing.assert_allclose(z, (1e4 * 2.30 + 1e2 * 2.40) / (1e4 + 1e2), rtol=1e-9)  # 2.300990 m
    # the uncertainty filter of DenseMapConfig still applies: B / depth = 0.2 > 0.1 is dropped
    m2 = VoxelMap(1.0)
    assert m2.integrate(0, np.full((4, 4), 2.0), eye, cam, uncertainty=np.full((4, 4), 0.4)) == 0


def test_a_keyframe_is_integrated_once():
    depth, T_w_c = _tilted_plane()
    m = VoxelMap(0.05)
    m.integrate(7, depth, T_w_c, CAM)
    with pytest.raises(ValueError, match="keyframe 7 is already in the fused map"):
        m.integrate(7, depth, T_w_c, CAM)
    assert 7 in m and m.keyframes == [7]


class _Provider:
    def __init__(self, depth):
        self._d = depth
        self.uncertainty = np.full(depth.shape, 0.01)

    def exact(self, code):
        return self._d


class _Net:
    code_dim = 2
    decoder_calls = 0


class _Kf:
    def __init__(self, T_w_b):
        self.T_w_b = T_w_b


class _Backend:
    def __init__(self, poses):
        self.poses = poses
        self.window = sorted(poses)

    def window_ids(self):
        return list(self.window)

    def keyframe(self, k):
        return _Kf(self.poses[k])


def _mapper(poses, depth):
    m = DenseMapper.__new__(DenseMapper)  # the mapper's fusion only: no network, no backend
    m.cfg = DenseConfig(save_maps=False, map=DenseMapConfig(max_rel_uncertainty=None))
    m.T_b_c, m.net_cam, m.net, m.depth_gt, m.probe = T_B_C, CAM, _Net(), None, None
    m.per_kf_metrics, m.stats, m.dense_map, m.timers, m._pool = {}, _Stats(), None, defaultdict(float), None
    m.fused_map = VoxelMap.from_config(m.cfg.map)
    m.tsdf = TsdfVolume.from_config(m.cfg.map)
    img = np.full((H, W), 200, np.uint8)
    m.kfs = {k: _KfDense(k, k, _done(_Provider(depth)), np.zeros((0, 2)), img, np.zeros(2)) for k in poses}
    return m


def _done(value) -> Future:
    f = Future()
    f.set_result(value)
    return f


def test_the_mapper_fuses_a_keyframe_when_it_leaves_the_window_and_not_again_at_finish(tmp_path):
    T_w_b = body_pose((0.0, 0.0, 0.5), (0.2, -0.1, 0.3))
    depth = plane_depth(T_w_b, K, (H, W), 3.0)
    poses = {1: T_w_b, 2: T_w_b, 3: T_w_b}
    m, b = _mapper(poses, depth), _Backend(poses)
    m.on_marginalize(b, 1)  # keyframe 1 leaves the window with its final pose
    b.window.remove(1)
    m.close()  # the integration runs on the network thread
    assert m.fused_map.keyframes == [1] and 1 not in m.kfs
    res = m.finish(b, tmp_path)
    assert m.fused_map.keyframes == [1, 2, 3]  # 2 and 3 at the end, 1 only once
    assert res["dense_map_keyframes"] == 3
    xyz, rgb, nrm, count = m.fused_map.points()
    assert count.max() == 3  # a voxel counts each keyframe once
    m.finish(b, tmp_path)  # a second finish integrates nothing again
    assert m.fused_map.keyframes == [1, 2, 3]
    got, got_rgb = read_ply(tmp_path / "dense_map.ply")
    assert got.shape[0] == res["dense_map_points"] == len(xyz) and (got_rgb == 200).all()
    np.testing.assert_allclose(got[:, 0], 3.0, atol=1e-5)  # float32 file


def test_ply_round_trip_with_normals(tmp_path):
    depth, T_w_c = _tilted_plane()
    m = VoxelMap(0.02)
    m.integrate(0, depth, T_w_c, CAM, image=np.full((H, W, 3), (10, 20, 30), np.uint8))
    m.integrate(1, depth[:, : W // 2], T_w_c, Camera(*K, W // 2, H))  # the left half seen twice
    xyz, rgb, nrm, count = m.points()
    path = write_fused_map(tmp_path, xyz, rgb, nrm, count)
    assert path.name == "dense_map.ply"
    got, got_rgb = read_ply(path)
    got_n = read_ply_normals(path)
    np.testing.assert_array_equal(got, xyz.astype(np.float32))
    np.testing.assert_array_equal(got_n, nrm.astype(np.float32))
    np.testing.assert_array_equal(read_ply_vertex(path)["keyframes"], count)
    assert set(count.tolist()) == {1, 2}
    assert (got_rgb[count == 1] == (10, 20, 30)).all()  # the second keyframe is grey (128)
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "property float nx" in header and "property uchar red" in header


def test_surface_metrics_known_answers():
    rng = np.random.default_rng(1)
    g = rng.uniform(0, 2, (3000, 3))
    same = surface_metrics(g, g, 0.05)
    assert same["accuracy"] == same["completeness"] == 1.0 and same["acc_median_m"] == 0.0
    # a plane against the same plane moved 10 cm along its normal: nothing within 5 cm, distances 10 cm
    v, u = np.mgrid[0:50, 0:50] * 0.02 + 0.01  # voxel centres of the 2 cm grid
    plane = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], -1)
    shifted = surface_metrics(plane + [0, 0, 0.10], plane, 0.05, gt_voxel=0.02)
    assert shifted["accuracy"] == shifted["completeness"] == 0.0
    assert shifted["acc_mean_m"] == pytest.approx(0.10) and shifted["comp_median_m"] == pytest.approx(0.10)
    # half the map 10 cm off: accuracy 1/2, completeness 1
    half = plane.copy()
    half[::2, 2] += 0.10
    m = surface_metrics(np.concatenate([plane, half[::2]]), plane, 0.05)
    assert m["accuracy"] == pytest.approx(len(plane) / (len(plane) + len(half[::2]))) and m["completeness"] == 1.0
    assert np.isnan(surface_metrics(np.zeros((0, 3)), plane)["accuracy"])


def test_voxels_are_found_again_after_the_index_merges(monkeypatch):
    import runtime.dense.fusion as fusion

    monkeypatch.setattr(fusion, "TAIL_MAX", 50)  # merge the new voxels into the sorted index often
    depth, T_w_c = _tilted_plane()
    m = VoxelMap(0.02)
    m.integrate(0, depth, T_w_c, CAM)
    n = len(m)
    assert n > 500 and m._n_indexed > 0  # merged
    shifted = T_w_c.copy()
    shifted[1, 3] += 0.3  # half new wall, half the same voxels
    m.integrate(1, depth, shifted, CAM)
    m.integrate(2, depth, T_w_c, CAM)
    _, _, _, count = m.points()
    keys = m.key[: len(m)]
    assert np.unique(keys).size == len(m)  # no voxel twice
    assert count[:n].min() >= 2 and count.max() == 3 and len(m) > n


def test_the_map_points_are_the_weighted_means_of_their_voxels():
    """``points()`` against the sums it keeps (a reference computed here from the map's rows): weighted mean
    position and colour, unit mean normal (zero without one), keyframe counts; with and without a support filter."""
    rng = np.random.default_rng(4)
    cam = Camera(60.0, 60.0, 31.5, 23.5, 64, 48)
    m = VoxelMap(0.02)
    for i in range(12):
        T = np.eye(4)
        T[:3, 3] = rng.normal(size=3) * 0.05
        d = 2 + rng.normal(size=(48, 64)).cumsum(1) * 0.01
        d[rng.random((48, 64)) < 0.05] = 0  # holes: pixels without a normal
        m.integrate(i, d, T, cam, rng.uniform(0.01, 0.2, (48, 64)), rng.integers(0, 255, (48, 64), dtype=np.uint8))
    n = len(m)
    for min_kf in (1, 3):
        keep = m.n_kf[:n] >= min_kf
        xyz, rgb, nrm, count = m.points(min_kf)
        w = m.w[:n][keep][:, None]
        np.testing.assert_array_equal(xyz, m.wp[:n][keep] / w)
        np.testing.assert_array_equal(rgb, np.clip(np.rint(m.wc[:n][keep] / w), 0, 255).astype(np.uint8))
        wn = m.wn[:n][keep].astype(np.float64)
        norm = np.linalg.norm(wn, axis=1, keepdims=True)
        np.testing.assert_array_equal(nrm, np.where(norm > 0, wn / np.where(norm > 0, norm, 1.0), 0.0))
        np.testing.assert_array_equal(count, m.n_kf[:n][keep])
        assert 0 < len(xyz) <= n and (len(xyz) == n) == (min_kf == 1)
        assert np.signbit(nrm[(norm == 0)[:, 0]]).sum() == 0 and (norm == 0).any()  # zero normals are +0.0
