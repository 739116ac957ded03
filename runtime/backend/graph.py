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
* whatever each registered :class:`FactorProvider` adds (depth priors and residuals of Eq. 13-14).

Marginalisation eliminates ``X, V, B`` of the oldest keyframe from its prior, a visual fix of its pose (its
own
observations with the landmarks held, ``marginal_visual_fix``, see
:meth:`SlidingWindowBackend._visual_prior`), its
IMU link and zero-motion factors, giving a Gaussian prior on the next keyframe's state; its reprojection
factors
stay in the window through the anchored pose.

Marginalised keyframes of the last ``archive_s`` seconds keep their final state, the factors that linked
them (IMU, zero motion) and what the window knew of their state when they left (their marginal prior with
their own visual fix) in an archive: after a long loss of visual tracking, :meth:`SlidingWindowBackend.bridge`
re-estimates the coasted stretch over those links between the last visual fix and a relocalisation, and (with
``smooth_coast``) keeps it in the window's optimisations until the relocalised keyframe leaves the window.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from runtime.backend.factors import huber_noise, make_projection_factors, pose_prior_noise_world
from runtime.backend.imu import make_bias
from runtime.geometry import from_pose3, inv_T, to_pose3

log = logging.getLogger(__name__)


def _sym():
    from gtsam.symbol_shorthand import B, C, L, V, X

    return X, V, B, L, C


def _insert_state(values, k: int, T_w_b: np.ndarray, v_w: np.ndarray, bias: np.ndarray) -> None:
    """Insert keyframe ``k``'s ``X, V, B`` (pose (4, 4), velocity (3,), bias (6,)) into ``values``."""
    X, V, B, _, _ = _sym()
    values.insert(X(k), to_pose3(T_w_b))
    values.insert(V(k), np.asarray(v_w, dtype=np.float64))
    values.insert(B(k), make_bias(bias))


def _state_priors(k: int, T_w_b, v_w, bias, pose_noise, vel_sigma: float, bias_sigmas) -> list:
    """Prior factors on keyframe ``k``'s pose (noise model ``pose_noise``), velocity (isotropic ``vel_sigma``)
    and bias (diagonal ``bias_sigmas``: 3 accelerometer then 3 gyroscope)."""
    import gtsam

    X, V, B, _, _ = _sym()
    return [
        gtsam.PriorFactorPose3(X(k), to_pose3(T_w_b), pose_noise),
        gtsam.PriorFactorVector(V(k), v_w, gtsam.noiseModel.Isotropic.Sigma(3, float(vel_sigma))),
        gtsam.PriorFactorConstantBias(
            B(k), make_bias(bias), gtsam.noiseModel.Diagonal.Sigmas(np.asarray(bias_sigmas, np.float64))
        ),
    ]


def _linear_prior(remaining, lin_pt) -> list:
    """The factors left by a partial elimination, as nonlinear factors linearised at ``lin_pt``."""
    import gtsam

    return [
        gtsam.LinearContainerFactor(remaining.at(i), lin_pt)
        for i in range(remaining.size())
        if remaining.at(i) is not None
    ]


@dataclass
class BackendConfig:
    """Sliding-window backend settings."""

    window_size: int = 10  # active keyframes (full X, V, B states)
    anchor_old_observations: bool = True  # keep observations of keyframes that left, poses held fixed
    max_anchor_keyframes: int = 15
    anchor_sigma: float = 1e-4  # rad and m: how firmly anchored poses are held
    pixel_sigma: float = 1.0  # px, reprojection noise
    huber_k: float = 1.5  # Huber threshold in sigmas
    lm_max_iterations: int = 8
    lm_relative_tol: float = 1e-3
    marginal_visual_fix: bool = True  # marginalise with a visual fix of the leaving keyframe's pose
    visual_fix_sigma: float = 0.01  # m, how firmly its landmarks are held for that fix
    # initial priors (first keyframe): yaw and position are the gauge, roll/pitch from gravity
    prior_yaw_sigma: float = 1e-3  # rad
    prior_roll_pitch_sigma: float = 0.02  # rad
    prior_pos_sigma: float = 1e-3  # m
    prior_vel_sigma: float = 0.02  # m/s
    prior_acc_bias_sigma: float = 0.1  # m/s^2
    prior_gyro_bias_sigma: float = 2e-3  # rad/s
    still_rot_sigma: float = 2e-3  # rad, zero-motion between keyframes at rest
    still_pos_sigma: float = 2e-3  # m
    still_vel_sigma: float = 0.01  # m/s
    outlier_px: float = 3.0  # observations above this after optimisation are removed
    min_depth: float = 0.1  # m, observations closer (or behind) are removed
    max_speed: float = 15.0  # m/s, above this the estimate is declared diverged
    gap_vel_sigma: float = 0.3  # m/s, velocity prior of a keyframe after an IMU gap
    gap_rot_sigma: float = 0.1  # rad, pose prior of a keyframe after an IMU gap (around the propagated pose)
    gap_pos_sigma: float = 0.3  # m
    archive_s: float = 60.0  # s, marginalised keyframes' states and inertial links kept for a coast bridge
    smooth_coast: bool = True  # a bridged coast stays in the window's optimisations until the relocalised kf leaves


@dataclass
class Keyframe:
    """State of one keyframe (body frame, world frame z up)."""

    kf_id: int
    ts: int  # ns
    frame_idx: int
    T_w_b: np.ndarray  # (4, 4)
    v_w: np.ndarray  # (3,) m/s
    bias: np.ndarray  # (6,) [ba (m/s^2), bg (rad/s)], GTSAM order
    still: bool = False  # at rest since the previous keyframe


