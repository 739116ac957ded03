"""``dit-slam``: monocular visual-inertial SLAM on an EuRoC-layout sequence (Hydra config ``conf/slam/slam.yaml``).

    dit-slam [sequence=DIR|FILE.bag [calib=DIR] [topics.image=...]] [out=DIR] [viz=none|rerun]
             [runtime=default|fast] [runtime.x.y=...]
             [dense=true [model=DIR] [dense_settings.x=...]]

With no ``sequence`` it renders the default synthetic sequence (``sim`` settings of the config) into a cache
folder once and runs on it. Libraries raise; this entry point turns expected failures into one clear message
and exit status 2.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

__all__ = ["main"]


class UsageError(Exception):
    """An expected failure of the command (bad setting, unreadable input): one line, exit status 2."""


def _setup_logging(cfg) -> None:
    level = getattr(logging, str(cfg.log_level).upper(), logging.INFO)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    for name in list(logging.root.manager.loggerDict):  # a logging config may have muted existing loggers
        if name.split(".")[0] in ("runtime", "dit-slam"):
            logging.getLogger(name).disabled = False
    logging.getLogger("runtime").setLevel(level)


def _settings(cfg):
    """The typed SLAM and dense settings and the model folder; the model is loaded once to fail early."""
    from omegaconf import OmegaConf

    from runtime.slam import SlamConfig

    try:
        slam_cfg = SlamConfig.from_dict(OmegaConf.to_container(cfg.runtime, resolve=True))
    except ValueError as e:
        raise UsageError(f"bad setting: {e}") from e
    if not bool(cfg.get("dense", False)):
        return slam_cfg, None, None
    from runtime.dense import DenseConfig
    from runtime.network import DepthNetwork, ModelError, default_model_dir

    try:
        dense_cfg = DenseConfig.from_dict(OmegaConf.to_container(cfg.get("dense_settings") or {}, resolve=True))
    except ValueError as e:
        raise UsageError(f"bad setting: {e}") from e
    model_dir = Path(str(cfg.model)).expanduser() if cfg.get("model") is not None else default_model_dir()
    try:
        DepthNetwork(model_dir)  # fail before the run, naming the problem
    except (ModelError, OSError) as e:
        raise UsageError(f"cannot load the depth model: {e}") from e
    return slam_cfg, dense_cfg, model_dir


def _sequence(cfg):
    """The sequence to run on: ``sequence=DIR`` or a bag (with ``calib=DIR``), or the default synthetic one."""
    from runtime.io.bag import BagTopics
    from runtime.io.sequence import open_sequence

    if cfg.sequence is None:
        from sim.cache import cached_sequence

        s = cfg.sim
        try:
            root = cached_sequence(
                str(s.preset),
                float(s.duration),
                int(s.seed),
                bool(s.imu_noise),
                s.cache_dir,
                bool(cfg.progress),
                realism=bool(s.get("realism", True)),
            )
        except (ValueError, RuntimeError, FileExistsError) as e:
            raise UsageError(f"cannot render the default sequence: {e}") from e
    else:
        root = Path(str(cfg.sequence)).expanduser()
    t = cfg.get("topics") or {}
    topics = BagTopics(t.get("image"), t.get("imu"), t.get("gt", "auto"))
    calib = Path(str(cfg.calib)).expanduser() if cfg.get("calib") is not None else None
    try:
        return open_sequence(root, calib, topics)
    except (ValueError, OSError) as e:  # EurocFormatError names the file and the problem
        raise UsageError(f"cannot read the sequence: {e}") from e


def _summary(m: dict, out: Path, dense: bool) -> str:
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
    if dense:
        lines.append(f"  wrote {out}/{{dense_map.ply, keyframe_depth/}} ({m.get('dense_map_points', 0)} points)")
    lines.append(f"  wrote {out}/{{trajectory.txt, keyframes.txt, sparse_map.ply, metrics.json, trajectory_top.png}}")
    return "\n".join(lines)


def run(cfg) -> int:
    """Run ``dit-slam`` with a composed config; returns the exit status."""
    _setup_logging(cfg)
    from runtime.run import run_sequence

    slam_cfg, dense_cfg, model_dir = _settings(cfg)
    seq = _sequence(cfg)
    out = Path(str(cfg.out)) if cfg.out is not None else Path("outputs") / "slam" / (Path(seq.root).name or "sequence")
    n = len(seq) if cfg.max_frames is None else min(len(seq), int(cfg.max_frames))
    print(f"dit-slam: {seq.root} ({n} frames, {'with' if seq.gt is not None else 'no'} ground truth) -> {out}")
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
        raise UsageError(str(e)) from e
    print(_summary(m, out, dense_cfg is not None))
    return 1 if m.get("error") else 0


def main(argv: list[str] | None = None) -> None:
    """``dit-slam`` console entry point (Hydra overrides of ``conf/slam/slam.yaml``)."""
    import hydra

    args = list(sys.argv[1:] if argv is None else argv)
    status = {"code": 0}

    @hydra.main(version_base="1.3", config_path="pkg://conf.slam", config_name="slam")
    def _run(cfg) -> None:
        try:
            status["code"] = run(cfg)
        except UsageError as e:
            print(f"dit-slam: {e}", file=sys.stderr)
            status["code"] = 2

    saved = sys.argv
    sys.argv = [Path(saved[0]).name if saved else "dit-slam", *args]
    try:
        _run()
    finally:
        sys.argv = saved
    if status["code"]:
        sys.exit(status["code"])


if __name__ == "__main__":  # pragma: no cover
    main()
