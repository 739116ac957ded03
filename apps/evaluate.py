"""``dit-eval``: trajectory evaluation (ATE/RPE with evo) and the depth evaluation of ``train.evaluate``.

dit-eval trajectory est=TUM gt=TUM|EUROC_DIR|data.csv [out=DIR] [rpe_delta_s=1.0] [segments=auto|none|FILE]
dit-eval depth ...            (forwarded to train.evaluate.main, the depth evaluation)

The trajectory evaluation also estimates the time offset that fits the ground truth best and warns when it is
large, and says how many estimated poses lie outside the ground truth and were not evaluated. A trajectory in
several segments (``dit-slam`` re-initialised from scratch after a long IMU gap: each segment in its own frame;
``trajectory_segments.txt`` beside the estimate, or ``segments=FILE``) is also scored segment by segment.
Expected failures print one line and exit with status 2 (``--debug`` adds the traceback).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

__all__ = ["main"]

_EVAL_USAGE = (
    "usage: dit-eval trajectory est=TUM gt=TUM|EUROC_DIR|data.csv [out=DIR] [rpe_delta_s=1.0] [segments=auto]\n"
    "       dit-eval depth [overrides ...]"
)


def _eval_trajectory(args: list[str], debug: bool = False) -> int:
    from runtime import eval as ev
    from runtime.errors import EXPECTED, report

    opts = {"est": None, "gt": None, "out": None, "rpe_delta_s": "1.0", "segments": "auto"}
    for a in args:
        k, sep, v = a.partition("=")
        if not sep or k not in opts:
            print(f"dit-eval trajectory: unknown argument {a!r}\n{_EVAL_USAGE}", file=sys.stderr)
            return 2
        opts[k] = v
    if not opts["est"] or not opts["gt"]:
        print(f"dit-eval trajectory: est= and gt= are required\n{_EVAL_USAGE}", file=sys.stderr)
        return 2
    try:
        est_ts, est_T = ev.load_trajectory(opts["est"])
        gt_ts, gt_T = ev.load_trajectory(opts["gt"])
        m = ev.trajectory_metrics(est_ts, est_T, gt_ts, gt_T, rpe_delta_s=float(opts["rpe_delta_s"]))
        m.update(ev.best_time_offset(est_ts, est_T, gt_ts, gt_T))
        m["segments"] = _segments(opts, est_ts, est_T, gt_ts, gt_T)
    except EXPECTED as e:
        return report("dit-eval trajectory", e, debug)
    m["estimated_poses"] = int(len(est_ts))
    m["dropped_poses"] = int(len(est_ts) - m["eval_frames"])
    m["warnings"] = ev.evaluation_warnings(m, len(est_ts))
    for w in m["warnings"]:
        print(f"dit-eval trajectory: WARNING: {w}", file=sys.stderr)
    print(
        f"evaluated {m['eval_frames']} of {len(est_ts)} poses over {m['path_length_m']:.2f} m of ground truth"
        f" (best time offset {m.get('time_offset_s', float('nan')):+.3f} s)"
    )
    for k in (
        "ate_se3_rmse_m",
        "ate_se3_mean_m",
        "ate_se3_max_m",
        "ate_sim3_rmse_m",
        "sim3_scale",
        "rpe_trans_rmse_m",
        "rpe_rot_rmse_deg",
    ):
        print(f"  {k:18s} {m[k]:.5f}")
    if len(m["segments"]) > 1:
        print(f"  {len(m['segments'])} segments, each in its own frame (the figures above mix them):")
        for r in m["segments"]:
            ate = r.get("ate_se3_rmse_m")
            print(
                f"    segment {r['segment']}: {r['poses']} poses, ATE SE3 " + ("n/a" if ate is None else f"{ate:.5f} m")
            )
    if opts["out"]:
        from runtime.outputs import atomic_text, atomic_write, check_writable

        try:
            out = check_writable(opts["out"])
        except EXPECTED as e:
            return report("dit-eval trajectory", e, debug)
        atomic_text(out / "trajectory_metrics.json", json.dumps(m, indent=2))
        atomic_write(
            out / "trajectory_top.png",
            lambda p: ev.plot_top_view(p, est_ts, est_T, gt_ts, gt_T, title=Path(opts["est"]).name),
        )
        print(f"  wrote {out}/trajectory_metrics.json, trajectory_top.png")
    return 0


def _segments(opts: dict, est_ts, est_T, gt_ts, gt_T) -> list[dict]:
    """Each segment scored on its own (``segments``: ``auto`` reads ``trajectory_segments.txt`` beside the
    estimate when it is there, ``none`` skips, else a file of ``timestamp[s] segment`` lines)."""
    import numpy as np

    from runtime import eval as ev

    if opts["segments"] == "none":
        return []
    f = Path(opts["est"]).with_name("trajectory_segments.txt") if opts["segments"] == "auto" else Path(opts["segments"])
    if not f.is_file():
        if opts["segments"] != "auto":
            raise FileNotFoundError(f"segments file {f} not found")
        return []
    rows = np.loadtxt(f, comments="#", ndmin=2)
    if rows.shape[1] != 2 or rows.shape[0] != len(est_ts):
        raise ValueError(f"{f}: expected one 'timestamp segment' line per pose of {opts['est']} ({len(est_ts)})")
    seg = rows[:, 1].astype(np.int64)
    out = []
    for k in np.unique(seg):
        mk = seg == k
        r = {"segment": int(k), "poses": int(mk.sum())}
        try:
            r.update(ev.trajectory_metrics(est_ts[mk], est_T[mk], gt_ts, gt_T))
        except ValueError as e:
            r["eval_error"] = str(e)
        out.append(r)
    return out


def main(argv: list[str] | None = None) -> None:
    """``dit-eval`` console entry point: ``trajectory`` (here) or ``depth`` (``train.evaluate.main``)."""
    from runtime.errors import split_debug

    args, debug = split_debug(list(sys.argv[1:] if argv is None else argv))
    if not args or args[0] not in ("trajectory", "depth"):
        print(_EVAL_USAGE, file=sys.stderr)
        sys.exit(2)
    if args[0] == "trajectory":
        code = _eval_trajectory(args[1:], debug)
        if code:
            sys.exit(code)
        return
    import importlib

    try:
        mod = importlib.import_module("train.evaluate")
    except ImportError as e:
        sys.exit(f"dit-eval depth: the depth evaluation (train.evaluate) is unavailable: {e}")
    saved = sys.argv
    sys.argv = [saved[0] if saved else "dit-eval", *args[1:]]
    try:
        mod.main()
    finally:
        sys.argv = saved


if __name__ == "__main__":  # pragma: no cover
    main()
