"""Side by side with the peers: ``dit-slam`` (sparse, dense), ORB-SLAM3 (monocular, monocular-inertial) and cuVSLAM
(monocular, on the CPU) on the same sequences, in one run, scored by the same evo call.

    pip install -e ".[peers]"                      # pyorbslam3 and dim-odom (large CUDA wheels; never in CI)
    python benchmarks/bench_peers.py               # the issue's set: flight/handheld/tabletop seeds 0-2, whitewall,
                                                   # the MH_05 excerpt completed with an IMU; all five systems
    python benchmarks/bench_peers.py --sequences textured_s0 flight-ideal_s0 --runs 3
    python benchmarks/bench_peers.py --systems dit-slam-sparse dit-slam-dense --merge   # rerun ours only

Sequence names (:mod:`benchmarks.sequences`): ``PRESET_sSEED`` (``dit-sim euroc preset=PRESET seed=SEED
duration=--duration``, the preset's own realism), ``PRESET-ideal_sSEED`` (the same with ``realism=false``), ``mh05``
(``../shared/data``'s MH_05 excerpt completed by ``dit-sim imu``), ``mh05_sSEED`` (with IMU seed ``SEED``). They are
rendered once into ``--data`` and reused.

For each system and sequence: the peer's settings are written from the sequence's ``sensor.yaml`` files
(``benchmarks.peers.settings``), the system runs in a child process (its CPU time is the child's), and its
trajectory is scored with :func:`benchmarks.peers.scoring.score`: monocular systems Sim(3) against the
camera-frame ground truth, inertial ones SE(3) and Sim(3) against the body frame. ORB-SLAM3 is not
deterministic: ``--runs`` runs each (median and range); the others run once (deterministic).

ORB-SLAM3 uses a **home-trained vocabulary** (``benchmarks.peers.vocab``): the published ``ORBvoc.txt`` cannot be
downloaded here; it is trained on frames of a sequence rendered for it only (``--vocab-preset``, seed 100, not
an evaluated sequence) plus the real RGB-D frames of ``../shared/data/rgbd_real`` when present, and cached.

Where a peer beats us: ``python -m benchmarks.peers.diagnose`` (error over time, scale per window, drift, IMU-only
propagation; ``benchmarks/results/peers_diagnosis_*.json``), ``python -m benchmarks.peers.variants`` (the sequence
with one realism effect taken out, for ablations) and ``python -m benchmarks.peers.plot_errors`` (per-frame error).
``--merge`` / ``--combine`` replace the rows and runs of the (system, sequence) pairs run again and keep the rest,
with the commands, notes and vocabulary.

Rows of ``benchmarks/results/peers.json``: ``{"system", "sequence", "ate_m", "alignment", "tracked_frac", "fps",
"cpu_ms_per_frame", "runs", ...}`` (median over runs; ``ate_min_m``/``ate_max_m`` the range, ``losses``,
``resets``, ``note``), and ``ratios``: our ATE and frames/s over each peer's, per sequence and alignment.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, cache_dir, slam_machine, write_json
from benchmarks.peers import scoring
from benchmarks.sequences import BIN, dit_sim, ensure_sequence

RGBD_REAL = REPO.parent / "shared" / "data" / "rgbd_real"
DEFAULT_SEQUENCES = [f"{p}_s{s}" for p in ("flight", "handheld", "tabletop") for s in (0, 1, 2)] + [
    "whitewall_s0",
    "mh05",
]
OURS = ("dit-slam-sparse", "dit-slam-dense")
PEERS = ("orbslam3-mono", "orbslam3-mono-inertial", "cuvslam-mono")
VOCAB_NOTE = "home-trained ORB vocabulary (DBoW2 k={k}, L={L}, {n_img} images: {sources}); not the published ORBvoc.txt"


# ------------------------------------------------------------------------------------------------ data
def _vocab_images(data: Path, preset: str) -> tuple[list[np.ndarray], list[str]]:
    import cv2

    seq = data / "vocab_train"
    if not (seq / "mav0" / "cam0" / "data.csv").is_file():
        dit_sim("euroc", f"out={seq}", f"preset={preset}", "seed=100", "duration=6", "progress=false")
    paths = sorted((seq / "mav0" / "cam0" / "data").glob("*.png"))
    sources = [f"{len(paths)} frames of dit-sim preset={preset} seed=100 (not evaluated)"]
    real = sorted(RGBD_REAL.rglob("*color*.png"))[:60] + sorted(RGBD_REAL.rglob("*color*.jpg"))[:60]
    if real:
        sources.append(f"{len(real)} real RGB-D frames of ../shared/data/rgbd_real")
    imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in [*paths, *real]]
    return [i for i in imgs if i is not None], sources


def ensure_vocabulary(data: Path, preset: str, k: int, L: int) -> tuple[Path, str]:
    """The cached home-trained vocabulary (trained on first use) and its description."""
    from benchmarks.peers import vocab

    imgs, sources = _vocab_images(data, preset)
    des = vocab.orb_descriptors(imgs)
    key = vocab.fingerprint(des, k, L, 0)
    path = cache_dir() / "peers" / f"ORBvoc-home-{key}.txt"
    note = VOCAB_NOTE.format(k=k, L=L, n_img=len(imgs), sources="; ".join(sources))
    if not path.is_file():
        t0 = time.perf_counter()
        print(f"training the ORB vocabulary ({sum(len(d) for d in des)} descriptors) ...", flush=True)
        vocab.write_dbow2_text(vocab.train_vocabulary(des, k=k, L=L, seed=0), path)
        print(f"  {path} ({time.perf_counter() - t0:.0f} s)", flush=True)
    return path, note


# ------------------------------------------------------------------------------------------------ runs
def _child(cmd: list[str], timeout: float) -> tuple[subprocess.CompletedProcess, float, float]:
    """Run ``cmd``; returns the process, its wall time and its CPU time (user + system, from rusage)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired as e:
        r = subprocess.CompletedProcess(cmd, -9, e.stdout or "", f"timed out after {timeout:.0f} s")
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return r, wall, cpu


