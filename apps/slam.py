"""``dit-slam``: monocular visual-inertial SLAM on an EuRoC-layout sequence (Hydra config ``conf/slam/slam.yaml``).

    dit-slam [sequence=DIR|FILE.bag [calib=DIR] [topics.image=...]] [out=DIR] [viz=none|rerun]
             [runtime=default|fast] [runtime.x.y=...]
             [dense=true|false [model=DIR] [dense_settings.x=...]]

With no ``sequence`` it renders the default synthetic sequence (``sim`` settings of the config) into a cache
folder once and runs on it. The default ``out`` is ``outputs/slam/<sequence folder name>-<8 hex digits of its
absolute path>``, so two sequences with the same folder name never share it. ``out`` is checked (writable, not a
file) before any work, and the outputs of an earlier run there are removed first (the command says which).
Ctrl-C or SIGTERM stops after the current frame and writes everything processed so far (``"complete": false``
in ``metrics.json``; exit status 130 or 143).

Libraries raise; this entry point turns expected failures into one line naming the problem and exit status 2
(``--debug`` or ``HYDRA_FULL_ERROR=1`` also prints the traceback).
"""

from __future__ import annotations

import hashlib
import logging
import sys
from pathlib import Path

from runtime.errors import EXPECTED, UsageError, report, split_debug

__all__ = ["default_out", "main"]

EXIT_SIGNAL = {"SIGINT": 130, "SIGTERM": 143}


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
    if not bool(cfg.get("dense", True)):
        return slam_cfg, None, None
    from runtime.dense import DenseConfig
    from runtime.network import DepthNetwork, ModelError, default_model_dir

    try:
        dense_cfg = DenseConfig.from_dict(OmegaConf.to_container(cfg.get("dense_settings") or {}, resolve=True))
    except ValueError as e:
        raise UsageError(f"bad setting: {e}") from e
    model_dir = Path(str(cfg.model)).expanduser() if cfg.get("model") is not None else default_model_dir()
    try:
        DepthNetwork(model_dir).check_runtime()  # fail before the run, naming the problem
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
        seq = open_sequence(root, calib, topics)
    except (ValueError, OSError) as e:  # EurocFormatError names the file and the problem
        raise UsageError(f"cannot read the sequence: {e}") from e
    start = float(cfg.get("start_s") or 0.0)
    if start > 0:
        from runtime.io.sequence import StartView

        try:
            seq = StartView(seq, start)
        except ValueError as e:
            raise UsageError(str(e)) from e
    return seq


def default_out(root: str | Path) -> Path:
    """``outputs/slam/<folder name>-<8 hex digits of the absolute path>``: unique per sequence."""
    root = Path(root).resolve()
    tag = hashlib.sha1(str(root).encode()).hexdigest()[:8]
    return Path("outputs") / "slam" / f"{root.name or 'sequence'}-{tag}"


def _check_args(cfg) -> None:
    """Settings of the command itself, checked before any work."""
    if str(cfg.viz) not in ("none", "rerun"):
        raise UsageError(f"viz={cfg.viz!r}: expected none or rerun")
    if str(cfg.viz) == "rerun":
        try:
            import rerun  # noqa: F401
        except ImportError as e:
            raise UsageError(f"viz=rerun needs rerun-sdk (pip install rerun-sdk): {e}") from e
    mf = cfg.max_frames
    if mf is not None and (isinstance(mf, bool) or not isinstance(mf, int) or mf < 1):
        raise UsageError(f"max_frames={mf!r}: expected a positive number of frames or null (all)")
    st = cfg.get("start_s")
    if st is not None and (isinstance(st, bool) or not isinstance(st, (int, float)) or not 0 <= st < float("inf")):
        raise UsageError(f"start_s={st!r}: expected seconds >= 0 from the sequence's first frame")


