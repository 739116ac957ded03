"""Run the SLAM system over a whole sequence: prefetched images, the per-frame loop, and the outputs.

Outputs in ``out_dir``: ``trajectory.txt`` (TUM, ``T_w_b`` per frame after initialisation; see
:meth:`runtime.slam.SlamSystem.trajectory`), ``frames.csv`` (each of those poses' status and the seconds it rests on
the IMU alone: :func:`runtime.trajectory.frame_status`), ``keyframes.txt``, ``sparse_map.ply``, ``metrics.json``,
``trajectory_top.png`` (the top view, its poses on the IMU alone in orange) and, with ``viz=rerun``,
``slam.rrd``. With a dense configuration (:mod:`runtime.dense`) also ``dense_map.ply``, ``keyframe_depth/`` and the
dense metrics.

The earlier run's outputs in ``out_dir`` are removed first and ``metrics.json`` is written at once as a stub
with ``"complete": false`` (:mod:`runtime.outputs`); the files are written atomically. SIGINT (Ctrl-C) or
SIGTERM during the frame loop stops after the current frame and writes everything processed so far, with
``"complete": false`` and ``"interrupted_by"`` in ``metrics.json``; a second signal aborts at once.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from runtime.geometry import ns_to_s
from runtime.image_check import ImageCheck
from runtime.live import LiveSlam
from runtime.outputs import atomic_text, atomic_write, prepare_run_dir
from runtime.slam import SlamConfig, SlamSystem
from runtime.trajectory import IMU_ONLY, frame_status

log = logging.getLogger(__name__)


def run_sequence(
    seq,
    out_dir: str | Path,
    cfg: SlamConfig | None = None,
    progress: bool = True,
    max_frames: int | None = None,
    viz: str | None = None,
    plot: bool = True,
    dense=None,
    model_dir: str | Path | None = None,
    depth_source=None,
    probe=None,
    run_id: str | None = None,
) -> dict:
    """Run the system over an io ``EurocSequence`` and write every output into ``out_dir``.

    ``dense``: a :class:`runtime.dense.DenseConfig` runs the tightly coupled dense system with the network in
    ``model_dir`` (default: the shipped model) and also writes ``dense_map.ply``, ``keyframe_depth/`` and the
    dense metrics (depth metrics of the sparse points, the c = 0 prior, the window's codes and the map's codes
    when the sequence has ``mav0/depth0``); None: the sparse system. ``depth_source`` and ``probe``: diagnostics
    injected into the dense mapper (:class:`runtime.dense.DenseMapper`; e.g. the rendered depth in place of the network,
    :func:`runtime.diagnostics.oracle_depth.oracle_depth_source`). ``run_id``: the id of
    :func:`runtime.outputs.prepare_run_dir` when the caller prepared ``out_dir`` already (None: prepare it here).

    Returns:
        The metrics dictionary also written to ``metrics.json``.
    """
    cfg = cfg or SlamConfig()
    if max_frames is not None and int(max_frames) < 1:
        raise ValueError(f"max_frames must be a positive number of frames or null (all), got {max_frames}")
    if viz not in (None, "", "none", "rerun"):
        raise ValueError(f"viz={viz!r} is not 'rerun' or 'none'")
    out = Path(out_dir)
    if run_id is None:
        run_id = prepare_run_dir(out)[0]
    with _StopOnSignal() as stop:
        return _run(seq, out, cfg, progress, max_frames, viz, plot, dense, model_dir, depth_source, probe, run_id, stop)


def _run(seq, out, cfg, progress, max_frames, viz, plot, dense, model_dir, depth_source, probe, run_id, stop):
    n = len(seq) if max_frames is None else min(len(seq), int(max_frames))
    rss_scope = "run" if _reset_peak_rss() else "process"
    net = _load_network(model_dir) if dense is not None else None  # a bad model fails before the first pass
    _preload()
    t_start, cpu_start = time.perf_counter(), time.process_time()
    cache = ImageCache()  # the first pass's decoded images, read again by the run
    seq, intrinsics = _refine_intrinsics(seq, cfg, n, progress, stop, cache)
    t_loop = time.perf_counter()
    mapper = _make_mapper(seq, dense, net, depth_source, probe) if dense is not None else None
    live = LiveSlam(seq.camera, seq.T_b_c, seq.imu, cfg, dense=mapper)  # the one code path, as live users feed it
    system = live.system
    recorder = _make_recorder(viz, out, seq)
    images = ImageCheck()
    done = _run_frames(live, seq, n, recorder, progress, stop, images, read=cache.take)
    cache.clear()
    t_drain = time.perf_counter()
    if mapper is not None:
        mapper.drain()  # the network thread's map codes, depth metrics and fusion of the frames run count in wall_s
    wall, cpu = time.perf_counter() - t_start, time.process_time() - cpu_start
    drain_s = time.perf_counter() - t_drain
    frames = frame_status(system.records)  # each pose's status and seconds on the IMU alone
    ts, T, pts = _write_trajectory_and_map(system, out, frames)
    metrics = {
        "run_id": run_id,
        "complete": done == n,
        "interrupted_by": stop.signal,
        "sequence": str(getattr(seq, "root", "")),
        "start_s": float(getattr(seq, "start_s", 0.0)),  # a run started later than the sequence (dit-slam start_s)
        "frames": int(n),
        "frames_processed": int(done),
        "frames_with_pose": int(len(ts)),
        "keyframes": int(len(system.map.history)),
        "map_points": int(pts.shape[0]),
        "wall_s": wall,  # the intrinsics pass and the frame loop; modules and the network are loaded before
        "fps": done / wall if wall > 0 else float("nan"),
        # the frame loop alone (the intrinsics' first pass left out): the speed of a run past its first seconds
        "fps_frame_loop": done / (t_start + wall - t_loop) if t_start + wall > t_loop else float("nan"),
        "cpu_s": cpu,  # CPU time of the process (all threads): robust to other jobs sharing the machine
        "cpu_ms_per_frame": 1e3 * cpu / max(done, 1),
        "peak_rss_mb": None,  # the largest resident memory, outputs included (set last; scope: peak_rss_scope)
        "peak_rss_scope": rss_scope,  # "run": since this run began; "process": of the whole process
        "image_warnings": images.warnings,
        "timing_ms_per_frame": system.timing_summary(),
        "keyframe_reasons": dict(system.kf_reasons),
        **_status_counts(frames),
        "map_points_refound": system.n_map_matches,
        "initialised_at_s": (ns_to_s(ts[0]) if len(ts) else None),
        "initialisation": system.init_info,  # method, when, and the figures of the solve
        "intrinsics": intrinsics,  # the written and the refined camera intrinsics (runtime.calibration)
        "events": system.events[:200],
        "n_events": len(system.events),
        "relocalisations": system.relocalisations,
        "restarts": system.restarts,
        "config": _jsonable(asdict(cfg)),
    }
    if mapper is not None:
        t0 = time.perf_counter()
        metrics.update(mapper.finish(system.backend, out))
        tm = system.timing_summary()
        metrics["timing_dense_ms_per_frame"] = {
            "network": tm.get("dense_network", 0.0),  # on the background thread with DenseConfig.background
            "keyframe_inputs": tm.get("dense_keyframe", 0.0),  # undistorted image and sparse depth, tracking thread
            "waiting_for_network": tm.get("dense_wait", 0.0),  # tracking thread blocked on a network pass
            "map_codes": tm.get("dense_map_codes", 0.0),  # the map's codes at fixed poses, network thread
            "factor_building": tm.get("dense_factors", 0.0),
            "optimisation": tm.get("optimize", 0.0) - tm.get("dense_factors", 0.0),
            "outputs_s": time.perf_counter() - t0,
        }
        metrics["dense_later_work_after_last_frame_s"] = drain_s  # inside wall_s: frames/s pays for it
    if len(ts) == 0 and done == n:
        why = system.initializer.last_reason or "no rest and no motion found"
        if not system.events:
            why += "; no events were logged: check the camera-IMU time overlap"
        metrics["error"] = f"never initialised ({why})"
        log.error("never initialised: no trajectory (%s)", why)
    metrics.update(_evaluate(seq, ts, T, out, plot, np.isin(frames[0], IMU_ONLY)))
    if (fs := _from_start(seq, frames, ts, T)) is not None:
        metrics["from_start"] = fs
    if plot and mapper is not None and mapper.dense_map is not None:
        from runtime.render import depth_panels, map_views

        _write_png(out / "dense_map.png", map_views(*mapper.dense_map, T[:, :3, 3] if len(T) else None))
        if mapper.depth_views:
            _write_png(out / "keyframe_depth.png", depth_panels(mapper.depth_views))
    metrics["segments"] = _segments(system, seq, ts, T, out)
    if recorder is not None:
        recorder.log_final(system, ts, T, pts, dense_map=mapper.dense_map if mapper is not None else None)
        recorder.close()
    metrics["peak_rss_mb"] = _peak_rss_mb()
    atomic_text(out / "metrics.json", json.dumps(_jsonable(metrics), indent=2))
    return metrics


class _StopOnSignal:
    """SIGINT / SIGTERM while active: remember the signal (the frame loop stops after the current frame); a
    second signal raises KeyboardInterrupt. Only installed in the main thread (signals are delivered there)."""

    def __init__(self) -> None:
        self.signal: str | None = None
        self._old: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._old[s] = signal.getsignal(s)
                signal.signal(s, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.signal is not None:
            raise KeyboardInterrupt(f"second {signal.Signals(signum).name}")
        self.signal = signal.Signals(signum).name
        log.warning("%s: stopping after the current frame, writing what was processed", self.signal)

    def __exit__(self, *exc) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)


def _make_recorder(viz: str | None, out: Path, seq):
    """The Rerun recorder of ``viz="rerun"`` (``out/slam.rrd``), or None."""
    if viz in (None, "", "none"):
        return None
    if viz != "rerun":
        raise ValueError(f"viz={viz!r} is not 'rerun' or 'none'")
    from runtime.viz import RerunRecorder

    return RerunRecorder(out / "slam.rrd", seq.camera, seq.T_b_c)


def _reset_peak_rss() -> bool:
    """Set the process's peak resident memory back to its current value (Linux: ``/proc/self/clear_refs``), so
    that ``peak_rss_mb`` is this run's peak, not that of earlier work in the same process (a benchmark, the
    tests); False where that cannot be done."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def _peak_rss_mb() -> float | None:
    """The process's peak resident memory [MiB] (``getrusage``; None where there is none, as on Windows)."""
    try:
        import resource
    except ImportError:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


