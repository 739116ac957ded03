"""What decides the ``whitewall`` ATE: the IMU-only coast in front of the bare wall, and how the trajectory after
the relocalisation ties back to the one before it.

    python benchmarks/bench_dense.py --presets whitewall      # the runs (once)
    python benchmarks/bench_coast.py                          # seeds 0 1 2, 60 s, the same folders

While the camera sees nothing but the bare wall, no visual residual constrains the motion: a monocular system
is left with the IMU between two visual fixes, and depth on a blank plane could at best add the distance to it
(its normal component), if the depth followed the distance. Two tables:

**Oracles** (what the coast allows). Per sequence the script smooths keyframe states every ``--dt-kf`` seconds
over the coast with GTSAM (``CombinedImuFactor`` on the sequence's noisy IMU, bias random walk included) from
the ground-truth state at the loss (pose, velocity, biases), and at the regain:

* ``end pose``: the ground-truth pose only (what a relocalisation's PnP gives);
* ``end pose+vel``: pose and velocity (what the tracking after the relocalisation gives);
* ``+ wall distance``: the latter plus the exact camera-to-wall distance at every keyframe (a perfect depth
  sensor on the wall, 1 cm sigma).

It prints their position RMSE over the coast [mm] in the ground-truth frame.

**Runs** (where each run's ATE comes from). For every run folder of the sequence (``bench_dense``'s modes): the
ATE (SE(3) alignment of the whole trajectory, positions), the RMSE before, over and after the coast under that
alignment, the RMSE of the part before and of the part after the coast each aligned on its own, and the
disagreement of those two alignments at the last coasted pose (the relocalisation): how far apart [mm] and how
much rotated [deg] the two parts' frames are. A large jump with small one-sided errors means that the ATE is
set by the tie between the two parts, not by the coast.

The coast interval comes from the sparse run's events ("visual tracking lost" / "regained"); without a run, from
the sequence's white-wall hold widened by ``--widen`` seconds. The oracles and the split are
:mod:`runtime.diagnostics.coast`; this script runs them over the sequences and writes ``bench_coast.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, cpu_model
from runtime.diagnostics.coast import ORACLES, coast_row

SEGMENTS = ("ate", "pre", "coast", "post", "pre_only", "post_only", "jump_m")


def fmt_tables(rows: list[dict]) -> str:
    """The oracle table (coast RMSE [mm]) and the per-run segment table (mm, deg)."""
    head = f"{'seed':>4s} {'coast [s]':>13s} " + " ".join(f"{c:>16s}" for c in ORACLES)
    lines = ["position RMSE over the coast [mm], keyframes smoothed over the IMU from exact end states", head]
    for r in rows:
        cells = " ".join(f"{1e3 * r[c]:16.1f}" for c in ORACLES)
        lines.append(f"{r['seed']:4d} {r['t0_s']:6.2f}-{r['t1_s']:6.2f} {cells}")
    lines.append(f"{'mean':>4s} {'':13s} " + " ".join(f"{1e3 * np.mean([r[c] for r in rows]):16.1f}" for c in ORACLES))
    runs = sorted({m for r in rows for m in r["runs"]})
    if runs:
        lines += [
            "",
            "runs [mm]: ATE, then RMSE before / over / after the coast (whole alignment), each side aligned",
            "alone, and the two sides' alignments apart at the relocalisation (jump)",
        ]
        head = f"{'seed':>4s} {'run':18s} " + " ".join(f"{c:>9s}" for c in SEGMENTS) + f" {'jump deg':>9s}"
        lines.append(head)
        for mode in runs:
            got = [r["runs"][mode] for r in rows if mode in r["runs"]]
            for r in rows:
                if mode in r["runs"]:
                    s = r["runs"][mode]
                    cells = " ".join(f"{1e3 * s[c]:9.1f}" for c in SEGMENTS)
                    lines.append(f"{r['seed']:4d} {mode:18s} {cells} {s['jump_deg']:9.3f}")
            cells = " ".join(f"{1e3 * np.nanmean([s[c] for s in got]):9.1f}" for c in SEGMENTS)
            lines.append(f"{'mean':>4s} {mode:18s} {cells} {np.nanmean([s['jump_deg'] for s in got]):9.3f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--data", default=str(REPO / "data" / "sim" / "bench_dense"), help="bench_dense's sequences")
    ap.add_argument("--runs", default=str(REPO / "outputs" / "bench_dense"), help="bench_dense's run folders")
    ap.add_argument("--dt-kf", type=float, default=0.4, help="keyframe spacing of the oracle coasts [s]")
    ap.add_argument("--widen", type=float, default=2.0, help="coast = the hold widened by this, without runs [s]")
    ap.add_argument("--out", default=str(REPO / "outputs" / "bench_coast"))
    args = ap.parse_args(argv)
    rows = []
    for seed in args.seeds:
        root = Path(args.data) / f"euroc_whitewall_{args.duration:g}s_s{seed}_x{args.scale:g}"
        if not (root / "mav0").is_dir():
            raise SystemExit(f"bench_coast: no sequence {root}; run benchmarks/bench_dense.py --presets whitewall")
        runs = {run.name.split("_", 2)[2]: run for run in sorted(Path(args.runs).glob(f"whitewall_s{seed}_*"))}
        rows.append(coast_row(root, seed, runs, args.dt_kf, args.widen))
        print(f"bench_coast: seed {seed} done ({rows[-1]['source']})", flush=True)
    table = fmt_tables(rows)
    print(table)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = {
        "machine": {"cpu": cpu_model(), "platform": platform.platform(), "data": "synthetic (sim/)"},
        "args": vars(args),
        "rows": rows,
        "table": table,
    }
    (out / "bench_coast.json").write_text(json.dumps(res, indent=2, default=float))
    print(f"bench_coast: wrote {out / 'bench_coast.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
