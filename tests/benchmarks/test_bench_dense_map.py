"""benchmarks/bench_dense_map.py end to end at a tiny size: on an RGB-D folder the fusion of the true depth is
exact, and on a rendered sequence the map is moved into the ground truth's frame by the ATE's alignment."""

import json

import cv2
import numpy as np
import pytest

from benchmarks import bench_dense_map
from runtime.dense.fusion import VoxelMap, write_fused_map
from runtime.dense.map import gt_depth_to_network
from runtime.dense.tsdf import TsdfVolume, write_mesh_ply
from runtime.geometry import NetworkMapping, make_T, so3_exp
from runtime.io.euroc import read_euroc
from runtime.io.tum import write_tum
from runtime.network import DepthNetwork, default_model_dir


def _rgbd_folder(root, n=2):
    """n frames of a textured wall 1.5 m away (mm depth), the camera moving 5 cm sideways per frame."""
    root.mkdir()
    np.savetxt(root / "camera-intrinsics.txt", [[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    rng = np.random.default_rng(0)
    tex = cv2.resize(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8), (320, 240), interpolation=cv2.INTER_NEAREST)
    for i in range(n):
        cv2.imwrite(str(root / f"frame-{i:06d}.color.png"), tex)
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), np.full((240, 320), 1500, np.uint16))
        np.savetxt(root / f"frame-{i:06d}.pose.txt", make_T(np.eye(3), [0.05 * i, 0, 0]))
    return root


def test_real_folder_true_depth_row_is_exact(tmp_path, capsys):
    folder = _rgbd_folder(tmp_path / "wall")
    out = tmp_path / "res.json"
    bench_dense_map.main(["--seq", str(folder), "--out", str(out)])
    res = json.loads(out.read_text())["sequences"]["wall"]
    rows = res["rows"]
    gt_row = rows["true depth at network resolution (upper bound)"]
    assert gt_row["accuracy"] == 1.0 and gt_row["completeness"] > 0.95 and gt_row["acc_mean_m"] < 0.01
    assert res["frames"] == 2 and len(rows) == 11
    mesh = rows["TSDF mesh: true depth at network resolution (upper bound)"]
    assert mesh["accuracy"] == 1.0 and mesh["acc_mean_m"] < 0.01 and mesh["mesh_faces"] > 100
    assert "| true depth at network resolution (upper bound) |" in capsys.readouterr().out


def test_map_voxel_sets_the_fused_maps_voxel(tmp_path):
    folder = _rgbd_folder(tmp_path / "wall")
    rows = {}
    for v in (0.02, 0.08):
        res = bench_dense_map.main(["--seq", str(folder), "--map-voxel", str(v), "--out", str(tmp_path / f"{v}.json")])
        assert res["map_voxel_m"] == v
        rows[v] = res["sequences"]["wall"]["rows"]["true depth at network resolution (upper bound)"]
    assert rows[0.08]["n_map"] < rows[0.02]["n_map"] / 8  # a plane: (0.08 / 0.02)^2 = 16 times fewer voxels
    assert rows[0.08]["accuracy"] == 1.0  # the wall's points stay on the wall


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    sim_euroc = pytest.importorskip("sim.euroc")
    out = tmp_path_factory.mktemp("seq") / "s"
    return sim_euroc.write_euroc_sequence(out, "textured", duration=4.0, seed=1, progress=False, scale=0.5)


def test_synthetic_map_is_aligned_like_the_ate(seq, tmp_path):
    """A 'SLAM output' in another world frame (the ground truth moved by a known SE(3)), with the rendered depth
    fused as its map: once aligned it lies on the ground truth."""
    s = read_euroc(seq)
    net = DepthNetwork(default_model_dir())
    mapping = NetworkMapping.fit(s.camera.width, s.camera.height, net.width, net.height)
    net_cam = mapping.camera(s.camera.pinhole())
    A_inv = make_T(so3_exp(np.array([0.1, -0.2, 0.7])), [1.0, -2.0, 0.5])  # ground-truth world -> estimate world
    ts = s.frame_ts[::3]
    T_est = np.stack([A_inv @ s.gt_pose_at(int(t)) for t in ts])
    out = tmp_path / "slam"
    write_tum(out / "trajectory.txt", ts, T_est)
    kf = np.arange(0, len(ts), 4)
    write_tum(out / "keyframes.txt", ts[kf], T_est[kf])
    m, vol = VoxelMap(0.02), TsdfVolume(0.04)
    for j in kf:
        i = int(np.searchsorted(s.frame_ts, ts[j]))
        g = gt_depth_to_network(s.depth(i), s.camera, mapping)
        m.integrate(int(j), g, T_est[j] @ s.T_b_c, net_cam)
        vol.integrate(int(j), g, T_est[j] @ s.T_b_c, net_cam)
    write_fused_map(out, *m.points())
    write_mesh_ply(out, *vol.mesh())
    res = bench_dense_map.main(["--seq", str(seq), "--slam-out", str(out), "--out", str(tmp_path / "r.json")])
    r = res["sequences"][seq.name]
    assert r["ate_se3_rmse_m"] < 1e-6
    aligned = r["rows"]["dit-slam dense_map.ply (SE(3)-aligned)"]
    assert aligned["accuracy"] > 0.99 and aligned["completeness"] > 0.95
    assert r["rows"]["rendered depth fused at the SLAM keyframe poses"]["accuracy"] > 0.99
    mesh = r["rows"]["dit-slam dense_mesh.ply (SE(3)-aligned)"]
    assert mesh["accuracy"] > 0.99 and mesh["completeness"] > 0.9 and mesh["mesh_faces"] > 100
    assert r["rows"]["TSDF mesh of the rendered depth at the SLAM keyframe poses"]["accuracy"] > 0.99
