"""Benchmark of the VI-SLAM (sparse; ``--dense``: the default dense system): ATE, frames with a pose, time to
initialise, losses, FPS, time per stage.

    python benchmarks/bench_slam.py                      # realistic textured, whitewall, flight, handheld (30 s,
                                                         # seeds 0 1 2) and the MH_05 excerpt (real timing and
                                                         # with a 2 s still period prepended)
    python benchmarks/bench_slam.py --presets textured --synthetic --seeds 0 --duration 20   # earlier data
    python benchmarks/bench_slam.py --seeds 0 --duration 20 --set backend.window_size=8
    python benchmarks/bench_slam.py --dense --out outputs/bench_slam_dense   # the same runs, dense
    python benchmarks/bench_slam.py --presets --mh05-runs --mh05-starts 5 10 15 20   # MH_05 started in flight
    python benchmarks/bench_slam.py --detectors          # gftt vs fast vs orb: detection time, track life,
    ATE

Sequences are rendered with ``sim`` into ``--data`` once (reused afterwards); the MH_05 excerpt of
``../shared/data`` (real images, no IMU) is completed with ``dit-sim imu`` (vibration on; IMU seed = each of
``--seeds``) into ``--data``, with real timing (it starts in flight: in-motion initialisation) and with
``still=2``; ``--mh05-starts`` adds runs started later in the excerpt (``dit-slam start_s``). Skipped with a note
when the excerpt is absent. Every run is a fresh system in
this process, one after another; FPS is frames / wall time of the whole run (image decoding included). The
machine is shared and noisy: compare ratios measured in one invocation. Prints a table and writes JSON,
after every run too (``"complete": false`` until the end): an interrupted invocation keeps its finished runs, and
the same command with ``--resume`` runs only the missing ones.

The JSON's ``bars`` are the real-sensor issue's, per family of runs: a realistic preset at most 1 % of its path
(SE(3)) on every run, every frame posed and at least 20 frames/s; an MH_05 run initialised within 2 s of data, a
pose for at least 97 % of its frames and SE(3) at most 0.05 m.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, resumable_rows, slam_machine, write_json
from runtime.io.euroc import read_euroc
from runtime.io.tum import read_tum
from runtime.run import run_sequence
from runtime.slam import SlamConfig
from sim.cache import cached_sequence as default_sequence

STAGES = (
    "read",
    "imu",
    "track",
    "refine",
    "keyframe",
    "detect",
    "triangulate",
    "reloc",
    "optimize",
    "marginalize",
    "init",
)


def _load_preset(name: str) -> dict:
    from runtime.presets import runtime_preset

    try:
        return runtime_preset(name)
    except ValueError as e:
        raise SystemExit(f"bench_slam: {e}") from e


def parse_value(text: str):
    """A command-line value as YAML, with ``1e-5`` read as a number (YAML 1.1 wants ``1.0e-5``).

    >>> [parse_value(t) for t in ("1e-5", "8", "false", "null", "full")]
    [1e-05, 8, False, None, 'full']
    """
    import yaml

    v = yaml.safe_load(text)
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return v
    return v


def apply_override(d: dict, key: str, value: str) -> None:
    parts = key.split(".")
    for p in parts[:-1]:
        d = d.setdefault(p, {})
    d[parts[-1]] = parse_value(value)


def make_config(preset: str, overrides: list[str]) -> SlamConfig:
    d = _load_preset(preset)
    for o in overrides:
        k, sep, v = o.partition("=")
        if not sep:
            raise SystemExit(f"bench_slam: --set needs key=value, got {o!r}")
        apply_override(d, k, v)
    return SlamConfig.from_dict(d)


def run_one(root: Path, cfg: SlamConfig, out: Path, dense: bool = False, start_s: float = 0.0) -> dict:
    from runtime.dense import DenseConfig
    from runtime.io.sequence import StartView

    seq = read_euroc(root)
    if start_s > 0:  # as a recording started that late (dit-slam start_s)
        seq = StartView(seq, start_s)
    m = run_sequence(seq, out, cfg, progress=False, plot=True, dense=DenseConfig() if dense else None)
    m["rest_s"], m["rest_drift_m"] = rest_drift(seq, out / "trajectory.txt")
    return m


def rest_drift(seq, trajectory: Path, still_m: float = 1e-3, min_rest_s: float = 0.5) -> tuple[float, float | None]:
    """How long a sequence rests at its start, and how far its estimate moves meanwhile.

    The rest is the leading frames of ``trajectory`` (TUM, as ``dit-slam`` writes it) whose ground-truth position
    stays within ``still_m`` of the first one's (the ``flight`` preset waits 1-3 s on the floor, rotors on); the
    drift is the largest distance of their estimated positions from the first of them. Returns ``(rest_s,
    drift_m)``, with ``drift_m`` None without ground truth or with less than ``min_rest_s`` of rest.
    """
    if seq.gt is None or not trajectory.is_file():
        return 0.0, None
    ts, T = read_tum(trajectory)
    inside = (ts >= seq.gt.ts[0]) & (ts <= seq.gt.ts[-1])
    ts, p = ts[inside], T[inside, :3, 3]
    if ts.size < 2:
        return 0.0, None
    p_gt = seq.gt_pose_at(ts)[:, :3, 3]
    moved = np.linalg.norm(p_gt - p_gt[0], axis=1) > still_m
    n = int(np.argmax(moved)) if moved.any() else ts.size
    rest_s = float(ts[n - 1] - ts[0]) * 1e-9
    if rest_s < min_rest_s:
        return rest_s, None
    return rest_s, float(np.linalg.norm(p[:n] - p[0], axis=1).max())


def _pct_path(row: dict) -> float:
    """A run's SE(3) ATE in % of its path length (nan without either)."""
    ate, path = row.get("ate_se3_rmse_m"), row.get("path_length_m")
    return 100 * ate / path if ate is not None and path else float("nan")


