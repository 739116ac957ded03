"""TSDF and mesh (runtime.dense.tsdf): known surfaces rendered from known poses, orientation, no geometry where no
keyframe saw, the 1 / B^2 weights, the PLY round trip, bad input."""

import numpy as np
import pytest

from runtime.dense.config import DenseMapConfig
from runtime.dense.tsdf import BLOCK, TsdfVolume, _unpack, sample_mesh, write_mesh_ply
from runtime.geometry import Camera, inv_T, make_T
from runtime.io.ply import read_ply, read_ply_faces, read_ply_normals, write_ply
from tests.dense.fakes import T_B_C, body_pose, network_K, plane_depth

H, W = 48, 64
K = network_K(H, W)
CAM = Camera(*K, W, H)
NO_FILTER = DenseMapConfig(max_rel_uncertainty=None)


def _face_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _look_at(eye, target) -> np.ndarray:
    """T_w_c of a camera at ``eye`` looking at ``target`` (z forward, y roughly down = -z_w)."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.stack([x, np.cross(z, x), z], 1), eye)


def _sphere_depth(T_w_c, centre, r):
    """z-depth (H, W) of a sphere seen by CAM at T_w_c; 0 where a ray misses it."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u)], -1) @ T_w_c[:3, :3].T
    oc = T_w_c[:3, 3] - centre
    a, b, c = (rays**2).sum(-1), 2 * rays @ oc, oc @ oc - r**2
    disc = b**2 - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)  # z-depth: rays have z_c = 1
    return np.where(disc > 0, t, 0.0)


def test_a_wall_seen_from_several_poses_meshes_onto_the_wall_facing_the_cameras():
    poses = [body_pose((0.0, 0.0, yaw), (0.0, y, 0.1)) for yaw, y in ((0.0, 0.0), (0.3, -0.4), (-0.25, 0.5))]
    vol = TsdfVolume(0.05, 0.15)
    for k, T_w_b in enumerate(poses):
        assert vol.integrate(k, plane_depth(T_w_b, K, (H, W), 3.0), T_w_b @ T_B_C, CAM, cfg=NO_FILTER) > 0
    v, f, rgb, n = vol.mesh()
    assert len(v) > 200 and len(f) > 300 and f.max() == len(v) - 1  # every vertex in a face
    # on the wall x_w = 3
    np.testing.assert_allclose(v[:, 0], 3.0, atol=0.02 * vol.voxel)
    assert n[:, 0].max() < -0.99 and _face_normals(v, f)[:, 0].max() < -0.99  # -x: towards the cameras
    assert (rgb == 128).all()  # no image: grey
    # sparse: blocks only along the truncation band of the wall, 11 bytes a voxel (+ 24 a block for its key)
    edge = BLOCK * vol.voxel
    centres = (_unpack(vol.block_key[: vol.n_blocks]) + 0.5) * edge
    assert vol.n_blocks > 10 and np.abs(centres[:, 0] - 3.0).max() < vol.trunc + np.sqrt(3) * edge
    assert vol.nbytes == vol.n_blocks * (11 * BLOCK**3 + 24)


def test_a_sphere_seen_from_around_meshes_within_a_fraction_of_a_voxel_with_outward_normals():
    centre, r = np.array([0.2, -0.1, 1.0]), 0.5
    vol = TsdfVolume(0.04, 0.12)
    for k, yaw in enumerate(np.linspace(0, 2 * np.pi, 8, endpoint=False)):
        eye = centre + 2.0 * np.array([np.cos(yaw), np.sin(yaw), 0.3])
        T_w_c = _look_at(eye, centre)
        d = _sphere_depth(T_w_c, centre, r)
        img = np.full((H, W), 40 + 20 * k, np.uint8)
        vol.integrate(k, d, T_w_c, CAM, image=img, cfg=NO_FILTER)
    v, f, rgb, n = vol.mesh()
    radial = v - centre
    dist = np.linalg.norm(radial, axis=1)
    assert len(v) > 500
    err = np.abs(dist - r)  # worst at the rim of the seen band, seen at grazing angles only
    assert err.mean() < 0.1 * vol.voxel and np.percentile(err, 95) < 0.25 * vol.voxel and err.max() < 0.5 * vol.voxel
    out = radial / dist[:, None]
    cos = np.sum(n * out, 1)
    assert cos.min() > 0.9 and cos.mean() > 0.99  # vertex normals point out of the sphere, to the cameras
    fc = v[f].mean(1) - centre
    assert (np.sum(_face_normals(v, f) * fc, 1) > 0).all()  # every face wound outwards
    # the band of the sphere the cameras saw (z from about 0.55 to 1.45): no cap at the poles they missed
    assert v[:, 2].min() > centre[2] - r + 0.05 and v[:, 2].max() < centre[2] + r
    pts = sample_mesh(v, f, 0.01)
    assert len(pts) > len(f) and np.abs(np.linalg.norm(pts - centre, axis=1) - r).max() < 0.5 * vol.voxel


