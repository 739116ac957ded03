"""Sliding-window visual-inertial factor graph on GTSAM, solved by Levenberg-Marquardt (Sec. 5.1, Eq. 9-12).

Variables (keys as DESIGN.md): ``X(i)`` Pose3 ``T_w_b``, ``V(i)`` velocity in w, ``B(i)`` IMU bias of active
keyframe ``i``; ``L(j)`` Point3 landmark in w for track ``j``; extra per-keyframe variables (the depth codes
``C(k)`` of the dense system) come from :class:`FactorProvider` plug-ins.

Factors rebuilt at each optimisation:

* the marginal prior on the oldest active keyframe (``LinearContainerFactor`` from eliminating the states that
  left the window; the first keyframe has the initialisation priors instead);
* ``CombinedImuFactor`` between consecutive active keyframes (Eq. 11-12, bias random walk included);
* zero-motion factors between keyframes taken at rest (a still camera gives a still trajectory);
* ``GenericProjectionFactorCal3_S2`` with ``body_P_sensor = T_b_c`` and a Huber kernel for every observation
  of a landmark by an active keyframe, and (``anchor_old_observations``) by the last keyframes that left the
  window, whose poses are then held by tight priors (as ORB-SLAM3's local BA fixes the keyframes around its
  window): old views keep constraining the map without fill-in from marginalising landmarks;
* whatever each registered :class:`FactorProvider` adds (depth priors and residuals of Eq. 13-14);
* while a re-estimated coast is kept (:mod:`runtime.backend.coast`), its archived keyframes and links from the
  anchor in place of the marginal prior.

Marginalisation eliminates ``X, V, B`` of the oldest keyframe from its prior, a visual fix of its pose (its own
observations with the landmarks held, :func:`runtime.backend.priors.visual_prior`), its IMU link and zero-motion
factors, giving a Gaussian prior on the next keyframe's state; its reprojection factors stay in the window
through the anchored pose. The keyframe, its links and its marginal prior go to the coast archive.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from runtime.backend.coast import Coast, CoastArchive, CoastConfig, inertial_chain, smooth_chain
from runtime.backend.factors import huber_noise, make_projection_factors
from runtime.backend.priors import carried_prior, eliminate, gap_link, gravity_aligned_priors, visual_prior, zero_motion
from runtime.backend.state import Keyframe, Landmark, MapState, insert_state, keys
from runtime.geometry import NS_PER_S, from_pose3, inv_T, to_pose3

log = logging.getLogger(__name__)


@dataclass
class BackendConfig:
    """Sliding-window backend settings."""

    window_size: int = 30  # active keyframes (X, V, B); 10 left the metric scale 2-5 % off (reports/ablations.md)
    anchor_old_observations: bool = True  # keep observations of keyframes that left, poses held fixed
    max_anchor_keyframes: int = 30
    anchor_sigma: float = 3e-3  # rad and m: how firmly anchored poses are held (1e-4 froze the metric scale)
    pixel_sigma: float = 1.0  # px, reprojection noise
    huber_k: float = 1.5  # Huber threshold in sigmas
    lm_max_iterations: int = 8
    lm_relative_tol: float = 1e-3
    marginal_visual_fix: bool = True  # marginalise with a visual fix of the leaving keyframe's pose
    visual_fix_sigma: float = 0.01  # m, how firmly its landmarks are held for that fix
    visual_fix_min_landmarks: int = 6  # fewer observed landmarks: no visual fix (the plain prior)
    # initial priors (first keyframe): yaw and position are the gauge, roll/pitch from gravity
    prior_yaw_sigma: float = 1e-3  # rad
    prior_roll_pitch_sigma: float = 0.02  # rad
    prior_pos_sigma: float = 1e-3  # m
    prior_vel_sigma: float = 0.02  # m/s
    prior_acc_bias_sigma: float = 0.1  # m/s^2
    prior_gyro_bias_sigma: float = 2e-3  # rad/s
    # loose priors around the oldest keyframe after a relocalisation moved it (roll/pitch and gyro bias keep
    # the initial priors' confidence)
    loose_yaw_sigma: float = 0.1  # rad
    loose_pos_sigma: float = 0.5  # m
    loose_vel_sigma: float = 0.2  # m/s
    loose_acc_bias_sigma: float = 0.02  # m/s^2
    still_rot_sigma: float = 2e-3  # rad, zero-motion between keyframes at rest
    still_pos_sigma: float = 2e-3  # m
    still_vel_sigma: float = 0.01  # m/s
    outlier_px: float = 3.0  # observations above this after optimisation are removed
    min_depth: float = 0.1  # m, observations closer (or behind) are removed
    max_speed: float = 15.0  # m/s, above this the estimate is declared diverged
    max_acc_bias: float = 2.0  # m/s^2, a larger accelerometer bias: diverged
    max_gyro_bias: float = 0.5  # rad/s, a larger gyroscope bias: diverged
    gap_vel_sigma: float = 0.3  # m/s, velocity prior of a keyframe after an IMU gap
    gap_rot_sigma: float = 0.1  # rad, pose prior of a keyframe after an IMU gap (around the propagated pose)
    gap_pos_sigma: float = 0.3  # m
    coast: CoastConfig = field(default_factory=CoastConfig)


class FactorProvider(Protocol):
    """Plug-in point for extra variables and factors (the dense system's depth codes ``C(k)`` and Eq. 13-14).

    The backend calls, in order, at each optimisation: ``add_factors`` (insert new variables into ``values``
    and factors into ``graph``; the window's states and landmarks are already there), then ``on_optimized``
    with the LM result. Before a keyframe's ``X, V, B`` are marginalised, ``on_marginalize`` is called (drop or
    summarise variables tied to it). Providers read the window through the backend's read interface
    (:attr:`SlidingWindowBackend.map`, :class:`runtime.backend.state.MapState`).
    """

    def add_factors(self, backend: SlidingWindowBackend, graph, values) -> None: ...

    def on_optimized(self, backend: SlidingWindowBackend, result) -> None: ...

    def on_marginalize(self, backend: SlidingWindowBackend, kf_id: int) -> None: ...


class SlidingWindowBackend:
    """Keyframe window over GTSAM (LM); see the module docstring for the factors.

    Args:
        K: (fx, fy, cx, cy) of the undistorted (pinhole) camera the observations are expressed in.
        T_b_c: (4, 4) camera-to-body.
        preint_params: ``gtsam.PreintegrationCombinedParams``.
        cfg: settings.
    """

    def __init__(self, K, T_b_c: np.ndarray, preint_params, cfg: BackendConfig | None = None) -> None:
        import gtsam

        self.cfg = cfg or BackendConfig()
        if self.cfg.window_size < 2:
            raise ValueError(f"backend.window_size={self.cfg.window_size}: must be >= 2")
        self.K_tuple = tuple(float(k) for k in K)
        fx, fy, cx, cy = self.K_tuple
        self.cal = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
        self.T_b_c = np.asarray(T_b_c, dtype=np.float64)
        self.T_c_b = inv_T(self.T_b_c)
        self.body_P_sensor = to_pose3(self.T_b_c)
        self.preint_params = preint_params
        self.proj_noise = huber_noise([self.cfg.pixel_sigma] * 2, self.cfg.huber_k, scalar=False)
        self.providers: list[FactorProvider] = []
        self.archive = CoastArchive(self.cfg.coast)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget everything, including the archived keyframe poses and map points."""
        self.map = MapState()
        self.n_optimizations = 0
        self.clear_window()

    def clear_window(self) -> None:
        """Forget the window (states, landmarks, factors); final poses and map points stay."""
        self.map.clear_window()
        self.imu_factors: dict[int, list] = {}  # inertial link (or gap priors), keyed by the later keyframe
        self.still_between: dict[int, object] = {}  # keyed by the later keyframe
        self.vel_priors: dict[int, object] = {}  # keyed by the keyframe
        self.prior_factors: list = []  # on the oldest active keyframe
        self.last_stats: dict = {}
        self.archive.clear()
        self.init_kf_id: int | None = None  # the keyframe that started this window (set by initialize)

    @property
    def initialized(self) -> bool:
        return bool(self.map.active)

    @property
    def latest(self) -> Keyframe:
        return self.map.latest

    # the read interface of factor providers (the map's, :class:`runtime.backend.state.MapState`)
    def window_ids(self) -> list[int]:
        return self.map.window_ids()

    def has_keyframe(self, kf_id: int) -> bool:
        return self.map.has_keyframe(kf_id)

    def keyframe(self, kf_id: int) -> Keyframe:
        return self.map.keyframe(kf_id)

    def observations(self, kf_id: int, min_views: int = 1):
        return self.map.observations(kf_id, min_views)

    def covisible_keyframes(self, kf_id: int, n: int) -> list[int]:
        return self.map.covisible_keyframes(kf_id, n)

    def add_provider(self, provider: FactorProvider) -> None:
        """Register a :class:`FactorProvider` (e.g. the depth-code factors of the dense system)."""
        self.providers.append(provider)

    # ------------------------------------------------------------------ building
    def initialize(self, kf: Keyframe, sigmas: dict | None = None) -> None:
        """Start a new window with ``kf`` and priors on its state (gauge: position and yaw).

        ``sigmas`` overrides the config's ``prior_*_sigma`` (keys without the ``prior_`` prefix and ``_sigma``
        suffix: ``roll_pitch``, ``vel``, ``gyro_bias``, ...), e.g. the looser priors of an in-motion start.
        Final keyframe poses and map points of earlier windows are kept.
        """
        self.clear_window()
        self.init_kf_id = kf.kf_id
        c = {
            k: getattr(self.cfg, f"prior_{k}_sigma")
            for k in ("roll_pitch", "yaw", "pos", "vel", "acc_bias", "gyro_bias")
        }
        unknown = set(sigmas or {}) - set(c)
        if unknown:
            raise ValueError(f"unknown prior sigma(s) {sorted(unknown)}; known: {sorted(c)}")
        c.update(sigmas or {})
        self.map.insert_keyframe(kf)
        self.prior_factors = gravity_aligned_priors(
            kf,
            c["roll_pitch"],
            c["yaw"],
            c["pos"],
            c["vel"],
            [c["acc_bias"]] * 3 + [c["gyro_bias"]] * 3,
        )

    def add_keyframe(self, kf: Keyframe, pim) -> None:
        """Append a keyframe linked to the newest one by the preintegrated IMU ``pim`` (zero motion if still).

        ``pim=None`` (the IMU had a gap): no inertial link; the bias continues through a between factor and the
        pose and velocity get loose priors around ``kf``'s values (the landmarks then fix the pose).
        """
        import gtsam

        X, V, B, _, _ = keys()
        if not self.map.active:
            raise RuntimeError("add_keyframe before initialize")
        prev = self.map.active[-1]
        if kf.kf_id in self.map.keyframes or kf.kf_id <= prev:
            raise ValueError(f"keyframe id {kf.kf_id} is not new (latest is {prev})")
        self.map.insert_keyframe(kf)
        i, j = prev, kf.kf_id
        c = self.cfg
        if pim is None:
            self.imu_factors[j] = gap_link(i, kf, c)
        else:
            self.imu_factors[j] = [gtsam.CombinedImuFactor(X(i), V(i), X(j), V(j), B(i), B(j), pim)]
        if kf.still:
            self.still_between[j], self.vel_priors[j] = zero_motion(i, j, c)

    def add_observations(self, kf_id: int, lm_ids: np.ndarray, uv: np.ndarray) -> None:
        """Observations (undistorted pixels (N, 2)) of existing landmarks by keyframe ``kf_id``."""
        m = self.map
        if kf_id not in m.keyframes:
            raise KeyError(f"keyframe {kf_id} is not in the window")
        X, _, _, L, _ = keys()
        ids = [int(j) for j in lm_ids if int(j) in m.landmarks]
        if not ids:
            return
        sel = np.isin(lm_ids, ids)
        uvs = np.asarray(uv, dtype=np.float64)[sel]
        lids = np.asarray(lm_ids)[sel]
        facs = make_projection_factors(
            np.array([L(int(j)) for j in lids]),
            np.full(lids.size, X(kf_id)),
            uvs,
            self.cal,
            self.body_P_sensor,
            self.proj_noise,
        )
        obs = m.kf_obs[kf_id]
        for j, u, f in zip(lids, uvs, facs, strict=False):
            lm = m.landmarks[int(j)]
            lm.obs[kf_id] = u
            lm.factors[kf_id] = f
            obs.add(int(j))

    def add_landmarks(self, lm_ids: np.ndarray, X_w: np.ndarray, obs: list[dict]) -> None:
        """New landmarks at positions (N, 3) with their observations ``{kf_id: uv (2,)}``."""
        m = self.map
        for j, P, o in zip(lm_ids, np.asarray(X_w, dtype=np.float64), obs, strict=False):
            j = int(j)
            if j in m.landmarks:
                raise ValueError(f"landmark {j} exists already")
            m.landmarks[j] = Landmark(j, P.copy())
            for kf_id, u in o.items():
                if kf_id in m.keyframes:
                    self.add_observations(kf_id, np.array([j]), np.asarray(u, dtype=np.float64).reshape(1, 2))

    def reactivate_landmarks(
        self, ids: np.ndarray, X_map: np.ndarray, kf_id: int, uv: np.ndarray, sigma: float
    ) -> None:
        """Bring map points back into the window, observed by keyframe ``kf_id`` (undistorted pixels (N, 2)),
        each held near its map position by a prior of ``sigma`` metres (the map is older and better known)."""
        import gtsam

        _, _, _, L, _ = keys()
        m = self.map
        noise = gtsam.noiseModel.Isotropic.Sigma(3, float(sigma))
        for j, P in zip(ids, np.asarray(X_map, dtype=np.float64), strict=False):
            j = int(j)
            if j in m.landmarks:
                continue
            m.map_points.pop(j, None)
            m.landmarks[j] = Landmark(j, P.copy(), map_prior=gtsam.PriorFactorPoint3(L(j), P, noise))
        self.add_observations(kf_id, np.asarray(ids), np.asarray(uv, dtype=np.float64))

    # ------------------------------------------------------------------ optimisation
    def _build(self):
        import gtsam

        X, _, _, L, _ = keys()
        m = self.map
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for k in m.active:
            kf = m.keyframes[k]
            insert_state(values, k, kf.T_w_b, kf.v_w, kf.bias)
        chain = self.archive.window_chain(m.active)
        if chain is None:
            for f in self.prior_factors:
                graph.add(f)
        else:  # the coast from its anchor instead of the marginal prior that summarises it
            for f in self.archive.coast.anchor_priors:
                graph.add(f)
            for kf in chain:
                insert_state(values, kf.kf_id, kf.T_w_b, kf.v_w, kf.bias)
            for k in [kf.kf_id for kf in chain[1:]] + [m.active[0]]:
                for f in self.archive.links[k]:
                    graph.add(f)
        in_chain = {kf.kf_id for kf in chain or ()}
        links = gtsam.NonlinearFactorGraph()  # inter-keyframe factors (IMU, zero motion)
        for k in m.active[1:]:
            for f in self.imu_factors[k]:
                links.add(f)
            if k in self.still_between:
                links.add(self.still_between[k])
        for k in m.active:
            if k in self.vel_priors:
                graph.add(self.vel_priors[k])
        used_anchors, proj_lm = self._add_landmarks_to(graph, values)
        anchor_noise = gtsam.noiseModel.Isotropic.Sigma(6, self.cfg.anchor_sigma)
        for k in used_anchors - in_chain:  # coasted keyframes are variables of the smoother instead
            kf = m.keyframes[k]
            values.insert(X(k), to_pose3(kf.T_w_b))
            graph.add(gtsam.PriorFactorPose3(X(k), to_pose3(kf.T_w_b), anchor_noise))
        return graph, links, values, proj_lm, chain

    def _add_landmarks_to(self, graph, values) -> tuple[set, set]:
        """Landmarks seen by an active keyframe and their projection factors; returns the anchor keyframes
        they use and the landmark ids."""
        _, _, _, L, _ = keys()
        active = set(self.map.active)
        used_anchors, lm_ids = set(), set()
        for j, lm in self.map.landmarks.items():
            if len(lm.obs) < lm.min_views or not any(k in active for k in lm.obs):
                continue
            values.insert(L(j), lm.X_w)
            if lm.map_prior is not None:
                graph.add(lm.map_prior)
            for k, f in lm.factors.items():
                graph.add(f)
                lm_ids.add(j)
                if k not in active:
                    used_anchors.add(k)
        return used_anchors, lm_ids

    def optimize(self) -> dict:
        """Run LM on the window; write the result back into keyframes and landmarks.

        Returns:
            stats: ``{"iterations", "error_before", "error_after", "n_factors", "n_landmarks", "t_build",
            "t_solve", "ok"}``.
        """
        import gtsam

        t0 = time.perf_counter()
        base, links, values, proj_lm, chain = self._build()
        for p in self.providers:
            p.add_factors(self, base, values)
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(base)
        graph.push_back(links)
        t1 = time.perf_counter()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.lm_max_iterations)
        params.setRelativeErrorTol(self.cfg.lm_relative_tol)
        params.setAbsoluteErrorTol(1e-6)
        stats = {"n_factors": int(graph.size()), "n_landmarks": len(proj_lm)}
        try:
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
            err0 = opt.error()  # LM evaluates the graph at the start and keeps the error of its current estimate
            result = opt.optimize()
            err1 = opt.error()
            stats.update(iterations=int(opt.iterations()), error_before=float(err0), error_after=float(err1), ok=True)
        except RuntimeError as e:  # IndeterminantLinearSystem and the like: keep the previous estimate
            log.warning("backend: LM failed (%s); keeping the previous estimate", str(e).splitlines()[0][:200])
            stats.update(iterations=0, error_before=float("nan"), error_after=float("nan"), ok=False)
            self.last_stats = stats
            return stats
        t2 = time.perf_counter()
        self._take_states([self.map.keyframes[k] for k in self.map.active], result)
        _, _, _, L, _ = keys()
        for j in proj_lm:
            self.map.landmarks[j].X_w = np.asarray(result.atPoint3(L(j)), dtype=np.float64).copy()
        if chain is not None:
            self._take_states(chain, result)
            self._carried_prior(chain + [self.map.keyframes[self.map.active[0]]], self.archive.coast.anchor_priors)
            stats["coast_keyframes"] = len(chain)
        for p in self.providers:
            p.on_optimized(self, result)
        self.n_optimizations += 1
        stats.update(t_build=t1 - t0, t_solve=t2 - t1)
        self.last_stats = stats
        return stats

    def diverged(self) -> str | None:
        """A reason string when the window's estimate is not plausible, else None."""
        c = self.cfg
        for k in self.map.active:
            kf = self.map.keyframes[k]
            if not (np.isfinite(kf.T_w_b).all() and np.isfinite(kf.v_w).all() and np.isfinite(kf.bias).all()):
                return f"non-finite state at keyframe {k}"
            if np.linalg.norm(kf.v_w) > c.max_speed:
                return f"speed {np.linalg.norm(kf.v_w):.1f} m/s at keyframe {k}"
            if np.linalg.norm(kf.bias[:3]) > c.max_acc_bias or np.linalg.norm(kf.bias[3:]) > c.max_gyro_bias:
                return f"implausible IMU bias {np.round(kf.bias, 3).tolist()} at keyframe {k}"
        return None

    # ------------------------------------------------------------------ outliers
    def reprojection_errors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All observations of the window: (kf ids (M,), landmark ids (M,), errors (M,) px, depths (M,) m)."""
        return self.map.reprojection_errors(self.K_tuple, self.T_c_b)

    def remove_outliers(self) -> tuple[np.ndarray, int]:
        """Drop observations with large reprojection error or bad depth; landmarks left with too few views go.

        Returns:
            ids of landmarks whose newest observation was rejected or that were removed (the frontend should
            stop tracking them), and the number of observations removed.
        """
        m = self.map
        kfs, lms, err, z = self.reprojection_errors()
        bad = (err > self.cfg.outlier_px) | (z < self.cfg.min_depth) | ~np.isfinite(err)
        if not bad.any():
            return np.zeros(0, np.int64), 0
        newest = m.active[-1]
        drop_tracks = set()
        for k, j in zip(kfs[bad], lms[bad], strict=False):
            k, j = int(k), int(j)
            if j not in m.landmarks:
                continue
            m.remove_observation(k, j)
            if k == newest:
                drop_tracks.add(j)
        for j in set(lms[bad].tolist()):
            lm = m.landmarks.get(j)
            if lm is not None and len(lm.obs) < lm.min_views:
                m.delete_landmark(j)
                drop_tracks.add(j)
        return np.array(sorted(drop_tracks), dtype=np.int64), int(bad.sum())

    # ------------------------------------------------------------------ marginalisation
    def marginalize(self) -> list[int]:
        """Marginalise the oldest active keyframes until the window has ``window_size``; returns their ids."""
        X, V, B, _, _ = keys()
        m, c = self.map, self.cfg
        dropped = []
        while len(m.active) > c.window_size:
            o, n = m.active[0], m.active[1]
            for p in self.providers:
                p.on_marginalize(self, o)
            fix = (
                visual_prior(m, self.prior_factors, o, c.visual_fix_sigma, c.visual_fix_min_landmarks)
                if c.marginal_visual_fix
                else None
            )
            own_prior = fix if fix is not None else list(self.prior_factors)
            link = list(self.imu_factors.pop(n))
            if n in self.still_between:
                link.append(self.still_between.pop(n))
            self.archive.add_link(n, link)
            factors = own_prior + link
            if o in self.vel_priors:
                vp = self.vel_priors.pop(o)
                factors.append(vp)
                self.archive.add_link(o, [vp])
            ko, kn = m.keyframes[o], m.keyframes[n]
            self.prior_factors = eliminate(factors, [ko, kn], [X(o), V(o), B(o)], kn)
            m.active.pop(0)
            dropped.append(o)
            self.archive.end_coast_with(o)
            self.archive.keep(ko, own_prior)
            if c.anchor_old_observations:
                m.anchors.append(o)
            else:
                m.forget_keyframe(o)
        while len(m.anchors) > c.max_anchor_keyframes:
            m.forget_keyframe(m.anchors.pop(0))
        if dropped:
            m.freeze_landmarks()
            self.archive.prune(m.latest.ts - int(c.coast.archive_s * NS_PER_S))
        return dropped

    # ------------------------------------------------------------------ relocalisation
    def apply_correction(self, correction, t_from: int) -> None:
        """Move keyframes (and their landmarks) by world-frame corrections ``correction(ts) -> (4, 4)``.

        Used when relocalisation finds that the window drifted from the map and no inertial chain can be
        smoothed: every keyframe at or after ``t_from`` (ns) in memory and in ``history`` gets
        ``T_w_b <- C(ts) T_w_b`` (velocities rotate with it), landmarks follow the correction of their newest
        observing keyframe (re-activated map points stay). The marginal prior on the oldest keyframe (linearised
        at the old state) is replaced by loose priors around the corrected state.
        """
        m = self.map
        corr = {}
        for k, (ts, T) in list(m.history.items()):
            if ts >= t_from:
                C = correction(ts)
                corr[k] = C
                m.history[k] = (ts, C @ T)
        for kf in list(m.keyframes.values()) + list(self.archive.states.values()):
            C = corr.get(kf.kf_id)
            if C is not None:
                kf.T_w_b = C @ kf.T_w_b
                kf.v_w = C[:3, :3] @ kf.v_w
        m.move_landmarks(corr)
        self._loose_oldest_prior()

    def _link(self, k: int) -> list:
        """The factors between keyframe ``k`` and its predecessor (and ``k``'s zero-velocity prior)."""
        if k in self.archive.links:
            return self.archive.links[k]
        out = list(self.imu_factors.get(k, ()))
        for d in (self.still_between, self.vel_priors):
            if k in d:
                out.append(d[k])
        return out

    def bridge(self, t_from: int, kf_id: int, T_fix: np.ndarray, init=None) -> dict[int, np.ndarray] | None:
        """Re-estimate a coasted stretch between two visual fixes (:mod:`runtime.backend.coast`).

        Smooths the keyframe states from the last keyframe at or before ``t_from`` (the anchor, the last one
        tracked visually before the loss) to ``kf_id`` (the relocalised keyframe, PnP pose ``T_fix``) over their
        recorded IMU links. The window, the archive and ``history`` take the smoothed states; landmarks follow
        their newest observing keyframe; the marginal prior on the oldest active keyframe, when it moved,
        becomes the anchor prior carried over the archived links; and the coast stays in the window's
        optimisations until ``kf_id`` leaves the window.

        Args:
            init: optional ``correction(ts) -> (4, 4)`` applied to the current estimates to start LM from.

        Returns:
            ``kf_id -> (4, 4)`` world-frame corrections ``T_new T_old^-1`` of the moved keyframes, or None when
            there is no inertial chain to smooth (the caller then spreads the correction instead).
        """
        m = self.map
        states = {**self.archive.states, **{k: m.keyframes[k] for k in m.active}}
        chain = inertial_chain(states, t_from, kf_id, self._link)
        if chain is None or len(chain) < 2:
            return None
        anchor = chain[0]
        anchor_priors = self.archive.anchor_priors(anchor)
        result = smooth_chain(chain, anchor_priors, self._link, kf_id, T_fix, self.cfg.coast, init)
        if result is None:
            return None
        corr = self._take_states(chain, result)
        m.move_landmarks(corr)
        o = m.active[0]
        if o in corr and o != anchor.kf_id:
            self._carried_prior(chain, anchor_priors)
        if anchor.kf_id < m.active[0]:
            self.archive.coast = Coast(anchor.kf_id, anchor_priors, kf_id)
        return corr

    def _take_states(self, kfs: list[Keyframe], result) -> dict[int, np.ndarray]:
        """Write the ``X, V, B`` of keyframes ``kfs`` from an LM result into the window, the archive and
        ``history``; returns the world-frame corrections ``T_new T_old^-1`` by keyframe id."""
        X, V, B, _, _ = keys()
        m = self.map
        corr = {}
        for kf in kfs:
            k = kf.kf_id
            T = from_pose3(result.atPose3(X(k)))
            corr[k] = T @ inv_T(kf.T_w_b)
            v = np.asarray(result.atVector(V(k)), dtype=np.float64).copy()
            b = result.atConstantBias(B(k))
            bias = np.concatenate([b.accelerometer(), b.gyroscope()])
            for target in (m.keyframes.get(k), self.archive.states.get(k)):
                if target is not None:
                    target.T_w_b, target.v_w, target.bias = T.copy(), v.copy(), bias.copy()
            if k in m.history:
                m.history[k] = (kf.ts, T.copy())
        return corr

    def _carried_prior(self, chain: list[Keyframe], anchor_priors: list) -> None:
        """The oldest active keyframe's marginal prior carried from the anchor over the archived links
        (:func:`runtime.backend.priors.carried_prior`); loose priors when that is indeterminate."""
        o = self.map.keyframes[self.map.active[0]]
        try:
            self.prior_factors = carried_prior(chain, anchor_priors, self.archive.links, o)
        except RuntimeError as e:
            log.info("backend: carried prior unavailable (%s); loose priors", str(e).splitlines()[0][:120])
            self._loose_oldest_prior()

    def _loose_oldest_prior(self) -> None:
        """Priors around the oldest active keyframe's current state: roll/pitch and gyro bias keep their
        confidence, position, yaw, velocity and accelerometer bias are loose (after a relocalisation moved it)."""
        c = self.cfg
        self.prior_factors = gravity_aligned_priors(
            self.map.keyframes[self.map.active[0]],
            c.prior_roll_pitch_sigma,
            c.loose_yaw_sigma,
            c.loose_pos_sigma,
            c.loose_vel_sigma,
            [c.loose_acc_bias_sigma] * 3 + [c.prior_gyro_bias_sigma] * 3,
        )