def fmt_table(rows: list[dict]) -> str:
    head = (
        f"{'sequence':14s} {'seed':>4s} {'ATE SE3 m':>10s} {'ATE Sim3 m':>10s} {'% path':>7s} {'posed':>6s} "
        f"{'init':>12s} {'losses':>6s} {'RPE m/1s':>9s} {'FPS':>6s} {'CPU ms':>6s} {'KF':>4s} {'MiB':>5s}"
    )
    lines = [head, "-" * len(head)]
    nan = float("nan")
    for r in rows:
        pct = _pct_path(r)
        init = f"{r['init_method'] or '-'}@{r['init_after_s']:.1f}s" if r.get("init_after_s") is not None else "never"
        lines.append(
            f"{r['preset']:14s} {r['seed']:>4d} {r.get('ate_se3_rmse_m', nan):10.4f} "
            f"{r.get('ate_sim3_rmse_m', nan):10.4f} {pct:7.2f} {100 * r['posed_frac']:5.1f}% {init:>12s} "
            f"{r['tracking_losses']:6d} {r.get('rpe_trans_rmse_m', nan):9.4f} {r['fps']:6.1f} "
            f"{r['cpu_ms_per_frame']:6.1f} {r['keyframes']:4d} {r.get('peak_rss_mb') or nan:5.0f}"
        )
    return "\n".join(lines)


def mh05_jobs(args) -> list[tuple[str, float, float]]:
    """(name, still seconds, start seconds) of the MH_05 runs asked for, or none (with a note) without the
    excerpt: real timing, with a 2 s still period, and real timing started ``--mh05-starts`` seconds in."""
    if not (args.mh05_runs or args.mh05_starts):
        return []
    if not (Path(args.mh05) / "mav0" / "cam0").is_dir():
        print(f"MH_05 excerpt not found at {args.mh05}: its rows are skipped")
        return []
    jobs = [("mh05" if r == "real" else "mh05_still2", 0.0 if r == "real" else 2.0, 0.0) for r in args.mh05_runs]
    return jobs + [(f"mh05_from{s:g}", 0.0, float(s)) for s in args.mh05_starts]