def _story(m: dict) -> str | None:
    """How the run went, in one line: its start, restarts, IMU-only stretches, relocalisations and segments."""
    ini = m.get("initialisation") or {}
    if not ini:
        return None
    t_first = ini["t_s"] - ini["after_s"]
    parts = [f"started ({ini['method']}) {ini['after_s']:.2f} s in"]
    for r in m.get("restarts") or []:
        parts.append(f"restarted at {r['t_s'] - t_first:.2f} s ({r['why']})")
    status = m.get("frame_status") or {}
    if status.get("imu_backfill"):
        back = (m.get("from_start") or {}).get("left_out_imu_max_s")
        parts.append(
            f"{status['imu_backfill']} frames before a (re)start posed by the IMU alone"
            + (f" (up to {back:.1f} s)" if back else "")
        )
    if status.get("building"):
        parts.append(f"{status['building']} frames on the IMU before visual tracking was acquired")
    if status.get("coasting"):
        parts.append(f"{status['coasting']} frames coasting on the IMU")
    if m.get("relocalisations"):
        parts.append(f"{len(m['relocalisations'])} relocalisation(s)")
    if len(m.get("segments") or []) > 1:
        parts.append(f"{len(m['segments'])} segments (reset after a divergence or an IMU gap)")
    return "  " + "; ".join(parts)


def _summary(m: dict, out: Path, dense: bool) -> str:
    lines = []
    if not m.get("complete", True):
        lines.append(
            f"  INTERRUPTED ({m.get('interrupted_by')}) after {m['frames_processed']} of {m['frames']} frames: "
            'the outputs hold what was processed ("complete": false in metrics.json)'
        )
    rss = m.get("peak_rss_mb")
    first_pass = (m.get("intrinsics") or {}).get("first_pass_frames") and m.get("fps_frame_loop") is not None
    lines.append(
        f"  frames {m.get('frames_processed', m['frames'])} (with pose {m['frames_with_pose']}), keyframes "
        f"{m['keyframes']}, map points {m['map_points']}, {m['fps']:.1f} frames/s"
        + (f" ({m['fps_frame_loop']:.1f} after the intrinsics' first pass)" if first_pass else "")
        + (f", peak memory {rss:.0f} MiB" if rss else "")
    )
    story = _story(m)
    if story:
        lines.append(story)
    if "ate_se3_rmse_m" in m:
        lines.append(
            f"  ATE RMSE {m['ate_se3_rmse_m']:.4f} m (SE3), {m['ate_sim3_rmse_m']:.4f} m (Sim3, scale "
            f"{m['sim3_scale']:.4f}); RPE/{m['rpe_delta_frames']} frames {m['rpe_trans_rmse_m']:.4f} m, "
            f"{m['rpe_rot_rmse_deg']:.3f} deg"
        )
        fs = m.get("from_start")
        if fs and "ate_se3_rmse_m" in fs:
            lines.append(
                f"  ATE from the start on {fs['ate_se3_rmse_m']:.4f} m (SE3), {fs['ate_sim3_rmse_m']:.4f} m (Sim3): "
                f"without the {fs['frames_left_out']} frames before a (re)start, posed by the IMU alone "
                f"(up to {fs['left_out_imu_max_s']:.1f} s of it; frames.csv)"
            )
        if m.get("scale_by_piece"):
            from runtime.eval import SCALE_PIECE_S

            pieces = " ".join("-" if c is None else f"{c:.3f}" for c in m["scale_by_piece"])
            lines.append(f"  Sim3 scale of each {SCALE_PIECE_S:g} s alone (scale drift): {pieces}")
    intr = m.get("intrinsics") or {}
    if intr.get("refined"):
        td = ""
        if "time_offset_s" in intr:
            sd = (intr.get("std") or {}).get("time_offset_s")
            td = f"; camera-IMU time offset {1e3 * intr['time_offset_s']:+.1f} ms"
            td += (f" (sd {1e3 * sd:.1f})" if sd else "") + ", the camera's stamps moved by it"
        fx, fy = (100 * v for v in intr["focal_change_rel"])
        cx, cy = intr["principal_change_px"]
        lines.append(
            f"  camera refined over the first {intr['first_pass_frames']} frames: fx {fx:+.2f} %, fy {fy:+.2f} %, "
            f"cx {cx:+.1f} px, cy {cy:+.1f} px{td}"
        )
    if m.get("error"):
        lines.append(f"  ERROR: {m['error']}")
    dm = m.get("depth_metrics")
    if dm:
        lines.append(
            "  depth RMSE [m] on "
            f"{m.get('depth_metrics_keyframes', 0)} keyframes: sparse points {dm['sparse']['rmse']:.3f}, "
            f"prior c=0 {dm['prior']['rmse']:.3f}, window code {dm['optimised']['rmse']:.3f}"
            + (f", map code {dm['map']['rmse']:.3f}" if dm.get("map") else "")
            + (f"; references: interpolated input {dm['interpolated']['rmse']:.3f}" if dm.get("interpolated") else "")
            + (f", median of the true depth {dm['median']['rmse']:.3f}" if dm.get("median") else "")
        )
    if dense:
        names = ("dense_map.ply", "dense_map.png", "keyframe_depth.png", "dense_mesh.ply", "keyframe_depth/")
        dense_files = ", ".join(n for n in names if (out / n).exists())
        mesh = (
            f", mesh {m['dense_mesh_vertices']} vertices {m['dense_mesh_faces']} faces"
            if "dense_mesh_faces" in m
            else ""
        )
        lines.append(f"  dense map: {m.get('dense_map_points', 0)} points{mesh}; wrote {out}/{{{dense_files}}}")
        behind = m.get("dense_later_jobs_at_last_frame")
        if behind:
            lines.append(
                f"  the network thread was {behind} jobs of later work behind at the last frame (map codes, depth "
                f"metrics, fusion; at most {m['dense_later_jobs_peak']}): "
                f"{m['dense_later_work_after_last_frame_s']:.1f} s to finish them, counted in frames/s"
            )
    from runtime.outputs import RUN_OUTPUTS

    lines.append(f"  wrote {out}/{{{', '.join(n for n in RUN_OUTPUTS if (out / n).exists())}}}")
    return "\n".join(lines)