def _preload() -> None:
    """Import the modules that the run would import on first use (GTSAM, SciPy's rotations for the trajectory's
    pose blending: about 0.3 s), so that ``wall_s`` and ``fps`` time the run, not module loading, as the peers'
    figures leave out their start-up (``benchmarks/peers/run_peer.py``)."""
    import gtsam  # noqa: F401
    import scipy.spatial.transform  # noqa: F401


def _load_network(model_dir):
    """The depth network in ``model_dir`` (None: the shipped one), checked for the runtime."""
    from runtime.network import DepthNetwork, default_model_dir

    return DepthNetwork(model_dir if model_dir is not None else default_model_dir()).check_runtime()


def _make_mapper(seq, dense, net, depth_source, probe):
    """The dense mapper of configuration ``dense`` with the depth network ``net``."""
    from runtime.dense import DenseMapper

    depth_gt = seq.depth if getattr(seq, "has_depth", False) else None
    return DenseMapper(net, seq.camera, seq.T_b_c, dense, depth_gt=depth_gt, depth_source=depth_source, probe=probe)


def _refine_intrinsics(seq, cfg: SlamConfig, n: int, progress: bool, stop, cache=None) -> tuple[object, dict]:
    """A first sparse pass over ``cfg.intrinsics.seconds`` of the sequence and the bundle adjustment of
    :func:`runtime.calibration.refine_intrinsics`; returns the sequence seen with the refined camera (or as it is)
    and the report for ``metrics.json``. ``cache``: an :class:`ImageCache` that keeps the pass's images."""
    from runtime.calibration import not_refined, refine_intrinsics
    from runtime.io.sequence import CameraView

    c = cfg.intrinsics
    if not c.refine:
        return seq, {"refined": False, "reason": "off (runtime.intrinsics.refine=false)"}
    if (why := not_refined(seq.camera)) is not None:
        log.info("intrinsics: kept the written calibration (%s); no first pass", why)
        return seq, {"refined": False, "reason": why}
    t0 = time.perf_counter()
    first, n1 = first_pass(seq, cfg, n, progress, stop, read=cache.keep if cache is not None else None)
    if stop is not None and stop.signal is not None:
        return seq, {"refined": False, "reason": f"interrupted by {stop.signal}"}
    traj_ts, traj_T = first.system.trajectory()
    res = refine_intrinsics(
        seq.camera,
        seq.T_b_c,
        seq.imu,
        first.imu,
        first.system.feature_log,
        traj_ts,
        traj_T,
        first.system.noise_scales,
        c,
    )
    report = {"refined": res.accepted, "first_pass_frames": n1, **res.report}
    report["seconds_total"] = round(time.perf_counter() - t0, 3)
    return (CameraView(seq, res.camera, res.time_offset_ns) if res.accepted else seq), report