def mh05_sequence(source: Path, data: Path, still: float, seed: int = 0) -> Path:
    """The MH_05 excerpt completed with a vibrating IMU of seed ``seed`` (``dit-sim imu``), cached in ``data``."""
    from sim.complete import complete_imu

    out = data / f"euroc_mh05_imu_still{still:g}_s{seed}"
    if not (out / "mav0" / "imu0" / "data.csv").is_file():
        print(f"completing {source} with an IMU (still={still:g}, seed {seed}) into {out}")
        complete_imu(source, out, still=still, seed=seed)
    return out


def result_row(m: dict) -> dict:
    """The benchmark's columns from a run's metrics."""
    keys = ("frames", "frames_with_pose", "keyframes", "fps", "cpu_ms_per_frame", "timing_ms_per_frame", "n_events")
    row = {k: m[k] for k in keys}
    for k in ("ate_se3_rmse_m", "ate_sim3_rmse_m", "sim3_scale", "rpe_trans_rmse_m", "rpe_rot_rmse_deg"):
        if k in m:
            row[k] = m[k]
    row["path_length_m"] = m.get("path_length_m")
    row["error"] = m.get("error")
    init = m.get("initialisation") or {}
    row["init_method"] = init.get("method")
    row["init_after_s"] = init.get("after_s")
    row["posed_frac"] = m["frames_with_pose"] / max(m["frames"], 1)
    row["tracking_losses"] = sum("visual tracking lost" in e[1] for e in m.get("events", []))
    row["restarts"] = len(m.get("restarts", []))
    row["peak_rss_mb"] = m.get("peak_rss_mb")  # the run's own peak (runtime.run resets it at each run's start)
    row["rest_s"], row["rest_drift_m"] = m.get("rest_s"), m.get("rest_drift_m")
    return row


def _row_key(row: dict) -> tuple[str, int]:
    return row["preset"], int(row["seed"])


def fmt_stages(rows: list[dict]) -> str:
    keys = [k for k in STAGES if any(k in r["timing_ms_per_frame"] for r in rows)]
    head = f"{'preset':10s} {'seed':>4s} " + " ".join(f"{k[:9]:>9s}" for k in keys)
    lines = ["per-stage time [ms per frame]", head, "-" * len(head)]
    for r in rows:
        t = r["timing_ms_per_frame"]
        lines.append(f"{r['preset']:10s} {r['seed']:>4d} " + " ".join(f"{t.get(k, 0.0):9.2f}" for k in keys))
    return "\n".join(lines)


def summary(rows: list[dict]) -> dict:
    out = {}
    for preset in sorted({r["preset"] for r in rows}):
        rs = [r for r in rows if r["preset"] == preset]
        ate = np.array([r.get("ate_se3_rmse_m", np.nan) for r in rs])
        sim3 = np.array([r.get("ate_sim3_rmse_m", np.nan) for r in rs])
        start = [r["init_after_s"] for r in rs if r.get("init_after_s") is not None]
        out[preset] = {
            "runs": len(rs),
            "ate_se3_rmse_m_mean": float(np.nanmean(ate)),
            "ate_se3_rmse_m_max": float(np.nanmax(ate)),
            "ate_sim3_rmse_m_mean": float(np.nanmean(sim3)),
            "ate_sim3_rmse_m_max": float(np.nanmax(sim3)),
            "never_initialised": len(rs) - len(start),
            "init_after_s_max": max(start) if start else None,
            "restarts_total": int(sum(r.get("restarts", 0) for r in rs)),
            "ate_pct_path_max": float(np.nanmax([_pct_path(r) for r in rs])),
            "posed_frac_min": float(np.min([r["posed_frac"] for r in rs])),
            "tracking_losses_total": int(sum(r["tracking_losses"] for r in rs)),
            "rpe_trans_rmse_m_mean": float(np.nanmean([r.get("rpe_trans_rmse_m", np.nan) for r in rs])),
            "rpe_rot_rmse_deg_mean": float(np.nanmean([r.get("rpe_rot_rmse_deg", np.nan) for r in rs])),
            "fps_mean": float(np.mean([r["fps"] for r in rs])),
            "fps_min": float(np.min([r["fps"] for r in rs])),
        }
    return out


