"""A paired ablation of ``dit-slam`` settings: every arm on every sequence, paired against the first arm, with the
rule that decides it stored beside the runs.

    python -m benchmarks.ablate --rule RULE.md --title "one LM iteration per window solve" \\
        --arm D "" --arm L "runtime.backend.lm_max_iterations=1" \\
        --sequences flight_s70 flight_s71 handheld_s70 whitewall_s70 mh05_s70 mh05_s71 \\
        --systems sparse dense --out benchmarks/results/slam_ablations/lm_one_step.json

The project decides its defaults by rules written before the runs (``reports/ablations.md``); this script runs
such a rule's arms. ``--rule`` is required: the file holding the rule's text, which goes into the result file
unchanged. The first ``--arm`` is the baseline; each arm is a name and its Hydra overrides of ``dit-slam`` (one
string, ``""`` for none). Sequences are named as in :mod:`benchmarks.sequences` (``PRESET_sSEED``,
``PRESET-ideal_sSEED``, ``mh05``, ``mh05_sSEED``) and rendered into ``--data`` on first use. ``--systems``:
``sparse`` (``dense=false``) and/or ``dense`` (``dense=true``, the default system).

The arms of one sequence and system run at the same time (``--jobs``, default 2), so that the pairs share the
machine's load. SLAM runs are deterministic on one machine and chaotic across CPUs: compare only runs of one
machine, and take speed from the CPU seconds (``cpu_s``, each process's own), not from frames/s under load.

Every run's outputs stay in ``--work``/SEQUENCE/SYSTEM/ARM, with its log (``run.log``: the events of the
intrinsics' first pass too, which ``metrics.json`` leaves out, so that one can see where a candidate acted); a run
whose ``metrics.json`` is complete and whose command is the same is not run again, so an interrupted ablation
resumes where it stopped. The result file is
written after every run (atomically) and holds the rule, the arms, the machine, every run and the summary:
per system and arm, the paired SE(3) and Sim(3) differences to the baseline [mm] (mean, standard error, runs
lower), the same per family (the preset, or ``mh05``), the MH_05 runs at or under ``--mh05-bar``, runs with fewer
frames posed than their baseline, diverged runs (SE(3) above ``--diverged-m``) and the median CPU ratio to the
baseline. ``outcome`` is left for the person who applies the rule (kept when the file is written again).
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, slam_machine, write_json
from benchmarks.sequences import BIN, ensure_sequence, parse_sequence

SYSTEMS = {"sparse": "false", "dense": "true"}

__all__ = ["family", "run_row", "slam_command", "summarise", "main"]


def family(sequence: str) -> str:
    """The family a sequence's pairs are grouped by: its preset (``flight``, ``flight-ideal``) or ``mh05``."""
    spec = parse_sequence(sequence)
    if spec["kind"] == "mh05":
        return "mh05"
    return spec["preset"] + ("-ideal" if spec["realism"] is False else "")


def slam_command(slam: str | Path, seq: Path, out: Path, system: str, overrides: list[str]) -> list[str]:
    """The ``dit-slam`` command line of one run; the system is always explicit (``dit-slam`` is dense by default)."""
    if system not in SYSTEMS:
        raise ValueError(f"system {system!r} is not one of {sorted(SYSTEMS)}")
    return [str(slam), f"sequence={seq}", f"out={out}", "progress=false", f"dense={SYSTEMS[system]}", *overrides]


def run_row(m: dict) -> dict:
    """The figures of one run kept in the result file, from its ``metrics.json``."""
    intr, ini = m.get("intrinsics") or {}, m.get("initialisation") or {}
    return {
        "complete": bool(m.get("complete")),
        "se3_m": m.get("ate_se3_rmse_m"),
        "sim3_m": m.get("ate_sim3_rmse_m"),
        "sim3_scale": m.get("sim3_scale"),
        "frames": m.get("frames"),
        "frames_with_pose": m.get("frames_with_pose"),
        "cpu_s": m.get("cpu_s"),
        "fps": m.get("fps"),
        "first_pass_s": intr.get("seconds_total"),
        "init": ini.get("method"),  # how and when the run started (issue #21: within 2 s of data)
        "init_after_s": ini.get("after_s"),
        "error": m.get("error") or m.get("eval_error"),
    }


def _metrics(out: Path) -> dict:
    try:
        return json.loads((out / "metrics.json").read_text())
    except (OSError, ValueError):
        return {}


