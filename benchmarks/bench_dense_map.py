"""Accuracy and completeness of the fused dense map (:mod:`runtime.dense.fusion`) against ground truth.

Metric (:func:`runtime.dense.fusion.surface_metrics`), at ``--threshold`` (5 cm): **accuracy** = fraction of map
points within 5 cm of the ground-truth cloud (and their mean / median distance), **completeness** = fraction of
ground-truth points within 5 cm of the map; k-d trees both ways; the ground-truth cloud is voxel-downsampled to
``--gt-voxel`` (2 cm). The ground truth covers the network's field of view only (the centre crop the network
sees, :class:`runtime.geometry.NetworkMapping`), so the crop does not count as incompleteness.

Mesh rows (:mod:`runtime.dense.tsdf`): the surface of a TSDF (``DenseMapConfig.tsdf_voxel``, ``tsdf_trunc``) is
scored by points sampled uniformly on its triangles (:func:`runtime.dense.tsdf.sample_mesh`, one per
``--mesh-spacing`` squared, 1 cm), so a large triangle counts by its area; the ground truth is the same.

Two kinds of ``--seq``:

* **synthetic** (a rendered EuRoC-layout sequence with ``mav0/depth0``): the ``dense_map.ply`` of a
  ``dit-slam dense=true`` output folder ``--slam-out`` (run here when it has no ``dense_map.ply``). Ground truth:
  the rendered depth of every keyframe of ``keyframes.txt`` (nearest frame), at network resolution
  (:func:`runtime.dense.map.gt_depth_to_network`), back-projected with the ground-truth poses. The SLAM map is in
  the estimate's world frame: it is moved into the ground truth's with the SE(3) alignment of the ATE
  (``evo`` ``align(correct_scale=False)`` of ``trajectory.txt`` against the ground truth at the estimate's
  timestamps, as :func:`runtime.eval.trajectory_metrics`). Rows ``>= k keyframes``: the voxels the PLY's
  ``keyframes`` property says were seen by k keyframes or more. Reference row: the same fusion fed the rendered depth
  at the SLAM keyframe poses (aligned), i.e. the map's error due to the poses alone. Mesh rows: the output's
  ``dense_mesh.ply`` (aligned the same way) and the TSDF of the same rendered depth at the same poses.
* **real** (an ``rgbd_real`` frame folder, :mod:`runtime.io.rgbd_frames`, with its poses): every frame is a
  keyframe at its recorded pose. Rows: the fusion fed (a) the depth network's prior (``--model``, default the
  shipped model; input as the G-S protocol of ``dit-eval depth real=...``: network-resolution image and the true
  depth at 125 FAST corners, no noise, c = 0; weights ``1 / B^2`` and the uncertainty filter), (b) the same
  without the weights (uniform, filter kept), (c) the interpolated sparse points
  (:func:`runtime.densify.interpolate_sparse`, weight 1), (d) the true depth at network resolution (weight 1:
  the fusion's own upper bound). Ground truth: every frame's full-resolution depth (mm PNG, 0 invalid) inside the
  network's crop, back-projected with the recorded poses. Accuracy counts every map point, also those where the
  sensor has no depth (beyond its range): a fill there (interpolation, network) is scored as inaccurate.
  Rows ``>= 2 keyframes`` keep only voxels seen by two keyframes or more (``VoxelMap.points(2)``). Mesh rows:
  the same depth maps with the same weights and filter integrated into a TSDF, its surface.

Usage::

    python benchmarks/bench_dense_map.py --seq ../shared/data/rgbd_real/sun3d_fragment1
    python benchmarks/bench_dense_map.py --seq SEQ_WITH_DEPTH0 --slam-out OUT   # OUT of dit-slam dense=true
    python benchmarks/bench_dense_map.py --seq SEQ1 SEQ2 REAL_DIR --slam-out OUT1 OUT2   # outputs in --seq order

Prints a table per sequence and writes ``--out`` (default ``benchmarks/results/dense_map.json``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.common import markdown_table, slam_machine, write_json  # noqa: E402
from runtime.dense.config import DenseMapConfig  # noqa: E402
from runtime.dense.fusion import VoxelMap, surface_metrics  # noqa: E402
from runtime.dense.map import backproject, gt_depth_to_network, voxel_downsample  # noqa: E402
from runtime.dense.tsdf import TsdfVolume, sample_mesh  # noqa: E402

COLUMNS = ["map", "points", "accuracy", "acc mean [m]", "acc median [m]", "completeness", "comp mean [m]"]


def _row(name: str, m: dict) -> list:
    return [name, m["n_map"], m["accuracy"], m["acc_mean_m"], m["acc_median_m"], m["completeness"], m["comp_mean_m"]]


def _mesh_metrics(v: np.ndarray, f: np.ndarray, gt_xyz: np.ndarray, args) -> dict:
    """:func:`surface_metrics` of points sampled on a mesh's triangles, with the mesh's size."""
    m = surface_metrics(sample_mesh(v, f, args.mesh_spacing), gt_xyz, args.threshold)
    m.update(mesh_vertices=int(len(v)), mesh_faces=int(len(f)))
    return m


# ------------------------------------------------------------------------------------------------ synthetic
def _se3_alignment(traj_path: Path, gt) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t) taking the estimate's world to the ground truth's, as the ATE's SE(3) alignment; and the ATE."""
    import copy

    from evo.core import metrics

    from runtime.eval import _traj
    from runtime.geometry import interpolate_poses
    from runtime.io.tum import read_tum

    ts, T = read_tum(traj_path)
    ref_T, inside = interpolate_poses(ts, gt.ts, gt.T_w_b)
    est, ref = _traj(ts[inside], T[inside]), _traj(ts[inside], ref_T[inside])
    est_al = copy.deepcopy(est)
    R, t, _ = est_al.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_al))
    return np.asarray(R), np.asarray(t), float(ape.get_statistic(metrics.StatisticsType.rmse))