#: the real-sensor issue's bars: realistic presets (every run) and the MH_05 excerpt (each run)
PRESET_MAX_PCT_PATH, PRESET_MIN_FPS = 1.0, 20.0
REST_PRESETS, REST_MAX_DRIFT_M = ("flight",), 0.01  # a resting sensor: initialised, drift under 1 cm over the rest
MH05_MAX_INIT_S, MH05_MIN_POSED, MH05_MAX_ATE_M = 2.0, 0.97, 0.05


def bars(rows: list[dict]) -> dict:
    """Per family of runs (a preset, ``mh05``, ``mh05_still2``), whether the real-sensor issue's bar holds.

    A preset: SE(3) ATE at most 1 % of the path and every frame posed on every run, and at least 20 frames/s;
    ``flight``, which starts at rest on the floor, also initialised with its estimate moving at most 1 cm over that
    rest (:func:`rest_drift`) on every run that rests.
    An MH_05 family: the runs that start within 2 s of data, pose at least 97 % of their frames and end at most
    0.05 m SE(3), out of its runs. A run that never initialised or has no ATE fails. The runs started later in the
    excerpt (``mh05_fromS``) are reported, not held to a bar: the issue sets none for them.

    >>> r = dict(seed=0, ate_se3_rmse_m=0.02, path_length_m=10.0, posed_frac=1.0, fps=30.0, init_after_s=1.0)
    >>> b = bars([dict(r, preset="flight"), dict(r, preset="mh05"), dict(r, preset="mh05", seed=1, init_after_s=2.5)])
    >>> b["flight"]["met"], b["mh05"]["runs_met"], b["mh05"]["runs"], b["mh05"]["met"]
    (True, 1, 2, False)
    """
    nan = float("nan")
    out = {}
    for fam in sorted({r["preset"] for r in rows if not r["preset"].startswith("mh05_from")}):
        rs = [r for r in rows if r["preset"] == fam]
        ate = [r.get("ate_se3_rmse_m", nan) for r in rs]
        if fam.startswith("mh05"):
            ok = [
                r.get("init_after_s") is not None
                and r["init_after_s"] <= MH05_MAX_INIT_S
                and r["posed_frac"] >= MH05_MIN_POSED
                and a <= MH05_MAX_ATE_M
                for r, a in zip(rs, ate, strict=True)
            ]
            out[fam] = {
                "bar": f"each run: started within {MH05_MAX_INIT_S:g} s, >= {100 * MH05_MIN_POSED:g} % posed, "
                f"SE(3) <= {MH05_MAX_ATE_M:g} m",
                "runs": len(rs),
                "runs_met": int(sum(ok)),
                "seeds_missed": [r["seed"] for r, k in zip(rs, ok, strict=True) if not k],
                "met": all(ok),
            }
            continue
        pct = [_pct_path(r) for r in rs]
        ok = [p <= PRESET_MAX_PCT_PATH and r["posed_frac"] >= 1.0 for r, p in zip(rs, pct, strict=True)]
        fps_min = float(min(r["fps"] for r in rs))
        out[fam] = {
            "bar": f"every run: SE(3) <= {PRESET_MAX_PCT_PATH:g} % of the path, every frame posed; "
            f">= {PRESET_MIN_FPS:g} frames/s",
            "runs": len(rs),
            "pct_path_max": float(np.nanmax(pct)) if not np.all(np.isnan(pct)) else None,
            "fps_min": fps_min,
        }
        if fam in REST_PRESETS:
            rest = [r.get("rest_drift_m") for r in rs]
            ok = [k and (d is None or (d <= REST_MAX_DRIFT_M and r.get("init_after_s") is not None))
                  for k, d, r in zip(ok, rest, rs, strict=True)]  # fmt: skip
            out[fam]["bar"] += f"; at rest: initialised, drift <= {100 * REST_MAX_DRIFT_M:g} cm"
            out[fam]["rest_drift_m_max"] = max((d for d in rest if d is not None), default=None)
            out[fam]["runs_at_rest"] = sum(d is not None for d in rest)
        out[fam]["seeds_missed"] = [r["seed"] for r, k in zip(rs, ok, strict=True) if not k]
        out[fam]["met"] = all(ok) and fps_min >= PRESET_MIN_FPS
    return out


