"""What limits the intrinsics refinement: its adjustment on the front end's tracks and on exact ones.

The adjustment on the front end's tracks, on the same tracks made exact, and on the tracks cut into short pieces.

    python benchmarks/intrinsics_tracks.py --sequences DIR [DIR ...] [--pieces 5 10] [--out F.json]

Each DIR is a sequence rendered by ``dit-sim euroc`` (``mav0/depth0``, ground truth, ``sim_info.json`` with the
``render_camera`` and ``time_offset_s``; an ``ideal=true`` sequence's written camera is the true one). The first pass
of ``dit-slam``'s intrinsics refinement runs (:func:`runtime.run.first_pass`, the default settings),
then :func:`runtime.calibration.refine_intrinsics` solves on:

* ``tracks``: the first pass's tracks, as ``dit-slam`` does;
* ``exact``: the same tracks on the same frames, each pixel replaced by the true projection of the point that the
  track's first observation sees (back-projected with the rendered depth and the true camera and pose; tracks
  that start on a depth edge are left out; see :mod:`benchmarks.track_drift`);
* ``exact, true poses``: the exact tracks with the ground truth's poses as the solve's starting point;
* ``exact, no time offset``: exact tracks of a camera on the IMU's clock (sequences with a ``time_offset_s``);
* ``pieces L``: the first pass's tracks cut into pieces of at most ``L`` adjustment frames, each piece its own
  landmark (a track's drift then stays within its piece).

It prints the error of the refined focal lengths [%] and principal point [px] against the rendered camera, per
sequence and as the mean absolute error per variant, and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.common import write_json
from benchmarks.track_drift import time_offset_ns, true_camera, true_pose, true_projections
from runtime.run import first_pass


def exact_features(seq, features: list, cam, offset_ns: int) -> list:
    """``features`` with every pixel the true projection of its track's point (the point its first observation sees
    at the rendered depth); the normalised coordinates are those of the written camera, as the front end's are."""
    from runtime.frontend.tracking import FrameFeatures

    index = {int(t): i for i, t in enumerate(np.asarray(seq.frame_ts, dtype=np.int64))}
    points: dict[int, np.ndarray | None] = {}
    out = []
    for f in features:
        i = index[int(f.ts)]
        T_w_c = true_pose(seq, f.ts, offset_ns) @ seq.T_b_c
        uv = seq.camera.project(np.c_[f.xn, np.ones(len(f.xn))])[0]
        q, ok = true_projections(seq, i, f.ids, uv, points, cam, T_w_c)
        xn = seq.camera.pixel_to_normalized(q[ok])
        out.append(FrameFeatures(f.ts, f.ids[ok], q[ok], xn, q[ok], f.flow_px, f.n_lost))
    return out


def in_pieces(length: int):
    """``tracks_from_features`` whose tracks are cut into pieces of at most ``length`` adjustment frames."""
    from runtime import calibration

    whole = calibration.tracks_from_features

    def cut(camera, features, frame_ts, min_views):
        tracks, xn = whole(camera, features, frame_ts, 1)
        pieces = [
            (t[s : s + length], x[s : s + length])
            for t, x in zip(tracks, xn, strict=True)
            for s in range(0, len(t), length)
        ]
        pieces = [p for p in pieces if len(p[0]) >= min_views]
        return [t for t, _ in pieces], [x for _, x in pieces]

    return cut


def errors(camera, cam_true) -> list[float]:
    """fx, fy [%] and cx, cy [px] of ``camera`` minus the true ones."""
    return [
        100 * (camera.fx / cam_true.fx - 1),
        100 * (camera.fy / cam_true.fy - 1),
        camera.cx - cam_true.cx,
        camera.cy - cam_true.cy,
    ]


def one_sequence(path: Path, pieces: list[int]) -> dict:
    from unittest import mock

    from runtime import calibration
    from runtime.io.euroc import read_euroc
    from runtime.slam import SlamConfig

    seq = read_euroc(path)
    info = json.loads((path / "sim_info.json").read_text())
    cam = true_camera(seq, info)
    offset_ns = time_offset_ns(info)
    cfg = SlamConfig()
    live, _ = first_pass(seq, cfg, len(seq))
    ts, T = live.system.trajectory()

    def solve(features, poses=T, tracks=None):
        with mock.patch.object(calibration, "tracks_from_features", tracks or calibration.tracks_from_features):
            res = calibration.refine_intrinsics(
                seq.camera, seq.T_b_c, seq.imu, live.imu, features, ts, poses, live.system.noise_scales, cfg.intrinsics
            )
        fx, fy, cx, cy = res.report["estimated"][:4]
        return errors(replace(seq.camera, fx=fx, fy=fy, cx=cx, cy=cy), cam)

    exact = exact_features(seq, live.system.feature_log, cam, offset_ns)
    T_true = np.array([true_pose(seq, t, offset_ns) for t in ts])
    rows = {"written": errors(seq.camera, cam), "tracks": solve(live.system.feature_log)}
    rows["exact"] = solve(exact)
    rows["exact, true poses"] = solve(exact, T_true)
    if offset_ns:
        rows["exact, no time offset"] = solve(exact_features(seq, live.system.feature_log, cam, 0))
    for n in pieces:
        rows[f"pieces {n}"] = solve(live.system.feature_log, tracks=in_pieces(n))
    return rows


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequences", nargs="+", required=True, help="dit-sim euroc folders")
    ap.add_argument("--pieces", nargs="*", type=int, default=[5, 10], help="piece lengths [adjustment frames]")
    ap.add_argument("--out", default=None, help="JSON path")
    args = ap.parse_args(argv)
    from runtime.run import _preload

    _preload()
    res = {}
    for s in args.sequences:
        p = Path(s)
        if not ((p / "mav0" / "depth0").is_dir() and (p / "sim_info.json").is_file()):
            sys.exit(f"intrinsics_tracks: {s} is not a dit-sim euroc sequence (mav0/depth0, sim_info.json)")
        res[p.name] = one_sequence(p, args.pieces)
        print(f"\n{p.name}: refined minus true, fx fy [%], cx cy [px]")
        for k, e in res[p.name].items():
            print(f"  {k:18s} {e[0]:+.3f} {e[1]:+.3f}  {e[2]:+.2f} {e[3]:+.2f}", flush=True)
    variants = list(next(iter(res.values())))
    summary = {}
    print("\n| variant | mean abs focal error [%] | mean abs principal point error [px] |\n|---|---|---|")
    for k in variants:
        e = np.array([r[k] for r in res.values()])
        summary[k] = {"focal_pct": float(np.abs(e[:, :2]).mean()), "principal_px": float(np.abs(e[:, 2:]).mean())}
        print(f"| {k} | {summary[k]['focal_pct']:.3f} | {summary[k]['principal_px']:.2f} |")
    doc = {"sequences": args.sequences, "per_sequence": res, "mean_abs": summary}
    if args.out:
        print(f"wrote {write_json(args.out, doc)}")
    return doc


if __name__ == "__main__":
    main()