def eval_synthetic(seq_dir: Path, slam_out: Path, args) -> dict:
    from runtime.dense import DenseConfig
    from runtime.geometry import NetworkMapping, make_T
    from runtime.io.euroc import read_euroc
    from runtime.io.ply import read_ply_faces, read_ply_vertex
    from runtime.io.tum import read_tum
    from runtime.network import DepthNetwork, default_model_dir

    seq = read_euroc(seq_dir)
    if not seq.has_depth or seq.gt is None:
        raise ValueError(f"{seq_dir}: a synthetic sequence needs mav0/depth0 and ground truth")
    slam_out = Path(slam_out)
    if not (slam_out / "dense_map.ply").is_file():
        from runtime.run import run_sequence

        print(f"running dit-slam dense=true on {seq_dir} into {slam_out} ...", flush=True)
        dense = DenseConfig(map=DenseMapConfig(voxel=args.map_voxel))
        run_sequence(seq, slam_out, dense=dense, progress=False, plot=False)
    net = DepthNetwork(args.model or default_model_dir())
    mapping = NetworkMapping.fit(seq.camera.width, seq.camera.height, net.width, net.height)
    net_cam = mapping.camera(seq.camera.pinhole())
    R, t, ate = _se3_alignment(slam_out / "trajectory.txt", seq.gt)
    A = make_T(R, t)
    kts, kT = read_tum(slam_out / "keyframes.txt")
    mcfg = DenseMapConfig(voxel=args.map_voxel)
    gt_pts, ref_map, t_fuse = [], VoxelMap(mcfg.voxel), 0.0
    ref_tsdf, t_tsdf = TsdfVolume.from_config(DenseMapConfig()), 0.0
    for j, ts in enumerate(kts):
        i = int(np.argmin(np.abs(seq.frame_ts - ts)))
        g = gt_depth_to_network(seq.depth(i), seq.camera, mapping)
        T_w_c = seq.gt_pose_at(int(seq.frame_ts[i])) @ seq.T_b_c
        p, _ = backproject(g, net_cam, g > 0)
        gt_pts.append(p @ T_w_c[:3, :3].T + T_w_c[:3, 3])
        t0 = time.perf_counter()
        ref_map.integrate(j, g, A @ kT[j] @ seq.T_b_c, net_cam, cfg=mcfg)
        t1 = time.perf_counter()
        ref_tsdf.integrate(j, g, A @ kT[j] @ seq.T_b_c, net_cam, cfg=DenseMapConfig())
        t_fuse, t_tsdf = t_fuse + t1 - t0, t_tsdf + time.perf_counter() - t1
    gt_xyz, _ = voxel_downsample(np.concatenate(gt_pts), args.gt_voxel)
    v = read_ply_vertex(slam_out / "dense_map.ply")
    xyz = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64) @ R.T + t
    support = v.get("keyframes", np.ones(len(xyz)))
    rows = {}
    for k in (1, 2, 3):
        name = "dit-slam dense_map.ply (SE(3)-aligned)" + (f", >= {k} keyframes" if k > 1 else "")
        rows[name] = surface_metrics(xyz[support >= k], gt_xyz, args.threshold)
    ref = ref_map.points()[0]
    rows["rendered depth fused at the SLAM keyframe poses"] = surface_metrics(ref, gt_xyz, args.threshold)
    mesh_path = slam_out / "dense_mesh.ply"
    if mesh_path.is_file():
        v = read_ply_vertex(mesh_path)
        mv = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64) @ R.T + t
        rows["dit-slam dense_mesh.ply (SE(3)-aligned)"] = _mesh_metrics(mv, read_ply_faces(mesh_path), gt_xyz, args)
    t0 = time.perf_counter()
    rv, rf, _, _ = ref_tsdf.mesh()
    t_mesh = time.perf_counter() - t0
    rows["TSDF mesh of the rendered depth at the SLAM keyframe poses"] = _mesh_metrics(rv, rf, gt_xyz, args)
    return {
        "kind": "synthetic",
        "slam_out": str(slam_out),
        "keyframes": int(len(kts)),
        "ate_se3_rmse_m": ate,
        "fusion_ms_per_keyframe": 1e3 * t_fuse / max(len(kts), 1),
        "fused_voxels": len(ref_map),
        "tsdf_ms_per_keyframe": 1e3 * t_tsdf / max(len(kts), 1),
        "tsdf_blocks": ref_tsdf.n_blocks,
        "tsdf_mb": ref_tsdf.nbytes / 1e6,
        "mesh_extraction_s": t_mesh,
        "gt_points": int(len(gt_xyz)),
        "rows": rows,
    }


