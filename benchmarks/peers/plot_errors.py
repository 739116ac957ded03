"""Per-frame position error of every system of a ``bench_peers`` run on one sequence, after the same alignment as
its score (Sim(3) for the monocular peers against the camera frame; Sim(3) for the inertial systems against the
body frame, so that every curve is scale-free and comparable).

    python -m benchmarks.peers.plot_errors --work outputs/peers/runs_A [more folders] --sequence textured_s0 \\
        --data outputs/peers/seq --out reports/peers_textured_s0.png
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import numpy as np

from benchmarks.peers import scoring
from runtime.geometry import interpolate_poses, ns_to_s


def aligned_errors(system: str, est_ts, est_T, gt_ts, gt_T_w_b, T_b_c, alignment: str = "sim3"):
    """(ts [ns], per-frame position error [m]) after the alignment ``alignment`` to the system's reference."""
    from evo.core.trajectory import PoseTrajectory3D

    ref_all = scoring.reference_poses(gt_T_w_b, T_b_c, scoring.reference_frame(system))
    ref_T, inside = interpolate_poses(np.asarray(est_ts, np.int64), gt_ts, ref_all)
    ts = np.asarray(est_ts, np.int64)[inside]
    est = PoseTrajectory3D(poses_se3=list(np.asarray(est_T)[inside]), timestamps=ns_to_s(ts))
    ref = PoseTrajectory3D(poses_se3=list(ref_T), timestamps=ns_to_s(ts))
    est = copy.deepcopy(est)
    est.align(ref, correct_scale=(alignment == "sim3"))
    return ts, np.linalg.norm(est.positions_xyz - ref.positions_xyz, axis=1)


def main(argv: list[str] | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from runtime.io.euroc import read_euroc
    from runtime.io.tum import read_tum

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--work", required=True, nargs="+", help="bench_peers --work folders (the first with a system's runs wins)"
    )
    ap.add_argument("--sequence", required=True)
    ap.add_argument("--data", required=True, help="bench_peers --data folder")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    seq = read_euroc(Path(a.data) / a.sequence)
    fig, ax = plt.subplots(figsize=(9, 3.6))
    t0 = int(seq.frame_ts[0])
    for system in scoring.SYSTEMS:
        runs = []  # the first --work folder with a run of this system: all its runs
        for w in a.work:
            files = sorted((Path(w) / a.sequence).glob(f"{system}_run*/trajectory.txt"))
            runs = [f for f in files if f.stat().st_size > 0]
            if runs:
                break
        curves = []
        for f in runs:
            est_ts, est_T = read_tum(f)
            if len(est_ts) >= 3:
                ts, err = aligned_errors(system, est_ts, est_T, seq.gt.ts, seq.gt.T_w_b, seq.T_b_c)
                curves.append((float(np.sqrt(np.mean(err**2))), ts, err))
        if not curves:
            continue
        curves.sort(key=lambda c: c[0])
        rmse, ts, err = curves[(len(curves) - 1) // 2]  # the median run (the lower one of an even count)
        which = f", median of {len(curves)} runs" if len(curves) > 1 else ""
        ax.plot(
            (ts - t0) * 1e-9,
            1e3 * err,
            lw=1,
            label=f"{system} (Sim3 vs {scoring.reference_frame(system)}, {1e3 * rmse:.1f} mm{which})",
        )
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [mm]")
    ax.set_yscale("log")
    ax.set_title(f"{a.sequence}: per-frame error after Sim(3) alignment (the median run of each system)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    out = Path(a.out)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    main()