def test_no_geometry_where_no_keyframe_saw_and_none_across_an_occlusion_edge():
    vol = TsdfVolume(0.04)
    assert all(len(a) == 0 for a in vol.mesh())  # an empty volume: an empty mesh
    T_w_c = body_pose() @ T_B_C
    d = np.full((H, W), 2.0)
    d[:, W // 2 :] = 3.0  # a step: a near half-wall in front of a far one
    d[:10, :] = 0.0  # rows with no depth
    vol.integrate(0, d, T_w_c, CAM, cfg=NO_FILTER)
    v, f, _, n = vol.mesh()
    p_c = v @ inv_T(T_w_c)[:3, :3].T + inv_T(T_w_c)[:3, 3]
    z = p_c[:, 2]
    near, far = np.abs(z - 2.0) < 1e-6, np.abs(z - 3.0) < 1e-6
    assert near.sum() > 50 and far.sum() > 50 and (near | far).all()  # no wall joining the two depths
    vpix = CAM.fy * p_c[:, 1] / z + CAM.cy
    upix = CAM.fx * p_c[:, 0] / z + CAM.cx
    assert vpix.min() > 10 - 1.5 and upix[near].max() < W // 2 + 0.5  # nothing in the rows with no depth
    assert upix[far].min() > W // 2 - 1.5
    # the pixels of the far wall behind the near one were never seen: the far wall has a hole there
    assert not ((upix[far] < W // 2 - 4) & (vpix[far] > 15)).any()
    np.testing.assert_allclose(n @ T_w_c[:3, 2], -1.0, atol=1e-6)  # all facing the camera


def test_the_low_uncertainty_depth_map_wins():
    eye, cam = np.eye(4), Camera(20.0, 20.0, 15.5, 15.5, 32, 32)

    def surface(b1, b2):
        vol = TsdfVolume(0.04, 0.12)
        vol.integrate(0, np.full((32, 32), 2.0), eye, cam, uncertainty=np.full((32, 32), b1))
        vol.integrate(1, np.full((32, 32), 2.1), eye, cam, uncertainty=np.full((32, 32), b2))
        return vol.mesh()[0][:, 2]

    z = surface(0.01, 0.1)  # weights 1e4 and 1e2
    assert z.size > 0 and np.abs(z - 2.0).max() < 0.005
    z = surface(0.1, 0.01)
    assert np.abs(z - 2.1).max() < 0.005
    z = surface(0.05, 0.05)  # equal weights: in between
    assert np.abs(z - 2.05).max() < 0.005
    vol = TsdfVolume(0.04)  # the filter of DenseMapConfig: B / depth = 0.2 > 0.1 is not integrated
    assert vol.integrate(0, np.full((32, 32), 2.0), eye, cam, uncertainty=np.full((32, 32), 0.4)) == 0
    assert vol.n_blocks == 0


def test_mesh_ply_round_trip(tmp_path):
    T_w_b = body_pose((0.0, 0.0, 0.4), (0.1, 0.2, 0.0))
    vol = TsdfVolume(0.05)
    vol.integrate(
        0, plane_depth(T_w_b, K, (H, W), 3.0), T_w_b @ T_B_C, CAM, image=np.full((H, W, 3), (9, 8, 7), np.uint8)
    )
    v, f, rgb, n = vol.mesh()
    path = write_mesh_ply(tmp_path, v, f, rgb, n)
    assert path.name == "dense_mesh.ply" and [p.name for p in tmp_path.iterdir()] == ["dense_mesh.ply"]
    got, got_rgb = read_ply(path)
    np.testing.assert_array_equal(got, v.astype(np.float32))
    np.testing.assert_array_equal(got_rgb, rgb)
    assert (rgb == (9, 8, 7)).all()
    np.testing.assert_array_equal(read_ply_normals(path), n.astype(np.float32))
    np.testing.assert_array_equal(read_ply_faces(path), f)
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert f"element face {len(f)}" in header and "property list uchar int vertex_indices" in header
    assert read_ply_faces(write_ply(tmp_path / "cloud.ply", v)).shape == (0, 3)  # a cloud has no faces


def test_bad_input_raises_naming_the_problem(tmp_path):
    with pytest.raises(ValueError, match="voxel=-0.1: must be > 0"):
        TsdfVolume(-0.1)
    with pytest.raises(ValueError, match="trunc=0.02: must be > voxel"):
        TsdfVolume(0.04, 0.02)
    with pytest.raises(ValueError, match="tsdf_trunc=0.03: must be > tsdf_voxel"):
        DenseMapConfig(tsdf_voxel=0.04, tsdf_trunc=0.03)
    with pytest.raises(ValueError, match="tsdf_voxel=0.0"):
        DenseMapConfig(tsdf_voxel=0.0)
    vol, eye, d = TsdfVolume(0.05), np.eye(4), np.full((H, W), 2.0)
    with pytest.raises(ValueError, match="depth map has shape"):
        vol.integrate(0, d[:, :10], eye, CAM)
    with pytest.raises(ValueError, match="T_w_c must be a finite"):
        vol.integrate(0, d, np.full((4, 4), np.nan), CAM)
    with pytest.raises(ValueError, match="image must be uint8"):
        vol.integrate(0, d, eye, CAM, image=np.zeros((H, W), np.float32))
    vol.integrate(3, d, eye, CAM)
    with pytest.raises(ValueError, match="keyframe 3 is already in the TSDF"):
        vol.integrate(3, d, eye, CAM)
    far = eye.copy()
    far[0, 3] = 1e6
    with pytest.raises(ValueError, match="beyond"):
        vol.integrate(4, d, far, CAM)
    with pytest.raises(ValueError, match="faces index vertices"):
        write_ply(tmp_path / "m.ply", np.zeros((3, 3)), faces=np.array([[0, 1, 3]]))
    with pytest.raises(ValueError, match="spacing"):
        sample_mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), 0.0)


def test_the_mapper_writes_the_mesh_of_every_keyframe_it_fused(tmp_path):
    from tests.dense.test_fusion import _Backend, _mapper

    T_w_b = body_pose((0.0, 0.0, 0.5), (0.2, -0.1, 0.3))
    poses = {1: T_w_b, 2: T_w_b}  # the fake provider gives every keyframe the same depth map
    m, b = _mapper(poses, plane_depth(T_w_b, K, (H, W), 3.0)), _Backend(poses)
    m.on_marginalize(b, 1)  # on the network thread, with the point map
    b.window.remove(1)
    res = m.finish(b, tmp_path)  # keyframe 2 at the end
    assert m.tsdf.keyframes == [1, 2] and m.fused_map.keyframes == [1, 2]
    v, f = read_ply(tmp_path / "dense_mesh.ply")[0], read_ply_faces(tmp_path / "dense_mesh.ply")
    assert res["dense_mesh_vertices"] == len(v) > 100 and res["dense_mesh_faces"] == len(f) > 100
    assert res["dense_tsdf_blocks"] == m.tsdf.n_blocks and res["dense_tsdf_ms_per_keyframe"] > 0
    np.testing.assert_allclose(v[:, 0], 3.0, atol=1e-3)  # the wall x_w = 3 (float32 file)
