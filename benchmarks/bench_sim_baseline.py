"""Today's sparse ``dit-slam`` (no tuning) on the realistic presets and on the completed real MH_05 excerpt.

    python benchmarks/bench_sim_baseline.py [--presets flight handheld tabletop] [--seeds 0 1 2]
        [--duration 30] [--scale 0.5] [--mh05]

Renders each preset and seed with its realistic defaults (``dit-sim euroc preset=P seed=S duration=D
scale=X``), completes the MH_05 excerpt with an IMU (``dit-sim imu``, without and with a 2 s still period), runs
``dit-slam sequence=DIR out=DIR progress=false`` on each and reports the ATE (SE3 RMSE) or the error the run
ended with (e.g. "never initialised"). The baseline the robustness work has to improve; nothing is tuned here.
Prints a table and writes ``benchmarks/results/bench_sim_baseline.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, cpu_model, write_json

MH05 = REPO.parent / "shared" / "data" / "euroc_MH_05_excerpt"
BIN = Path(sys.executable).parent




def run_slam(seq: Path, out: Path) -> dict:
    t0 = time.perf_counter()
    res = subprocess.run(
        [str(BIN / "dit-slam"), f"sequence={seq}", f"out={out}", "progress=false"],
        capture_output=True,
        text=True,
        timeout=3600,
    )
    row = {"rc": res.returncode, "wall_s": time.perf_counter() - t0}
    first = next(ln for ln in (seq / "mav0" / "cam0" / "data.csv").read_text().splitlines() if not ln.startswith("#"))
    t_first = int(first.split(",")[0]) * 1e-9
    mfile = out / "metrics.json"
    if mfile.is_file():
        m = json.loads(mfile.read_text())
        for k in (
            "ate_se3_rmse_m",
            "ate_sim3_rmse_m",
            "frames",
            "frames_with_pose",
            "keyframes",
            "initialised_at_s",
            "relocalisations",
            "error",
            "n_events",
        ):
            if k in m:
                row[k] = m[k]
        if m.get("initialised_at_s") is not None:
            row["initialised_after_s"] = m["initialised_at_s"] - t_first
    else:
        row["error"] = (res.stderr.strip().splitlines() or ["no metrics.json"])[-1]
    return row


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["flight", "handheld", "tabletop"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--no-mh05", action="store_true", help="skip the real MH_05 excerpt")
    ap.add_argument(
        "--sim-set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="extra dit-sim overrides, e.g. realism=false (a diagnostic: the scenes without sensor physics)",
    )
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "bench_sim_baseline.json"))
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        for preset in args.presets:
            for seed in args.seeds:
                seq = d / f"{preset}_s{seed}"
                subprocess.run(
                    [
                        str(BIN / "dit-sim"),
                        "euroc",
                        f"out={seq}",
                        f"preset={preset}",
                        f"seed={seed}",
                        f"duration={args.duration:g}",
                        f"scale={args.scale:g}",
                        f"workers={args.workers}",
                        "progress=false",
                        *args.sim_set,
                    ],
                    check=True,
                    capture_output=True,
                    text=True,
                )
                row = {
                    "data": "synthetic",
                    "preset": " ".join([preset, *args.sim_set]),
                    "seed": seed,
                    **run_slam(seq, d / f"slam_{preset}_{seed}"),
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
        if not args.no_mh05 and (MH05 / "mav0").is_dir():
            for still in (0.0, 2.0):
                seq = d / f"mh05_still{still:g}"
                subprocess.run(
                    [str(BIN / "dit-sim"), "imu", f"source={MH05}", f"out={seq}", f"still={still:g}"],
                    check=True,
                    capture_output=True,
                    text=True,
                )
                row = {
                    "data": "real MH_05 excerpt + synthesised IMU",
                    "preset": f"mh05 still={still:g}s",
                    "seed": 0,
                    **run_slam(seq, d / f"slam_mh05_{still:g}"),
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
    print(f"\nsparse dit-slam baseline ({cpu_model()}; synthetic: {args.duration:g} s, scale {args.scale:g})")
    print(f"{'sequence':32s} {'seed':>4s} {'ATE SE3 [m]':>12s} {'init after [s]':>14s} {'posed':>9s}  note")
    for r in rows:
        ate = f"{r['ate_se3_rmse_m']:.4f}" if "ate_se3_rmse_m" in r else "-"
        init = f"{r['initialised_after_s']:.1f}" if r.get("initialised_after_s") is not None else "-"
        posed = f"{r.get('frames_with_pose', 0)}/{r.get('frames', 0)}"
        print(f"{r['preset']:32s} {r['seed']:4d} {ate:>12s} {init:>14s} {posed:>9s}  {r.get('error') or ''}")
    res = {"cpu": cpu_model(), "duration_s": args.duration, "scale": args.scale, "sim_set": args.sim_set, "rows": rows}
    write_json(args.out, res)
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
