"""Do a sequence's ground-truth poses explain its images? Tracks triangulated from given camera poses, reprojected.

    python benchmarks/gt_reprojection.py --sequence DIR [--gt CSV] [--estimate RUN_DIR] [--shifts-ms 0 10 20]
        [--out FILE.json]

OpenCV's pyramidal KLT (not the runtime's front end, so that the check does not share its choices) follows corners
through the images, keeping forward-backward consistent tracks of at least 6 frames. Each track is triangulated
by the runtime's linear triangulation (:func:`runtime.frontend.triangulation.triangulate`) from the camera poses
``T_w_b(t) @ T_b_c`` and reprojected into the frames that saw it; the error [px] is summarised over the tracks
whose every view lies within 5 px (the others are counted as outliers). A ground truth
that matches the images up to a similarity gives errors at the level of the tracking noise.

Variants: the ground truth as it is, with its positions shifted in time by ``--shifts-ms`` (the rotation left on
the camera clock), and the camera poses of a ``dit-slam`` run (``--estimate``, its ``trajectory.txt``). ``--gt``
reads the poses from another ``state_groundtruth_estimate0/data.csv`` (e.g. a source sequence whose ground truth
extends beyond the shifted times). Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import write_json

MIN_VIEWS = 6
MAX_PX = 5.0


def klt_tracks(seq, max_len: int = 25, target: int = 300, fb_px: float = 0.3) -> list[dict[int, np.ndarray]]:
    """Forward-backward checked KLT tracks ``{frame index: pixel (2,)}`` of at least ``MIN_VIEWS`` frames."""
    import cv2

    cam = seq.camera
    tracks: list[dict[int, np.ndarray]] = []
    active: list[tuple[int, np.ndarray]] = []
    prev = None
    for i in range(len(seq.frame_ts)):
        img = seq.image(i)
        if prev is not None and active:
            p0 = np.float32([q for _, q in active]).reshape(-1, 1, 2)
            p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, p0, None, winSize=(21, 21), maxLevel=3)
            pb, st2, _ = cv2.calcOpticalFlowPyrLK(img, prev, p1, None, winSize=(21, 21), maxLevel=3)
            ok = (st.ravel() == 1) & (st2.ravel() == 1)
            ok &= np.linalg.norm((pb - p0).reshape(-1, 2), axis=1) < fb_px
            ok &= cam.in_image(p1.reshape(-1, 2), 8)
            kept = []
            for (ti, _), q, k in zip(active, p1.reshape(-1, 2), ok, strict=True):
                if k and len(tracks[ti]) < max_len:
                    tracks[ti][i] = q.astype(np.float64)
                    kept.append((ti, q))
            active = kept
        if len(active) < target * 5 // 6:
            mask = np.full(img.shape, 255, np.uint8)
            for _, q in active:
                cv2.circle(mask, (int(q[0]), int(q[1])), 12, 0, -1)
            found = cv2.goodFeaturesToTrack(img, target - len(active), 0.01, 12, mask=mask)
            for q in [] if found is None else found.reshape(-1, 2):
                tracks.append({i: q.astype(np.float64)})
                active.append((len(tracks) - 1, q))
        prev = img
    return [t for t in tracks if len(t) >= MIN_VIEWS]


def reprojection(tracks_n: list[tuple[np.ndarray, np.ndarray]], T_w_c: np.ndarray, f_px: float) -> dict:
    """Each track triangulated from the camera poses (the runtime's linear triangulation) and its reprojection
    error [px] in every view."""
    from runtime.frontend.triangulation import stack_views, triangulate

    T, xn, mask = stack_views(T_w_c, tracks_n)
    X, _, diag = triangulate(T, xn, mask, focal=f_px)
    p_c = np.einsum("mvji,mvj->mvi", T[..., :3, :3], X[:, None, :] - T[..., :3, 3])
    z = np.where(mask, p_c[..., 2], 1.0)
    err = np.linalg.norm(p_c[..., :2] / z[..., None] - xn, axis=-1) * f_px
    front = (diag["min_depth"] >= 0.2) & np.isfinite(X).all(1)
    outlier = front & (diag["max_err_px"] > MAX_PX)
    kept = front & ~outlier
    e = err[kept][mask[kept]]
    return {
        "median_px": float(np.median(e)) if e.size else float("nan"),
        "rms_px": float(np.sqrt(np.mean(e**2))) if e.size else float("nan"),
        "p90_px": float(np.percentile(e, 90)) if e.size else float("nan"),
        "tracks": int(kept.sum()),
        "outlier_tracks": int(outlier.sum()),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", required=True, help="EuRoC-layout folder with cam0 images and a ground truth")
    ap.add_argument("--gt", default=None, help="another state_groundtruth_estimate0/data.csv for the poses")
    ap.add_argument("--estimate", default=None, help="a dit-slam output folder (trajectory.txt)")
    ap.add_argument("--shifts-ms", type=float, nargs="*", default=[0.0], help="position time shifts [ms]")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    from runtime.geometry import interpolate_poses
    from runtime.io.euroc import read_euroc, read_groundtruth
    from runtime.io.tum import read_tum

    try:
        seq = read_euroc(Path(args.sequence))
        gt = read_groundtruth(args.gt) if args.gt else seq.gt
    except (OSError, ValueError) as e:
        sys.exit(f"gt_reprojection: {e}")
    if gt is None:
        sys.exit(f"gt_reprojection: {args.sequence} has no ground truth (give --gt)")
    ts = seq.frame_ts.astype(np.int64)
    tracks = klt_tracks(seq)
    tracks_n = []
    for t in tracks:
        frames = np.array(sorted(t))
        tracks_n.append((frames, seq.camera.pixel_to_normalized(np.array([t[k] for k in frames]))))
    f_px = float(seq.camera.intrinsics[0])
    print(f"{args.sequence}: {len(ts)} frames, {len(tracks)} KLT tracks of >= {MIN_VIEWS} frames")
    rows = {}
    R_gt = np.array([gt.pose_at(int(t)) for t in ts])
    for d in args.shifts_ms:
        T = R_gt.copy()
        T[:, :3, 3] = np.array([gt.pose_at(int(t + d * 1e6)) for t in ts])[:, :3, 3]
        rows[f"ground truth, positions {d:+g} ms"] = reprojection(tracks_n, T @ seq.T_b_c, f_px)
    if args.estimate:
        est_ts, est_T = read_tum(Path(args.estimate) / "trajectory.txt")
        inside = (ts >= est_ts[0]) & (ts <= est_ts[-1])
        T_e, _ = interpolate_poses(ts[inside], est_ts, est_T)
        sel = np.flatnonzero(inside)
        remap = {int(i): k for k, i in enumerate(sel)}
        sub = [(np.array([remap[int(f)] for f in fr]), xn) for fr, xn in tracks_n if all(int(f) in remap for f in fr)]
        rows["dit-slam estimate"] = reprojection(sub, T_e @ seq.T_b_c, f_px)
    print(f"{'poses':34s} {'median':>8s} {'rms':>8s} {'p90':>8s} {'tracks':>7s} {'outliers':>9s}")
    for k, r in rows.items():
        print(
            f"{k:34s} {r['median_px']:6.3f}px {r['rms_px']:6.3f}px {r['p90_px']:6.3f}px {r['tracks']:7d} "
            f"{r['outlier_tracks']:9d}"
        )
    res = {"sequence": str(args.sequence), "gt": args.gt, "tracks": len(tracks), "rows": rows}
    if args.out:
        write_json(args.out, res)
        print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