def first_pass(seq, cfg: SlamConfig, n: int, progress: bool = False, stop=None, read=None) -> tuple[LiveSlam, int]:
    """The intrinsics refinement's first sparse pass: a live system over the first ``cfg.intrinsics.seconds`` of the
    sequence (at most ``n`` frames), logging the front end's features; returns it and the frames it took.
    ``stop`` and ``read``: as for :func:`_run_frames`."""
    ts = np.asarray(seq.frame_ts, dtype=np.int64)
    n1 = min(n, int(np.searchsorted(ts, int(ts[0] + cfg.intrinsics.seconds * 1e9), "right")))
    log.info("intrinsics: a first sparse pass over %d frames (%.1f s) to refine the camera", n1, cfg.intrinsics.seconds)
    # no restart for want of visual tracking in this pass: it only feeds the calibration, which such a restart moved
    # by chance (MH_05 IMU seed 377: the run after it 32.7 mm worse, dense; reports/ablations.md)
    first = LiveSlam(seq.camera, seq.T_b_c, seq.imu, replace(cfg, building_restart_s=0.0))
    first.system.feature_log = []
    _run_frames(first, seq, n1, None, progress, stop, desc="intrinsics", read=read)
    return first, n1


def _run_frames(
    live: LiveSlam, seq, n: int, recorder, progress: bool, stop=None, images=None, desc="dit-slam", read=None
) -> int:
    """Feed the first ``n`` frames (images decoded ahead in a thread), each after the IMU samples up to its time,
    to ``live``, until ``stop.signal`` is set; then the IMU samples after the last frame. ``images``: an
    :class:`ImageCheck` that looks at the images; ``read``: ``(seq, i) -> (image, error)`` (default
    :func:`_read_image`; :meth:`ImageCache.keep` or :meth:`ImageCache.take`). Returns the number of frames processed."""
    system, k = live.system, 0
    bar = None
    done = 0
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="frame", desc=desc, dynamic_ncols=True)
    for i, img, err, t_wait in _prefetched_images(seq, n, read=read if read is not None else _read_image):
        if stop is not None and stop.signal is not None:
            break
        ts = int(seq.frame_ts[i])
        if err is not None:
            system.event(ts, f"frame {i}: cannot read image ({err})")
        if images is not None and img is not None:
            for msg in images.look(i, img, seq):
                system.event(ts, msg)
        system.timers["read"] += t_wait
        k = _feed_imu(live, seq, k, ts)
        state = live.add_image(ts, img)
        rec = state.record if state is not None else None
        done = i + 1
        if recorder is not None and img is not None and state is not None:
            recorder.log_frame(system, ts, img, rec)
        if bar is not None:
            bar.update(1)
            if i % 20 == 0:
                bar.set_postfix(kf=len(system.map.history), lm=system.map.n_landmarks, st=rec.status if rec else "init")
    if stop is None or stop.signal is None:
        _feed_imu(live, seq, k, None)
    live.flush()
    if bar is not None:
        bar.close()
    return done


