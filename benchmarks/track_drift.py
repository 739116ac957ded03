"""How far the front end's tracks drift from the true projection of the point they started on, by track age.

    python benchmarks/track_drift.py --sequence DIR [--line-delay 0 auto] [--frames N] [--out F.json]

Needs a sequence rendered by ``dit-sim euroc`` (ground-truth depth in ``mav0/depth0``, ground truth, and
``sim_info.json``, whose ``render_camera`` and ``time_offset_s`` give the true camera and clock). The runtime's
:class:`runtime.frontend.tracking.FeatureTracker` follows corners through the images (replenished below 150 tracks);
each track's point is fixed at its second observation, the first with a velocity, by back-projecting the pixel
with the rendered depth (left out where the depth varies by more than 1 % within 1 px: edges) through the
ground-truth camera pose. In every later frame the point is projected with the true camera and compared with
the track's pixel as the estimator sees it: :meth:`FeatureTracker.rolling_shutter_pixels`, the image pixel moved to
the stamp's time when ``--line-delay`` is not 0. ``auto`` takes the line delay that cam0's ``sensor.yaml`` states.

The error of a track grows with its age: the KLT follows a patch whose look changes with the viewpoint, and a
rolling shutter puts each row at its own time. Prints the median and 90th percentile per age bin for each line
delay, and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import write_json
from runtime.dense.lookup import bilinear

#: Track ages [frames] reported; each bin holds the ages from its value to 1.25 times it.
AGES = (1, 2, 5, 10, 20, 30, 50, 80)
#: A point whose depth varies by more than this fraction within 1 px of its bilinear support lies on an edge.
EDGE_REL = 0.01
#: Fewest tracks before new corners are detected.
MIN_TRACKS = 150


def true_camera(seq, info: dict):
    """The camera the images were rendered with: ``sim_info.json``'s ``render_camera`` (intrinsics, radial-tangential
    distortion) on the written camera's model and size; the written camera when there is none (``ideal=true``)."""
    from dataclasses import replace

    rc = info.get("render_camera")
    return replace(seq.camera, fx=rc[0], fy=rc[1], cx=rc[2], cy=rc[3], dist=tuple(rc[4:8])) if rc else seq.camera


def time_offset_ns(info: dict) -> int:
    """``sim_info.json``'s camera time offset [ns]: the image stamped ``t`` shows the scene at ``t`` plus it."""
    return int(round(float(info.get("time_offset_s") or 0.0) * 1e9))


def true_pose(seq, ts_ns: int, offset_ns: int) -> np.ndarray:
    """(4, 4) true body pose ``T_w_b`` of the image stamped ``ts_ns``: at its true time, held inside the ground
    truth's range."""
    return seq.gt.pose_at(min(max(int(ts_ns) + offset_ns, int(seq.gt.ts[0])), int(seq.gt.ts[-1])))


def back_project(depth: np.ndarray, uv: np.ndarray, camera, T_w_c: np.ndarray) -> np.ndarray | None:
    """The world point (3,) that pixel ``uv`` of ``camera`` at ``T_w_c`` sees at the rendered ``depth`` (None on a
    depth edge, outside the image or without depth; :func:`_bilinear`)."""
    z = _bilinear(depth, uv)
    if z <= 0:
        return None
    xn = camera.pixel_to_normalized(np.asarray(uv, np.float64)[None])[0]
    return T_w_c[:3, :3] @ (np.array([xn[0], xn[1], 1.0]) * z) + T_w_c[:3, 3]