def _read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from runtime.io.tum import read_tum

    if not path.is_file() or path.stat().st_size == 0:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    return read_tum(path)


def ours_command(system: str, seq: Path, out: Path) -> list[str]:
    """The ``dit-slam`` command line of ``system``; the mode is always explicit (``dit-slam`` is dense by default)."""
    if system not in OURS:
        raise ValueError(f"{system!r} is not one of {OURS}")
    dense = "true" if system == "dit-slam-dense" else "false"
    return [str(BIN / "dit-slam"), f"sequence={seq}", f"out={out}", "progress=false", f"dense={dense}"]


def run_ours(system: str, seq: Path, out: Path, timeout: float) -> dict:
    r, wall, cpu = _child(ours_command(system, seq, out), timeout)
    m = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    n = int(m.get("frames") or 0)
    res = {
        "rc": r.returncode,
        "frames": n,
        "frames_with_pose": int(m.get("frames_with_pose") or 0),
        "losses": len(m.get("relocalisations") or []),  # losses that ended in a relocalisation
        "resets": None,
        "loop_wall_s": (n / m["fps"]) if m.get("fps") else math.nan,
        "loop_cpu_s": m.get("cpu_s", math.nan),
        "child_wall_s": wall,
        "child_cpu_s": cpu,
    }
    if m.get("error") or r.returncode != 0:
        err = m.get("error") or (r.stderr.strip().splitlines() or ["no metrics.json"])[-1]
        res["note"] = "not initialised" if "never initialised" in str(err) else str(err)[:200]
    return res


def failure_note(r: subprocess.CompletedProcess) -> str:
    """Why a peer's run gave no result, for the table: the signal that killed it, whether ORB-SLAM3's map was empty
    when it saved it (it then crashes in SaveTrajectoryEuRoC), else the last line it printed.
    """
    why = []
    if r.returncode < 0:
        try:
            why.append(f"killed by {signal.Signals(-r.returncode).name}")
        except ValueError:
            why.append(f"killed by signal {-r.returncode}")
    kfs = [int(k) for k in re.findall(r"Map \d+ has (\d+) KFs", r.stdout or "")]
    if kfs and max(kfs) == 0:
        why.append("its map had no keyframe left when saved")
    if not why:
        tail = (r.stderr.strip().splitlines() or r.stdout.strip().splitlines() or ["no output"])[-1]
        why.append(tail[:200])
    return "failed: " + "; ".join(why)


