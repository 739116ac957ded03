"""Fault injection: ``dit-slam`` and ``dit-export`` interrupted at random points; are the outputs whole or marked?

    python benchmarks/bench_faults.py [--n 10] [--seed 0] [--duration 30] [--scale 0.5] [--signal INT|TERM]
                                      [--skip-export] [--skip-slam] [--sequence DIR] [--out JSON]

``dit-slam``: one full run on a rendered sequence (``--duration`` s, ``textured``, image scale ``--scale``; or
``--sequence DIR``) gives the run time; then ``--n`` runs into one output folder, each sent the signal at a
uniformly random time in [0.2 s, window] (the window: the shortest uninterrupted run so far). After each the
folder is classified:

* ``complete``: ``metrics.json`` says ``"complete": true`` and every output it lists parses (TUM, PLY);
* ``partial``: ``metrics.json`` says ``"complete": false`` (the stub of a run stopped before its frames were
  written, or the outputs of the frames processed), and whatever files exist parse;
* ``bad``: anything else (no or unreadable ``metrics.json``, a file that does not parse, ``complete`` with files
  missing, an unexpected exit status or a traceback).

``dit-export``: a tiny checkpoint (DiT, ``grays``, 64x96, width 0.25) is exported once; then ``--n`` exports of a
second checkpoint into the same folder, each interrupted at a random time in [0.2 s, full export time] (the
shortest uninterrupted export so far: the first one runs with a cold cache). After
each: ``old`` (the earlier export, verified by its SHA-256 manifest), ``new`` (the new one, verified), ``absent``
(no model folder: killed between the two renames; clearly no model) or ``bad`` (a folder that
:class:`runtime.network.DepthNetwork` refuses or that mixes two exports). Leftover temporary folders are counted.

Prints a table and writes ``benchmarks/results/faults.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO, RESULTS, markdown_table, run_provenance, slam_machine, write_json

SIGNALS = {"INT": signal.SIGINT, "TERM": signal.SIGTERM}


def _env() -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _run_killed(cmd: list[str], delay: float | None, sig: int, timeout: float = 900) -> tuple[int, str, float, bool]:
    """Run ``cmd``; send ``sig`` after ``delay`` s (None: let it finish). Returns (status, stderr, seconds, whether
    the signal was sent: False when the command ended first)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sent = False
    if delay is not None:
        try:
            p.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            p.send_signal(sig)
            sent = True
    _, err = p.communicate(timeout=timeout)
    return p.returncode, err, time.perf_counter() - t0, sent


# ------------------------------------------------------------------------------------------------ dit-slam
def classify_slam_out(out: Path, rc: int, err: str, previous: str | None = None) -> tuple[str, str]:
    """``(outcome, why)`` of a dit-slam output folder after a run that ended with status ``rc``; ``previous``:
    the run id found there before the run."""
    from runtime.io.ply import read_ply
    from runtime.io.tum import read_tum

    if "Traceback" in err:
        return "bad", "traceback: " + err.strip().splitlines()[-1][:200]
    try:
        m = json.loads((out / "metrics.json").read_text())
    except (OSError, ValueError) as e:
        return "bad", f"metrics.json: {e}"
    readers = {"trajectory.txt": read_tum, "keyframes.txt": read_tum, "sparse_map.ply": read_ply}
    for name, read in readers.items():
        p = out / name
        if p.exists():
            try:
                read(p)
            except Exception as e:  # noqa: BLE001 - any failure to parse is a bad outcome
                return "bad", f"{name} does not parse: {e}"
        elif m.get("complete") is True:
            return "bad", f"complete but {name} is missing"
    if m.get("complete") is True:
        return "complete", "" if m.get("run_id") != previous else "the earlier run's (stopped before it began)"
    if m.get("complete") is False and rc in (130, 143, -2, -15):
        return "partial", f"{m.get('frames_processed', 0)} frames" if "frames" in m else "stub (before the frames)"
    return "bad", f"complete={m.get('complete')!r} with status {rc}"


def _run_id(out: Path) -> str | None:
    try:
        return json.loads((out / "metrics.json").read_text()).get("run_id")
    except (OSError, ValueError):
        return None


def bench_slam(args, rng: random.Random, sig: int, work: Path) -> dict:
    if args.sequence:
        seq = Path(args.sequence)
    else:
        from sim.euroc import write_euroc_sequence

        seq = work / "seq"
        print(f"rendering a {args.duration:g} s sequence at scale {args.scale:g} into {seq}")
        write_euroc_sequence(seq, "textured", duration=args.duration, seed=0, progress=False, scale=args.scale)
    out = work / "slam_out"
    cmd = [
        sys.executable,
        "-c",
        "from apps.slam import main; main()",
        f"sequence={seq}",
        f"out={out}",
        "progress=false",
    ]
    rc, err, full, _ = _run_killed(cmd, None, sig)
    first = classify_slam_out(out, rc, err)
    print(f"dit-slam full run: {full:.1f} s, {first[0]} {first[1]}")
    trials = []
    for k in range(args.n):
        delay = rng.uniform(0.2, full)
        previous = _run_id(out)
        rc, err, took, sent = _run_killed(cmd, delay, sig)
        if not sent:  # it finished before the signal: a shorter window for the next ones
            full = min(full, took)
        outcome, why = classify_slam_out(out, rc, err, previous)
        trials.append({"delay_s": round(delay, 3), "signalled": sent, "status": rc, "outcome": outcome, "detail": why})
        print(f"  dit-slam #{k}: signal at {delay:6.2f} s -> status {rc}, {outcome} {why}")
    return {"sequence": str(seq), "window_s": full, "full_run_outcome": first[0], "trials": trials}


