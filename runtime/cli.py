"""Console entry points ``dit-slam`` and ``dit-eval``.

    dit-slam [sequence=DIR] [out=DIR] [dense=false] [viz=none|rerun] [runtime=default|fast] [runtime.x.y=...]
             [dense=true [model=DIR] [dense_settings.x=...]]
    dit-eval trajectory est=TUM gt=TUM|EUROC_DIR|data.csv [out=DIR] [rpe_delta_s=1.0]
    dit-eval depth ...            (forwarded to train.evaluate.main, the depth evaluation)

``dit-slam`` with no ``sequence`` renders the default synthetic sequence (``sim`` settings of
``conf/slam.yaml``)
into a cache folder once and runs on it. Libraries raise; these entry points turn errors into one clear
message
and a non-zero exit status.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

__all__ = ["slam_main", "eval_main", "default_sequence"]

log = logging.getLogger("dit-slam")


def default_sequence(
    preset: str, duration: float, seed: int, imu_noise: bool, cache_dir: str | Path, progress: bool = True
) -> Path:
    """The default synthetic sequence, rendered with ``sim`` into ``cache_dir`` on first use, reused after."""
    cache = Path(cache_dir) / f"euroc_{preset}_{duration:g}s_s{seed}{'' if imu_noise else '_exact'}"
    info = cache / "sim_info.json"
    if info.is_file() and (cache / "mav0" / "cam0" / "data.csv").is_file():
        meta = json.loads(info.read_text())
        if (
            meta.get("preset"),
            float(meta.get("duration_s", -1)),
            int(meta.get("seed", -1)),
            bool(meta.get("imu_noise")),
        ) == (preset, float(duration), int(seed), bool(imu_noise)):
            return cache
    try:
        from sim.euroc import write_euroc_sequence
    except ImportError as e:  # pragma: no cover - sim ships with the package
        raise RuntimeError(f"no sequence given and the simulator is unavailable ({e})") from e
    print(
        f"dit-slam: rendering the default synthetic sequence ({preset}, {duration:g} s, seed {seed}) "
        f"into {cache}"
    )
    return Path(
        write_euroc_sequence(
            cache,
            preset=preset,
            duration=float(duration),
            seed=int(seed),
            imu_noise=bool(imu_noise),
            progress=progress,
        )
    )


def _slam(cfg) -> int:
    from omegaconf import OmegaConf

    level = getattr(logging, str(cfg.log_level).upper(), logging.INFO)
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S"
    )
    for name in list(logging.root.manager.loggerDict):  # a logging config may have muted existing loggers
        if name.split(".")[0] in ("runtime", "dit-slam"):
            logging.getLogger(name).disabled = False
    logging.getLogger("runtime").setLevel(level)
    from runtime.io.euroc import read_euroc
    from runtime.slam import SlamConfig, run_sequence

    try:
        slam_cfg = SlamConfig.from_dict(OmegaConf.to_container(cfg.runtime, resolve=True))
    except ValueError as e:
        print(f"dit-slam: bad setting: {e}", file=sys.stderr)
        return 2
    dense_cfg, model_dir = None, None
    if bool(cfg.get("dense", False)):
        from runtime.dense import DenseConfig
        from runtime.network import DepthNetwork, ModelError, default_model_dir

        try:
            dense_cfg = DenseConfig.from_dict(
                OmegaConf.to_container(cfg.get("dense_settings") or {}, resolve=True)
            )
        except ValueError as e:
            print(f"dit-slam: bad setting: {e}", file=sys.stderr)
            return 2
        model_dir = (
            Path(str(cfg.model_dir)).expanduser() if cfg.get("model_dir") is not None else default_model_dir()
        )
        try:
            DepthNetwork(model_dir)  # fail before the run, naming the problem
        except (ModelError, OSError) as e:
            print(f"dit-slam: cannot load the depth model: {e}", file=sys.stderr)
            return 2
    if cfg.sequence is None:
        s = cfg.sim
        try:
            root = default_sequence(
                str(s.preset),
                float(s.duration),
                int(s.seed),
                bool(s.imu_noise),
                s.cache_dir,
                bool(cfg.progress),
            )
        except (ValueError, RuntimeError, FileExistsError) as e:
            print(f"dit-slam: cannot render the default sequence: {e}", file=sys.stderr)
            return 2
    else:
        root = Path(str(cfg.sequence)).expanduser()
    try:
        seq = read_euroc(root)
    except (ValueError, OSError) as e:  # EurocFormatError names the file and the problem
        print(f"dit-slam: cannot read the sequence: {e}", file=sys.stderr)
        return 2
    name = Path(seq.root).name or "sequence"
    out = Path(str(cfg.out)) if cfg.out is not None else Path("outputs") / "slam" / name
    n = len(seq) if cfg.max_frames is None else min(len(seq), int(cfg.max_frames))
    print(
        f"dit-slam: {seq.root} ({n} frames, {'with' if seq.gt is not None else 'no'} ground truth) -> {out}"
    )
    try:
        m = run_sequence(
            seq,
            out,
            slam_cfg,
            progress=bool(cfg.progress),
            max_frames=cfg.max_frames,
            viz=None if str(cfg.viz) == "none" else str(cfg.viz),
            dense=dense_cfg,
            model_dir=model_dir,
        )
    except ImportError as e:  # e.g. viz=rerun without rerun-sdk
        print(f"dit-slam: {e}", file=sys.stderr)
        return 2
    lines = [
        f"  frames {m['frames']} (with pose {m['frames_with_pose']}), keyframes {m['keyframes']}, "
        f"map points {m['map_points']}, {m['fps']:.1f} frames/s",
    ]
    if "ate_se3_rmse_m" in m:
        lines.append(
            f"  ATE RMSE {m['ate_se3_rmse_m']:.4f} m (SE3), {m['ate_sim3_rmse_m']:.4f} m (Sim3, scale "
            f"{m['sim3_scale']:.4f}); RPE/{m['rpe_delta_frames']} frames {m['rpe_trans_rmse_m']:.4f} m, "
            f"{m['rpe_rot_rmse_deg']:.3f} deg"
        )
    if m.get("error"):
        lines.append(f"  ERROR: {m['error']}")
    dm = m.get("depth_metrics")
    if dm:
        lines.append(
            "  depth RMSE [m] on "
            f"{m.get('depth_metrics_keyframes', 0)} keyframes: sparse points {dm['sparse']['rmse']:.3f}, "
            f"prior c=0 {dm['prior']['rmse']:.3f}, optimised code {dm['optimised']['rmse']:.3f}"
        )
    if dense_cfg is not None:
        lines.append(
            f"  wrote {out}/{{dense_map.ply, keyframe_depth/}} ({m.get('dense_map_points', 0)} points)"
        )
    lines.append(
        f"  wrote {out}/{{trajectory.txt, keyframes.txt, sparse_map.ply, metrics.json, trajectory_top.png}}"
    )
    print("\n".join(lines))
    return 1 if m.get("error") else 0


def slam_main(argv: list[str] | None = None) -> None:
    """``dit-slam`` console entry point (Hydra overrides of ``conf/slam.yaml``)."""
    import hydra

    args = list(sys.argv[1:] if argv is None else argv)
    status = {"code": 0}

    @hydra.main(version_base="1.3", config_path="pkg://conf", config_name="slam")
    def _run(cfg) -> None:
        status["code"] = _slam(cfg)

    # ``model=DIR`` names the depth network; Hydra would read it as the training config group conf/model/
    args = [("model_dir=" + a[len("model=") :]) if a.startswith("model=") else a for a in args]
    saved = sys.argv
    sys.argv = [Path(saved[0]).name if saved else "dit-slam", *args]
    try:
        _run()
    finally:
        sys.argv = saved
    if status["code"]:
        sys.exit(status["code"])


# ---------------------------------------------------------------------- dit-eval
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


def eval_main(argv: list[str] | None = None) -> None:
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
    slam_main()