def run_peer(system: str, seq: Path, out: Path, vocab: Path | None, args) -> dict:
    cmd = [args.peers_python, "-m", "benchmarks.peers.run_peer", "--system", system, "--sequence", str(seq)]
    cmd += ["--out", str(out), "--imu-noise-scale", f"{args.imu_noise_scale:g}"]
    if vocab is not None:
        cmd += ["--vocab", str(vocab)]
    r, wall, cpu = _child(cmd, args.timeout)
    (out / "log.txt").write_text(f"{r.stdout}\n--- stderr ---\n{r.stderr}")  # the peer's own messages (resets, ...)
    f = out / "result.json"
    if r.returncode != 0 or not f.is_file():
        return {
            "rc": r.returncode,
            "frames": 0,
            "frames_with_pose": 0,
            "note": failure_note(r),
            "child_wall_s": wall,
            "child_cpu_s": cpu,
        }
    m = json.loads(f.read_text())
    if system == "cuvslam-mono":  # its counters are logged at the end: "... resets=N ..."
        found = re.findall(r"resets\S*?=\S*?(\d+)", re.sub(r"\x1b\[[0-9;]*m", "", r.stdout + r.stderr))
        m["resets"] = int(found[-1]) if found else None
    return {
        "rc": 0,
        "frames": m["frames"],
        "frames_with_pose": m["frames_with_pose"],
        "losses": m.get("losses"),
        "resets": m.get("resets"),
        "states": m.get("states"),
        "loop_wall_s": m["wall_s"],
        "loop_cpu_s": m["cpu_s"],
        "child_wall_s": wall,
        "child_cpu_s": cpu,
        "trajectory_kind": m.get("trajectory"),
    }


def score_run(system: str, seq: Path, out: Path, res: dict) -> dict:
    from runtime.io.euroc import read_euroc

    s = read_euroc(seq)
    est_ts, est_T = _read_tum(out / "trajectory.txt")
    n = res.get("frames") or len(s)
    res["frames"] = n
    res["tracked_frac"] = scoring.tracked_fraction(len(est_ts), n)
    res["scores"] = scoring.score(system, est_ts, est_T, s.gt.ts, s.gt.T_w_b, s.T_b_c)
    return res


# ------------------------------------------------------------------------------------------------ rows
def _med(vals) -> float:
    return scoring.median_range(vals)[0]


def aggregate(system: str, sequence: str, runs: list[dict]) -> list[dict]:
    rows = []
    for a in scoring.alignments(system):
        ates = [r["scores"][a]["ate_m"] for r in runs if "scores" in r]
        med, lo, hi = scoring.median_range(ates)
        fps = [r["frames"] / r["loop_wall_s"] for r in runs if r.get("loop_wall_s") and r["loop_wall_s"] > 0]
        cpu = [1e3 * r["loop_cpu_s"] / r["frames"] for r in runs if r.get("frames") and r.get("loop_cpu_s")]
        cpu_child = [1e3 * r["child_cpu_s"] / r["frames"] for r in runs if r.get("frames")]
        notes = sorted({r["note"] for r in runs if r.get("note")})
        rows.append(
            {
                "system": system,
                "sequence": sequence,
                "ate_m": med,
                "ate_min_m": lo,
                "ate_max_m": hi,
                "alignment": a,
                "reference_frame": scoring.reference_frame(system),
                "tracked_frac": _med([r.get("tracked_frac", 0.0) for r in runs]),
                "fps": _med(fps),
                "cpu_ms_per_frame": _med(cpu),
                "cpu_ms_per_frame_process": _med(cpu_child),
                "losses": _med([r["losses"] for r in runs if r.get("losses") is not None]),
                "resets": _med([r["resets"] for r in runs if r.get("resets") is not None]),
                "sim3_scale": _med([r["scores"][a]["scale"] for r in runs if "scores" in r]),
                "runs": len(runs),
                "per_run_ate_m": ates,
                "note": "; ".join(notes) if notes else None,
            }
        )
    return rows