def _feed_imu(live: LiveSlam, seq, k: int, until_ns: int | None) -> int:
    """Add IMU samples ``k, k+1, ...`` with stamps up to ``until_ns`` (None: all); returns the next index."""
    end = seq.imu_ts.size if until_ns is None else int(np.searchsorted(seq.imu_ts, until_ns, "right"))
    for j in range(k, end):
        live.add_imu(int(seq.imu_ts[j]), seq.gyro[j], seq.accel[j])
    return max(k, end)


def _write_trajectory_and_map(system: SlamSystem, out: Path, frames: tuple[list[str], np.ndarray]):
    """``trajectory.txt``, ``frames.csv`` (``frames``: :func:`runtime.trajectory.frame_status` of the system's
    records), ``keyframes.txt`` and ``sparse_map.ply``; returns the trajectory and the points."""
    from runtime.io.ply import write_ply
    from runtime.io.tum import write_tum

    ts, T = system.trajectory()
    kts, kT = system.keyframe_trajectory()
    atomic_write(out / "trajectory.txt", lambda p: write_tum(p, ts, T))
    atomic_write(out / "keyframes.txt", lambda p: write_tum(p, kts, kT))
    _, pts = system.map.all_points()
    pts = pts[np.isfinite(pts).all(1)] if pts.size else np.zeros((0, 3))
    atomic_write(out / "sparse_map.ply", lambda p: write_ply(p, pts))
    status, imu_s = frames
    rows = "".join(f"{t},{st},{s:.3f}\n" for t, st, s in zip(ts.tolist(), status, imu_s.tolist(), strict=True))
    atomic_text(out / "frames.csv", "#timestamp [ns],status,imu_only_s\n" + rows)
    return ts, T, pts


