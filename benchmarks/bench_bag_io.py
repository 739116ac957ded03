"""Reading a sequence from a ROS bag vs its ASL folder: time and peak memory, in one run (ratios).

    python benchmarks/bench_bag_io.py [--duration 60] [--scale 1.0] [--repeats 3]

Renders one ``textured`` sequence (cached under ``<cache>/bench-bag-io-*``), writes it as a ROS1 bag and a ROS2
(sqlite3) bag, then reads each input in a fresh process: open it (IMU and ground truth in memory, image stamps)
and decode every image in order, as ``dit-slam`` does. Each child reports its wall and CPU time and its peak
resident memory (``ru_maxrss``), also above the memory after its imports (the same for all inputs: ``rosbags``
is imported first everywhere; the "above imports" ratio divides by at least 1 MB). Inputs alternate over the repeats;
medians are reported. Prints a table and writes ``benchmarks/results/bench_bag_io.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks.common import REPO, cache_dir, machine_info, markdown_table, write_json

CHILD = """
import json, resource, sys, time
from runtime.io.sequence import open_sequence
import numpy as np
import rosbags.highlevel, rosbags.rosbag1, rosbags.rosbag2  # both inputs start from the same imports
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t0, c0 = time.perf_counter(), time.process_time()
seq = open_sequence(sys.argv[1], None if sys.argv[2] == '-' else sys.argv[2])
t_open = time.perf_counter() - t0
total = 0
for i in range(len(seq)):
    total += int(seq.image(i)[::16, ::16].sum())
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(dict(wall_s=wall, cpu_s=cpu, open_s=t_open, frames=len(seq), imu=int(seq.imu_ts.size),
                      peak_rss_mb=rss, import_rss_mb=rss0, checksum=total)))
"""


def _prepare(duration: float, scale: float, seed: int) -> dict[str, tuple[Path, str]]:
    from sim.bag import write_bag
    from sim.euroc import write_euroc_sequence

    root = cache_dir() / f"bench-bag-io-{duration:g}s-x{scale:g}-s{seed}"
    asl = root / "asl"
    if not (asl / "sim_info.json").is_file():
        write_euroc_sequence(asl, "textured", duration=duration, seed=seed, progress=True, scale=scale, workers=2)
    ros1, ros2, calib = root / "seq.bag", root / "seq_ros2", root / "calib"
    if not ros1.exists():
        write_bag(asl, ros1, "bag", calib_dir=calib)
    if not ros2.exists():
        write_bag(asl, ros2, "ros2")
    return {"asl": (asl, "-"), "ros1_bag": (ros1, str(calib)), "ros2_db3": (ros2, str(calib))}


def _du_mb(p: Path) -> float:
    files = [p] if p.is_file() else [f for f in p.rglob("*") if f.is_file()]
    return sum(f.stat().st_size for f in files) / 2**20


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "bench_bag_io.json"))
    args = ap.parse_args(argv)
    inputs = _prepare(args.duration, args.scale, args.seed)
    runs: dict[str, list[dict]] = {k: [] for k in inputs}
    for _ in range(args.repeats):
        for name, (path, calib) in inputs.items():
            out = subprocess.run([sys.executable, "-c", CHILD, str(path), calib], capture_output=True, text=True)
            if out.returncode:
                raise RuntimeError(f"{name}: {out.stderr[-2000:]}")
            runs[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    sums = {r["checksum"] for rs in runs.values() for r in rs}
    if len(sums) != 1:
        raise RuntimeError(f"the inputs decoded to different images (checksums {sums})")
    med = {
        n: {
            k: statistics.median(r[k] for r in rs)
            for k in ("wall_s", "cpu_s", "open_s", "peak_rss_mb", "import_rss_mb")
        }
        for n, rs in runs.items()
    }
    base = med["asl"]
    rows, summary = [], {}
    for n, m in med.items():
        above = m["peak_rss_mb"] - m["import_rss_mb"]
        s = {
            **m,
            "size_mb": _du_mb(inputs[n][0]),
            "rss_above_imports_mb": above,
            "time_ratio_vs_asl": m["wall_s"] / base["wall_s"],
            "cpu_ratio_vs_asl": m["cpu_s"] / base["cpu_s"],
            "peak_rss_ratio_vs_asl": m["peak_rss_mb"] / base["peak_rss_mb"],
            "rss_above_imports_ratio_vs_asl": above / max(base["peak_rss_mb"] - base["import_rss_mb"], 1.0),
        }
        summary[n] = s
        rows.append(
            [
                n,
                f"{s['size_mb']:.0f}",
                f"{m['wall_s']:.2f}",
                f"{m['cpu_s']:.2f}",
                f"{s['time_ratio_vs_asl']:.2f}",
                f"{m['peak_rss_mb']:.0f}",
                f"{above:.0f}",
                f"{s['peak_rss_ratio_vs_asl']:.2f}",
                f"{s['rss_above_imports_ratio_vs_asl']:.2f}",
            ]
        )
    frames = runs["asl"][0]["frames"]
    print(f"reading {frames} frames ({args.duration:g} s, scale {args.scale:g}), median of {args.repeats} runs each")
    print(
        markdown_table(
            [
                "input",
                "size MB",
                "wall s",
                "CPU s",
                "time / ASL",
                "peak RSS MB",
                "above imports MB",
                "RSS / ASL",
                "above imports / ASL",
            ],
            rows,
        )
    )
    res = {"args": vars(args), "machine": machine_info(), "frames": frames, "summary": summary, "runs": runs}
    write_json(args.out, res)
    return res


if __name__ == "__main__":
    main()