# ---------------------------------------------------------------------------------------------- dit-export
def _checkpoint(run: Path, seed: int) -> Path:
    """A training run directory with a tiny checkpoint (DiT, grays, 64x96, width 0.25) of seed ``seed``."""
    import torch
    import yaml

    from benchmarks.common import standin_net

    net_cfg = {"name": "dit", "modality": "grays", "height": 64, "width": 96, "width_mult": 0.25}
    (run / ".hydra").mkdir(parents=True, exist_ok=True)
    (run / "checkpoints").mkdir(exist_ok=True)
    (run / ".hydra" / "config.yaml").write_text(
        yaml.safe_dump({"model": {"net": {"_target_": "models.build_model", **net_cfg}}})
    )
    net = standin_net("grays", 64, 96, width_mult=0.25, seed=seed)
    sd = {f"net.{k}": v for k, v in net.state_dict().items()}
    path = run / "checkpoints" / "last.ckpt"
    torch.save({"state_dict": sd, "net_config": net_cfg}, path)
    return path


def classify_model(out: Path, old_id: str, rc: int, err: str) -> tuple[str, str]:
    from runtime.network import DepthNetwork, ModelError

    if "Traceback" in err:
        return "bad", "traceback: " + err.strip().splitlines()[-1][:200]
    if not out.exists():
        return "absent", ""
    try:
        net = DepthNetwork(out)
    except (ModelError, OSError) as e:
        return "bad", str(e)[:200]
    if net.run_id == old_id:
        return "old", ""
    return ("new", "") if rc == 0 else ("bad", f"a new model but status {rc}")


def bench_export(args, rng: random.Random, sig: int, work: Path) -> dict:
    ck_old, ck_new = _checkpoint(work / "run_a", 0), _checkpoint(work / "run_b", 1)
    out = work / "model"
    base = [sys.executable, "-c", "from export.cli import main; main()", f"out={out}", "n_parity=1"]
    rc, err, full, _ = _run_killed([*base, f"ckpt={ck_old}"], None, sig)
    if rc != 0:
        raise RuntimeError(f"the first export failed ({rc}): {err[-2000:]}")
    old_id = json.loads((out / "manifest.json").read_text())["run_id"]
    print(f"dit-export full run: {full:.1f} s (run {old_id})")
    trials = []
    for k in range(args.n):
        delay = rng.uniform(0.2, full)
        rc, err, took, sent = _run_killed([*base, f"ckpt={ck_new}"], delay, sig)
        outcome, why = classify_model(out, old_id, rc, err)
        stray = sorted(p.name for p in work.glob(".model.*"))
        trials.append(
            {
                "delay_s": round(delay, 3),
                "signalled": sent,
                "status": rc,
                "outcome": outcome,
                "detail": why,
                "stray": stray,
            }
        )
        print(f"  dit-export #{k}: signal at {delay:6.2f} s -> status {rc}, {outcome} {why} stray={len(stray)}")
        if outcome == "new":  # back to the old model for the next trial
            if rc == 0:  # it finished before the signal: a shorter window for the next ones
                full = min(full, took)
            rc, err, took, _ = _run_killed([*base, f"ckpt={ck_old}"], None, sig)
            full = min(full, took)
            old_id = json.loads((out / "manifest.json").read_text())["run_id"]
    return {"window_s": full, "trials": trials}


def _counts(trials: list[dict]) -> dict:
    c: dict = {"signalled": sum(bool(t.get("signalled")) for t in trials)}
    for t in trials:
        c[t["outcome"]] = c.get(t["outcome"], 0) + 1
    return c


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=10, help="interrupted runs per command")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of the rendered sequence")
    ap.add_argument("--scale", type=float, default=0.5, help="image scale of the rendered sequence")
    ap.add_argument("--sequence", default=None, help="run on this EuRoC-layout sequence instead")
    ap.add_argument("--signal", choices=sorted(SIGNALS), default="INT")
    ap.add_argument("--skip-slam", action="store_true")
    ap.add_argument("--skip-export", action="store_true")
    ap.add_argument("--out", default=str(RESULTS / "faults.json"))
    ap.add_argument("--update", action="store_true", help="keep the other command's part of an existing --out")
    args = ap.parse_args(argv)
    rng = random.Random(args.seed)
    sig = SIGNALS[args.signal]
    res: dict = {}
    if args.update and Path(args.out).is_file():
        res = json.loads(Path(args.out).read_text())
    res.update({"machine": slam_machine(), "provenance": run_provenance(REPO)})
    with tempfile.TemporaryDirectory(prefix="bench_faults_") as tmp:
        work = Path(tmp)
        if not args.skip_slam:
            res["slam"] = bench_slam(args, rng, sig, work)
            res["slam"].update(counts=_counts(res["slam"]["trials"]), args=vars(args))
        if not args.skip_export:
            res["export"] = bench_export(args, rng, sig, work)
            res["export"].update(counts=_counts(res["export"]["trials"]), args=vars(args))
    rows = []
    for name, outcomes in (("slam", ("complete", "partial", "bad")), ("export", ("old", "new", "absent", "bad"))):
        if name in res:
            c = res[name]["counts"]
            rows.append(
                [
                    f"dit-{name}",
                    len(res[name]["trials"]),
                    c["signalled"],
                    ", ".join(f"{o} {c.get(o, 0)}" for o in outcomes),
                ]
            )
    print(f"\nSIG{args.signal} at random points (seed {args.seed}):\n")
    print(markdown_table(["command", "runs", "signalled before the end", "outcomes"], rows))
    print(f"\nwrote {write_json(args.out, res)}")
    return res


if __name__ == "__main__":
    main()
