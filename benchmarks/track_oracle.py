"""What exact feature tracks would buy the trajectory: the sparse system with its KLT tracks and with exact ones.

``dit-slam`` (sparse) with the front end's tracks, against the same run with every track snapped to the true
projection of its point.

    python benchmarks/track_oracle.py --sequences DIR [DIR ...] --work DIR [--out F.json]

Each DIR is a global-shutter sequence rendered by ``dit-sim euroc`` (``mav0/depth0``, ground truth and
``sim_info.json``). In the ``exact`` arm the KLT runs as always, and after each step every track's pixel is replaced
by the projection of its point through the rendered camera at the image's true time (``time_offset_s``): what a
tracker without drift would report. A track's point is fixed the first time it is tracked, by back-projecting
its pixel with the rendered depth (:func:`benchmarks.track_drift.back_project`). A track whose first pixel lies on a
depth edge has no such point (a corner made by an occlusion is not a point of the scene); it is dropped. So the arm
is exact tracks without the edge corners. Everything else is the default system, the intrinsics refinement's
first pass included. The difference between the arms bounds what a better tracker could gain on these sequences.
Prints SE(3) and Sim(3) ATE per run and the paired difference, and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import numpy as np

from benchmarks.common import slam_machine, write_json
from benchmarks.track_drift import time_offset_ns, true_camera, true_pose, true_projections

__all__ = ["ExactTracks", "exact_tracks", "main"]


class ExactTracks:
    """Snaps a :class:`runtime.frontend.tracking.FeatureTracker`'s tracks of ``seq`` to their true pixels."""

    def __init__(self, seq, info: dict) -> None:
        self.camera = true_camera(seq, info)
        self.offset_ns = time_offset_ns(info)
        self.seq = seq
        self.index = {int(t): i for i, t in enumerate(np.asarray(seq.frame_ts, dtype=np.int64))}
        self.points: dict[int, np.ndarray | None] = {}  # of the tracker snapped last (track ids are per tracker)
        self.snapped = self.dropped = 0

    def snap(self, tracker, ts: int) -> None:
        """Replace the tracks' pixels at image ``ts`` by their points' true projections; drop tracks without one."""
        i = self.index.get(int(ts))
        if i is None or tracker.ids.size == 0:
            return
        T = true_pose(self.seq, ts, self.offset_ns) @ self.seq.T_b_c
        self.points = tracker.__dict__.setdefault("_exact_points", {})  # the first pass's tracker has its own ids
        uv = tracker.uv.astype(np.float64)
        q, ok = true_projections(self.seq, i, tracker.ids, uv, self.points, self.camera, T)
        self.snapped += int(ok.sum())
        self.dropped += int((~ok).sum())
        tracker.ids, tracker.uv, tracker.vel = tracker.ids[ok], q[ok].astype(np.float32), tracker.vel[ok]


@contextmanager
def exact_tracks(seq, info: dict):
    """Within the block every new ``FeatureTracker`` reports exact tracks of ``seq``; yields the
    :class:`ExactTracks` (its counts)."""
    from runtime.frontend.tracking import FeatureTracker

    if float(getattr(seq.camera, "line_delay_s", 0.0) or 0.0) > 0:
        raise ValueError(
            f"{seq.root}: a rolling-shutter sequence (line_delay_s > 0); exact tracks need a global shutter"
        )
    oracle = ExactTracks(seq, info)
    track = FeatureTracker.track

    def exact(self, ts, image, R_b0_b1=None):
        f = track(self, ts, image, R_b0_b1)
        oracle.snap(self, ts)
        return self._features(ts, f.flow_px, f.n_lost, f.n_ransac_out)

    with mock.patch.object(FeatureTracker, "track", exact):
        yield oracle


def run_pair(path: Path, work: Path) -> dict:
    """Both arms of one sequence: the metrics that matter and the oracle's counts."""
    from runtime.io.euroc import read_euroc
    from runtime.run import run_sequence
    from runtime.slam import SlamConfig

    info = json.loads((path / "sim_info.json").read_text())
    row = {}
    for arm in ("klt", "exact"):
        seq = read_euroc(path)
        out = work / path.name / arm
        if arm == "klt":
            m = run_sequence(seq, out, SlamConfig(), progress=False, plot=False)
            counts = {}
        else:
            with exact_tracks(seq, info) as oracle:
                m = run_sequence(seq, out, SlamConfig(), progress=False, plot=False)
            counts = {"snapped": oracle.snapped, "dropped": oracle.dropped}
        keys = ("ate_se3_rmse_m", "ate_sim3_rmse_m", "frames", "frames_with_pose", "path_length_m")
        row[arm] = {k: m[k] for k in keys} | counts
    return row


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequences", nargs="+", required=True, help="dit-sim euroc folders (global shutter)")
    ap.add_argument("--work", required=True, help="folder for the runs' outputs")
    ap.add_argument("--out", default=None, help="JSON path")
    args = ap.parse_args(argv)
    from runtime.io.euroc import read_euroc
    from runtime.run import _preload

    paths = [Path(s) for s in args.sequences]
    for p in paths:
        if not ((p / "mav0" / "depth0").is_dir() and (p / "sim_info.json").is_file()):
            sys.exit(f"track_oracle: {p} is not a dit-sim euroc sequence (mav0/depth0, sim_info.json)")
        if float(read_euroc(p).camera.line_delay_s or 0.0) > 0:
            sys.exit(
                f"track_oracle: {p} has a rolling shutter (line_delay_s in cam0's sensor.yaml); "
                "exact tracks need a global shutter"
            )
    _preload()
    rows = {}
    print("| sequence | SE(3) KLT | SE(3) exact | Sim(3) KLT | Sim(3) exact | tracks dropped |")
    print("|---|---|---|---|---|---|")
    for p in paths:
        r = rows[p.name] = run_pair(p, Path(args.work))
        k, e = r["klt"], r["exact"]
        share = e["dropped"] / max(e["snapped"] + e["dropped"], 1)
        print(
            f"| {p.name} | {1e3 * k['ate_se3_rmse_m']:.1f} | {1e3 * e['ate_se3_rmse_m']:.1f} | "
            f"{1e3 * k['ate_sim3_rmse_m']:.1f} | {1e3 * e['ate_sim3_rmse_m']:.1f} | {100 * share:.0f} % |",
            flush=True,
        )
    summary = {}
    for key in ("ate_se3_rmse_m", "ate_sim3_rmse_m"):
        d = 1e3 * np.array([r["exact"][key] - r["klt"][key] for r in rows.values()])
        se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan")
        summary[key] = {"exact_minus_klt_mm": float(d.mean()), "se_mm": se, "exact_lower": int((d < 0).sum())}
        print(f"{key}: exact - KLT {d.mean():+.1f} ± {se:.1f} mm, lower on {(d < 0).sum()} of {d.size}")
    doc = {"sequences": args.sequences, "machine": slam_machine(), "runs": rows, "summary": summary}
    if args.out:
        print(f"wrote {write_json(args.out, doc)}")
    return doc


if __name__ == "__main__":
    main()