def ratios(rows: list[dict]) -> list[dict]:
    """Our ATE and frames/s over each peer's, on each sequence, with the peer's alignment."""
    out = []
    idx = {(r["system"], r["sequence"], r["alignment"]): r for r in rows}
    for r in rows:
        if r["system"] not in PEERS:
            continue
        for ours in OURS:
            o = idx.get((ours, r["sequence"], r["alignment"]))
            if o is None or not o["tracked_frac"] > 0:  # ours did not track: no time per tracked frame to compare
                continue
            out.append(
                {
                    "ours": ours,
                    "peer": r["system"],
                    "sequence": r["sequence"],
                    "alignment": r["alignment"],
                    "ate_ratio": _ratio(o["ate_m"], r["ate_m"]),
                    "fps_ratio": _ratio(o["fps"], r["fps"]),
                    "cpu_ratio": _ratio(o["cpu_ms_per_frame"], r["cpu_ms_per_frame"]),
                    "peer_tracked_frac": r["tracked_frac"],
                }
            )
    return out


def _ratio(a, b) -> float:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return math.nan
    return a / b


def _f(x, scale=1.0, d=1) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x * scale:.{d}f}"


def print_table(rows: list[dict]) -> None:
    print(
        f"\n{'sequence':18s} {'system':24s} {'align':5s} {'ATE [mm]':>9s} {'range [mm]':>15s} {'tracked':>8s} "
        f"{'fps':>6s} {'CPU ms/f':>9s} {'runs':>4s}  note"
    )
    for r in sorted(rows, key=lambda r: (r["sequence"], r["system"], r["alignment"])):
        rng = f"{_f(r['ate_min_m'], 1e3)}-{_f(r['ate_max_m'], 1e3)}" if r["runs"] > 1 else ""
        print(
            f"{r['sequence']:18s} {r['system']:24s} {r['alignment']:5s} {_f(r['ate_m'], 1e3):>9s} {rng:>15s} "
            f"{100 * r['tracked_frac']:7.0f}% {_f(r['fps']):>6s} {_f(r['cpu_ms_per_frame']):>9s} {r['runs']:4d}  "
            f"{r['note'] or ''}"
        )


def merge_results(old: dict, new: dict) -> dict:
    """``old`` with the rows and runs of every (system, sequence) that ``new`` ran replaced by ``new``'s; the
    commands, notes and the vocabulary's description of both are kept (a merge that only reruns ``dit-slam``
    has no vocabulary of its own), and the ratios are recomputed."""
    done = {(r["system"], r["sequence"]) for r in new.get("rows", [])}
    rows = [r for r in old.get("rows", []) if (r["system"], r["sequence"]) not in done] + list(new.get("rows", []))
    runs = [r for r in old.get("runs", []) if (r.get("system"), r.get("sequence")) not in done]
    commands = list(old.get("commands") or [old.get("command")]) + list(new.get("commands") or [new.get("command")])
    commands = [c for c in commands if c]
    vocabs = [v for v in (old.get("vocabulary"), new.get("vocabulary")) if v]
    notes = list(old.get("notes") or [])
    notes += [n for n in new.get("notes") or [] if n not in notes]
    loads = list((old.get("machine") or {}).get("loadavg_each_run") or [(old.get("machine") or {}).get("loadavg")])
    loads += list((new.get("machine") or {}).get("loadavg_each_run") or [(new.get("machine") or {}).get("loadavg")])
    return {
        **old,
        **{k: v for k, v in new.items() if v is not None},
        "command": " ; then ".join(commands),
        "commands": commands,
        "machine": {**(old.get("machine") or {}), **(new.get("machine") or {}), "loadavg_each_run": loads},
        "vocabulary": " | ".join(dict.fromkeys(vocabs)) if vocabs else None,
        "rows": rows,
        "ratios": ratios(rows),
        "runs": runs + list(new.get("runs", [])),
        "notes": notes,
    }


def combine(files: list[Path], out: Path, notes: list[str] | None = None) -> dict:
    """Merge result files (runs made one after another or in parallel) into ``out``: a later file's rows and
    runs replace those of the same system and sequence (:func:`merge_results`); ``notes`` are added."""
    res = json.loads(files[0].read_text())
    for f in files[1:]:
        res = merge_results(res, json.loads(f.read_text()))
    res["notes"] = list(res.get("notes") or []) + [n for n in notes or [] if n not in (res.get("notes") or [])]
    print_table(res["rows"])
    write_json(out, res)
    print(f"wrote {out}")
    return res