def _run(cmd: list[str], out: Path, timeout: float) -> tuple[dict, bool]:
    """Run ``cmd`` unless ``out`` holds a complete run of the same command; returns its row and whether it ran."""
    stamp = out / "ablate_command.json"
    m = _metrics(out)
    if m.get("complete") and stamp.is_file() and json.loads(stamp.read_text()) == cmd:
        return run_row(m), False
    out.mkdir(parents=True, exist_ok=True)
    stamp.unlink(missing_ok=True)
    (out / "metrics.json").unlink(missing_ok=True)  # a run that fails before writing its own must not show the last
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        (out / "run.log").write_text(r.stdout + r.stderr)  # both passes' events: where a candidate acted
        failure = None if r.returncode == 0 else (r.stderr.strip().splitlines() or [f"exit status {r.returncode}"])[-1]
    except subprocess.TimeoutExpired as e:
        (out / "run.log").write_text(_text(e.stdout) + _text(e.stderr))
        failure = f"timed out after {timeout:.0f} s"
    m = _metrics(out)
    row = run_row(m)
    if failure is not None:
        row["error"] = row["error"] or failure[:300]
    elif m.get("complete"):
        stamp.write_text(json.dumps(cmd))
    return row, True


def _text(b) -> str:
    return b.decode(errors="replace") if isinstance(b, bytes) else (b or "")


def _mean_se(x: list[float]) -> list[float | None]:
    if not x:
        return [None, None]
    se = float(np.std(x, ddof=1) / np.sqrt(len(x))) if len(x) > 1 else None
    return [round(float(np.mean(x)), 2), None if se is None else round(se, 2)]


def summarise(runs: list[dict], baseline: str, mh05_bar: float = 0.05, diverged_m: float = 1.0) -> dict:
    """Per system and arm, the paired figures against ``baseline`` (module docstring); ``runs`` are rows with
    ``sequence``, ``system``, ``arm`` and the fields of :func:`run_row`. A pair counts when both runs are complete
    and were scored."""
    by = {(r["sequence"], r["system"], r["arm"]): r for r in runs}
    out: dict = {}
    for system in sorted({r["system"] for r in runs}):
        for arm in sorted({r["arm"] for r in runs if r["arm"] != baseline}):
            d3, ds, fam, cpu, first, mh = [], [], {}, [], [], {"baseline": 0, "arm": 0, "pairs": 0}
            fewer = diverged_b = diverged_a = 0
            for seq in sorted({r["sequence"] for r in runs if r["system"] == system}):
                b, a = by.get((seq, system, baseline)), by.get((seq, system, arm))
                if not (b and a and b["complete"] and a["complete"]) or b["se3_m"] is None or a["se3_m"] is None:
                    continue
                d3.append(1e3 * (a["se3_m"] - b["se3_m"]))
                if a["sim3_m"] is not None and b["sim3_m"] is not None:
                    ds.append(1e3 * (a["sim3_m"] - b["sim3_m"]))
                fam.setdefault(family(seq), []).append(d3[-1])
                if a["cpu_s"] and b["cpu_s"]:
                    cpu.append(a["cpu_s"] / b["cpu_s"])
                if a["first_pass_s"] and b["first_pass_s"]:
                    first.append(a["first_pass_s"] / b["first_pass_s"])
                fewer += int((a["frames_with_pose"] or 0) < (b["frames_with_pose"] or 0))
                diverged_b += int(b["se3_m"] > diverged_m)
                diverged_a += int(a["se3_m"] > diverged_m)
                if family(seq) == "mh05":
                    mh["pairs"] += 1
                    mh["baseline"] += int(b["se3_m"] <= mh05_bar)
                    mh["arm"] += int(a["se3_m"] <= mh05_bar)
            out[f"{system}/{arm}"] = {
                "pairs": len(d3),
                "se3_mm": _mean_se(d3),
                "se3_lower": int(sum(x < 0 for x in d3)),
                "sim3_mm": _mean_se(ds),
                "sim3_lower": int(sum(x < 0 for x in ds)),
                "se3_mm_by_family": {k: {"mean_se": _mean_se(v), "n": len(v)} for k, v in sorted(fam.items())},
                f"mh05_at_or_under_{mh05_bar:g}m": mh,
                "fewer_frames_posed": fewer,
                "diverged": {"baseline": diverged_b, "arm": diverged_a},
                "cpu_ratio_median": round(float(np.median(cpu)), 3) if cpu else None,
                "first_pass_ratio_median": round(float(np.median(first)), 3) if first else None,
            }
    return out


def _fmt(v, scale=1.0, d=1) -> str:
    return "-" if v is None else f"{v * scale:.{d}f}"


