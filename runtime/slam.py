"""The sparse monocular visual-inertial SLAM system (Sec. 3.1, 5.1): per-frame loop, state and outputs.

Per camera frame (DROID-SLAM's split: shared state here, the parts in ``frontend/`` and ``backend/``):

1. IMU samples since the previous frame: gyro rotation for the KLT prediction, preintegration since the last
   keyframe (GTSAM ``PreintegratedCombinedMeasurements``).
2. KLT tracking (forward-backward check, RANSAC) of the current tracks into the image.
3. Before initialisation: the static initialiser watches the IMU (and the feature motion) for a still second.
4. After: the IMU-predicted pose is refined against the tracked landmarks (motion-only, numpy Gauss-Newton);
   with too few landmarks the system coasts on the IMU and says so.
5. Keyframe decision (parallax, tracked ratio, time). A keyframe enters the backend window with its IMU
factor,
   new corners are detected, tracks seen by enough keyframes are triangulated into landmarks (each gets an ORB
   descriptor), old map points are re-found among the new tracks (guided by their predicted projection), LM
   runs, outliers are removed and the oldest keyframe is marginalised.
6. After a long loss of visual tracking (a white wall), the first keyframes with texture are matched against
   the map (descriptors + RANSAC PnP, :mod:`runtime.frontend.mapdb`): the coasted keyframes are re-estimated
   over their recorded IMU links between the last visual fix before the loss and the PnP pose (the backend's
   coast bridge), and the matched map points re-enter the window.

Outputs (:func:`run_sequence`): ``trajectory.txt`` (TUM, ``T_w_b`` per frame after initialisation; poses of
non-keyframes are stored relative to their keyframe and composed with its final estimate, as DROID-SLAM's
trajectory filler does; ``trajectory_mode=online`` writes the causal estimates instead), ``keyframes.txt``,
``sparse_map.ply``, ``metrics.json``, ``trajectory_top.png`` and, with ``viz=rerun``, ``slam.rrd``. With
``dense`` (:mod:`runtime.dense`): depth codes and the Eq. 13-14 factors join the window through the backend's
provider hook, and ``dense_map.ply`` (also into ``slam.rrd``), ``keyframe_depth/`` and the dense metrics are
written too.

This module never imports torch (checked by a test).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections import defaultdict, deque
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from runtime.backend.factors import refine_pose
from runtime.backend.graph import BackendConfig, Keyframe, SlidingWindowBackend
from runtime.backend.imu import (
    ImuNoiseConfig,
    ImuStream,
    integrate,
    integrate_rotation,
    make_bias,
    preintegration_params,
)
from runtime.frontend.features import FeatureConfig
from runtime.frontend.keyframes import KeyframeConfig, KeyframeSelector, rotation_compensated_parallax
from runtime.frontend.mapdb import MapDescriptors, RelocConfig, candidates_in_view, guided_match, match, pnp
from runtime.frontend.tracking import FeatureTracker, FrameFeatures, TrackerConfig
from runtime.frontend.triangulation import TriangulationConfig, triangulate
from runtime.geometry import Camera, inv_T, so3_exp, so3_log, to_pose3
from runtime.init import InitConfig, StaticInitializer

log = logging.getLogger(__name__)

NS = 1e-9


@dataclass
class SlamConfig:
    """Everything the system needs besides the data (Hydra ``conf/slam.yaml`` maps onto this)."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    init: InitConfig = field(default_factory=InitConfig)
    imu: ImuNoiseConfig = field(default_factory=ImuNoiseConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    reloc: RelocConfig = field(default_factory=RelocConfig)
    refine_non_keyframes: bool = True  # motion-only refinement of every frame against tracked landmarks
    refine_min_landmarks: int = 8  # fewer: keep the IMU prediction
    refine_prior_rot_sigma: float = 0.01  # rad, IMU-predicted pose as a prior
    refine_prior_trans_sigma: float = 0.02  # m
    refine_iterations: int = 4
    max_track_views: int = 8  # keyframe observations used to triangulate a track
    still_disp_px: float = (
        0.6  # median track displacement since the last keyframe below this (+ quiet IMU) = still
    )
    still_gyro_rad_s: float = 0.01  # |gyro - bias| bound for rest
    still_accel_m_s2: float = 0.1  # | |f| - g | and std bound for rest
    lost_min_landmarks: int = 6  # fewer tracked landmarks: visual tracking lost, coasting on the IMU
    lost_reproj_factor: float = (
        4.0  # while lost, triangulation accepts this many times the reprojection error
    )
    lost_min_kf_interval_s: float = (
        0.25  # while lost, keyframes at most this often (baselines for triangulation)
    )
    redetect_ratio: float = 0.6  # detect at any frame when tracks fall below this fraction of max_features
    imu_gap_reinit_s: float = 0.25  # an IMU gap longer than this re-initialises from the propagated state
    trajectory_mode: str = "refined"  # refined | online

    @classmethod
    def from_dict(cls, d: dict | None) -> SlamConfig:
        """Build from a nested mapping (e.g. Hydra's ``runtime`` group); unknown keys raise naming the key."""
        return _dataclass_from_dict(cls, d or {}, "runtime")


def _dataclass_from_dict(cls, d, path: str):
    import dataclasses

    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in dict(d).items():
        if k not in fields:
            raise ValueError(f"unknown setting {path}.{k} (known: {', '.join(fields)})")
        default = getattr(cls(), k)
        if dataclasses.is_dataclass(default):
            if not isinstance(v, dict):
                raise ValueError(f"setting {path}.{k} must be a mapping, got {v!r}")
            kwargs[k] = _dataclass_from_dict(type(default), v, f"{path}.{k}")
        else:
            if isinstance(default, bool):
                if not isinstance(v, bool):
                    raise ValueError(f"setting {path}.{k} must be true/false, got {v!r}")
            elif isinstance(default, (int, float)) and not isinstance(default, bool):
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise ValueError(f"setting {path}.{k} must be a number, got {v!r}")
                if isinstance(default, int) and not float(v).is_integer():
                    raise ValueError(f"setting {path}.{k} must be an integer, got {v!r}")
                v = type(default)(v)
            elif isinstance(default, str) and not isinstance(v, str):
                raise ValueError(f"setting {path}.{k} must be a string, got {v!r}")
            kwargs[k] = v
    return cls(**kwargs)


@dataclass
class FrameRecord:
    """What the system decided for one frame after initialisation."""

    ts: int
    frame_idx: int
    ref_kf: int  # keyframe the pose is stored relative to
    T_rel: np.ndarray  # (4, 4) T_kf_b: pose relative to the reference keyframe at the time
    T_online: np.ndarray  # (4, 4) causal estimate T_w_b
    is_kf: bool
    status: str  # tracking | coasting | no_image | still
    T_created: np.ndarray | None = None  # keyframes: the pose they entered the window with (before LM)


class SlamSystem:
    """Sparse VI-SLAM over one camera + IMU.

    Args:
        camera: raw cam0 model (with distortion).
        T_b_c: (4, 4) cam0-to-body.
        imu: the cleaned IMU stream.
        imu_params: noise densities (io ``ImuParams``).
        cfg: settings.
        tracker: optional replacement of the KLT tracker (same interface; tests feed synthetic features).
        dense: optional :class:`runtime.dense.DenseMapper` (``dense=true``): registered with the backend as a
            factor provider and given every new keyframe's image; None: the sparse system, unchanged.
    """

    def __init__(
        self,
        camera: Camera,
        T_b_c: np.ndarray,
        imu: ImuStream,
        imu_params,
        cfg: SlamConfig | None = None,
        tracker=None,
        dense=None,
    ) -> None:
        import gtsam

        self.cfg = cfg = cfg or SlamConfig()
        if cfg.trajectory_mode not in ("refined", "online"):
            raise ValueError(f"trajectory_mode={cfg.trajectory_mode!r} is not 'refined' or 'online'")
        self.camera = camera
        self.T_b_c = np.asarray(T_b_c, dtype=np.float64)
        self.T_c_b = inv_T(self.T_b_c)
        self.K = camera.pinhole().K
        self.imu = imu
        self.pim_params = preintegration_params(imu_params, cfg.imu)
        self.backend = SlidingWindowBackend(camera.intrinsics, self.T_b_c, self.pim_params, cfg.backend)
        self.tracker = tracker or FeatureTracker(camera, self.T_b_c, cfg.features, cfg.tracker)
        self.selector = KeyframeSelector(cfg.keyframes)
        self.initializer = StaticInitializer(cfg.init, cfg.imu.gravity)
        self.mapdb = MapDescriptors()
        self._gtsam = gtsam
        self.timers: dict[str, float] = defaultdict(float)
        self.events: list[tuple[float, str]] = []
        self.relocalisations: list[dict] = []  # per relocalisation: when, how long lost, drift corrected
        self.records: list[FrameRecord] = []
        self.n_frames = 0
        self.n_map_matches = 0
        self.kf_reasons: dict[str, int] = defaultdict(int)
        self.dense = dense
        if dense is not None:
            dense.timers = self.timers
            self.backend.add_provider(dense)
        self._reset_state()

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
        self.flow_hist: deque = deque()
        self.still_since_kf = True
        self.lost = False
        self.lost_since: int | None = None  # ns, start of the current loss of visual tracking
        self.reloc_pending: dict | None = None  # set when tracking resumed after a long loss
        self.next_kf_id = getattr(self, "next_kf_id", 0)
        self.initializer.reset()

    def event(self, ts: int, msg: str, level: int = logging.WARNING) -> None:
        """Log a notable event with its timestamp (also kept for ``metrics.json``)."""
        self.events.append((round(ts * NS, 4), msg))
        log.log(level, "t=%.3f s: %s", ts * NS, msg)

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
        if ts < self.imu.t_start:
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
        bias = self.backend.latest.bias if self.initialized else np.zeros(6)
        t0 = self._toc("imu", t0)

        # ---- tracking
        feats = None
        if image is not None:
            rot_from = self.img_ts if self.img_ts is not None else ts
            g2, _, d2 = (gyro, acc, dt) if rot_from == prev else self.imu.segment(rot_from, ts)
            R_b0_b1 = integrate_rotation(g2, d2, bias[3:])
            try:
                feats = self.tracker.track(ts, image, R_b0_b1)
            except ValueError as e:
                self.event(ts, f"frame {frame_idx}: image rejected ({e})")
                image = None
            else:
                self.img_ts = ts
                if not self.initialized:  # snapshots of the tracks for the stillness test of the initialiser
                    self.flow_hist.append((ts, feats.ids, feats.uv))
                    while self.flow_hist and self.flow_hist[0][0] < ts - int(
                        1.5e9 * self.cfg.init.still_duration_s
                    ):
                        self.flow_hist.popleft()
        t0 = self._toc("track", t0)

        if not self.initialized:
            rec = self._try_initialize(frame_idx, ts, image, feats)
            self._toc("init", t0)
            return rec

        # ---- IMU propagation
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

        # ---- motion-only refinement against tracked landmarks
        T_cur = T_pred
        X, has = self.backend.landmark_positions(feats.ids)
        n_lm = int(has.sum())
        if self.cfg.refine_non_keyframes and n_lm >= self.cfg.refine_min_landmarks:
            c = self.cfg
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
                keep = ~np.isin(feats.ids, bad)
                feats = _subset(feats, keep)
                n_lm -= int(bad.size)
        self.T_cur, self.v_cur = T_cur, v_pred
        if n_lm < self.cfg.lost_min_landmarks and not self.lost and self.backend.landmarks:
            self.lost = True
            self.lost_since = ts
            self.event(ts, f"visual tracking lost ({n_lm} landmarks tracked): coasting on the IMU")
        elif self.lost and n_lm >= self.cfg.lost_min_landmarks:
            self.lost = False
            dur = (ts - self.lost_since) * NS
            self.event(ts, f"visual tracking regained ({n_lm} landmarks) after {dur:.2f} s", logging.INFO)
            if self.cfg.reloc.enabled and dur >= self.cfg.reloc.min_lost_s:
                self.reloc_pending = {"since": self.lost_since, "regained": ts, "attempts": 0}
        t0 = self._toc("refine", t0)

        # ---- stillness and keyframe decision
        lk = self.last_kf_feats
        common, i_kf, i_cur = np.intersect1d(lk.ids, feats.ids, assume_unique=True, return_indices=True)
        disp = (
            float(np.median(np.linalg.norm(feats.uv[i_cur] - lk.uv[i_kf], axis=1)))
            if common.size >= 15
            else None
        )
        still = self._still(ts, disp, kf)
        self.still_since_kf = self.still_since_kf and still
        R_ccur_ckf = self.T_c_b[:3, :3] @ T_cur[:3, :3].T @ kf.T_w_b[:3, :3] @ self.T_b_c[:3, :3]
        par = rotation_compensated_parallax(lk.xn[i_kf], feats.xn[i_cur], R_ccur_ckf, self.camera.fx)
        parallax = float(np.median(par)) if par.size else 0.0
        if self.lost and (ts - kf.ts) * NS < self.cfg.lost_min_kf_interval_s:
            is_kf, why = False, ""
        else:
            is_kf, why = self.selector.decide(
                (ts - kf.ts) * NS,
                lk.ids.size,
                common.size,
                parallax,
                n_lm,
                still=self.still_since_kf,
                n_tracks=feats.ids.size,
            )
        if gap > self.cfg.imu_gap_reinit_s:
            is_kf, why = True, "imu_gap"
        t0 = self._toc("keyframe", t0)
        if not is_kf:
            if feats.ids.size < self.cfg.redetect_ratio * self.cfg.features.max_features:
                self.tracker.replenish(ts, image)
                self._toc("detect", t0)
            return self._record(
                frame_idx, ts, False, "coasting" if self.lost else ("still" if still else "tracking")
            )
        return self._keyframe(
            frame_idx, ts, image, T_cur, v_pred, why, imu_gap=gap > self.cfg.imu_gap_reinit_s
        )

    def _still(self, ts: int, disp_px: float | None, kf: Keyframe) -> bool:
        """At rest: the tracks have not moved since the last keyframe (median ``disp_px``, needs >= 15 common
        tracks: without image evidence constant-velocity motion would look still) and the IMU is quiet."""
        c = self.cfg
        if disp_px is None or disp_px > c.still_disp_px:
            return False
        _, g, a = self.imu.window(ts - int(0.1e9), ts)
        if g.shape[0] < 2:
            return False
        g_dev = np.linalg.norm(g.mean(0) - kf.bias[3:])
        a_std = float(np.max(np.std(a, axis=0)))
        a_err = abs(float(np.linalg.norm(a.mean(0))) - c.imu.gravity)
        return g_dev < c.still_gyro_rad_s and a_std < c.still_accel_m_s2 and a_err < c.still_accel_m_s2

    def _try_initialize(self, frame_idx: int, ts: int, image, feats) -> FrameRecord | None:
        c = self.cfg
        if image is not None and self.tracker.n_tracks < c.redetect_ratio * c.features.max_features:
            feats = self.tracker.replenish(ts, image)
        w0 = ts - int(c.init.still_duration_s * 1e9)
        its, ig, ia = self.imu.window(w0, ts)
        flow = None  # median net displacement of the tracks over the window [px]
        snaps = [s for s in self.flow_hist if s[0] >= w0]
        if snaps and feats is not None:
            _, i0, i1 = np.intersect1d(snaps[0][1], feats.ids, assume_unique=True, return_indices=True)
            if i0.size >= 10:
                flow = float(np.median(np.linalg.norm(snaps[0][2][i0] - feats.uv[i1], axis=1)))
        res = self.initializer.check(ts, its, ig, ia, flow)
        if res is None or feats is None:
            return None
        kf = Keyframe(self._kf_id(), ts, frame_idx, res.T_w_b, res.v_w, res.bias, still=True)
        self.backend.initialize(kf)
        self.initialized = True
        self.lost = False
        self.pim = self._new_pim(kf.bias)
        self.T_cur, self.v_cur = kf.T_w_b.copy(), kf.v_w.copy()
        self._register_kf_observations(kf.kf_id, feats)
        self.last_kf_feats = feats
        self.still_since_kf = True
        self.event(
            ts,
            f"initialised (static): gyro bias {np.round(res.bias[3:], 4).tolist()} rad/s, roll/pitch from "
            f"gravity, gyro std {res.gyro_std:.4f} rad/s, accel std {res.accel_std:.3f} m/s^2",
            logging.INFO,
        )
        self.kf_reasons["init"] += 1
        return self._record(frame_idx, ts, True, "still")

    def _kf_id(self) -> int:
        k = self.next_kf_id
        self.next_kf_id += 1
        return k

    def _register_kf_observations(self, kf_id: int, feats: FrameFeatures) -> None:
        """Keyframe observations: existing landmarks go to the backend, other tracks are remembered."""
        is_lm = np.array([int(j) in self.backend.landmarks for j in feats.ids], dtype=bool)
        if is_lm.any():
            self.backend.add_observations(kf_id, feats.ids[is_lm], feats.uv_u[is_lm])
        for j, xn, uv in zip(feats.ids[~is_lm], feats.xn[~is_lm], feats.uv_u[~is_lm], strict=False):
            self.track_obs.setdefault(int(j), {})[kf_id] = (xn, uv)
        alive = set(int(j) for j in feats.ids[~is_lm])
        for j in [j for j in self.track_obs if j not in alive]:
            del self.track_obs[j]

    def _triangulate(self, image: np.ndarray | None = None) -> int:
        """Triangulate tracks seen by >= 2 keyframes still known to the backend; returns landmarks added."""
        cand = [j for j, o in self.track_obs.items() if sum(k in self.backend.keyframes for k in o) >= 2]
        if not cand:
            return 0
        V = self.cfg.max_track_views
        M = len(cand)
        T = np.tile(np.eye(4), (M, V, 1, 1))
        xn = np.zeros((M, V, 2))
        mask = np.zeros((M, V), bool)
        for m, j in enumerate(cand):
            ks = [k for k in sorted(self.track_obs[j]) if k in self.backend.keyframes][-V:]
            for v, k in enumerate(ks):
                T[m, v] = self.backend.keyframes[k].T_w_b @ self.T_b_c
                xn[m, v] = self.track_obs[j][k][0]
                mask[m, v] = True
        tcfg = self.cfg.triangulation
        if self.lost:  # dead-reckoned keyframe poses are off: accept rougher points, the window refines them
            tcfg = dataclasses.replace(
                tcfg,
                max_reproj_px=tcfg.max_reproj_px * self.cfg.lost_reproj_factor,
                min_views=max(tcfg.min_views, 3),
            )
        X_w, ok, diag = triangulate(T, xn, mask, focal=self.camera.fx, cfg=tcfg)
        # tracks with enough parallax that still do not fit are bad tracks: stop following them
        bad = (
            (~ok)
            & (diag["parallax_deg"] > 2 * self.cfg.triangulation.min_parallax_deg)
            & (diag["max_err_px"] > 2 * self.cfg.triangulation.max_reproj_px)
        )
        if bad.any():
            bad_ids = np.array(cand, dtype=np.int64)[bad]
            self.tracker.drop(bad_ids)
            for j in bad_ids:
                self.track_obs.pop(int(j), None)
        new_ids = [cand[m] for m in np.nonzero(ok)[0]]
        obs = [{k: v[1] for k, v in self.track_obs[j].items()} for j in new_ids]
        new_arr = np.array(new_ids, dtype=np.int64)
        self.backend.add_landmarks(new_arr, X_w[ok], obs)
        for j in new_ids:
            del self.track_obs[j]
        if image is not None and self.cfg.reloc.enabled and new_arr.size:
            cur = self.tracker.current(0)
            _, ia, ib = np.intersect1d(new_arr, cur.ids, assume_unique=True, return_indices=True)
            desc, okd = self.mapdb.describe(image, cur.uv[ib])
            self.mapdb.add(new_arr[ia], desc, okd)
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
        if self.reloc_pending is not None and not self.lost:
            self._relocalize(kf, image)
        elif self.cfg.reloc.enabled and self.cfg.reloc.guided and not self.lost:
            self._guided_map_match(kf, image)
        t0 = self._toc("reloc", t0)
        if self.dense is not None:
            self.dense.on_keyframe(self.backend, kf.kf_id, frame_idx, image, self.tracker.current(ts).uv_u)
            t0 = self._tic()  # the network's time is in the "dense_network" timer
        stats = self.backend.optimize()
        drop, n_out = self.backend.remove_outliers()
        if n_out > 0.05 * max(stats.get("n_factors", 1), 1):
            self.backend.optimize()
        if drop.size:
            self.tracker.drop(drop)
        t0 = self._toc("optimize", t0)
        self.backend.marginalize()
        t0 = self._toc("marginalize", t0)
        reason = self.backend.diverged()
        if reason is not None:
            self.event(
                ts, f"estimate diverged ({reason}): resetting, waiting for a still period to re-initialise"
            )
            self._hard_reset()
            return self._record(frame_idx, ts, False, "lost", record=False)
        latest = self.backend.latest
        self.pim = self._new_pim(latest.bias)
        self.T_cur, self.v_cur = latest.T_w_b.copy(), latest.v_w.copy()
        self.last_kf_feats = self.tracker.current(ts)
        self.still_since_kf = True
        rec = self._record(frame_idx, ts, True, "coasting" if self.lost else "tracking")
        if rec is not None:
            rec.T_created = T_cur.copy()
        return rec

    def _relocalize(self, kf: Keyframe, image: np.ndarray) -> bool:
        """Match the keyframe's features with old map points; on a PnP fix, correct the drift.

        With ``reloc.bridge`` (the default) the keyframes from the last one tracked before the loss to this one
        are re-estimated over their IMU links, held at both ends (:meth:`SlidingWindowBackend.bridge`): the
        velocity error at the loss and the biases that made the drift are estimated instead of assumed. Without
        it, or when the inertial chain is broken (an IMU gap, a loss longer than the backend's archive), a
        4-DoF correction (yaw and translation: roll and pitch are observable from gravity) is spread: keyframes
        since the loss get the fraction ``((t - t_lost) / (t_resumed - t_lost)) ** drift_exponent`` of it (the
        dead-reckoning error starts flat and grows about quadratically: bias and tilt errors integrated
        twice), those after tracking resumed the whole of it. The 4-DoF correction also gives the bridge its
        starting point. The matched map points re-enter the window.
        """
        c = self.cfg.reloc
        pend = self.reloc_pending
        pend["attempts"] += 1
        if pend["attempts"] > c.max_attempts:
            self.event(
                kf.ts,
                f"relocalisation gave up after {c.max_attempts} keyframes: continuing on the drifted estimate",
            )
            self.reloc_pending = None
            return False
        mp = self.backend.map_points
        if len(mp) < c.min_inliers:
            return False
        ids = np.fromiter(mp.keys(), dtype=np.int64, count=len(mp))
        Xm = np.array([mp[int(j)] for j in ids])
        view = candidates_in_view(
            kf.T_w_b @ self.T_b_c,
            Xm,
            self.K,
            self.camera.width,
            self.camera.height,
            c.frustum_margin,
            c.max_depth,
        )
        dm, okm = self.mapdb.get(ids[view])
        ids_c, X_c, dm = ids[view][okm], Xm[view][okm], dm[okm]
        feats = self.tracker.current(kf.ts)
        df, okf = self.mapdb.describe(image, feats.uv)
        f_idx = np.nonzero(okf)[0]
        qi, ti = match(df[f_idx], dm, c.max_hamming, c.ratio)
        if qi.size < c.min_inliers:
            return False
        fi = f_idx[qi]
        T_w_c, inl = pnp(X_c[ti], feats.xn[fi], c.pnp_reproj_px / self.camera.fx)
        n_in = int(inl.sum())
        if T_w_c is None or n_in < c.min_inliers or n_in < c.min_inlier_ratio * qi.size:
            return False
        T_new = T_w_c @ self.T_c_b
        dR = T_new[:3, :3] @ kf.T_w_b[:3, :3].T
        yaw = float(np.arctan2(dR[1, 0], dR[0, 0]))
        shift = float(np.linalg.norm(T_new[:3, 3] - kf.T_w_b[:3, 3]))
        bridged = False
        if shift >= c.min_correction_m:
            t0, t1 = pend["since"], pend["regained"]

            def correction(ts: int) -> np.ndarray:
                a = float(np.clip((ts - t0) / max(t1 - t0, 1), 0.0, 1.0)) ** c.drift_exponent
                ca, sa = np.cos(a * yaw), np.sin(a * yaw)
                C = np.eye(4)
                C[:3, :3] = [[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]]
                # rotate about the keyframe's position so that a partial correction does not swing far points
                C[:3, 3] = (
                    a * (T_new[:3, 3] - kf.T_w_b[:3, 3]) + kf.T_w_b[:3, 3] - C[:3, :3] @ kf.T_w_b[:3, 3]
                )
                return C

            corr = None
            if c.bridge:
                corr = self.backend.bridge(
                    t0 - int(c.bridge_anchor_lead_s * 1e9),
                    kf.kf_id,
                    T_new,
                    np.array([c.bridge_fix_rot_sigma, c.bridge_fix_pos_sigma]),
                    np.array(
                        [
                            c.bridge_anchor_rot_sigma,
                            c.bridge_anchor_pos_sigma,
                            c.bridge_anchor_vel_sigma,
                            c.bridge_anchor_acc_bias_sigma,
                            c.bridge_anchor_gyro_bias_sigma,
                        ]
                    ),
                    init=correction,
                    anchor_marginal=c.bridge_anchor_marginal,
                )
            bridged = corr is not None
            if bridged:
                self.T_cur = corr[kf.kf_id] @ self.T_cur
            else:
                self.backend.apply_correction(correction, t0)
                self.T_cur = correction(kf.ts) @ self.T_cur

        # re-activate the matched map points; their tracks take the map point's id
        m_ids, t_ids = ids_c[ti][inl], feats.ids[fi][inl]
        for j in t_ids:
            if int(j) in self.backend.landmarks:
                self.backend._delete_landmark(int(j))
            self.track_obs.pop(int(j), None)
        self.tracker.rename(t_ids, m_ids)
        self.backend.reactivate_landmarks(
            m_ids, X_c[ti][inl], kf.kf_id, feats.uv_u[fi][inl], c.map_point_sigma
        )
        self.relocalisations.append(
            {
                "t_s": round(kf.ts * NS, 4),
                "lost_s": round((pend["regained"] - pend["since"]) * NS, 3),
                "drift_m": shift,
                "yaw_deg": float(np.degrees(yaw)),
                "inliers": n_in,
                "bridged": bridged,
            }
        )
        self.event(
            kf.ts,
            f"relocalised against {n_in} map points ({qi.size} matches) after "
            f"{(pend['regained'] - pend['since']) * NS:.1f} s "
            f"without visual tracking: drift correction {shift:.3f} m, yaw {np.degrees(yaw):.2f} deg"
            + (" (coast re-estimated over its IMU links)" if bridged else " (spread over the coast)"),
        )
        self.reloc_pending = None
        return True

    def _guided_map_match(self, kf: Keyframe, image: np.ndarray) -> int:
        """Re-find old map points among the keyframe's tracks that are not landmarks yet (small search radius
        around the predicted projections, descriptor check); matched tracks take the map point's id."""
        c = self.cfg.reloc
        mp = self.backend.map_points
        if not mp:
            return 0
        ids = np.fromiter(mp.keys(), dtype=np.int64, count=len(mp))
        Xm = np.array([mp[int(j)] for j in ids])
        T_c_w = inv_T(kf.T_w_b @ self.T_b_c)
        p = Xm @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        z = p[:, 2]
        zs = np.where(z > 1e-6, z, 1.0)
        uv = np.stack(
            [self.K[0, 0] * p[:, 0] / zs + self.K[0, 2], self.K[1, 1] * p[:, 1] / zs + self.K[1, 2]], -1
        )
        view = (
            (z > 0.1)
            & (z < c.max_depth)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < self.camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < self.camera.height)
        )
        if not view.any():
            return 0
        dm, okm = self.mapdb.get(ids[view])
        ids_c, X_c, uv_c, dm = ids[view][okm], Xm[view][okm], uv[view][okm], dm[okm]
        feats = self.tracker.current(kf.ts)
        free = np.array([int(j) not in self.backend.landmarks for j in feats.ids], dtype=bool)
        if not free.any() or ids_c.size == 0:
            return 0
        fidx = np.nonzero(free)[0]
        df, okf = self.mapdb.describe(image, feats.uv[fidx])
        fidx = fidx[okf]
        mi, fi = guided_match(
            uv_c, dm, feats.uv_u[fidx], df[okf], c.guided_radius_px, c.guided_max_hamming, c.ratio
        )
        if mi.size == 0:
            return 0
        t_ids, m_ids = feats.ids[fidx[fi]], ids_c[mi]
        for j in t_ids:
            self.track_obs.pop(int(j), None)
        self.tracker.rename(t_ids, m_ids)
        self.backend.reactivate_landmarks(m_ids, X_c[mi], kf.kf_id, feats.uv_u[fidx[fi]], c.map_point_sigma)
        self.n_map_matches += int(mi.size)
        return int(mi.size)

    def _hard_reset(self) -> None:
        self.backend._clear_window()
        self.tracker.reset()
        self._reset_state()

    def _record(
        self, frame_idx: int, ts: int, is_kf: bool, status: str, record: bool = True
    ) -> FrameRecord | None:
        if not record or not self.initialized:
            return None
        ref = self.backend.latest
        rec = FrameRecord(
            ts, frame_idx, ref.kf_id, inv_T(ref.T_w_b) @ self.T_cur, self.T_cur.copy(), is_kf, status
        )
        self.records.append(rec)
        return rec

    # ------------------------------------------------------------------ results
    def trajectory(self, mode: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Poses of every frame after initialisation: ts (N,) ns, T_w_b (N, 4, 4).

        ``refined``: keyframes take their final estimates; a frame between keyframes ``a`` and ``b`` takes its
        pose relative to each (as estimated online) composed with their final estimates, blended by time
        (position linearly, rotation by slerp), so the trajectory stays continuous across keyframes even where
        the window later moved them (a relocalisation's correction, a coasted stretch). ``online``: the
        estimates as they were when each frame was processed.
        """
        mode = mode or self.cfg.trajectory_mode
        ts = np.array([r.ts for r in self.records], dtype=np.int64)
        if mode == "online":
            return ts, np.array([r.T_online for r in self.records]).reshape(-1, 4, 4)
        hist = self.backend.history
        kf_recs = [r for r in self.records if r.is_kf and r.ref_kf in hist]
        kf_ts = np.array([r.ts for r in kf_recs], dtype=np.int64)
        out = []
        for r in self.records:
            if r.ref_kf not in hist:
                out.append(r.T_online)
                continue
            T_a = hist[r.ref_kf][1] @ r.T_rel
            if r.is_kf:
                out.append(T_a)
                continue
            i = int(np.searchsorted(kf_ts, r.ts, "right"))
            nb = kf_recs[i] if i < len(kf_recs) else None
            if nb is None or nb.T_created is None:
                out.append(T_a)
                continue
            T_b = hist[nb.ref_kf][1] @ inv_T(nb.T_created) @ r.T_online
            t_a = hist[r.ref_kf][0]
            w = float(np.clip((r.ts - t_a) / max(nb.ts - t_a, 1), 0.0, 1.0))
            T = np.eye(4)
            T[:3, 3] = (1 - w) * T_a[:3, 3] + w * T_b[:3, 3]
            T[:3, :3] = T_a[:3, :3] @ so3_exp(w * so3_log(T_a[:3, :3].T @ T_b[:3, :3]))
            out.append(T)
        return ts, np.array(out).reshape(-1, 4, 4)

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Final keyframe poses: ts (K,) ns, T_w_b (K, 4, 4) in keyframe order."""
        ids = sorted(self.backend.history)
        ts = np.array([self.backend.history[k][0] for k in ids], dtype=np.int64)
        T = np.array([self.backend.history[k][1] for k in ids]).reshape(-1, 4, 4)
        return ts, T

    def timing_summary(self) -> dict:
        """Mean milliseconds per processed frame for each stage."""
        n = max(self.n_frames, 1)
        return {k: 1e3 * v / n for k, v in sorted(self.timers.items())}


def _subset(f: FrameFeatures, keep: np.ndarray) -> FrameFeatures:
    return FrameFeatures(
        f.ts, f.ids[keep], f.uv[keep], f.xn[keep], f.uv_u[keep], f.flow_px, f.n_lost, f.n_ransac_out
    )


# ---------------------------------------------------------------------- whole-sequence driver
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
) -> dict:
    """Run the system over an io ``EurocSequence`` and write every output into ``out_dir``.

    ``dense``: a :class:`runtime.dense.DenseConfig` runs the tightly coupled dense system with the network in
    ``model_dir`` (default: the shipped model) and also writes ``dense_map.ply``, ``keyframe_depth/`` and the
    dense metrics (depth metrics of the sparse points, the c = 0 prior and the optimised codes when the
    sequence has ``mav0/depth0``); None: the sparse system.

    Returns:
        The metrics dictionary also written to ``metrics.json``.
    """
    from runtime import eval as ev
    from runtime.io.ply import write_ply
    from runtime.io.tum import write_tum

    cfg = cfg or SlamConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    imu = ImuStream.from_sequence(seq, cfg.imu.gap_factor)
    mapper = None
    if dense is not None:
        from runtime.dense import DenseMapper
        from runtime.network import DepthNetwork, default_model_dir

        net = DepthNetwork(model_dir if model_dir is not None else default_model_dir())
        depth_gt = seq.depth if getattr(seq, "has_depth", False) else None
        mapper = DenseMapper(net, seq.camera, seq.T_b_c, dense, depth_gt=depth_gt)
    system = SlamSystem(seq.camera, seq.T_b_c, imu, seq.imu, cfg, dense=mapper)
    recorder = None
    if viz == "rerun":
        from runtime.viz import RerunRecorder

        recorder = RerunRecorder(out / "slam.rrd", seq.camera, seq.T_b_c)
    elif viz not in (None, "", "none"):
        raise ValueError(f"viz={viz!r} is not 'rerun' or 'none'")
    n = len(seq) if max_frames is None else min(len(seq), int(max_frames))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="frame", desc="dit-slam", dynamic_ncols=True)
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    for i, img, err, t_wait in _prefetched_images(seq, n):
        ts = int(seq.frame_ts[i])
        if err is not None:
            system.event(ts, f"frame {i}: cannot read image ({err})")
        system.timers["read"] += t_wait
        rec = system.process(i, ts, img)
        if recorder is not None and img is not None:
            recorder.log_frame(system, ts, img, rec)
        if bar is not None:
            bar.update(1)
            if i % 20 == 0:
                bar.set_postfix(
                    kf=len(system.backend.history),
                    lm=len(system.backend.landmarks),
                    st=rec.status if rec else "init",
                )
    wall = time.perf_counter() - t_start
    cpu = time.process_time() - cpu_start
    if bar is not None:
        bar.close()

    ts, T = system.trajectory()
    kts, kT = system.keyframe_trajectory()
    write_tum(out / "trajectory.txt", ts, T)
    write_tum(out / "keyframes.txt", kts, kT)
    _, pts = system.backend.all_points()
    pts = pts[np.isfinite(pts).all(1)] if pts.size else np.zeros((0, 3))
    write_ply(out / "sparse_map.ply", pts)
    metrics = {
        "sequence": str(getattr(seq, "root", "")),
        "frames": int(n),
        "frames_with_pose": int(len(ts)),
        "keyframes": int(len(kts)),
        "map_points": int(pts.shape[0]),
        "wall_s": wall,
        "fps": n / wall if wall > 0 else float("nan"),
        "cpu_s": cpu,  # CPU time of the process (all threads): robust to other jobs sharing the machine
        "cpu_ms_per_frame": 1e3 * cpu / max(n, 1),
        "timing_ms_per_frame": system.timing_summary(),
        "keyframe_reasons": dict(system.kf_reasons),
        "map_points_refound": system.n_map_matches,
        "initialised_at_s": (float(ts[0] * NS) if len(ts) else None),
        "events": system.events[:200],
        "n_events": len(system.events),
        "relocalisations": system.relocalisations,
        "config": _jsonable(asdict(cfg)),
    }
    if mapper is not None:
        t0 = time.perf_counter()
        metrics.update(mapper.finish(system.backend, out))
        tm = system.timing_summary()
        metrics["timing_dense_ms_per_frame"] = {
            "network": tm.get("dense_network", 0.0),
            "factor_building": tm.get("dense_factors", 0.0),
            "optimisation": tm.get("optimize", 0.0) - tm.get("dense_factors", 0.0),
            "outputs_s": time.perf_counter() - t0,
        }
    if len(ts) == 0:
        metrics["error"] = "never initialised (no still period found; see events)"
        log.error("never initialised: no trajectory; see the events in metrics.json")
    if seq.gt is not None and len(ts) >= 2:
        try:
            gt_ts, gt_T = seq.gt.ts, seq.gt.T_w_b
            metrics.update(ev.trajectory_metrics(ts, T, gt_ts, gt_T))
            if plot:
                ev.plot_top_view(
                    out / "trajectory_top.png", ts, T, gt_ts, gt_T, title=Path(str(seq.root)).name
                )
        except Exception as e:  # noqa: BLE001 - evaluation must not lose the run's outputs
            metrics["eval_error"] = f"{type(e).__name__}: {e}"
            log.error("evaluation failed: %s", e)
    elif plot and len(ts) >= 2:
        ev.plot_top_view(out / "trajectory_top.png", ts, T, None, None, title=Path(str(seq.root)).name)
    if recorder is not None:
        recorder.log_final(system, ts, T, pts, dense_map=mapper.dense_map if mapper is not None else None)
        recorder.close()
    (out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=2))
    return metrics


def _read_image(seq, i: int):
    try:
        return seq.image(i), None
    except Exception as e:  # noqa: BLE001 - a corrupt or vanished image must not stop the run
        return None, f"{type(e).__name__}: {str(e)[:200]}"


def _prefetched_images(seq, n: int, depth: int = 3):
    """Yield ``(i, image or None, error or None, seconds waited)``; PNG decoding runs ahead in a thread
    (OpenCV releases the GIL, so it overlaps with tracking and optimisation on the second core)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="imread") as ex:
        futs = deque(ex.submit(_read_image, seq, i) for i in range(min(depth, n)))
        for i in range(n):
            t0 = time.perf_counter()
            img, err = futs.popleft().result()
            waited = time.perf_counter() - t0
            if i + depth < n:
                futs.append(ex.submit(_read_image, seq, i + depth))
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
