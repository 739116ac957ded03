"""The live interface: feed IMU samples and camera images as they arrive, read the state after each image.

``LiveSlam`` wraps :class:`runtime.slam.SlamSystem` with an IMU stream that grows as samples come in. Samples may
arrive in any causal interleaving: an image is held until the IMU has reached its timestamp (a sample at or after
it has arrived), then processed exactly as a batch run over the whole recording would process it, so that the
same samples give the same trajectory whatever the order of arrival (IMU late, images early). ``close()``
processes the images still waiting and writes the outputs.

Example (a rendered sequence fed sample by sample; ``seq`` from :func:`runtime.io.sequence.open_sequence`):

    >>> from runtime.live import LiveSlam
    >>> slam = LiveSlam(seq.camera, seq.T_b_c, seq.imu, on_keyframe=print)  # doctest: +SKIP
    >>> for t, g, a in zip(seq.imu_ts, seq.gyro, seq.accel):  # doctest: +SKIP
    ...     slam.add_imu(t, g, a)
    ...     # ... and slam.add_image(t_img, image) whenever a frame comes in
    >>> state = slam.add_image(t_img, image)  # doctest: +SKIP
    >>> state.T_w_b if state is not None and state.initialized else None  # doctest: +SKIP
    >>> metrics = slam.close("outputs/live")  # doctest: +SKIP
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.backend.imu import ImuStream
from runtime.geometry import ns_to_s
from runtime.slam import SlamConfig, SlamSystem

log = logging.getLogger(__name__)

__all__ = ["LiveSlam", "LiveState", "GrowingImuStream"]


@dataclass(frozen=True)
class LiveState:
    """The system's state after one image.

    Attributes:
        ts: the image's timestamp [ns].
        frame_idx: its index in the order of processing.
        initialized: False until the static initialisation has succeeded (then ``T_w_b`` and ``v_w`` are set).
        status: ``initialising``, ``tracking``, ``still``, ``coasting`` (visual tracking lost, IMU only),
            ``building`` (after a start, visual tracking not yet acquired, IMU only), ``no_image`` (the image was
            None) or ``keyframe``.
        T_w_b: (4, 4) body pose in the world (causal estimate), or None.
        v_w: (3,) body velocity [m/s], or None.
        is_keyframe: the image became a keyframe.
        n_keyframes: keyframes so far.
        n_landmarks: landmarks in the map.
        record: the system's :class:`runtime.trajectory.FrameRecord` of the image (None before initialisation).
    """

    ts: int
    frame_idx: int
    initialized: bool
    status: str
    T_w_b: np.ndarray | None
    v_w: np.ndarray | None
    is_keyframe: bool
    n_keyframes: int
    n_landmarks: int
    record: object = field(default=None, repr=False)


class GrowingImuStream(ImuStream):
    """An :class:`~runtime.backend.imu.ImuStream` that grows by :meth:`append` (same cleaning and queries).

    Non-finite samples are dropped (counted in ``dropped_ts``); a sample not after the last one raises.
    """

    def __init__(self, rate_hz: float, T_b_s: np.ndarray | None = None, gap_factor: float = 4.0) -> None:
        if not np.isfinite(rate_hz) or rate_hz <= 0:
            raise ValueError(f"IMU rate_hz={rate_hz!r} must be positive")
        R = None if T_b_s is None else np.asarray(T_b_s, dtype=np.float64)[:3, :3]
        self._R = None if R is None or np.allclose(R, np.eye(3), atol=1e-9) else R
        if T_b_s is not None and np.linalg.norm(np.asarray(T_b_s)[:3, 3]) > 1e-3:
            log.warning("IMU: T_b_s has a lever arm of %.3f m, ignored", np.linalg.norm(np.asarray(T_b_s)[:3, 3]))
        self.rate_hz = float(rate_hz)
        self.gap_ns = int(gap_factor * 1e9 / rate_hz)
        self.gaps: list[tuple[int, int]] = []
        self.dropped_ts = np.zeros(0, np.int64)
        self._n = 0
        self._ts = np.zeros(1024, np.int64)
        self._v = np.zeros((1024, 6))
        self._views()

    def _views(self) -> None:
        self.ts, self.gyro, self.accel = self._ts[: self._n], self._v[: self._n, :3], self._v[: self._n, 3:]

    def __len__(self) -> int:
        return self._n

    @property
    def t_start(self) -> int:
        if self._n == 0:
            raise ValueError("IMU stream is empty")
        return int(self._ts[0])

    def append(self, t_ns: int, gyro, accel) -> bool:
        """Add one sample (rad/s and m/s^2 in the IMU frame); False when dropped as non-finite."""
        g = np.asarray(gyro, dtype=np.float64).reshape(3)
        a = np.asarray(accel, dtype=np.float64).reshape(3)
        if not (np.isfinite(g).all() and np.isfinite(a).all()):
            self.dropped_ts = np.append(self.dropped_ts, np.int64(t_ns))
            log.warning("IMU: dropped a non-finite sample at t=%.3f s", ns_to_s(int(t_ns)))
            return False
        if self._n and int(t_ns) <= int(self._ts[self._n - 1]):
            raise ValueError(f"IMU sample at {int(t_ns)} ns is not after the previous one ({self._ts[self._n - 1]} ns)")
        if self._n == self._ts.size:
            self._ts = np.concatenate([self._ts, np.zeros_like(self._ts)])
            self._v = np.concatenate([self._v, np.zeros_like(self._v)])
        if self._R is not None:  # the batch stream rotates all rows at once: (N, 3) @ R^T
            g, a = g[None] @ self._R.T, a[None] @ self._R.T
        if self._n and int(t_ns) - int(self._ts[self._n - 1]) > self.gap_ns:
            self.gaps.append((int(self._ts[self._n - 1]), int(t_ns)))
            log.warning(
                "IMU: gap of %.3f s at t=%.3f s", ns_to_s(self.gaps[-1][1] - self.gaps[-1][0]), ns_to_s(int(t_ns))
            )
        self._ts[self._n] = int(t_ns)
        self._v[self._n, :3], self._v[self._n, 3:] = g.ravel(), a.ravel()
        self._n += 1
        self._views()
        return True


class LiveSlam:
    """Visual-inertial SLAM fed sample by sample.

    Args:
        camera: cam0 model (:class:`runtime.geometry.Camera`; radial-tangential, or the pinhole camera of
            undistorted fisheye images, see :class:`runtime.io.sequence.PinholeView`).
        T_b_c: (4, 4) cam0 pose in the body (IMU) frame.
        imu_params: IMU noise model and rate (:class:`runtime.io.sensor_yaml.ImuParams`).
        cfg: settings (default :class:`runtime.slam.SlamConfig`).
        dense: a :class:`runtime.dense.DenseMapper` for the dense system, or None (sparse).
        on_frame: called with the :class:`LiveState` of every processed image.
        on_keyframe: called with the :class:`LiveState` of every new keyframe.
        on_map: called after every new keyframe's optimisation with the map: ``(ids (N,), X_w (N, 3))`` of every
            point (the window's landmarks and the map points that left it).
        on_depth: with ``dense``, called after every new keyframe with ``(kf_id, depth)``: the newest keyframe's
            dense depth (network resolution, metres) decoded from its current code (the call waits for the network
            thread to reach it, so it costs tracking time).

    Timestamps are int64 ns on one clock for both sensors. Images are (H, W) uint8 grey as the camera gives them
    (``None``: a frame whose image could not be read; the system coasts on the IMU through it).
    """

    def __init__(
        self,
        camera,
        T_b_c: np.ndarray,
        imu_params,
        cfg: SlamConfig | None = None,
        *,
        dense=None,
        on_frame: Callable[[LiveState], None] | None = None,
        on_keyframe: Callable[[LiveState], None] | None = None,
        on_map: Callable[[np.ndarray, np.ndarray], None] | None = None,
        on_depth: Callable[[int, np.ndarray], None] | None = None,
    ) -> None:
        self.cfg = cfg or SlamConfig()
        self.imu = GrowingImuStream(imu_params.rate_hz, getattr(imu_params, "T_b_s", None), self.cfg.imu.gap_factor)
        self.system = SlamSystem(camera, T_b_c, self.imu, imu_params, self.cfg, dense=dense)
        self.dense = dense
        self.on_frame, self.on_keyframe = on_frame, on_keyframe
        self.on_map, self.on_depth = on_map, on_depth
        self._pending: deque[tuple[int, np.ndarray | None]] = deque()
        self._n_frames = 0
        self._last_image_ts: int | None = None
        self.closed = False

    @property
    def n_frames(self) -> int:
        """Images processed so far (not counting those waiting for IMU)."""
        return self._n_frames

    @property
    def n_pending(self) -> int:
        """Images waiting for the IMU to reach their timestamp."""
        return len(self._pending)

    def add_imu(self, t_ns: int, gyro, accel) -> list[LiveState]:
        """Add one IMU sample; returns the states of the images it released (possibly none)."""
        self._check_open()
        self.imu.append(int(t_ns), gyro, accel)
        return self._release(final=False)

    def add_image(self, t_ns: int, image: np.ndarray | None) -> LiveState | None:
        """Add one image; returns its state, or None while it waits for the IMU to reach ``t_ns``.

        Raises:
            ValueError: an image not after the previous one.
        """
        self._check_open()
        t_ns = int(t_ns)
        if self._last_image_ts is not None and t_ns <= self._last_image_ts:
            raise ValueError(f"image at {t_ns} ns is not after the previous one ({self._last_image_ts} ns)")
        self._last_image_ts = t_ns
        self._pending.append((t_ns, image))
        states = self._release(final=False)
        return states[-1] if states and states[-1].ts == t_ns else None

    def flush(self) -> list[LiveState]:
        """Process the images still waiting (the IMU will not reach them: end of the recording)."""
        self._check_open()
        return self._release(final=True)

    def _ready(self, t_ns: int) -> bool:
        return len(self.imu) > 0 and int(self.imu.ts[-1]) >= t_ns

    def _release(self, final: bool) -> list[LiveState]:
        out = []
        while self._pending and (final or self._ready(self._pending[0][0])):
            t, img = self._pending.popleft()
            if len(self.imu) == 0:
                self.system.event(t, "image before any IMU sample at the end of the stream, dropped")
                continue
            out.append(self._process(t, img))
        return out

    def _process(self, t: int, img: np.ndarray | None) -> LiveState:
        s = self.system
        rec = s.process(self._n_frames, t, img)
        self._n_frames += 1
        state = LiveState(
            ts=t,
            frame_idx=self._n_frames - 1,
            initialized=bool(s.initialized),
            status=("keyframe" if rec.is_kf else rec.status) if rec is not None else "initialising",
            T_w_b=None if rec is None else rec.T_online.copy(),
            v_w=None if rec is None or s.v_cur is None else np.array(s.v_cur, dtype=np.float64),
            is_keyframe=bool(rec is not None and rec.is_kf),
            n_keyframes=len(s.map.history),
            n_landmarks=int(s.map.n_landmarks),
            record=rec,
        )
        if self.on_frame is not None:
            self.on_frame(state)
        if state.is_keyframe:
            self._keyframe_callbacks(state)
        return state

    def _keyframe_callbacks(self, state: LiveState) -> None:
        if self.on_keyframe is not None:
            self.on_keyframe(state)
        if self.on_map is not None:
            self.on_map(*self.system.map.all_points())
        if self.on_depth is not None and self.dense is not None and self.dense.kfs:
            kf_id = max(self.dense.kfs)
            self.on_depth(kf_id, self.dense.final_depth(self.dense.kfs[kf_id]))

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Poses of every processed frame after initialisation: ts (N,) ns, ``T_w_b`` (N, 4, 4)."""
        return self.system.trajectory()

    def close(self, out_dir: str | Path | None = None) -> dict:
        """Process the waiting images, write ``trajectory.txt``, ``frames.csv``, ``keyframes.txt``, ``sparse_map.ply``
        and ``metrics.json`` into ``out_dir`` (nothing when None), and return the metrics."""
        import json

        self.flush()
        self.closed = True
        s = self.system
        ts, _ = s.trajectory()
        metrics = {
            "frames": self._n_frames,
            "frames_with_pose": int(len(ts)),
            "keyframes": int(len(s.map.history)),
            "imu_samples": len(self.imu),
            "imu_dropped": int(self.imu.dropped_ts.size),
            "initialised_at_s": ns_to_s(ts[0]) if len(ts) else None,
            "n_events": len(s.events),
        }
        from runtime.run import _status_counts, _write_trajectory_and_map
        from runtime.trajectory import frame_status

        frames = frame_status(s.records)
        metrics.update(_status_counts(frames))  # frames with a pose by status, the longest on the IMU alone
        if out_dir is not None:
            out = Path(out_dir)
            out.mkdir(parents=True, exist_ok=True)
            _, _, pts = _write_trajectory_and_map(s, out, frames)
            metrics["map_points"] = int(pts.shape[0])
            (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
        return metrics

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError("LiveSlam is closed")