def _status_counts(frames: tuple[list[str], np.ndarray]) -> dict:
    """``frame_status``: frames with a pose by status (``frames.csv``; ``frames`` from
    :func:`runtime.trajectory.frame_status`), and ``imu_only_max_s``: the longest any pose rested on the IMU alone."""
    status, imu_s = frames
    return {"frame_status": dict(Counter(status)), "imu_only_max_s": round(float(imu_s.max(initial=0.0)), 3)}


def _from_start(seq, frames: tuple[list[str], np.ndarray], ts: np.ndarray, T: np.ndarray) -> dict | None:
    """ATE of the frames from the start on, without those kept from before it, or from before a restart's window,
    and posed by the IMU alone (``imu_backfill``: up to ``dynamic_init.backfill_s`` of dead reckoning, which can
    dominate a run's ATE); None when there are none or no ground truth."""
    from runtime import eval as ev

    status, imu_s = frames
    keep = np.array([s != "imu_backfill" for s in status], dtype=bool)
    if seq.gt is None or keep.all() or keep.sum() < 3:
        return None
    try:
        m = ev.trajectory_metrics(ts[keep], T[keep], seq.gt.ts, seq.gt.T_w_b)
    except Exception as e:  # noqa: BLE001 - evaluation must not lose the run's outputs
        return {"eval_error": f"{type(e).__name__}: {e}"}
    return {k: m[k] for k in ("ate_se3_rmse_m", "ate_sim3_rmse_m", "sim3_scale", "eval_frames")} | {
        "frames_left_out": int((~keep).sum()),
        "left_out_imu_max_s": round(float(imu_s[~keep].max()), 3),
    }


def _segments(system: SlamSystem, seq, ts: np.ndarray, T: np.ndarray, out: Path) -> list[dict]:
    """The trajectory's segments (a new one, in its own frame, after each re-initialisation from scratch), each
    scored on its own; with more than one, ``trajectory_segments.txt`` gives each pose's segment."""
    from runtime import eval as ev

    seg = np.array([r.segment for r in system.records], dtype=np.int64)
    out_list = []
    for k in np.unique(seg):
        m = seg == k
        row = {
            "segment": int(k),
            "t_start_s": ns_to_s(int(ts[m][0])),
            "t_end_s": ns_to_s(int(ts[m][-1])),
            "poses": int(m.sum()),
        }
        if seq.gt is not None and m.sum() >= 2 and len(np.unique(seg)) > 1:
            try:
                row.update(
                    {
                        k2: v
                        for k2, v in ev.trajectory_metrics(ts[m], T[m], seq.gt.ts, seq.gt.T_w_b).items()
                        if "ate" in k2
                    }
                )
            except Exception as e:  # noqa: BLE001 - as in _evaluate: a segment's score must not lose the outputs
                row["eval_error"] = f"{type(e).__name__}: {e}"
        out_list.append(row)
    if len(out_list) > 1:
        lines = "".join(f"{ns_to_s(int(t)):.9f} {int(s)}\n" for t, s in zip(ts, seg, strict=True))
        atomic_text(out / "trajectory_segments.txt", "# timestamp[s] segment\n" + lines)
    return out_list


