"""The map's code fit (:mod:`runtime.dense.refine`) on real RGB-D frames, at their recorded poses.

    python benchmarks/map_codes.py --real ../shared/data/rgbd_real [--gap 5] [--limit N] [--out F.json]

``dit-slam`` refines each keyframe's code for the dense map when the keyframe leaves the window. It fits the
keyframe's code jointly with those of its most co-visible keyframes, to Eq. 14 at the window's poses. This
benchmark asks what that fit does on real images, where the poses are the recorded ones.

Each frame of a folder gets the paper's G-S input, as ``dit-eval depth`` builds it: 125 FAST points with their true
depth, at network resolution. Its group is the frame plus ``neighbours`` others, ``gap``, ``2 gap``, ... frames
away (after, then before; in time order they are the co-visible ones). The fit then runs with the settings of
``dense_settings`` (:class:`runtime.dense.config.DenseConfig`). The samples come from the Sec. 5.2 sampler on the
FAST points. Reported per folder, as the mean of per-image figures: RMSE and AbsRel at c = 0, of the fitted
code (the exact decoder), and of the interpolated sparse points; and the share of frames the fit improved.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np


def folder_frames(folder: Path, net, limit: int | None = None) -> list[dict]:
    """The G-S input of every frame with a pose (:func:`benchmarks.common.posed_gs_frames`): its prior (linearised
    at c = 0), true depth, sparse points, camera pose ``T_w_c`` and network intrinsics."""
    from benchmarks.common import posed_gs_frames
    from runtime.dense.linearized import LinearizedDepth
    from runtime.io.rgbd_frames import RgbdFolder

    out = []
    for f in posed_gs_frames(RgbdFolder(folder, limit), net):
        provider = LinearizedDepth(f.kd)
        provider.relinearize(np.zeros(net.code_dim))
        out.append(
            {
                "provider": provider,
                "gt": np.asarray(f.gt, np.float64),
                "sparse": f.sparse,
                "T_w_c": f.T_w_c,
                "K": f.net_cam.intrinsics,
            }
        )
    return out


def group_of(i: int, n: int, neighbours: int, gap: int) -> list[int]:
    """Frame ``i`` and ``neighbours`` frames ``gap``, ``2 gap``, ... away (after first, then before), in range.

    >>> group_of(0, 20, 2, 5), group_of(10, 20, 2, 5), group_of(18, 20, 2, 5)
    ([0, 5, 10], [10, 15, 5], [18, 13, 8])
    """
    out, step = [i], 1
    while len(out) <= neighbours and step * gap < n:
        for j in (i + step * gap, i - step * gap):
            if 0 <= j < n and len(out) <= neighbours:
                out.append(j)
        step += 1
    return out


def _metrics(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """RMSE and AbsRel of one image, as ``metrics.json`` and ``dit-slam`` compute them."""
    from runtime.dense.map import depth_metrics

    m = depth_metrics(pred, gt)
    return m["rmse"], m["abs_rel"]


def evaluate(frames: list[dict], gap: int, cfg=None, seed: int = 0) -> dict:
    """c = 0, the fitted map code and the interpolation, per image (means), over one folder's ``frames``."""
    from runtime.dense.config import DenseConfig
    from runtime.dense.refine import refine_codes
    from runtime.dense.sampling import sample_consistency_pixels
    from runtime.densify import interpolate_sparse

    cfg = cfg or DenseConfig()
    mc = cfg.map_codes
    fcfg = dataclasses.replace(cfg.factors, sigma_per_b=mc.sigma_per_b)
    H, W = frames[0]["gt"].shape
    rows = {"c=0": [], "map code": [], "interpolation": []}
    norms = []
    for i in range(len(frames)):
        group = [frames[j] for j in group_of(i, len(frames), mc.neighbours, gap)]
        f = group[0]
        zero = np.zeros(f["provider"].code_dim)
        rows["c=0"].append(_metrics(f["provider"].exact(zero), f["gt"]))
        rows["interpolation"].append(_metrics(interpolate_sparse(f["sparse"]), f["gt"]))
        if len(group) < 2:
            rows["map code"].append(rows["c=0"][-1])
            continue
        samples = []
        for g in group:
            feat = np.argwhere(g["sparse"] > 0)[:, ::-1].astype(np.float64)
            rng = np.random.default_rng([seed, i, len(samples)])
            samples.append(sample_consistency_pixels(feat, W, H, mc.n_samples, rng=rng, margin=2).uv)
        codes, _ = refine_codes(
            [g["provider"] for g in group],
            [zero] * len(group),
            [g["T_w_c"] for g in group],
            samples,
            np.eye(4),
            f["K"],
            fcfg,
            cfg.code_prior_sigma,
            mc.iterations,
        )
        rows["map code"].append(_metrics(f["provider"].exact(codes[0]), f["gt"]))
        norms.append(float(np.linalg.norm(codes[0])))
    rmse = {k: float(np.mean([r[0] for r in v])) for k, v in rows.items()}
    absrel = {k: float(np.mean([r[1] for r in v])) for k, v in rows.items()}
    better = np.array([m[0] < z[0] for m, z in zip(rows["map code"], rows["c=0"], strict=True)])
    return {
        "frames": len(frames),
        "rmse_m": rmse,
        "abs_rel": absrel,
        "map_over_zero": rmse["map code"] / rmse["c=0"],
        "frames_better": float(better.mean()),
        "code_norm_median": float(np.median(norms)) if norms else 0.0,
    }


def main(argv: list[str] | None = None) -> dict:
    from benchmarks.common import machine_info, write_json
    from runtime.dense.config import DenseConfig
    from runtime.network import DepthNetwork, default_model_dir

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(default_model_dir()), help="exported model directory")
    ap.add_argument("--real", required=True, help="RGB-D frame folders in the rgbd_real layout (or one folder)")
    ap.add_argument("--gap", type=int, default=5, help="frames between a frame and its nearest neighbour")
    ap.add_argument("--limit", type=int, default=None, help="first N frames of each folder")
    ap.add_argument("--out", default=None, help="JSON path")
    args = ap.parse_args(argv)
    if args.gap < 1:
        raise SystemExit("map_codes: --gap must be >= 1")
    root = Path(args.real)
    if not root.is_dir():
        raise SystemExit(f"map_codes: {root} is not a folder")
    folders = sorted(p for p in root.iterdir() if p.is_dir()) or [root]
    net = DepthNetwork(args.model)
    cfg = DenseConfig()
    res = {}
    for folder in folders:
        frames = folder_frames(folder, net, args.limit)
        res[folder.name] = r = evaluate(frames, args.gap, cfg)
        print(f"\n{folder.name}: {r['frames']} frames, gap {args.gap}, {cfg.map_codes.neighbours} neighbours")
        print("| depth | RMSE [m] | AbsRel |")
        print("|---|---|---|")
        for k in r["rmse_m"]:
            print(f"| {k} | {r['rmse_m'][k]:.4f} | {r['abs_rel'][k]:.4f} |")
        print(f"map code over c = 0: {r['map_over_zero']:.3f}; better on {100 * r['frames_better']:.0f} % of frames")
    doc = {
        "model": str(args.model),
        "protocol": "gs",
        "gap": args.gap,
        "map_codes": dataclasses.asdict(cfg.map_codes),
        "folders": res,
        "machine": machine_info(),
    }
    if args.out:
        print(f"wrote {write_json(args.out, doc)}")
    return doc


if __name__ == "__main__":
    main()
