"""SLAM on a fisheye sequence vs the pinhole sequence of the same seed (same scene, motion and IMU).

    python benchmarks/bench_fisheye.py [--seeds 0 1 2] [--duration 30] [--scale 1.0]

Renders ``textured`` with ``camera=pinhole`` (EuRoC's cam0) and ``camera=fisheye`` (:data:`sim.euroc.FISHEYE_CAM0`,
equidistant, seen by the system through its pinhole view) for each seed (cached under
``<cache>/bench-fisheye-*``), runs the sparse system on both and reports the ATE (SE3) of each and their ratio.
Prints a table and writes ``benchmarks/results/bench_fisheye.json``.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile

from benchmarks.common import REPO, cache_dir, markdown_table, slam_machine, write_json


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "bench_fisheye.json"))
    args = ap.parse_args(argv)
    from runtime.io.sequence import open_sequence
    from runtime.run import run_sequence
    from sim.euroc import write_euroc_sequence

    rows, res = [], []
    for seed in args.seeds:
        row = {"seed": seed}
        for camera in ("pinhole", "fisheye"):
            root = cache_dir() / f"bench-fisheye-{camera}-{args.duration:g}s-x{args.scale:g}-s{seed}"
            if not (root / "sim_info.json").is_file():
                write_euroc_sequence(
                    root, "textured", args.duration, seed, scale=args.scale, workers=args.workers, camera=camera
                )
            with tempfile.TemporaryDirectory() as out:
                m = run_sequence(open_sequence(root), out, progress=False, plot=False)
            row[camera] = {
                k: m.get(k)
                for k in (
                    "ate_se3_rmse_m",
                    "ate_sim3_rmse_m",
                    "frames_with_pose",
                    "keyframes",
                    "map_points",
                    "cpu_ms_per_frame",
                    "error",
                )
            }
        a, b = row["pinhole"]["ate_se3_rmse_m"], row["fisheye"]["ate_se3_rmse_m"]
        row["ratio_fisheye_over_pinhole"] = b / a if a and b else None
        res.append(row)
        rows.append(
            [
                seed,
                f"{1e3 * a:.1f}" if a else "-",
                f"{1e3 * b:.1f}" if b else "-",
                f"{row['ratio_fisheye_over_pinhole']:.2f}" if row["ratio_fisheye_over_pinhole"] else "-",
                row["pinhole"]["frames_with_pose"],
                row["fisheye"]["frames_with_pose"],
            ]
        )
        print(rows[-1], flush=True)
    ratios = [r["ratio_fisheye_over_pinhole"] for r in res if r["ratio_fisheye_over_pinhole"]]
    print(markdown_table(["seed", "pinhole ATE mm", "fisheye ATE mm", "ratio", "poses pinhole", "poses fisheye"], rows))
    if ratios:
        print(f"ratio fisheye / pinhole: median {statistics.median(ratios):.2f}, max {max(ratios):.2f}")
    out = {"args": vars(args), "machine": slam_machine(), "runs": res, "ratios": ratios}
    write_json(args.out, out)
    return out


if __name__ == "__main__":
    main()
