"""``dit-eval``: trajectory evaluation (ATE/RPE with evo) and the depth evaluation of ``train.evaluate``.

dit-eval trajectory est=TUM gt=TUM|EUROC_DIR|data.csv [out=DIR] [rpe_delta_s=1.0]
dit-eval depth ...            (forwarded to train.evaluate.main, the depth evaluation)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

__all__ = ["main"]

_EVAL_USAGE = (
    "usage: dit-eval trajectory est=TUM gt=TUM|EUROC_DIR|data.csv [out=DIR] [rpe_delta_s=1.0]\n"
    "       dit-eval depth [overrides ...]"
)


def _eval_trajectory(args: list[str]) -> int:
    from runtime import eval as ev

    opts = {"est": None, "gt": None, "out": None, "rpe_delta_s": "1.0"}
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
    except (ValueError, OSError) as e:
        print(f"dit-eval trajectory: {e}", file=sys.stderr)
        return 2
    print(f"evaluated {m['eval_frames']} poses over {m['path_length_m']:.2f} m of ground truth")
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
    if opts["out"]:
        out = Path(opts["out"])
        out.mkdir(parents=True, exist_ok=True)
        (out / "trajectory_metrics.json").write_text(json.dumps(m, indent=2))
        ev.plot_top_view(out / "trajectory_top.png", est_ts, est_T, gt_ts, gt_T, title=Path(opts["est"]).name)
        print(f"  wrote {out}/trajectory_metrics.json, trajectory_top.png")
    return 0


def main(argv: list[str] | None = None) -> None:
    """``dit-eval`` console entry point: ``trajectory`` (here) or ``depth`` (``train.evaluate.main``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] not in ("trajectory", "depth"):
        sys.exit(_EVAL_USAGE)
    if args[0] == "trajectory":
        code = _eval_trajectory(args[1:])
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