@dataclass
class Landmark:
    """A map point seen by keyframes of the window (observations in undistorted pixels)."""

    lm_id: int
    X_w: np.ndarray  # (3,) m
    obs: dict = field(default_factory=dict)  # kf_id -> (2,) uv
    factors: dict = field(default_factory=dict)  # kf_id -> GenericProjectionFactorCal3_S2 (cached)
    map_prior: object = None  # PriorFactorPoint3 of a re-activated map point (relocalisation), else None


@dataclass
class _Coast:
    """A coast re-estimated by :meth:`SlidingWindowBackend.bridge` that stays in the smoother."""

    anchor: int  # kf_id of the last keyframe tracked visually before the loss
    anchor_priors: list  # the bridge's priors on the anchor's X, V, B
    until: int  # the relocalised keyframe: the coast leaves the smoother with it


class FactorProvider(Protocol):
    """Plug-in point for extra variables and factors (the dense issue's depth codes ``C(k)`` and Eq. 13-14).

    The backend calls, in order, at each optimisation: ``add_factors`` (insert new variables into ``values``
    and factors into ``graph``; the window's states and landmarks are already there, see
    :meth:`SlidingWindowBackend.window_view`), then ``on_optimized`` with the LM result. Before a keyframe's
    ``X, V, B`` are marginalised, ``on_marginalize`` is called (drop or summarise variables tied to it).
    Optionally, ``bridge_factors(backend, poses)`` returns extra factors on the poses ``X(k)`` of the keyframes
    a coast bridge re-estimates (``poses``: ``kf_id -> (4, 4)`` start values, archived keyframes included).
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
        self.K_tuple = tuple(float(k) for k in K)
        fx, fy, cx, cy = self.K_tuple
        self.K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        self.cal = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
        self.T_b_c = np.asarray(T_b_c, dtype=np.float64)
        self.T_c_b = inv_T(self.T_b_c)
        self.body_P_sensor = to_pose3(self.T_b_c)
        self.preint_params = preint_params
        self.proj_noise = huber_noise([self.cfg.pixel_sigma] * 2, self.cfg.huber_k, scalar=False)
        self.providers: list[FactorProvider] = []
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget everything, including the archived keyframe poses and map points."""
        self.history: dict[int, tuple[int, np.ndarray]] = {}  # kf_id -> (ts, final T_w_b) of every keyframe
        self.map_points: dict[int, np.ndarray] = {}  # landmarks that left the window (final positions)
        self.n_optimizations = 0
        self.landmarks = {}
        self._clear_window()

    def _clear_window(self) -> None:
        """Forget the window (states, landmarks, factors); archived poses and map points stay."""
        for j, lm in getattr(self, "landmarks", {}).items():
            if len(lm.obs) >= 2:
                self.map_points[j] = lm.X_w.copy()
        self.keyframes: dict[int, Keyframe] = {}  # active and anchor keyframes
        self.active: list[int] = []
        self.anchors: list[int] = []
        self.landmarks: dict[int, Landmark] = {}
        self.kf_obs: dict[int, set] = {}  # kf_id -> landmark ids it observes
        self.imu_factors: dict[int, list] = {}  # inertial link (or gap priors), keyed by the later keyframe
        self.still_between: dict[int, object] = {}  # keyed by the later keyframe
        self.vel_priors: dict[int, object] = {}  # keyed by the keyframe
        self.prior_factors: list = []  # on the oldest active keyframe
        self.last_stats: dict = {}
        # marginalised keyframes (the last ``archive_s`` seconds) for :meth:`bridge`: state and, per keyframe,
        # the factors that linked it to its predecessor (IMU, zero motion) and its zero-velocity prior
        self.archived_states: dict[int, Keyframe] = {}
        self.archived_links: dict[int, list] = {}
        self.archived_priors: dict[int, list] = {}  # what was known of X, V, B when the keyframe left
        # a bridged coast kept in the smoother (``smooth_coast``): the anchor's id and priors, and the
        # relocalised keyframe whose departure from the window ends it
        self.coast: _Coast | None = None
        self.init_kf_id: int | None = None  # the keyframe that started this window (set by initialize)

    @property
    def initialized(self) -> bool:
        return bool(self.active)

    @property
    def latest(self) -> Keyframe:
        return self.keyframes[self.active[-1]]

    def add_provider(self, provider: FactorProvider) -> None:
        """Register a :class:`FactorProvider` (e.g. the depth-code factors of the dense system)."""
        self.providers.append(provider)

    # ------------------------------------------------------------------ building
    def initialize(self, kf: Keyframe) -> None:
        """Start a new window with ``kf`` and priors on its state (gauge: position and yaw).

        Archived keyframe poses and map points of earlier windows are kept.
        """
        self._clear_window()
        self.init_kf_id = kf.kf_id
        c = self.cfg
        self._insert_kf(kf)
        pose_noise = pose_prior_noise_world(
            kf.T_w_b[:3, :3],
            np.array([c.prior_roll_pitch_sigma, c.prior_roll_pitch_sigma, c.prior_yaw_sigma]),
            c.prior_pos_sigma,
        )
        self.prior_factors = _state_priors(
            kf.kf_id,
            kf.T_w_b,
            kf.v_w,
            kf.bias,
            pose_noise,
            c.prior_vel_sigma,
            [c.prior_acc_bias_sigma] * 3 + [c.prior_gyro_bias_sigma] * 3,
        )

    def _insert_kf(self, kf: Keyframe) -> None:
        self.keyframes[kf.kf_id] = kf
        self.active.append(kf.kf_id)
        self.kf_obs[kf.kf_id] = set()
        self.history[kf.kf_id] = (kf.ts, kf.T_w_b.copy())

    def add_keyframe(self, kf: Keyframe, pim) -> None:
        """Append a keyframe linked to the newest one by the preintegrated IMU ``pim`` (zero motion if still).

        ``pim=None`` (the IMU had a gap): no inertial link; the bias continues through a between factor and
        the
        pose and velocity get loose priors around ``kf``'s values (the landmarks then fix the pose).
        """
        import gtsam

        X, V, B, _, _ = _sym()
        if not self.active:
            raise RuntimeError("add_keyframe before initialize")
        prev = self.active[-1]
        if kf.kf_id in self.keyframes or kf.kf_id <= prev:
            raise ValueError(f"keyframe id {kf.kf_id} is not new (latest is {prev})")
        self._insert_kf(kf)
        i, j = prev, kf.kf_id
        c = self.cfg
        if pim is None:
            self.imu_factors[j] = [
                gtsam.BetweenFactorConstantBias(
                    B(i),
                    B(j),
                    gtsam.imuBias.ConstantBias(),
                    gtsam.noiseModel.Diagonal.Sigmas(
                        np.array([c.prior_acc_bias_sigma] * 3 + [c.prior_gyro_bias_sigma] * 3)
                    ),
                ),
                gtsam.PriorFactorVector(V(j), kf.v_w, gtsam.noiseModel.Isotropic.Sigma(3, c.gap_vel_sigma)),
                gtsam.PriorFactorPose3(
                    X(j),
                    to_pose3(kf.T_w_b),
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([c.gap_rot_sigma] * 3 + [c.gap_pos_sigma] * 3)),
                ),
            ]
        else:
            self.imu_factors[j] = [gtsam.CombinedImuFactor(X(i), V(i), X(j), V(j), B(i), B(j), pim)]
        if kf.still:
            c = self.cfg
            self.still_between[j] = gtsam.BetweenFactorPose3(
                X(i),
                X(j),
                gtsam.Pose3.Identity(),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([c.still_rot_sigma] * 3 + [c.still_pos_sigma] * 3)),
            )
            self.vel_priors[j] = gtsam.PriorFactorVector(
                V(j), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, c.still_vel_sigma)
            )

    def add_observations(self, kf_id: int, lm_ids: np.ndarray, uv: np.ndarray) -> None:
        """Observations (undistorted pixels (N, 2)) of existing landmarks by keyframe ``kf_id``."""
        if kf_id not in self.keyframes:
            raise KeyError(f"keyframe {kf_id} is not in the window")
        X, _, _, L, _ = _sym()
        ids = [int(j) for j in lm_ids if int(j) in self.landmarks]
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
        obs = self.kf_obs[kf_id]
        for j, u, f in zip(lids, uvs, facs, strict=False):
            lm = self.landmarks[int(j)]
            lm.obs[kf_id] = u
            lm.factors[kf_id] = f
            obs.add(int(j))

    def add_landmarks(self, lm_ids: np.ndarray, X_w: np.ndarray, obs: list[dict]) -> None:
        """New landmarks at positions (N, 3) with their observations ``{kf_id: uv (2,)}``."""
        for j, P, o in zip(lm_ids, np.asarray(X_w, dtype=np.float64), obs, strict=False):
            j = int(j)
            if j in self.landmarks:
                raise ValueError(f"landmark {j} exists already")
            self.landmarks[j] = Landmark(j, P.copy())
            for kf_id, u in o.items():
                if kf_id in self.keyframes:
                    self.add_observations(kf_id, np.array([j]), np.asarray(u, dtype=np.float64).reshape(1, 2))

    # ------------------------------------------------------------------ views for plug-ins and the frontend
    def window_view(self) -> dict:
        """Arrays describing the window: active/anchor keyframe ids, landmark ids and positions, observations.

        Returns:
            ``{"active": [...], "anchors": [...], "lm_ids": (N,), "X_w": (N, 3), "obs_kf": (M,), "obs_lm":
            (M,),
            "obs_uv": (M, 2)}``.
        """
        lm_ids = np.array(list(self.landmarks.keys()), dtype=np.int64)
        X_w = np.array([self.landmarks[int(j)].X_w for j in lm_ids]).reshape(-1, 3)
        ok, ol, ou = [], [], []
        for j in lm_ids:
            for k, u in self.landmarks[int(j)].obs.items():
                ok.append(k)
                ol.append(int(j))
                ou.append(u)
        return {
            "active": list(self.active),
            "anchors": list(self.anchors),
            "lm_ids": lm_ids,
            "X_w": X_w,
            "obs_kf": np.array(ok, dtype=np.int64),
            "obs_lm": np.array(ol, dtype=np.int64),
            "obs_uv": np.array(ou, dtype=np.float64).reshape(-1, 2),
        }

    def covisible_keyframes(self, kf_id: int, n: int) -> list[int]:
        """The ``n`` active keyframes sharing most landmarks with ``kf_id`` (itself excluded), best first."""
        mine = self.kf_obs.get(kf_id, set())
        scores = [(len(mine & self.kf_obs[k]), k) for k in self.active if k != kf_id]
        scores.sort(key=lambda s: (-s[0], -s[1]))
        return [k for s, k in scores[:n] if s > 0]

    def window_ids(self) -> list[int]:
        """Ids of the active keyframes, oldest first (a copy)."""
        return list(self.active)

    def has_keyframe(self, kf_id: int) -> bool:
        """Whether ``kf_id`` is in the window (active or anchor)."""
        return kf_id in self.keyframes

    def keyframe(self, kf_id: int) -> Keyframe:
        """The window's keyframe ``kf_id`` (active or anchor); KeyError when it is not in the window."""
        return self.keyframes[kf_id]

    def observations(self, kf_id: int, min_views: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Landmarks of the window observed by keyframe ``kf_id`` with at least ``min_views`` observations:
        ids (N,), positions ``X_w`` (N, 3) [m] and the keyframe's undistorted pixels (N, 2), in the order of
        the keyframe's observation set."""
        ids = []
        for j in self.kf_obs.get(kf_id, ()):
            lm = self.landmarks.get(j)
            if lm is not None and kf_id in lm.obs and len(lm.obs) >= min_views:
                ids.append(j)
        X_w = np.array([self.landmarks[j].X_w for j in ids], dtype=np.float64).reshape(-1, 3)
        uv = np.array([self.landmarks[j].obs[kf_id] for j in ids], dtype=np.float64).reshape(-1, 2)
        return np.array(ids, dtype=np.int64), X_w, uv

    def landmark_positions(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 3) of landmarks by id and a mask of those that exist in the window."""
        out = np.zeros((len(ids), 3))
        ok = np.zeros(len(ids), bool)
        for n, j in enumerate(ids):
            lm = self.landmarks.get(int(j))
            if lm is not None:
                out[n] = lm.X_w
                ok[n] = True
        return out, ok

    # ------------------------------------------------------------------ optimisation
    def _coast_chain(self) -> list[Keyframe] | None:
        """The archived keyframes of the coast kept in the smoother (:attr:`coast`), from its anchor up to the
        oldest active keyframe (excluded); None when there is none, when the relocalised keyframe has left the
        window, or when the archive no longer holds an unbroken chain back to the anchor."""
        c = self.coast
        if c is None or not self.cfg.smooth_coast or c.until not in self.active:
            return None
        o = self.active[0]
        ids = sorted(k for k in self.archived_states if c.anchor <= k < o)
        if not ids or ids[0] != c.anchor or any(k not in self.archived_links for k in ids[1:] + [o]):
            return None
        return [self.archived_states[k] for k in ids]

    def _build(self):
        import gtsam

        X, _, _, L, _ = _sym()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for k in self.active:
            kf = self.keyframes[k]
            _insert_state(values, k, kf.T_w_b, kf.v_w, kf.bias)
        chain = self._coast_chain()
        if chain is None:
            for f in self.prior_factors:
                graph.push_back(f)
        else:  # the coast from its anchor instead of the marginal prior that summarises it
            for f in self.coast.anchor_priors:
                graph.push_back(f)
            for kf in chain:
                _insert_state(values, kf.kf_id, kf.T_w_b, kf.v_w, kf.bias)
            for k in [kf.kf_id for kf in chain[1:]] + [self.active[0]]:
                for f in self.archived_links[k]:
                    graph.push_back(f)
        in_chain = {kf.kf_id for kf in chain or ()}
        links = {}  # inter-keyframe factors (IMU, zero motion), kept apart for the window marginal
        for k in self.active[1:]:
            lg = gtsam.NonlinearFactorGraph()
            for f in self.imu_factors[k]:
                lg.push_back(f)
            if k in self.still_between:
                lg.push_back(self.still_between[k])
            links[k] = lg
        for k in self.active:
            if k in self.vel_priors:
                graph.push_back(self.vel_priors[k])
        anchor_noise = gtsam.noiseModel.Isotropic.Sigma(6, self.cfg.anchor_sigma)
        used_anchors = set()
        active = set(self.active)
        proj_kf, proj_lm = [], []
        for j, lm in self.landmarks.items():
            if len(lm.obs) < (1 if lm.map_prior is not None else 2) or not any(k in active for k in lm.obs):
                continue
            values.insert(L(j), lm.X_w)
            if lm.map_prior is not None:
                graph.push_back(lm.map_prior)
            for k, f in lm.factors.items():
                graph.push_back(f)
                proj_kf.append(k)
                proj_lm.append(j)
                if k not in active:
                    used_anchors.add(k)
        for k in used_anchors - in_chain:  # coasted keyframes are variables of the smoother instead
            kf = self.keyframes[k]
            values.insert(X(k), to_pose3(kf.T_w_b))
            graph.push_back(gtsam.PriorFactorPose3(X(k), to_pose3(kf.T_w_b), anchor_noise))
        proj = (np.array(proj_kf, dtype=np.int64), np.array(proj_lm, dtype=np.int64))
        return graph, links, values, proj, chain

    def optimize(self) -> dict:
        """Run LM on the window; write the result back into keyframes and landmarks.

        Returns:
            stats: ``{"iterations", "error_before", "error_after", "n_factors", "n_landmarks", "t_build",
            "t_solve", "ok"}``.
        """
        import gtsam

        X, V, B, L, _ = _sym()
        t0 = time.perf_counter()
        base, links, values, (proj_kf, proj_lm), chain = self._build()
        for p in self.providers:
            p.add_factors(self, base, values)
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(base)
        for lg in links.values():
            graph.push_back(lg)
        t1 = time.perf_counter()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.lm_max_iterations)
        params.setRelativeErrorTol(self.cfg.lm_relative_tol)
        params.setAbsoluteErrorTol(1e-6)
        stats = {"n_factors": int(graph.size()), "n_landmarks": int(len(set(proj_lm.tolist())))}
        try:
            err0 = graph.error(values)
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
            result = opt.optimize()
            err1 = graph.error(result)
            stats.update(
                iterations=int(opt.iterations()), error_before=float(err0), error_after=float(err1), ok=True
            )
        except RuntimeError as e:  # IndeterminantLinearSystem and the like: keep the previous estimate
            log.warning(
                "backend: LM failed (%s); keeping the previous estimate", str(e).splitlines()[0][:200]
            )
            stats.update(iterations=0, error_before=float("nan"), error_after=float("nan"), ok=False)
            self.last_stats = stats
            return stats
        t2 = time.perf_counter()
        for k in self.active:
            kf = self.keyframes[k]
            kf.T_w_b = from_pose3(result.atPose3(X(k)))
            kf.v_w = np.asarray(result.atVector(V(k)), dtype=np.float64).copy()
            b = result.atConstantBias(B(k))
            kf.bias = np.concatenate([b.accelerometer(), b.gyroscope()])
            self.history[k] = (kf.ts, kf.T_w_b.copy())
        for j in set(proj_lm.tolist()):
            self.landmarks[j].X_w = np.asarray(result.atPoint3(L(j)), dtype=np.float64).copy()
        if chain is not None:
            self._take_coast(chain, result)
            stats["coast_keyframes"] = len(chain)
        for p in self.providers:
            p.on_optimized(self, result)
        self._last_result = result
        self.n_optimizations += 1
        stats.update(t_build=t1 - t0, t_solve=t2 - t1)
        self.last_stats = stats
        return stats

    def diverged(self) -> str | None:
        """A reason string when the window's estimate is not plausible, else None."""
        for k in self.active:
            kf = self.keyframes[k]
            if not (np.isfinite(kf.T_w_b).all() and np.isfinite(kf.v_w).all() and np.isfinite(kf.bias).all()):
                return f"non-finite state at keyframe {k}"
            if np.linalg.norm(kf.v_w) > self.cfg.max_speed:
                return f"speed {np.linalg.norm(kf.v_w):.1f} m/s at keyframe {k}"
            if np.linalg.norm(kf.bias[:3]) > 2.0 or np.linalg.norm(kf.bias[3:]) > 0.5:
                return f"implausible IMU bias {np.round(kf.bias, 3).tolist()} at keyframe {k}"
        return None

    # ------------------------------------------------------------------ outliers
    def reprojection_errors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All observations of the window: (kf ids (M,), landmark ids (M,), errors (M,) px, depths (M,) m)."""
        kfs, lms, uvs, Xs = [], [], [], []
        for j, lm in self.landmarks.items():
            for k, u in lm.obs.items():
                kfs.append(k)
                lms.append(j)
                uvs.append(u)
                Xs.append(lm.X_w)
        if not kfs:
            z = np.zeros(0)
            return z.astype(np.int64), z.astype(np.int64), z, z
        kfs_a = np.array(kfs, dtype=np.int64)
        uv = np.array(uvs)
        Xw = np.array(Xs)
        uniq, inv = np.unique(kfs_a, return_inverse=True)
        T_c_w = np.stack([self.T_c_b @ inv_T(self.keyframes[int(k)].T_w_b) for k in uniq])[inv]  # (M, 4, 4)
        p_c = np.einsum("mij,mj->mi", T_c_w[:, :3, :3], Xw) + T_c_w[:, :3, 3]
        z = p_c[:, 2]
        zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
        uv_hat = np.stack(
            [self.K[0, 0] * p_c[:, 0] / zs + self.K[0, 2], self.K[1, 1] * p_c[:, 1] / zs + self.K[1, 2]], -1
        )
        err = np.linalg.norm(uv_hat - uv, axis=1)
        return kfs_a, np.array(lms, dtype=np.int64), err, z

    def remove_outliers(self) -> tuple[np.ndarray, int]:
        """Drop observations with large reprojection error or bad depth; landmarks left with < 2 views go.

        Returns:
            ids of landmarks whose newest observation was rejected or that were removed (the frontend should
            stop tracking them), and the number of observations removed.
        """
        kfs, lms, err, z = self.reprojection_errors()
        bad = (err > self.cfg.outlier_px) | (z < self.cfg.min_depth) | ~np.isfinite(err)
        if not bad.any():
            return np.zeros(0, np.int64), 0
        newest = self.active[-1]
        drop_tracks = set()
        for k, j in zip(kfs[bad], lms[bad], strict=False):
            k, j = int(k), int(j)
            lm = self.landmarks.get(j)
            if lm is None:
                continue
            lm.obs.pop(k, None)
            lm.factors.pop(k, None)
            self.kf_obs[k].discard(j)
            if k == newest:
                drop_tracks.add(j)
        for j in set(lms[bad].tolist()):
            lm = self.landmarks.get(j)
            if lm is not None and len(lm.obs) < (1 if lm.map_prior is not None else 2):
                self._delete_landmark(j)
                drop_tracks.add(j)
        return np.array(sorted(drop_tracks), dtype=np.int64), int(bad.sum())

    def _delete_landmark(self, j: int) -> None:
        lm = self.landmarks.pop(j)
        for k in lm.obs:
            self.kf_obs.get(k, set()).discard(j)

    # ------------------------------------------------------------------ marginalisation
    def marginalize(self) -> list[int]:
        """Marginalise the oldest active keyframes until the window has ``window_size``; returns their ids."""
        import gtsam

        X, V, B, _, _ = _sym()
        dropped = []
        while len(self.active) > self.cfg.window_size:
            o, n = self.active[0], self.active[1]
            for p in self.providers:
                p.on_marginalize(self, o)
            fg = gtsam.NonlinearFactorGraph()
            window_prior = self._visual_prior(o) if self.cfg.marginal_visual_fix else None
            own_prior = window_prior if window_prior is not None else list(self.prior_factors)
            for f in own_prior:
                fg.push_back(f)
            self.archived_priors[o] = own_prior
            link = list(self.imu_factors.pop(n))
            if n in self.still_between:
                link.append(self.still_between.pop(n))
            for f in link:
                fg.push_back(f)
            self.archived_links[n] = link
            if o in self.vel_priors:
                vp = self.vel_priors.pop(o)
                fg.push_back(vp)
                self.archived_links.setdefault(o, []).append(vp)
            vals = gtsam.Values()
            for k in (o, n):
                kf = self.keyframes[k]
                _insert_state(vals, k, kf.T_w_b, kf.v_w, kf.bias)
            lin = fg.linearize(vals)
            ordering = gtsam.Ordering()
            for key in (X(o), V(o), B(o)):
                ordering.push_back(key)
            _, remaining = lin.eliminatePartialSequential(ordering)
            lin_pt = gtsam.Values()
            kfn = self.keyframes[n]
            _insert_state(lin_pt, n, kfn.T_w_b, kfn.v_w, kfn.bias)
            self.prior_factors = _linear_prior(remaining, lin_pt)
            self.active.pop(0)
            dropped.append(o)
            if self.coast is not None and self.coast.until == o:  # the coast's last say: it leaves the smoother
                self.coast = None
            ko = self.keyframes[o]
            self.archived_states[o] = Keyframe(
                o, ko.ts, ko.frame_idx, ko.T_w_b.copy(), ko.v_w.copy(), ko.bias.copy()
            )
            if self.cfg.anchor_old_observations:
                self.anchors.append(o)
            else:
                self._forget_keyframe(o)
        while len(self.anchors) > self.cfg.max_anchor_keyframes:
            self._forget_keyframe(self.anchors.pop(0))
        if dropped:
            self._freeze_landmarks()
            t_keep = self.latest.ts - int(self.cfg.archive_s * 1e9)
            for k in [k for k, a in self.archived_states.items() if a.ts < t_keep]:
                del self.archived_states[k]
                self.archived_links.pop(k, None)
                self.archived_priors.pop(k, None)
        return dropped

    def _visual_prior(self, o: int):
        """The prior on ``X, V, B`` of keyframe ``o`` plus a visual fix of its pose, as linear factors.

        The fix is what ``o``'s own observations say about its pose with its landmarks held near their current
        estimates (``visual_fix_sigma``): the map's word on where ``o`` is. Marginalising ``o`` with it and
        the
        link ``o -> n`` hands that information on: the window keeps a visually informed position and velocity
        when every landmark has gone (a textureless stretch). It is cheap (``o``'s factors only, no Schur
        complement over the window) and counts only ``o``'s own visual information twice (its observations
        stay in the window through its anchor); the inertial chain and the biases are never duplicated.
        Returns None (use the plain prior) when ``o`` sees fewer than 6 landmarks.
        """
        import gtsam

        _, _, _, L, _ = _sym()
        obs = [j for j in self.kf_obs.get(o, ()) if j in self.landmarks and o in self.landmarks[j].factors]
        if len(obs) < 6:
            return None
        kf = self.keyframes[o]
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        _insert_state(values, o, kf.T_w_b, kf.v_w, kf.bias)
        for f in self.prior_factors:
            graph.push_back(f)
        fix = gtsam.noiseModel.Isotropic.Sigma(3, self.cfg.visual_fix_sigma)
        lm_order = gtsam.Ordering()
        for j in obs:
            lm = self.landmarks[j]
            values.insert(L(j), lm.X_w)
            graph.push_back(lm.factors[o])
            graph.push_back(gtsam.PriorFactorPoint3(L(j), lm.X_w, fix))
            lm_order.push_back(L(j))
        try:
            _, remaining = graph.linearize(values).eliminatePartialSequential(lm_order)
        except RuntimeError as e:
            log.info("backend: visual fix of keyframe %d unavailable (%s)", o, str(e).splitlines()[0][:120])
            return None
        lin_pt = gtsam.Values()
        _insert_state(lin_pt, o, kf.T_w_b, kf.v_w, kf.bias)
        return _linear_prior(remaining, lin_pt)

    # ------------------------------------------------------------------ relocalisation
    def reactivate_landmarks(
        self, ids: np.ndarray, X_map: np.ndarray, kf_id: int, uv: np.ndarray, sigma: float
    ) -> None:
        """Bring map points back into the window, observed by keyframe ``kf_id`` (undistorted pixels (N, 2)),
        each held near its map position by a prior of ``sigma`` metres (the map is older and better known)."""
        import gtsam

        _, _, _, L, _ = _sym()
        noise = gtsam.noiseModel.Isotropic.Sigma(3, float(sigma))
        for j, P in zip(ids, np.asarray(X_map, dtype=np.float64), strict=False):
            j = int(j)
            if j in self.landmarks:
                continue
            self.map_points.pop(j, None)
            self.landmarks[j] = Landmark(j, P.copy(), map_prior=gtsam.PriorFactorPoint3(L(j), P, noise))
        self.add_observations(kf_id, np.asarray(ids), np.asarray(uv, dtype=np.float64))

    def apply_correction(self, correction, t_from: int) -> None:
        """Move keyframes (and their landmarks) by world-frame corrections ``correction(ts) -> (4, 4)``.

        Used when relocalisation finds that the window drifted from the map: every keyframe at or after
        ``t_from`` (ns) in memory and in ``history`` gets ``T_w_b <- C(ts) T_w_b`` (velocities rotate with
        it),
        landmarks follow the correction of their newest observing keyframe (re-activated map points stay). The
        marginal prior on the oldest keyframe (linearised at the old state) is replaced by priors around the
        corrected state: roll/pitch and biases keep their confidence, position, yaw and velocity become loose.
        """
        corr = {}
        for k, (ts, T) in list(self.history.items()):
            if ts >= t_from:
                C = correction(ts)
                corr[k] = C
                self.history[k] = (ts, C @ T)
        for kf in list(self.keyframes.values()) + list(self.archived_states.values()):
            C = corr.get(kf.kf_id)
            if C is not None:
                kf.T_w_b = C @ kf.T_w_b
                kf.v_w = C[:3, :3] @ kf.v_w
        self._move_landmarks(corr)
        self._loose_oldest_prior()

    def _move_landmarks(self, corr: dict[int, np.ndarray]) -> None:
        """Landmarks follow the world-frame correction ``corr[k]`` of their newest observing keyframe
        (re-activated map points stay)."""
        for lm in self.landmarks.values():
            if lm.map_prior is None and lm.obs:
                C = corr.get(max(lm.obs))
                if C is not None:
                    lm.X_w = lm.X_w @ C[:3, :3].T + C[:3, 3]

    def _chain(self, t_from: int, kf_id: int) -> list[Keyframe] | None:
        """Keyframes from the last one at or before ``t_from`` to ``kf_id`` (archived, then active), or None
        when the archive does not reach back that far or an IMU gap broke the inertial chain."""
        import gtsam

        states = {**self.archived_states, **{k: self.keyframes[k] for k in self.active}}
        ids = sorted(k for k in states if k <= kf_id)
        before = [k for k in ids if states[k].ts <= t_from]
        if not before or kf_id not in states:
            return None
        chain = [states[k] for k in ids if k >= before[-1]]
        for kf in chain[1:]:
            if not any(isinstance(f, gtsam.CombinedImuFactor) for f in self._link(kf.kf_id)):
                return None
        return chain

    def _link(self, k: int) -> list:
        """The factors between keyframe ``k`` and its predecessor (and ``k``'s zero-velocity prior)."""
        if k in self.archived_links:
            return self.archived_links[k]
        out = list(self.imu_factors.get(k, ()))
        for d in (self.still_between, self.vel_priors):
            if k in d:
                out.append(d[k])
        return out

    def bridge(
        self,
        t_from: int,
        kf_id: int,
        T_fix: np.ndarray,
        fix_sigmas: np.ndarray,
        anchor_sigmas: np.ndarray,
        init=None,
        anchor_marginal: bool = True,
    ) -> dict[int, np.ndarray] | None:
        """Re-estimate a coasted stretch between two visual fixes (the relocalisation's coast bridge).

        Smooths the keyframe states from the last keyframe at or before ``t_from`` (the anchor, the last one
        tracked visually before the loss) to ``kf_id`` (the relocalised keyframe) over their recorded IMU
        links: a prior on the anchor's state, the PnP pose ``T_fix`` of ``kf_id`` (``fix_sigmas``: rotation
        [rad], position [m], body frame), and the providers' ``bridge_factors`` (dense: Eq. 14 between the
        chain's depth maps). Velocities and biases are re-estimated with the poses, so a systematic drift (a
        velocity error at the loss, a bias) is explained rather than spread. The window, the archive and
        ``history`` take the smoothed states; landmarks follow their newest observing keyframe; the marginal
        prior on the oldest active keyframe, when it moved, becomes the anchor prior carried over the archived
        links (so the window's own links and the fix are not counted twice).

        With ``smooth_coast`` (:class:`BackendConfig`) the coast then stays in the smoother: until ``kf_id``
        leaves the window, every window optimisation runs over the whole chain (the anchor prior and the
        archived links in place of the marginal prior, coasted keyframes as variables), so the visual tracking
        after the relocalisation, its velocities and biases, reaches back into the coast. The PnP pose alone
        leaves the split between a velocity error at the loss and a bias error to the anchor prior; measured
        on the 60 s ``whitewall`` sequences it left 10 cm jumps where the archived coast met the window.

        Args:
            anchor_sigmas: the anchor prior's sigmas when it is not the archived marginal: rotation [rad],
                position [m], velocity [m/s], accelerometer bias [m/s^2], gyroscope bias [rad/s].
            init: optional ``correction(ts) -> (4, 4)`` applied to the current estimates to start LM from.
            anchor_marginal: the anchor prior is what the window knew of the anchor's ``X, V, B`` when it was
                marginalised (its marginal prior with its own visual fix, kept in :attr:`archived_priors`), when
                the archive holds it; else (or False) a diagonal prior of ``anchor_sigmas`` around its state.

        Returns:
            ``kf_id -> (4, 4)`` world-frame corrections ``T_new T_old^-1`` of the moved keyframes, or None when
            there is no inertial chain to smooth (the caller then spreads the correction instead).
        """
        import gtsam

        X, V, B, _, _ = _sym()
        chain = self._chain(t_from, kf_id)
        if chain is None or len(chain) < 2:
            return None
        anchor = chain[0]
        sa = np.asarray(anchor_sigmas, np.float64)
        if anchor_marginal and anchor.kf_id in self.archived_priors:
            anchor_priors = self.archived_priors[anchor.kf_id]
        else:
            anchor_priors = _state_priors(
                anchor.kf_id,
                anchor.T_w_b,
                anchor.v_w,
                anchor.bias,
                gtsam.noiseModel.Diagonal.Sigmas(np.array([sa[0]] * 3 + [sa[1]] * 3)),
                sa[2],
                [sa[3]] * 3 + [sa[4]] * 3,
            )
        graph = gtsam.NonlinearFactorGraph()
        for f in anchor_priors:
            graph.push_back(f)
        for kf in chain[1:]:
            for f in self._link(kf.kf_id):
                graph.push_back(f)
        sf = np.asarray(fix_sigmas, np.float64)
        graph.push_back(
            gtsam.PriorFactorPose3(
                X(kf_id),
                to_pose3(T_fix),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([sf[0]] * 3 + [sf[1]] * 3)),
            )
        )
        values = gtsam.Values()
        start = {}
        for kf in chain:
            C = init(kf.ts) if init is not None and kf is not anchor else np.eye(4)
            start[kf.kf_id] = C @ kf.T_w_b
            _insert_state(values, kf.kf_id, start[kf.kf_id], C[:3, :3] @ kf.v_w, kf.bias)
        for p in self.providers:
            if hasattr(p, "bridge_factors"):  # optional (FactorProvider)
                for f in p.bridge_factors(self, start):
                    graph.push_back(f)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(50)
        params.setRelativeErrorTol(1e-6)
        try:
            result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        except RuntimeError as e:
            log.warning("backend: coast bridge failed (%s)", str(e).splitlines()[0][:200])
            return None

        corr = self._take_states(chain, result)
        self._move_landmarks(corr)
        o = self.active[0]
        if o in corr and o != anchor.kf_id:
            self._carried_prior(chain, anchor_priors)
        if self.cfg.smooth_coast and anchor.kf_id < self.active[0]:
            self.coast = _Coast(anchor.kf_id, anchor_priors, kf_id)
        return corr

    def _take_states(self, kfs: list[Keyframe], result) -> dict[int, np.ndarray]:
        """Write the ``X, V, B`` of keyframes ``kfs`` from an LM result into the window, the archive and
        ``history``; returns the world-frame corrections ``T_new T_old^-1`` by keyframe id."""
        X, V, B, _, _ = _sym()
        corr = {}
        for kf in kfs:
            k = kf.kf_id
            T = from_pose3(result.atPose3(X(k)))
            corr[k] = T @ inv_T(kf.T_w_b)
            v = np.asarray(result.atVector(V(k)), dtype=np.float64).copy()
            b = result.atConstantBias(B(k))
            bias = np.concatenate([b.accelerometer(), b.gyroscope()])
            for target in (self.keyframes.get(k), self.archived_states.get(k)):
                if target is not None:
                    target.T_w_b, target.v_w, target.bias = T.copy(), v.copy(), bias.copy()
            if k in self.history:
                self.history[k] = (kf.ts, T.copy())
        return corr

    def _take_coast(self, chain: list[Keyframe], result) -> None:
        """After a window optimisation over the coast: the coasted keyframes take their smoothed states, and
        the marginal prior on the oldest active keyframe is carried from the anchor over the archived links at
        those states (what marginalising it next folds in)."""
        self._take_states(chain, result)
        self._carried_prior(chain + [self.keyframes[self.active[0]]], self.coast.anchor_priors)

    def _carried_prior(self, chain: list[Keyframe], anchor_priors: list) -> None:
        """The oldest active keyframe's marginal prior: the anchor prior and the archived links up to it,
        linearised at the chain's (bridged) states (the window's own links and the fix are not in it)."""
        import gtsam

        X, V, B, _, _ = _sym()
        o = self.active[0]
        fg = gtsam.NonlinearFactorGraph()
        for f in anchor_priors:
            fg.push_back(f)
        vals = gtsam.Values()
        elim = gtsam.Ordering()
        for kf in chain:
            k = kf.kf_id
            if k > o:
                break
            if kf is not chain[0]:
                for f in self.archived_links.get(k, ()):
                    fg.push_back(f)
            if k != o:
                for key in (X(k), V(k), B(k)):
                    elim.push_back(key)
            _insert_state(vals, k, kf.T_w_b, kf.v_w, kf.bias)
        lin_pt = gtsam.Values()
        ko = self.keyframes[o]
        _insert_state(lin_pt, o, ko.T_w_b, ko.v_w, ko.bias)
        try:
            _, remaining = fg.linearize(vals).eliminatePartialSequential(elim)
        except RuntimeError as e:
            log.info("backend: carried prior unavailable (%s); loose priors", str(e).splitlines()[0][:120])
            self._loose_oldest_prior()
            return
        self.prior_factors = _linear_prior(remaining, lin_pt)

    def _loose_oldest_prior(self) -> None:
        """Priors around the oldest active keyframe's current state: roll/pitch and biases keep their
        confidence, position, yaw and velocity are loose (after a relocalisation moved it)."""
        c = self.cfg
        o = self.keyframes[self.active[0]]
        self.prior_factors = _state_priors(
            o.kf_id,
            o.T_w_b,
            o.v_w,
            o.bias,
            pose_prior_noise_world(o.T_w_b[:3, :3], np.array([c.prior_roll_pitch_sigma] * 2 + [0.1]), 0.5),
            0.2,
            [0.02] * 3 + [c.prior_gyro_bias_sigma] * 3,
        )

    def _forget_keyframe(self, k: int) -> None:
        """Remove a keyframe's observations and state (its final pose stays in ``history``)."""
        for j in self.kf_obs.pop(k, set()):
            lm = self.landmarks.get(j)
            if lm is not None:
                lm.obs.pop(k, None)
                lm.factors.pop(k, None)
        self.keyframes.pop(k, None)

    def _freeze_landmarks(self) -> None:
        """Landmarks no longer seen by any active keyframe move to the map (their estimate is final)."""
        active = set(self.active)
        gone = [j for j, lm in self.landmarks.items() if not any(k in active for k in lm.obs)]
        for j in gone:
            lm = self.landmarks[j]
            if len(lm.obs) >= 2:
                self.map_points[j] = lm.X_w.copy()
            self._delete_landmark(j)

    def all_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Every landmark estimate (map and window): ids (N,), positions (N, 3)."""
        pts = dict(self.map_points)
        for j, lm in self.landmarks.items():
            if len(lm.obs) >= 2:
                pts[j] = lm.X_w
        ids = np.array(sorted(pts), dtype=np.int64)
        return ids, np.array([pts[int(j)] for j in ids]).reshape(-1, 3)
