"""The monocular visual-inertial SLAM system (Sec. 3.1, 5.1): the per-frame loop.

Per camera frame (DROID-SLAM's split: the shared map state in :mod:`runtime.backend.state`, the parts in
``frontend/``, ``backend/`` and ``reloc/``):

1. IMU samples since the previous frame: gyro rotation for the KLT prediction, preintegration since the last
   keyframe (GTSAM ``PreintegratedCombinedMeasurements``).
2. KLT tracking (forward-backward check, RANSAC) of the current tracks into the image.
3. Before initialisation: the static initialiser watches the IMU (and the feature motion) for a still second.
4. After: the IMU-predicted pose is refined against the tracked landmarks (motion-only, numpy Gauss-Newton);
   with too few landmarks the system coasts on the IMU and says so.
5. Keyframe decision (parallax, tracked ratio, time). A keyframe enters the backend window with its IMU factor,
   new corners are detected, tracks seen by enough keyframes are triangulated into landmarks (each gets an ORB
   descriptor), old map points are re-found among the new tracks (:mod:`runtime.reloc`), LM runs, outliers are
   removed and the oldest keyframe is marginalised.
6. After a long loss of visual tracking (a white wall), the first keyframes with texture are matched against
   the map and the coast is re-estimated (:class:`runtime.reloc.Relocalizer`).

With a dense mapper (:mod:`runtime.dense`), depth codes and the Eq. 13-14 factors join the window through the
backend's provider hook. :mod:`runtime.run` drives a whole sequence and writes the outputs.

This module never imports torch (checked by a test).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from runtime.backend.factors import refine_pose
from runtime.backend.imu import (
    ImuNoiseConfig,
    ImuStream,
    integrate,
    integrate_rotation,
    make_bias,
    preintegration_params,
)
from runtime.backend.state import Keyframe
from runtime.backend.window import BackendConfig, SlidingWindowBackend
from runtime.calibration import IntrinsicsConfig
from runtime.config import dataclass_from_dict
from runtime.frontend.features import FeatureConfig
from runtime.frontend.keyframes import KeyframeConfig, KeyframeSelector, rotation_compensated_parallax
from runtime.frontend.tracking import FeatureTracker, FrameFeatures, TrackerConfig
from runtime.frontend.triangulation import TriangulationConfig, triangulate
from runtime.geometry import inv_T, ns_to_s, s_to_ns, to_pose3
from runtime.init import DynamicInitConfig, InitConfig, imu_rest_stats
from runtime.init.runner import InitRunner, Snapshot, StartState
from runtime.reloc import Relocalizer, RelocConfig
from runtime.reloc.relocalizer import relocalize_pending
from runtime.start import (
    adapt_imu_noise,
    backfill_records,
    repose_diverged,
    repose_older,
    seed_window,
    try_restart,
    withdraw_diverged,
)
from runtime.trajectory import FrameRecord, fill_trajectory

log = logging.getLogger(__name__)

#: a first start not found this long after the first frame is reported as an event with the last attempt's reason,
#: and again every as long: on a user's own data, why it waits shows without DEBUG logs
INIT_WAIT_REPORT_S = 5.0


@dataclass
class SlamConfig:
    """Everything the system needs besides the data (Hydra ``conf/slam/runtime/*.yaml`` maps onto this)."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    init: InitConfig = field(default_factory=InitConfig)
    dynamic_init: DynamicInitConfig = field(default_factory=DynamicInitConfig)
    imu: ImuNoiseConfig = field(default_factory=ImuNoiseConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    reloc: RelocConfig = field(default_factory=RelocConfig)
    intrinsics: IntrinsicsConfig = field(default_factory=IntrinsicsConfig)
    refine_non_keyframes: bool = True  # motion-only refinement of every frame against tracked landmarks
    refine_min_landmarks: int = 8  # fewer: keep the IMU prediction
    refine_prior_rot_sigma: float = 0.01  # rad, IMU-predicted pose as a prior
    refine_prior_trans_sigma: float = 0.02  # m
    refine_iterations: int = 4
    max_track_views: int = 8  # keyframe observations used to triangulate a track
    still_disp_px: float = 0.6  # median track displacement since the last keyframe below this (+ quiet IMU) = still
    still_min_common_tracks: int = 15  # fewer tracks shared with the last keyframe: no image evidence of rest
    still_window_s: float = 0.25  # s of IMU samples for the rest test (several of init.block_s)
    still_gyro_rad_s: float = 0.02  # |mean gyro - bias| bound for rest
    still_accel_m_s2: float = 0.3  # | |mean f| - g | and block-mean spread bound for rest
    lost_min_landmarks: int = 6  # fewer tracked landmarks (once as many were tracked): visual tracking lost
    # a loss with this many tracks in view (two thirds of features.max_features; above it, never): the estimate
    # disagrees with a textured view (a wrong start's scale on the realistic ``handheld`` seed 115: 176 tracks);
    # healthy runs lost tracking with 4-62 in view, or with more just after a start, regained within 0.2 s, before
    # a restart's window can fill (runtime.start.try_restart)
    restart_lost_min_tracks: int = 120  # tracks in view at a loss of tracking that ask for an in-motion restart
    # a start that has not acquired visual tracking after this long in motion (frames ``building``), with
    # restart_lost_min_tracks tracks in view, disagrees with the images as well: re-initialise in motion (MH_05 IMU
    # seeds 352 and 360 on an Intel Xeon: 10-13 s without visual tracking after a start at 0.5x and 0.12x the true
    # path, then 1.4 and 4.6 m; healthy runs build for at most 2.2 s); 0: off
    building_restart_s: float = 4.0  # s in motion without visual tracking before that restart; 0: off
    lost_reproj_factor: float = 4.0  # while lost, triangulation accepts this many times the reprojection error
    lost_min_kf_interval_s: float = 0.25  # while lost, keyframes at most this often (baselines for triangulation)
    redetect_ratio: float = 0.6  # detect at any frame when tracks fall below this fraction of max_features
    imu_gap_reinit_s: float = 0.25  # an IMU gap longer than this re-initialises from the propagated state
    imu_gap_max_s: float = 1.0  # longer: no poses inside the gap, re-initialise from scratch (a new segment)
    trajectory_mode: str = "refined"  # refined | online

    def __post_init__(self) -> None:
        if self.trajectory_mode not in ("refined", "online"):
            raise ValueError(f"trajectory_mode={self.trajectory_mode!r} is not 'refined' or 'online'")

    @classmethod
    def from_dict(cls, d: dict | None) -> SlamConfig:
        """Build from a nested mapping (e.g. Hydra's ``runtime`` group); unknown keys raise naming the key."""
        return dataclass_from_dict(cls, d or {}, "runtime")


class SlamSystem:
    """Sparse VI-SLAM over one camera + IMU.

    Args:
        camera: raw cam0 model (with distortion).
        T_b_c: (4, 4) cam0-to-body.
        imu: the cleaned IMU stream.
        imu_params: noise densities (io ``ImuParams``).
        cfg: settings.
        tracker: optional replacement of the KLT tracker (same interface; tests feed synthetic features).
        dense: optional :class:`runtime.dense.DenseMapper`: registered with the backend as a factor provider and
            given every new keyframe's image; None: the sparse system.
    """

    def __init__(
        self,
        camera,
        T_b_c: np.ndarray,
        imu: ImuStream,
        imu_params,
        cfg: SlamConfig | None = None,
        tracker=None,
        dense=None,
    ) -> None:
        import gtsam

        self.cfg = cfg = cfg or SlamConfig()
        self.camera = camera
        self.T_b_c = np.asarray(T_b_c, dtype=np.float64)
        self.T_c_b = inv_T(self.T_b_c)
        self.K = camera.pinhole().K
        self.imu = imu
        self.imu_params = imu_params
        self.pim_params = preintegration_params(imu_params, cfg.imu)
        self.noise_scales = (cfg.imu.noise_scale, cfg.imu.noise_scale)
        self.backend = SlidingWindowBackend(camera.intrinsics, self.T_b_c, self.pim_params, cfg.backend)
        self.tracker = tracker or FeatureTracker(camera, self.T_b_c, cfg.features, cfg.tracker)
        self.selector = KeyframeSelector(cfg.keyframes.for_system(dense is not None))
        self.initializer = InitRunner(cfg.init, cfg.dynamic_init, imu, self.T_b_c, camera.fx, cfg.imu.gravity)
        self.init_info: dict | None = None  # how and when the system initialised (metrics.json)
        self.restarts: list[dict] = []  # re-initialisations in the same map frame (metrics.json)
        self.t_first: int | None = None  # first frame with IMU
        self.init_wait_reports = 0  # waits for the first start reported so far (INIT_WAIT_REPORT_S)
        self.reloc = Relocalizer(cfg.reloc, camera, self.T_b_c, self.backend, self.tracker)
        self._gtsam = gtsam
        self.timers: dict[str, float] = defaultdict(float)
        self.events: list[tuple[float, str]] = []
        self.relocalisations: list[dict] = []  # per relocalisation: when, how long lost, drift corrected
        self.records: list[FrameRecord] = []
        self.segment = 0  # current trajectory segment (see runtime.trajectory.FrameRecord)
        self.t_visual: int | None = None  # ns, the last frame with visual tracking (runtime.start.withdraw_diverged)
        self.diverged_pending: list[Snapshot] = []  # frames of a diverged estimate, for the next start to pose
        self.n_frames = 0
        self.n_map_matches = 0
        self.kf_reasons: dict[str, int] = defaultdict(int)
        self.next_kf_id = 0
        self.dense = dense
        self.feature_log: list[FrameFeatures] | None = None  # set to a list: every tracked frame's features
        if dense is not None:
            dense.timers = self.timers
            self.backend.add_provider(dense)
        self._reset_state()

    @property
    def dead_reckoning(self) -> bool:
        """Keyframe poses come from the IMU alone: visual tracking lost, or not yet acquired while the map holds its
        first landmarks (looser triangulation and sparser keyframes then, as while lost)."""
        return self.lost or self.building

    @property
    def map(self):
        """The shared map state (:class:`runtime.backend.state.MapState`)."""
        return self.backend.map

    # ------------------------------------------------------------------ state
    def _reset_state(self) -> None:
        self.initialized = False
        self.prev_ts: int | None = None  # last processed frame
        self.img_ts: int | None = None  # last frame whose image was tracked
        self.pim = None
        self.T_cur: np.ndarray | None = None
        self.v_cur: np.ndarray | None = None
        self.track_obs: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}  # track -> kf -> (xn, uv_u)
        self.last_kf_feats: FrameFeatures | None = None
        self.still_since_kf = True
        self.lost = False
        self.acquired = False  # visual tracking held (lost_min_landmarks tracked) since the (re)initialisation
        self.building = False  # not acquired yet, the map has its first landmarks
        self.building_since: int | None = None  # ns, the first frame recorded ``building`` since the (re)initialisation
        self.lost_since: int | None = None  # ns, start of the current loss of visual tracking
        self.coast_warned = False
        self.reloc_pending: dict | None = None  # set when tracking resumed after a long loss
        self.restart_until: int | None = None  # ns: try an in-motion re-initialisation until then
        # why the restart tried disagrees with the images (after a loss with tracks in view, or after building
        # without visual tracking; runtime.start.try_restart); None: a restart after a start turning in place
        self.restart_why: str | None = None
        self.older_pending: tuple[int, list] | None = None  # frames before the start's first keyframe (repose_older)
        self.initializer.reset()

    def event(self, ts: int, msg: str, level: int = logging.WARNING) -> None:
        """Log a notable event with its timestamp (also kept for ``metrics.json``)."""
        self.events.append((round(ns_to_s(ts), 4), msg))
        log.log(level, "t=%.3f s: %s", ns_to_s(ts), msg)

    def _tic(self) -> float:
        return time.perf_counter()

    def _toc(self, name: str, t0: float) -> float:
        t = time.perf_counter()
        self.timers[name] += t - t0
        return t

    def _new_pim(self, bias: np.ndarray):
        return self._gtsam.PreintegratedCombinedMeasurements(self.pim_params, make_bias(bias))

    # ------------------------------------------------------------------ per frame
    def process(self, frame_idx: int, ts: int, image: np.ndarray | None) -> FrameRecord | None:
        """Process one camera frame (``image`` None: unreadable, the system coasts on the IMU).

        Returns:
            The frame's record once initialised, else None.
        """
        self.n_frames += 1
        t0 = self._tic()
        if self.t_first is None and ts >= self._imu_from():
            self.t_first = ts
        seg = self._imu_since_last_frame(frame_idx, ts)
        if seg is None:
            return None
        gyro, acc, dt, gap, prev = seg
        since = self._since_imu(ts)  # > 0 inside a gap, before the IMU resumes
        if self.initialized and max(gap, since) > self.cfg.imu_gap_max_s:
            return self._gap_reset(ts, max(gap, since))
        if self.initialized and since > self.cfg.imu_gap_reinit_s:
            integrate(self.pim, gyro, acc, dt)  # inside an IMU gap: the propagation is stale, no pose
            return None
        bias = self.backend.latest.bias if self.initialized else np.zeros(6)
        t0 = self._toc("imu", t0)
        feats, image = self._track(frame_idx, ts, image, (gyro, acc, dt), prev, bias)
        t0 = self._toc("track", t0)
        if not self.initialized:
            rec = self._try_initialize(frame_idx, ts, image, feats)
            self._toc("init", t0)
            return rec
        if gap > self.cfg.imu_gap_reinit_s:
            self.event(
                ts,
                f"IMU gap of {gap:.3f} s: inertial link cut, re-initialising velocity and pose from the "
                "propagated and visual estimates with loose priors",
            )
        integrate(self.pim, gyro, acc, dt)
        kf = self.backend.latest
        nav = self.pim.predict(self._gtsam.NavState(to_pose3(kf.T_w_b), kf.v_w), make_bias(kf.bias))
        T_pred = np.asarray(nav.pose().matrix(), dtype=np.float64)
        v_pred = np.asarray(nav.velocity(), dtype=np.float64)
        t0 = self._toc("imu", t0)
        if image is None or feats is None:
            self.T_cur, self.v_cur = T_pred, v_pred
            self.event(ts, f"frame {frame_idx}: no usable image, pose from the IMU", logging.INFO)
            return self._record(frame_idx, ts, False, "no_image")
        T_cur, feats, n_lm = self._refine(T_pred, feats)
        self.T_cur, self.v_cur = T_cur, v_pred
        self._update_lost(ts, n_lm)
        if self.acquired and not self.lost:
            self.t_visual = ts
        if try_restart(self, frame_idx, ts, image, feats):
            self._toc("init", t0)
            last = self.records[-1] if self.records else None
            return last if last is not None and last.ts == ts else self._record(frame_idx, ts, False, "reinit")
        t0 = self._toc("refine", t0)
        is_kf, why, still = self._decide_keyframe(ts, feats, T_cur, kf, n_lm, gap)
        t0 = self._toc("keyframe", t0)
        if not is_kf:
            if feats.ids.size < self.cfg.redetect_ratio * self.cfg.features.max_features:
                self.tracker.replenish(ts, image)
                self._toc("detect", t0)
            status = "coasting" if self.lost else ("still" if still else self._visual_status())
            return self._record(frame_idx, ts, False, status)
        return self._keyframe(frame_idx, ts, image, T_cur, v_pred, why, imu_gap=gap > self.cfg.imu_gap_reinit_s)

    def _imu_from(self) -> int:
        """The first frame time [ns] with IMU: one sample period before the first sample, whose value is held back
        over it (as ``ImuStream.segment`` holds every sample over the next period). A camera-IMU time offset
        moves the first image a few ms before the first sample."""
        return self.imu.t_start - int(round(1e9 / self.imu.rate_hz))

    def _since_imu(self, ts: int) -> float:
        """Seconds since the last IMU sample at or before ``ts``; 0 within the period before the first one."""
        return 0.0 if self._imu_from() <= ts < self.imu.t_start else self.imu.since_last(ts)

    def _imu_since_last_frame(self, frame_idx: int, ts: int):
        """``(gyro, accel, dt, gap [s], previous frame ts)`` of the IMU since the last frame, or None when the
        frame is skipped (before the first IMU sample's period, or not after the previous frame)."""
        if ts < self._imu_from():
            if self.prev_ts is None:
                self.event(ts, "frame before the first IMU sample, skipped", logging.INFO)
            return None
        prev = self.prev_ts if self.prev_ts is not None else ts
        if ts <= prev and self.prev_ts is not None:
            self.event(ts, f"frame {frame_idx} timestamp not after the previous one, skipped")
            return None
        gyro, acc, dt = self.imu.segment(prev, ts)
        gap = self.imu.gap_in(prev, ts) if self.prev_ts is not None else 0.0
        self.prev_ts = ts
        return gyro, acc, dt, gap, prev

    def _track(self, frame_idx: int, ts: int, image, seg, prev: int, bias: np.ndarray):
        """KLT tracking with the gyro-predicted rotation since the last tracked image; ``(features, image)``
        (both None when the image is missing or rejected)."""
        if image is None:
            return None, None
        rot_from = self.img_ts if self.img_ts is not None else ts
        gyro, _, dt = seg if rot_from == prev else self.imu.segment(rot_from, ts)
        R_b0_b1 = integrate_rotation(gyro, dt, bias[3:])
        try:
            feats = self.tracker.track(ts, image, R_b0_b1)
        except ValueError as e:
            self.event(ts, f"frame {frame_idx}: image rejected ({e})")
            return None, None
        self.img_ts = ts
        if self.feature_log is not None:
            self.feature_log.append(feats)
        return feats, image

    def _refine(self, T_pred: np.ndarray, feats: FrameFeatures):
        """Motion-only refinement against the tracked landmarks; outlier tracks are dropped. Returns the pose,
        the features left and the number of landmarks among them."""
        c = self.cfg
        X, has = self.map.landmark_positions(feats.ids)
        n_lm = int(has.sum())
        if not (c.refine_non_keyframes and n_lm >= c.refine_min_landmarks):
            return T_pred, feats, n_lm
        T_cur, inl, _ = refine_pose(
            T_pred,
            X[has],
            feats.uv_u[has],
            self.K,
            self.T_b_c,
            T_prior=T_pred,
            prior_sigmas=np.array([c.refine_prior_rot_sigma] * 3 + [c.refine_prior_trans_sigma] * 3),
            pixel_sigma=c.backend.pixel_sigma,
            huber_k=c.backend.huber_k,
            iterations=c.refine_iterations,
        )
        bad = feats.ids[has][~inl]
        if bad.size:
            self.tracker.drop(bad)
            feats = _subset(feats, ~np.isin(feats.ids, bad))
            n_lm -= int(bad.size)
        return T_cur, feats, n_lm

    def _update_lost(self, ts: int, n_lm: int) -> None:
        """Visual tracking acquired, lost (too few landmarks tracked) or regained; a long loss asks for relocalisation.
        Lost only once acquired: after a static start the map's first landmarks come as the parallax grows."""
        c = self.cfg
        if not self.acquired:
            if n_lm >= c.lost_min_landmarks:
                self.acquired = True
                after = ns_to_s(ts) - self.init_info["t_s"] if self.init_info else 0.0
                msg = f"visual tracking acquired ({n_lm} landmarks) {after:.2f} s after initialisation"
                self.event(ts, msg, logging.INFO)
            self.building = not self.acquired and (self.building or self.map.n_landmarks > 0)
            self._restart_if_building(ts)
            return
        if n_lm < c.lost_min_landmarks and not self.lost:
            self.lost, self.lost_since, self.coast_warned = True, ts, False
            self.event(ts, f"visual tracking lost ({n_lm} landmarks tracked): coasting on the IMU")
            n_tracks = self.tracker.n_tracks
            if n_tracks >= c.restart_lost_min_tracks and self.restart_until is None:
                self._arm_restart(
                    ts, "after a loss with tracks in view", f"{n_tracks} tracks in view but {n_lm} landmarks"
                )
        elif self.lost and n_lm < c.lost_min_landmarks and not self.coast_warned and ts - self.lost_since >= s_to_ns(3):
            self.coast_warned = True  # once per loss
            self.event(ts, "no visual constraints for 3 s: the pose is IMU dead reckoning, its error grows quickly")
        elif self.lost and n_lm >= c.lost_min_landmarks:
            self.lost = False
            if self.restart_why:  # the images agree with the estimate again
                self.restart_until, self.restart_why = None, None
            dur = ns_to_s(ts - self.lost_since)
            self.event(ts, f"visual tracking regained ({n_lm} landmarks) after {dur:.2f} s", logging.INFO)
            if c.reloc.enabled and dur >= c.reloc.min_lost_s:
                self.reloc_pending = {"since": self.lost_since, "regained": ts, "attempts": 0}

    def _restart_if_building(self, ts: int) -> None:
        """Arm an in-motion restart (as after a loss with tracks in view) when the frames have been ``building``
        (moving, visual tracking not acquired since the start) for ``building_restart_s`` with
        ``restart_lost_min_tracks`` tracks in view; visual tracking acquired first cancels it."""
        c = self.cfg
        if self.acquired and self.building_since is not None:
            self.building_since = None
            if self.restart_why:  # the images agree with the estimate after all
                self.restart_until, self.restart_why = None, None
            return
        if self.building_since is None or c.building_restart_s <= 0 or self.restart_until is not None:
            return
        dur = ns_to_s(ts - self.building_since)
        n_tracks = self.tracker.n_tracks
        if dur >= c.building_restart_s and n_tracks >= c.restart_lost_min_tracks:
            self._arm_restart(
                ts,
                "after building without visual tracking",
                f"no visual tracking after {dur:.1f} s in motion since the start, with {n_tracks} tracks in view",
            )

    def _arm_restart(self, ts: int, why: str, seen: str) -> None:
        """Try an in-motion restart for ``refine_within_s`` from ``ts`` (:func:`runtime.start.try_restart`) because
        the estimate disagrees with the images (``why``, for ``restarts`` in metrics.json; ``seen``, for the event)."""
        self.restart_until = ts + s_to_ns(self.cfg.dynamic_init.refine_within_s)
        self.restart_why = why
        self.initializer.reset()
        self.event(ts, f"{seen}: the estimate disagrees with the images; re-initialising in motion")

    def _visual_status(self) -> str:
        """A moving frame's status while not lost: ``tracking`` once visual tracking is acquired, before that
        ``building`` (after a start, the map has fewer than ``lost_min_landmarks`` landmarks in view: the pose rests
        on the IMU alone, as when coasting; after a start turning in place on MH_05, 1.5-4.3 s)."""
        return "tracking" if self.acquired else "building"

    def _decide_keyframe(self, ts: int, feats: FrameFeatures, T_cur: np.ndarray, kf: Keyframe, n_lm: int, gap: float):
        """Stillness and the keyframe decision: ``(is_kf, reason, still)``."""
        c = self.cfg
        lk = self.last_kf_feats
        common, i_kf, i_cur = np.intersect1d(lk.ids, feats.ids, assume_unique=True, return_indices=True)
        disp = (
            float(np.median(np.linalg.norm(feats.uv[i_cur] - lk.uv[i_kf], axis=1)))
            if common.size >= c.still_min_common_tracks
            else None
        )
        still = self._still(ts, disp, kf)
        self.still_since_kf = self.still_since_kf and still
        R_ccur_ckf = self.T_c_b[:3, :3] @ T_cur[:3, :3].T @ kf.T_w_b[:3, :3] @ self.T_b_c[:3, :3]
        par = rotation_compensated_parallax(lk.xn[i_kf], feats.xn[i_cur], R_ccur_ckf, self.camera.fx)
        parallax = float(np.median(par)) if par.size else 0.0
        if self.dead_reckoning and ns_to_s(ts - kf.ts) < c.lost_min_kf_interval_s:
            is_kf, why = False, ""
        else:
            is_kf, why = self.selector.decide(
                ns_to_s(ts - kf.ts),
                lk.ids.size,
                common.size,
                parallax,
                n_lm,
                still=self.still_since_kf,
                n_tracks=feats.ids.size,
            )
        if gap > c.imu_gap_reinit_s:
            is_kf, why = True, "imu_gap"
        return is_kf, why, still

    def _still(self, ts: int, disp_px: float | None, kf: Keyframe) -> bool:
        """At rest: the tracks have not moved since the last keyframe (median ``disp_px``; None without enough
        common tracks: without image evidence constant-velocity motion would look still) and the IMU's
        low-frequency content is quiet (the rule of :mod:`runtime.init.static`, robust to vibration)."""
        c = self.cfg
        if disp_px is None or disp_px > c.still_disp_px:
            return False
        its, g, a = self.imu.window(ts - s_to_ns(c.still_window_s), ts)
        try:
            st = imu_rest_stats(its, g, a, c.init.block_s, c.imu.gravity)
        except ValueError:  # too few samples
            return False
        g_dev = float(np.linalg.norm(g.mean(0) - kf.bias[3:]))
        return g_dev < c.still_gyro_rad_s and st.accel_std < c.still_accel_m_s2 and st.gravity_err < c.still_accel_m_s2

    def _try_initialize(self, frame_idx: int, ts: int, image, feats) -> FrameRecord | None:
        c = self.cfg
        if image is None or feats is None:
            return None
        if self._since_imu(ts) > c.imu_gap_reinit_s:  # inside an IMU gap: start afresh after it
            self.initializer.reset()
            return None
        if self.tracker.n_tracks < c.redetect_ratio * c.features.max_features:
            feats = self.tracker.replenish(ts, image)
        keep_image = image if self.dense is not None else None
        self.initializer.add(Snapshot(frame_idx, ts, feats, keep_image), keep_since=self.t_first)
        st = self.initializer.step(ts)
        if st is None:
            self._report_wait(ts)
            return None
        return self._start(st, frame_idx, ts, feats)

    def _report_wait(self, ts: int) -> None:
        """Report a first start still not found every ``INIT_WAIT_REPORT_S`` after the first frame, with the last
        attempt's reason (a restart after a reset has its own events)."""
        if self.init_info is not None or self.t_first is None:
            return
        waited = ns_to_s(ts - self.t_first)
        due = int(waited // INIT_WAIT_REPORT_S)  # reports due by now
        if due <= self.init_wait_reports:
            return
        self.init_wait_reports = due
        why = self.initializer.last_reason or "no attempt yet: too few frames or tracks"
        self.event(ts, f"not initialised {waited:.1f} s after the first frame (the last attempt: {why})")

    def _start(self, st: StartState, frame_idx: int, ts: int, feats) -> FrameRecord:
        """Hand the initial states to the window and give the frames before initialisation their poses."""
        t0 = st.frames[0][0].ts if st.frames else st.keyframes[0][0].ts
        scales = adapt_imu_noise(self, t0, ts)
        if scales is not None:
            self.noise_scales = scales
        repose_diverged(self, st)
        kf_ids = seed_window(self, st)
        self.initialized = True
        self.lost = False
        self.last_kf_feats = feats
        backfill_records(self, st, kf_ids)
        t_after = ns_to_s(ts - self.t_first) if self.t_first is not None else 0.0
        self.init_info = {
            "method": st.method,
            "t_s": round(ns_to_s(ts), 4),
            "after_s": round(t_after, 3),
            "imu_noise_scales": [round(x, 2) for x in self.noise_scales],
            **st.info,
        }
        self.restart_until = ts + s_to_ns(self.cfg.dynamic_init.refine_within_s) if st.method == "hover" else None
        self.event(ts, f"initialised ({st.method}) {t_after:.2f} s after the first frame: {st.info}", logging.INFO)
        return self.records[-1]

    def _kf_id(self) -> int:
        k = self.next_kf_id
        self.next_kf_id += 1
        return k

    def _register_kf_observations(self, kf_id: int, feats: FrameFeatures) -> None:
        """Keyframe observations: existing landmarks go to the backend, other tracks are remembered."""
        is_lm = np.array([self.map.is_landmark(j) for j in feats.ids], dtype=bool)
        if is_lm.any():
            self.backend.add_observations(kf_id, feats.ids[is_lm], feats.uv_u[is_lm])
        for j, xn, uv in zip(feats.ids[~is_lm], feats.xn[~is_lm], feats.uv_u[~is_lm], strict=False):
            self.track_obs.setdefault(int(j), {})[kf_id] = (xn, uv)
        alive = set(int(j) for j in feats.ids[~is_lm])
        for j in [j for j in self.track_obs if j not in alive]:
            del self.track_obs[j]

    def _triangulate(self, image: np.ndarray | None = None) -> int:
        """Triangulate tracks seen by >= 2 keyframes still in the window; returns landmarks added."""
        m = self.map
        cand = [j for j, o in self.track_obs.items() if sum(m.has_keyframe(k) for k in o) >= 2]
        if not cand:
            return 0
        V = self.cfg.max_track_views
        M = len(cand)
        T = np.tile(np.eye(4), (M, V, 1, 1))
        xn = np.zeros((M, V, 2))
        mask = np.zeros((M, V), bool)
        for i, j in enumerate(cand):
            ks = [k for k in sorted(self.track_obs[j]) if m.has_keyframe(k)][-V:]
            for v, k in enumerate(ks):
                T[i, v] = m.keyframe(k).T_w_b @ self.T_b_c
                xn[i, v] = self.track_obs[j][k][0]
                mask[i, v] = True
        tcfg = base = self.cfg.triangulation
        if self.dead_reckoning:  # keyframe poses are off: accept rougher points, the window refines them
            f = self.cfg.lost_reproj_factor
            tcfg = dataclasses.replace(
                tcfg,
                pixel_sigma=tcfg.pixel_sigma * f,
                max_reproj_px=tcfg.max_reproj_px * f,
                min_views=max(tcfg.min_views, 3),
            )
        X_w, ok, diag = triangulate(T, xn, mask, focal=self.camera.fx, cfg=tcfg)
        # tracks with enough parallax that still do not fit are bad tracks: stop following them
        bad = (
            (~ok) & (diag["parallax_deg"] > 2 * base.min_parallax_deg) & (diag["max_err_px"] > 2 * base.reproj_bound_px)
        )
        if bad.any():
            bad_ids = np.array(cand, dtype=np.int64)[bad]
            self.tracker.drop(bad_ids)
            for j in bad_ids:
                self.track_obs.pop(int(j), None)
        new_ids = [cand[i] for i in np.nonzero(ok)[0]]
        obs = [{k: v[1] for k, v in self.track_obs[j].items()} for j in new_ids]
        new_arr = np.array(new_ids, dtype=np.int64)
        self.backend.add_landmarks(new_arr, X_w[ok], obs)
        for j in new_ids:
            del self.track_obs[j]
        if image is not None and self.cfg.reloc.enabled and new_arr.size:
            self.reloc.describe(image, new_arr)
        return len(new_ids)

    def _keyframe(self, frame_idx, ts, image, T_cur, v_cur, why: str, imu_gap: bool = False) -> FrameRecord:
        t0 = self._tic()
        prev = self.backend.latest
        still = self.still_since_kf and not imu_gap
        kf = Keyframe(self._kf_id(), ts, frame_idx, T_cur.copy(), v_cur.copy(), prev.bias.copy(), still)
        self.kf_reasons[why] += 1
        self.backend.add_keyframe(kf, None if imu_gap else self.pim)
        feats = self.tracker.replenish(ts, image)
        t0 = self._toc("detect", t0)
        self._register_kf_observations(kf.kf_id, feats)
        self._triangulate(image)
        t0 = self._toc("triangulate", t0)
        self._map_reuse(kf, image)
        t0 = self._toc("reloc", t0)
        if self.dense is not None:
            self.dense.on_keyframe(self.backend, kf.kf_id, frame_idx, image, self.tracker.current(ts).uv_u)
            t0 = self._tic()  # in the "dense_keyframe" and "dense_network" timers
        stats = self.backend.optimize()
        drop, n_out = self.backend.remove_outliers()
        if n_out > 0.05 * max(stats.get("n_factors", 1), 1):
            self.backend.optimize()
        if drop.size:
            self.tracker.drop(drop)
        repose_older(self)
        t0 = self._toc("optimize", t0)
        self.backend.marginalize()
        t0 = self._toc("marginalize", t0)
        reason = self.backend.diverged()
        if reason is not None:
            withdrawn = withdraw_diverged(self)
            self.event(ts, f"estimate diverged ({reason}): resetting, {withdrawn}; waiting to re-initialise")
            self._hard_reset()
            return self._record(frame_idx, ts, False, "lost", record=False)
        latest = self.backend.latest
        self.pim = self._new_pim(latest.bias)
        self.T_cur, self.v_cur = latest.T_w_b.copy(), latest.v_w.copy()
        self.last_kf_feats = self.tracker.current(ts)
        self.still_since_kf = True
        rec = self._record(
            frame_idx, ts, True, "coasting" if self.lost else ("tracking" if still else self._visual_status())
        )
        if rec is not None:
            rec.T_created = T_cur.copy()
        return rec

    def _map_reuse(self, kf: Keyframe, image: np.ndarray) -> None:
        """Relocalise after a long loss (when one is pending), else re-find map points near their projections."""
        c = self.cfg.reloc
        if self.reloc_pending is not None and not self.dead_reckoning:
            relocalize_pending(self, kf, image)
        elif c.enabled and c.guided and not self.dead_reckoning:
            t_ids = self.reloc.guided_match(kf, image)
            for j in t_ids:
                self.track_obs.pop(int(j), None)
            self.n_map_matches += int(t_ids.size)

    def _gap_reset(self, ts: int, gap: float) -> None:
        """An IMU gap too long to bridge: no poses until the system has re-initialised from the data after it,
        in a new trajectory segment (its own frame)."""
        self.event(ts, f"IMU gap of {gap:.2f} s: no poses inside it; re-initialising from the data after it "
                   f"(trajectory segment {self.segment + 1}, in a new frame)")  # fmt: skip
        self.segment += 1
        self.diverged_pending = []  # not across the gap
        self._hard_reset()

    def _hard_reset(self) -> None:
        self.backend.clear_window()
        self.tracker.reset()
        self._reset_state()

    def _record(self, frame_idx: int, ts: int, is_kf: bool, status: str, record: bool = True) -> FrameRecord | None:
        if not record or not self.initialized:
            return None
        ref = self.backend.latest
        rec = FrameRecord(ts, frame_idx, ref.kf_id, inv_T(ref.T_w_b) @ self.T_cur, self.T_cur.copy(), is_kf, status)
        rec.segment = self.segment
        self.records.append(rec)
        if status == "building" and self.building_since is None:
            self.building_since = ts
        return rec

    # ------------------------------------------------------------------ results
    def trajectory(self, mode: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Poses of every frame after initialisation: ts (N,) ns, T_w_b (N, 4, 4) (see
        :func:`runtime.trajectory.fill_trajectory`; ``mode``: ``refined`` or ``online``, default the config's)."""
        return fill_trajectory(self.records, self.map.history, mode or self.cfg.trajectory_mode)

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Final keyframe poses: ts (K,) ns, T_w_b (K, 4, 4) in time order (a keyframe made for frames before an
        in-motion start has a later id than the start's keyframe and an earlier time; ``keyframes.txt`` is a TUM
        file, whose stamps increase)."""
        hist = self.map.history
        ids = sorted(hist, key=lambda k: (hist[k][0], k))
        ts = np.array([hist[k][0] for k in ids], dtype=np.int64)
        T = np.array([hist[k][1] for k in ids]).reshape(-1, 4, 4)
        return ts, T

    def timing_summary(self) -> dict:
        """Mean milliseconds per processed frame for each stage."""
        n = max(self.n_frames, 1)
        return {k: 1e3 * v / n for k, v in sorted(self.timers.items())}


def _subset(f: FrameFeatures, keep: np.ndarray) -> FrameFeatures:
    return FrameFeatures(f.ts, f.ids[keep], f.uv[keep], f.xn[keep], f.uv_u[keep], f.flow_px, f.n_lost, f.n_ransac_out)