# ------------------------------------------------------------------------------------------------ real
def eval_real(folder: Path, args) -> dict:
    from benchmarks.common import posed_gs_frames
    from runtime.densify import interpolate_sparse
    from runtime.io.rgbd_frames import RgbdFolder
    from runtime.network import DepthNetwork, default_model_dir

    frames = RgbdFolder(folder, args.frames)
    net = DepthNetwork(args.model or default_model_dir())
    cfg = DenseMapConfig(voxel=args.map_voxel)
    maps = {k: VoxelMap(cfg.voxel) for k in ("network", "interp", "gt")}
    maps["network_unweighted"] = VoxelMap(cfg.voxel, min_uncertainty=1e3)  # every B clamped to 1 km: equal weights
    maps["network_unfiltered"] = VoxelMap(cfg.voxel)
    no_filter = DenseMapConfig(max_uncertainty=None, max_rel_uncertainty=None, voxel=args.map_voxel)
    tsdfs = {k: TsdfVolume.from_config(cfg) for k in ("network", "interp", "gt")}
    tsdfs["network_unweighted"] = TsdfVolume(cfg.tsdf_voxel, cfg.tsdf_trunc, min_uncertainty=1e3)
    t_tsdf, gt_pts = 0.0, []
    code = np.zeros(net.code_dim, np.float32)
    t0 = time.perf_counter()
    for f in posed_gs_frames(frames, net):  # the G-S input of dit-eval (seed 0, epoch 0)
        i, depth, T_w_c, cam, mapping, net_cam, sparse, kd = (
            f.index, f.depth, f.T_w_c, f.cam, f.mapping, f.net_cam, f.sparse, f.kd
        )  # fmt: skip
        H, W = depth.shape
        colour = mapping.image_to_network(f.rgb)
        d_net = kd.depth(code)
        maps["network"].integrate(i, d_net, T_w_c, net_cam, kd.uncertainty, colour, cfg)
        maps["network_unweighted"].integrate(i, d_net, T_w_c, net_cam, kd.uncertainty, colour, cfg)
        maps["network_unfiltered"].integrate(i, d_net, T_w_c, net_cam, kd.uncertainty, colour, no_filter)
        maps["interp"].integrate(i, interpolate_sparse(sparse), T_w_c, net_cam, None, colour, cfg)
        maps["gt"].integrate(i, f.gt, T_w_c, net_cam, None, colour, cfg)
        t1 = time.perf_counter()
        tsdfs["network"].integrate(i, d_net, T_w_c, net_cam, kd.uncertainty, colour, cfg)
        t_tsdf += time.perf_counter() - t1
        tsdfs["network_unweighted"].integrate(i, d_net, T_w_c, net_cam, kd.uncertainty, colour, cfg)
        tsdfs["interp"].integrate(i, interpolate_sparse(sparse), T_w_c, net_cam, None, colour, cfg)
        tsdfs["gt"].integrate(i, f.gt, T_w_c, net_cam, None, colour, cfg)
        # ground truth: the full-resolution depth inside the network's crop
        uv_all = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 2).astype(np.float64)
        uvn = mapping.points_to_network(uv_all)
        inside = ((uvn >= -0.5) & (uvn < np.array([net.width, net.height]) - 0.5)).all(1).reshape(H, W)
        p, _ = backproject(depth, cam.pinhole(), inside & (depth > 0))
        gt_pts.append(p @ T_w_c[:3, :3].T + T_w_c[:3, 3])
    seconds = time.perf_counter() - t0
    gt_xyz, _ = voxel_downsample(np.concatenate(gt_pts), args.gt_voxel)
    names = {
        "network": "network prior (125 FAST, c = 0), 1/B^2 weights",
        "network_unweighted": "network prior, uniform weights",
        "network_unfiltered": "network prior, 1/B^2 weights, no uncertainty filter",
        "interp": "interpolated sparse points",
        "gt": "true depth at network resolution (upper bound)",
    }
    rows = {names[k]: surface_metrics(m.points()[0], gt_xyz, args.threshold) for k, m in maps.items()}
    rows_2 = {
        names[k] + ", >= 2 keyframes": surface_metrics(m.points(2)[0], gt_xyz, args.threshold)
        for k, m in maps.items()
        if k in ("network", "interp")
    }
    t0 = time.perf_counter()
    meshes = {k: vol.mesh() for k, vol in tsdfs.items()}
    t_mesh = (time.perf_counter() - t0) / len(meshes)
    rows_mesh = {"TSDF mesh: " + names[k]: _mesh_metrics(m[0], m[1], gt_xyz, args) for k, m in meshes.items()}
    return {
        "kind": "real",
        "frames": len(frames),
        "tsdf_ms_per_keyframe": 1e3 * t_tsdf / max(len(frames), 1),
        "tsdf_blocks": tsdfs["network"].n_blocks,
        "tsdf_mb": tsdfs["network"].nbytes / 1e6,
        "mesh_extraction_s": t_mesh,
        "gt_points": int(len(gt_xyz)),
        "seconds": seconds,
        "network": f"{net.modality} {net.width}x{net.height}",
        "rows": {**rows, **rows_2, **rows_mesh},
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seq", nargs="+", required=True, help="rgbd_real frame folders and/or EuRoC sequences")
    ap.add_argument(
        "--slam-out", nargs="+", default=[], help="dit-slam dense=true output folders of the EuRoC --seq, in order"
    )
    ap.add_argument("--model", default=None, help="exported model folder (default: the shipped model)")
    ap.add_argument("--frames", type=int, default=None, help="first N frames of a real folder (default: all)")
    ap.add_argument("--threshold", type=float, default=0.05, help="distance of accuracy / completeness [m]")
    ap.add_argument("--gt-voxel", type=float, default=0.02, help="voxel of the ground-truth cloud [m]")
    ap.add_argument(
        "--map-voxel",
        type=float,
        default=DenseMapConfig().voxel,
        help="voxel of the fused maps made here [m] (a --slam-out's map has its run's dense_settings.map.voxel)",
    )
    ap.add_argument("--mesh-spacing", type=float, default=0.01, help="spacing of the points sampled on a mesh [m]")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "dense_map.json"))
    args = ap.parse_args(argv)
    results = {}
    slam_outs = list(args.slam_out)
    for s in args.seq:
        p = Path(s).expanduser()
        if (p / "mav0").is_dir():
            if not slam_outs:
                raise SystemExit(f"{p}: each EuRoC sequence needs its --slam-out (a dit-slam dense=true output)")
            res = eval_synthetic(p, Path(slam_outs.pop(0)), args)
        elif p.is_dir():
            res = eval_real(p, args)
        else:
            raise SystemExit(f"--seq {p}: no such folder")
        results[p.name] = res
        extra = {k: v for k, v in res.items() if k not in ("rows",)}
        print(f"\n### {p.name} ({extra})\n")
        print(markdown_table(COLUMNS, [_row(k, m) for k, m in res["rows"].items()]))
    out = {
        "threshold_m": args.threshold,
        "gt_voxel_m": args.gt_voxel,
        "map_voxel_m": args.map_voxel,
        "tsdf_voxel_m": DenseMapConfig().tsdf_voxel,
        "tsdf_trunc_m": DenseMapConfig().tsdf_trunc,
        "mesh_spacing_m": args.mesh_spacing,
        "machine": slam_machine(),
        "sequences": results,
        "command": "python benchmarks/bench_dense_map.py " + " ".join(argv if argv is not None else sys.argv[1:]),
    }
    print(f"\nwrote {write_json(args.out, out)}")
    return out


if __name__ == "__main__":
    main()