def print_summary(summary: dict, baseline: str) -> None:
    for key, s in summary.items():
        (m3, e3), (ms, es) = s["se3_mm"], s["sim3_mm"]
        mh = next(v for k, v in s.items() if k.startswith("mh05_at_or_under"))
        print(
            f"{key} - {baseline}: {s['pairs']} pairs, SE(3) {_fmt(m3)} +- {_fmt(e3)} mm ({s['se3_lower']} lower), "
            f"Sim(3) {_fmt(ms)} +- {_fmt(es)} mm ({s['sim3_lower']} lower); CPU {_fmt(s['cpu_ratio_median'], d=3)}x; "
            f"MH_05 at the bar {mh['baseline']} -> {mh['arm']} of {mh['pairs']}; "
            f"fewer posed {s['fewer_frames_posed']}; diverged {s['diverged']['baseline']} -> {s['diverged']['arm']}"
        )
        for f, v in s["se3_mm_by_family"].items():
            print(f"    {f}: {_fmt(v['mean_se'][0])} +- {_fmt(v['mean_se'][1])} mm ({v['n']})")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rule", required=True, help="file with the rule, written before the runs")
    ap.add_argument("--title", default="", help="what is ablated (one line, for the result file)")
    ap.add_argument(
        "--arm",
        nargs=2,
        action="append",
        required=True,
        metavar=("NAME", "OVERRIDES"),
        help='an arm and its dit-slam overrides in one string ("" for none); the first is the baseline',
    )
    ap.add_argument("--sequences", nargs="+", required=True, help="PRESET_sSEED, PRESET-ideal_sSEED, mh05_sSEED")
    ap.add_argument("--systems", nargs="+", default=["sparse", "dense"], choices=sorted(SYSTEMS))
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of each rendered sequence")
    ap.add_argument("--data", default=str(REPO / "outputs" / "ablate" / "seq"), help="rendered sequences (cache)")
    ap.add_argument("--work", default=str(REPO / "outputs" / "ablate" / "runs"), help="the runs' outputs")
    ap.add_argument("--out", required=True, help="result file (JSON)")
    ap.add_argument("--jobs", type=int, default=2, help="runs at the same time")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds one run may take")
    ap.add_argument("--mh05-bar", type=float, default=0.05, help="[m] the MH_05 SE(3) bar counted per arm")
    ap.add_argument("--diverged-m", type=float, default=1.0, help="[m] an SE(3) above this counts as diverged")
    ap.add_argument("--slam", default=str(BIN / "dit-slam"), help="the dit-slam executable")
    args = ap.parse_args(argv)

    rule = Path(args.rule)
    if not rule.is_file():
        ap.error(f"--rule {rule}: no such file (write the rule before the runs)")
    arms = {name: shlex.split(ov) for name, ov in args.arm}
    if len(arms) != len(args.arm) or len(arms) < 2:
        ap.error("--arm: give at least two arms, each with its own name")
    if args.jobs < 1:
        ap.error("--jobs must be >= 1")
    for name in args.sequences:
        try:
            parse_sequence(name)
        except ValueError as e:
            ap.error(str(e))
    baseline = args.arm[0][0]
    data, work, out = Path(args.data), Path(args.work), Path(args.out)
    data.mkdir(parents=True, exist_ok=True)
    try:
        old = json.loads(out.read_text()) if out.is_file() else {}
    except ValueError:
        old = {}

    seqs = {}
    for name in args.sequences:
        t0 = time.perf_counter()
        seqs[name] = ensure_sequence(name, data, args.duration)
        print(f"sequence {name}: {seqs[name]} ({time.perf_counter() - t0:.0f} s)", flush=True)

    result = {
        "title": args.title,
        "date": time.strftime("%Y-%m-%d", time.gmtime()),
        "machine": slam_machine(),
        "rule": rule.read_text(),
        "arms": {name: " ".join(ov) for name, ov in arms.items()},
        "baseline": baseline,
        "systems": args.systems,
        "sequences": args.sequences,
        "command": "python -m benchmarks.ablate " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:])),
        "runs": [],
        "summary": {},
        "outcome": old.get("outcome"),
    }
    tasks = [(s, sy, a) for s in args.sequences for sy in args.systems for a in arms]
    rows: dict[tuple[str, str, str], dict] = {}
    n_ran = 0
    with ThreadPoolExecutor(max_workers=args.jobs) as ex:
        futs = {}
        for seq, system, arm in tasks:
            run_dir = work / seq / system / arm
            cmd = slam_command(args.slam, seqs[seq], run_dir, system, arms[arm])
            futs[ex.submit(_run, cmd, run_dir, args.timeout)] = (seq, system, arm)
        for fut in as_completed(futs):
            seq, system, arm = futs[fut]
            row, ran = fut.result()
            n_ran += ran
            rows[(seq, system, arm)] = {"sequence": seq, "system": system, "arm": arm, **row}
            print(
                f"{seq} {system} {arm}: SE(3) {_fmt(row['se3_m'], 1e3)} mm, Sim(3) {_fmt(row['sim3_m'], 1e3)} mm, "
                f"posed {row['frames_with_pose']}/{row['frames']}, CPU {_fmt(row['cpu_s'])} s"
                + ("" if ran else " (kept from an earlier run)")
                + (f"; {row['error']}" if row["error"] else ""),
                flush=True,
            )
            result["runs"] = [rows[k] for k in tasks if k in rows]
            result["summary"] = summarise(result["runs"], baseline, args.mh05_bar, args.diverged_m)
            write_json(out, result)
    print(f"{n_ran} runs made, {len(tasks) - n_ran} kept; wrote {out}")
    print_summary(result["summary"], baseline)
    return result


if __name__ == "__main__":
    main()