def _evaluate(seq, ts: np.ndarray, T: np.ndarray, out: Path, plot: bool, imu_only: np.ndarray | None = None) -> dict:
    """Trajectory metrics against the sequence's ground truth (when it has one) and the top-view plot (``imu_only``:
    the poses resting on the IMU alone, marked in it)."""
    from runtime import eval as ev

    name = Path(str(seq.root)).name

    def top_view(gt_ts=None, gt_T=None) -> None:
        atomic_write(
            out / "trajectory_top.png",
            lambda p: ev.plot_top_view(p, ts, T, gt_ts, gt_T, title=name, imu_only=imu_only),
        )

    if seq.gt is None or len(ts) < 2:
        if plot and len(ts) >= 2:
            top_view()
        return {}
    res = {}
    try:
        res.update(ev.trajectory_metrics(ts, T, seq.gt.ts, seq.gt.T_w_b))
        if plot:
            top_view(seq.gt.ts, seq.gt.T_w_b)
    except Exception as e:  # noqa: BLE001 - evaluation must not lose the run's outputs
        res["eval_error"] = f"{type(e).__name__}: {e}"
        log.error("evaluation failed: %s", e)
    return res


def _write_png(path: Path, img: np.ndarray) -> None:
    """An RGB picture (``dense_map.png``: :func:`runtime.render.map_views`; ``keyframe_depth.png``:
    :func:`runtime.render.depth_panels`), written atomically."""
    import cv2

    def write(p: Path) -> None:
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))
        if not ok:
            raise OSError(f"{path}: PNG encoding failed")
        p.write_bytes(buf.tobytes())

    atomic_write(path, write)


def _read_image(seq, i: int):
    try:
        return seq.image(i), None
    except Exception as e:  # noqa: BLE001 - a corrupt or vanished image must not stop the run
        return None, f"{type(e).__name__}: {str(e)[:200]}"


class ImageCache:
    """Decoded images kept from the intrinsics refinement's first pass (:meth:`keep`, at most ``max_bytes``) for
    the run that follows, which takes each of them from memory once instead of decoding it again (:meth:`take`).
    The main command's run decodes 301 fewer PNGs, about 4 ms of CPU each at 752x480, on cores the dense system's
    threads share."""

    def __init__(self, max_bytes: int = 512 * 2**20) -> None:
        self.max_bytes = int(max_bytes)
        self._images: dict[int, np.ndarray] = {}
        self._bytes = 0

    def keep(self, seq, i: int):
        """``(image or None, error or None)`` of frame ``i``, decoded and kept while it fits."""
        img, err = _read_image(seq, i)
        if img is not None and self._bytes + img.nbytes <= self.max_bytes:
            self._images[i] = img
            self._bytes += img.nbytes
        return img, err

    def take(self, seq, i: int):
        """Frame ``i`` from memory (handed out once) when kept, else decoded; nothing is kept."""
        img = self._images.pop(i, None)
        if img is None:
            return _read_image(seq, i)
        self._bytes -= img.nbytes
        return img, None

    def __len__(self) -> int:
        return len(self._images)

    def clear(self) -> None:
        self._images.clear()
        self._bytes = 0


def _prefetched_images(seq, n: int, depth: int = 3, read=_read_image):
    """Yield ``(i, image or None, error or None, seconds waited)``; PNG decoding runs ahead in a thread
    (OpenCV releases the GIL, so it overlaps with tracking and optimisation on the second core)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="imread") as ex:
        futs = deque(ex.submit(read, seq, i) for i in range(min(depth, n)))
        for i in range(n):
            t0 = time.perf_counter()
            img, err = futs.popleft().result()
            waited = time.perf_counter() - t0
            if i + depth < n:
                futs.append(ex.submit(read, seq, i + depth))
            yield i, img, err, waited


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x