def detector_study(args) -> dict:
    """Detection time and track quality of gftt / fast / orb on one sequence, then SLAM with each."""
    import cv2

    from runtime.backend.imu import ImuStream, integrate_rotation
    from runtime.frontend.features import FeatureConfig, FeatureDetector
    from runtime.frontend.tracking import FeatureTracker, TrackerConfig

    root = default_sequence("textured", args.duration, args.seeds[0], True, args.data, progress=True)
    seq = read_euroc(root)
    imu = ImuStream.from_sequence(seq)
    n = min(len(seq), int(args.detector_frames))
    images = [seq.image(i) for i in range(n)]
    res = {}
    for det in ("gftt", "fast", "orb"):
        fcfg = FeatureConfig(detector=det)
        d = FeatureDetector(seq.camera.width, seq.camera.height, fcfg)
        t0 = time.perf_counter()
        for img in images[:: max(1, n // 50)]:
            d.detect(img)
        t_det = (time.perf_counter() - t0) / len(images[:: max(1, n // 50)]) * 1e3
        trk = FeatureTracker(seq.camera, seq.T_b_c, fcfg, TrackerConfig())
        births, deaths, born = {}, [], 0
        prev_ts = None
        for i, img in enumerate(images):
            ts = int(seq.frame_ts[i])
            R = None
            if prev_ts is not None:
                g, _, dt = imu.segment(prev_ts, ts)
                R = integrate_rotation(g, dt)
            before = set(trk.ids.tolist())
            f = trk.track(ts, img, R)
            after = set(f.ids.tolist())
            for j in before - after:
                deaths.append(i - births.pop(j))
            if i % 5 == 0 or f.ids.size < 100:
                f = trk.replenish(ts, img)
                for j in set(f.ids.tolist()) - after:
                    births[j] = i
                born += len(set(f.ids.tolist()) - after)
            prev_ts = ts
        life = np.array(deaths + [n - b for b in births.values()], dtype=float)
        cfg = make_config(args.runtime, args.set + [f"features.detector={det}"])
        m = run_one(root, cfg, Path(args.out) / f"detector_{det}")
        res[det] = {
            "detect_ms": t_det,
            "mean_track_life_frames": float(life.mean()) if life.size else 0.0,
            "median_track_life_frames": float(np.median(life)) if life.size else 0.0,
            "tracks_started": born,
            "slam_ate_se3_rmse_m": m.get("ate_se3_rmse_m"),
            "slam_fps": m["fps"],
            "slam_track_ms": m["timing_ms_per_frame"].get("track"),
            "slam_detect_ms": m["timing_ms_per_frame"].get("detect"),
        }
        print(
            f"{det:5s} detect {t_det:6.2f} ms  track life mean "
            f"{res[det]['mean_track_life_frames']:6.1f} frames  "
            f"SLAM ATE {res[det]['slam_ate_se3_rmse_m']:.4f} m  {m['fps']:.1f} FPS",
            flush=True,
        )
    del cv2
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="*", default=["textured", "whitewall", "flight", "handheld"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--synthetic", action="store_true", help="the earlier synthetic data (realism=false)")
    ap.add_argument("--dense", action="store_true", help="the dense system (dit-slam's default) instead of sparse")
    ap.add_argument("--mh05", default=str(REPO.parent / "shared" / "data" / "euroc_MH_05_excerpt"))
    ap.add_argument("--mh05-runs", nargs="*", default=["real", "still"], help="real timing and/or still=2")
    ap.add_argument(
        "--mh05-starts",
        nargs="*",
        type=float,
        default=[],
        help="also MH_05 with real timing started this many seconds into the excerpt (rows mh05_fromS; no bar)",
    )
    ap.add_argument("--no-imu-noise", action="store_true", help="exact IMU (default: noise on)")
    ap.add_argument("--runtime", default="default", help="conf/slam/runtime/<name>.yaml preset")
    ap.add_argument("--set", nargs="*", default=[], help="overrides key=value of the runtime config")
    ap.add_argument("--data", default=str(REPO / "data" / "sim" / "bench"), help="sequence cache folder")
    ap.add_argument("--out", default=str(REPO / "outputs" / "bench_slam"))
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the runs of an earlier invocation with the same arguments (its bench_slam.json in --out) and "
        "run only the missing ones",
    )
    ap.add_argument("--detectors", action="store_true", help="compare gftt / fast / orb instead")
    ap.add_argument("--detector-frames", type=int, default=400)
    args = ap.parse_args(argv)
    from sim.scenes import PRESETS

    if unknown := sorted(set(args.presets) - set(PRESETS)):  # before anything is rendered or run
        raise SystemExit(f"bench_slam: unknown preset(s) {unknown}; known: {sorted(PRESETS)}")
    run_args = {k: v for k, v in vars(args).items() if k != "resume"}
    make_config(args.runtime, args.set)  # a bad runtime preset or override fails here, before any rendering
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    machine = slam_machine(loadavg_start=os.getloadavg() if hasattr(os, "getloadavg") else None)
    if args.detectors:
        res = detector_study(args)
        (out / "bench_detectors.json").write_text(json.dumps({"machine": machine, "detectors": res}, indent=2))
        print(f"wrote {out / 'bench_detectors.json'}")
        return 0
    done = resumable_rows(out / "bench_slam.json", run_args, machine, _row_key, "runs") if args.resume else {}
    rows = []
    res = {
        "command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
        "machine": machine,
        "args": run_args,
        "duration_s": args.duration,
        "realism": not args.synthetic,
        "imu_noise": not args.no_imu_noise,
        "runtime": args.runtime,
        "system": "dense" if args.dense else "sparse",
        "overrides": args.set,
        "complete": False,
        "runs": rows,
    }
    jobs = [(p, seed, None, 0.0) for p in args.presets for seed in args.seeds]
    jobs += [(name, seed, still, start) for name, still, start in mh05_jobs(args) for seed in args.seeds]
    for preset, seed, still, start in jobs:
        if (preset, seed) in done:
            rows.append(done[preset, seed])
            print(f"{preset} seed {seed}: kept from the earlier invocation", flush=True)
            continue
        if preset.startswith("mh05"):
            root = mh05_sequence(Path(args.mh05), Path(args.data), still, seed)
        else:
            root = default_sequence(
                preset, args.duration, seed, not args.no_imu_noise, args.data, progress=True, realism=not args.synthetic
            )
        cfg = make_config(args.runtime, args.set)
        t0 = time.perf_counter()
        m = run_one(root, cfg, out / f"{preset}_s{seed}", dense=args.dense, start_s=start)
        row = {
            "preset": preset,
            "seed": seed,
            "sequence": str(root),
            "start_s": start,
            "wall_s": time.perf_counter() - t0,
        }
        row.update(result_row(m))
        rows.append(row)
        print(
            f"{preset} seed {seed}: ATE {row.get('ate_se3_rmse_m', float('nan')):.4f} m, "
            f"{100 * row['posed_frac']:.1f}% posed, {row['fps']:.1f} FPS",
            flush=True,
        )
        write_json(out / "bench_slam.json", res)  # an interruption loses only the run in progress
    machine["loadavg_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
    print()
    print(fmt_table(rows))
    print()
    print(fmt_stages(rows))
    summ = summary(rows)
    print()
    for p, s in summ.items():
        print(
            f"{p}: ATE SE3 mean {s['ate_se3_rmse_m_mean']:.4f} m, max {s['ate_se3_rmse_m_max']:.4f} m; "
            f"Sim3 mean {s['ate_sim3_rmse_m_mean']:.4f} m; FPS mean {s['fps_mean']:.1f}, min {s['fps_min']:.1f}"
        )
    b = bars(rows)
    print("\nbars of the real-sensor issue:")
    for p, v in b.items():
        print(f"  {p}: {'met' if v['met'] else 'NOT met'} ({v['bar']}; missed by seeds {v['seeds_missed']})")
    res.update(complete=True, summary=summ, bars=b)
    write_json(out / "bench_slam.json", res)
    print(f"wrote {out / 'bench_slam.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