def project(camera, T_w_c: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of world points (N, 3) in ``camera`` at ``T_w_c`` and the mask of those that project: rows of
    NaN (no point) and points nearer than 0.1 m in front of the camera do not."""
    X_c = (X - T_w_c[:3, 3]) @ T_w_c[:3, :3]
    with np.errstate(invalid="ignore"):
        q, ok = camera.project(X_c)
        ok &= np.isfinite(X_c[:, 2]) & (X_c[:, 2] > 0.1)
    return q, ok


def true_projections(
    seq, i: int, ids: np.ndarray, uv: np.ndarray, points: dict, camera, T_w_c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of the points of tracks ``ids`` (N,) in image ``i`` of ``seq`` (``camera`` at ``T_w_c``) and the
    mask of those that project. A track's point is fixed at its first sight: its pixel in ``uv`` (N, 2) back-projected
    at image ``i``'s rendered depth, kept in ``points`` (``id -> point``, None on a depth edge: no projection)."""
    depth = None
    for tid, p in zip(ids.tolist(), uv, strict=True):
        if tid not in points:
            depth = seq.depth(i) if depth is None else depth
            points[tid] = back_project(depth, p, camera, T_w_c)
    nan = np.full(3, np.nan)
    X = np.array([nan if points[t] is None else points[t] for t in ids.tolist()]).reshape(-1, 3)
    return project(camera, T_w_c, X)


def _bilinear(depth: np.ndarray, uv: np.ndarray) -> float:
    """Depth at a subpixel (2,), 0 outside the image or next to a pixel without depth, or across an edge."""
    x0, y0 = int(np.floor(uv[0])), int(np.floor(uv[1]))
    h, w = depth.shape
    if not (1 <= x0 < w - 2 and 1 <= y0 < h - 2):
        return 0.0
    patch = depth[y0 - 1 : y0 + 3, x0 - 1 : x0 + 3]
    if patch.min() <= 0 or patch.max() - patch.min() > EDGE_REL * patch.max():
        return 0.0
    return float(bilinear(depth.astype(np.float64), np.asarray(uv, np.float64)[None])[0])


def track_errors(seq, line_delay_s: float, frames: int | None = None) -> dict[int, list[float]]:
    """Errors [px] of the tracks against the true projection of their points, by age [frames]."""
    from runtime.frontend.tracking import FeatureTracker, TrackerConfig

    info = json.loads((Path(seq.root) / "sim_info.json").read_text())
    true_cam = true_camera(seq, info)
    offset_ns = time_offset_ns(info)
    tracker = FeatureTracker(seq.camera, seq.T_b_c, cfg=TrackerConfig(line_delay_s=line_delay_s))
    points: dict[int, tuple[int, np.ndarray] | None] = {}
    seen: set[int] = set()
    errors: dict[int, list[float]] = {}
    n = len(seq.frame_ts) if frames is None else min(frames, len(seq.frame_ts))
    for i in range(n):
        ts = int(seq.frame_ts[i])
        image = seq.image(i)
        tracker.track(ts, image)
        if tracker.n_tracks < MIN_TRACKS:
            tracker.replenish(ts, image)
        T_w_c = true_pose(seq, ts, offset_ns) @ seq.T_b_c
        uv_all = tracker.rolling_shutter_pixels()
        depth = None
        for tid, uv in zip(tracker.ids.tolist(), uv_all, strict=True):
            if tid not in seen:  # first observation: no velocity yet
                seen.add(tid)
                continue
            if tid not in points:
                depth = seq.depth(i) if depth is None else depth
                X = back_project(depth, uv, true_cam, T_w_c)
                points[tid] = None if X is None else (i, X)
                continue
            p = points[tid]
            if p is None:
                continue
            X_c = T_w_c[:3, :3].T @ (p[1] - T_w_c[:3, 3])
            if X_c[2] < 0.1:
                continue
            proj, _ = true_cam.project(X_c[None])
            errors.setdefault(i - p[0], []).append(float(np.linalg.norm(proj[0] - uv)))
    return errors


def summarise(errors: dict[int, list[float]]) -> list[dict]:
    """Median and 90th percentile [px] per age bin of :data:`AGES`."""
    rows = []
    for a in AGES:
        e = np.array([x for k in range(a, int(a * 1.25) + 1) for x in errors.get(k, [])])
        if e.size:
            med, p90 = float(np.median(e)), float(np.percentile(e, 90))
            rows.append({"age": a, "n": int(e.size), "median_px": med, "p90_px": p90})
    return rows


def main(argv: list[str] | None = None) -> dict:
    from runtime.io.euroc import read_euroc

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", required=True, help="a dit-sim euroc folder (with mav0/depth0 and sim_info.json)")
    ap.add_argument("--line-delay", nargs="+", default=["0", "auto"], help="s between rows, or auto (sensor.yaml)")
    ap.add_argument("--frames", type=int, default=None, help="the first N frames")
    ap.add_argument("--out", default=None, help="JSON path")
    args = ap.parse_args(argv)
    try:
        seq = read_euroc(Path(args.sequence))
    except (OSError, ValueError) as e:
        sys.exit(f"track_drift: {e}")
    if seq.gt is None or not seq.has_depth or not (Path(args.sequence) / "sim_info.json").is_file():
        sys.exit(f"track_drift: {args.sequence} needs a ground truth, mav0/depth0 and sim_info.json (dit-sim euroc)")
    res = {}
    for ld in args.line_delay:
        delay = seq.camera.line_delay_s if ld == "auto" else float(ld)
        rows = summarise(track_errors(seq, delay, args.frames))
        res[f"{delay:g}"] = rows
        print(f"\nline delay {delay:g} s ({ld}): track error against the true projection [px]")
        print("| age [frames] | observations | median | p90 |")
        print("|---|---|---|---|")
        for r in rows:
            print(f"| {r['age']} | {r['n']} | {r['median_px']:.3f} | {r['p90_px']:.3f} |")
    doc = {"sequence": str(args.sequence), "frames": args.frames, "by_line_delay": res}
    if args.out:
        print(f"wrote {write_json(args.out, doc)}")
    return doc


if __name__ == "__main__":
    main()