# ------------------------------------------------------------------------------------------------ main
def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequences", nargs="+", default=DEFAULT_SEQUENCES)
    ap.add_argument("--systems", nargs="+", default=[*OURS, *PEERS], choices=[*OURS, *PEERS])
    ap.add_argument("--runs", type=int, default=3, help="runs of ORB-SLAM3 (not deterministic); others run once")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of each rendered sequence")
    ap.add_argument("--data", default=str(REPO / "outputs" / "peers" / "seq"), help="rendered sequences (cache)")
    ap.add_argument("--work", default=str(REPO / "outputs" / "peers" / "runs"), help="outputs of the runs")
    ap.add_argument("--vocab-preset", default="handheld")
    ap.add_argument("--vocab-k", type=int, default=10)
    ap.add_argument("--vocab-L", type=int, default=5)
    ap.add_argument(
        "--imu-noise-scale", type=float, default=1.0, help="ORB-SLAM3 IMU noise = this x imu0/sensor.yaml's densities"
    )
    ap.add_argument(
        "--peers-python",
        default=sys.executable,
        help="python with the extra 'peers' installed (a separate environment needs only numpy, scipy, "
        "opencv-python-headless and pyyaml besides: its child reads the sequences' sensor.yaml files)",
    )
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--merge", action="store_true", help="keep the rows of --out for (system, sequence) not run")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "peers.json"))
    ap.add_argument(
        "--combine",
        nargs="+",
        metavar="JSON",
        help="only merge these result files (later ones replace the same system and sequence) into --out",
    )
    ap.add_argument("--note", action="append", default=[], help="a line for the report page's notes (repeatable)")
    args = ap.parse_args(argv)
    if args.combine:
        return combine([Path(p) for p in args.combine], Path(args.out), args.note)
    data, work = Path(args.data), Path(args.work)
    data.mkdir(parents=True, exist_ok=True)
    vocab_path, vocab_note = (None, None)
    if any(s.startswith("orbslam3") for s in args.systems):
        vocab_path, vocab_note = ensure_vocabulary(data, args.vocab_preset, args.vocab_k, args.vocab_L)
    rows, raw = [], []
    for name in args.sequences:
        seq = ensure_sequence(name, data, args.duration)
        for system in args.systems:
            n_runs = args.runs if system.startswith("orbslam3") else 1
            runs = []
            for i in range(n_runs):
                out = work / name / f"{system}_run{i}"
                out.mkdir(parents=True, exist_ok=True)
                res = (
                    run_ours(system, seq, out, args.timeout)
                    if system in OURS
                    else run_peer(system, seq, out, vocab_path, args)
                )
                res = score_run(system, seq, out, res)
                res.update(system=system, sequence=name, run=i)
                runs.append(res)
                raw.append(res)
                a = scoring.alignments(system)[0]
                print(
                    f"{name} {system} run {i}: ATE {a} {_f(res['scores'][a]['ate_m'], 1e3, 2)} mm, tracked "
                    f"{100 * res['tracked_frac']:.0f}%, {res.get('note') or ''}",
                    flush=True,
                )
            rows += aggregate(system, name, runs)
    res = {
        "command": "python benchmarks/bench_peers.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "machine": slam_machine(loadavg=list(os.getloadavg())),
        "vocabulary": vocab_note,
        "scoring": "evo via runtime.eval.trajectory_metrics; monocular: Sim(3) vs camera-frame ground truth; "
        "inertial: SE(3) and Sim(3) vs body-frame ground truth; ATE = RMSE of the aligned positions",
        "timing": "fps = frames / wall time of the frame loop (images decoded inside, fed as fast as taken); "
        "cpu_ms_per_frame = process CPU time of the loop (all threads) per frame; cpu_ms_per_frame_process = "
        "CPU time of the whole child process (start-up, vocabulary, outputs) per frame",
        "rows": rows,
        "ratios": ratios(rows),
        "runs": [{k: v for k, v in r.items()} for r in raw],
        "notes": args.note,
    }
    if args.merge and Path(args.out).is_file():
        res = merge_results(json.loads(Path(args.out).read_text()), res)
    print_table(res["rows"])
    write_json(args.out, res)
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