def run(cfg) -> int:
    """Run ``dit-slam`` with a composed config; returns the exit status."""
    _setup_logging(cfg)
    from runtime.outputs import check_writable, prepare_run_dir
    from runtime.run import run_sequence

    _check_args(cfg)
    if cfg.out is not None:
        check_writable(Path(str(cfg.out)))
    slam_cfg, dense_cfg, model_dir = _settings(cfg)
    seq = _sequence(cfg)
    out = Path(str(cfg.out)) if cfg.out is not None else default_out(seq.root)
    run_id, removed, previous = prepare_run_dir(out)
    if removed:
        print(
            f"dit-slam: removed the outputs of the earlier run {previous or '(unknown)'} in {out}: {', '.join(removed)}"
        )
    n = len(seq) if cfg.max_frames is None else min(len(seq), int(cfg.max_frames))
    start = f", from {seq.start_s:g} s (frame {seq.start_index})" if hasattr(seq, "start_index") else ""
    print(f"dit-slam: {seq.root} ({n} frames{start}, {'with' if seq.gt is not None else 'no'} ground truth) -> {out}")
    print(f"dit-slam: run {run_id}")
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
            run_id=run_id,
        )
    except ImportError as e:  # e.g. viz=rerun without rerun-sdk
        raise UsageError(str(e)) from e
    print(_summary(m, out, dense_cfg is not None))
    if not m.get("complete", True):
        return EXIT_SIGNAL.get(str(m.get("interrupted_by")), 130)
    return 1 if m.get("error") else 0


def main(argv: list[str] | None = None) -> None:
    """``dit-slam`` console entry point (Hydra overrides of ``conf/slam/slam.yaml``)."""
    import hydra

    args, debug = split_debug(list(sys.argv[1:] if argv is None else argv))
    status = {"code": 0}

    @hydra.main(version_base="1.3", config_path="pkg://conf.slam", config_name="slam")
    def _run(cfg) -> None:
        try:
            status["code"] = run(cfg)
        except EXPECTED as e:  # UsageError, a library's ValueError/OSError naming the problem
            status["code"] = report("dit-slam", e, debug)

    saved = sys.argv
    sys.argv = [Path(saved[0]).name if saved else "dit-slam", *args]
    try:
        _run()
    except KeyboardInterrupt:  # before or after the frame loop (which stops cleanly itself)
        print('dit-slam: interrupted; outputs of a started run are marked "complete": false', file=sys.stderr)
        status["code"] = 130
    finally:
        sys.argv = saved
    if status["code"]:
        sys.exit(status["code"])


if __name__ == "__main__":  # pragma: no cover
    main()
