"""The shared map state: keyframes, landmarks and their observations.

:class:`MapState` holds what the frontend, the backend, the relocalisation and the dense mapper all read: the
window's keyframes (active ones with full ``X, V, B`` states, and anchors whose poses are held), the landmarks
with their observations, the final pose of every keyframe ever made (``history``) and the map points that left
the window. The backend writes it; the others use its read interface (:meth:`MapState.observations`,
:meth:`MapState.landmark_positions`, :meth:`MapState.map_point_arrays`, ...) and a few narrow edits
(:meth:`MapState.delete_landmark`).

GTSAM keys (DESIGN.md): ``X(i)`` Pose3 ``T_w_b``, ``V(i)`` velocity in w, ``B(i)`` IMU bias, ``L(j)`` landmark,
``C(k)`` depth code.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from runtime.backend.imu import make_bias
from runtime.geometry import inv_T, project_pinhole, to_pose3


def keys():
    """GTSAM's symbol shorthands ``X, V, B, L, C`` (imported lazily: gtsam is heavy)."""
    from gtsam.symbol_shorthand import B, C, L, V, X

    return X, V, B, L, C


def insert_state(values, k: int, T_w_b: np.ndarray, v_w: np.ndarray, bias: np.ndarray) -> None:
    """Insert keyframe ``k``'s ``X, V, B`` (pose (4, 4), velocity (3,), bias (6,)) into ``values``."""
    X, V, B, _, _ = keys()
    values.insert(X(k), to_pose3(T_w_b))
    values.insert(V(k), np.asarray(v_w, dtype=np.float64))
    values.insert(B(k), make_bias(bias))


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

    def copy_state(self) -> Keyframe:
        """A copy of the state (arrays copied, ``still`` dropped): what the archive keeps."""
        return Keyframe(self.kf_id, self.ts, self.frame_idx, self.T_w_b.copy(), self.v_w.copy(), self.bias.copy())


@dataclass
class Landmark:
    """A map point seen by keyframes of the window (observations in undistorted pixels)."""

    lm_id: int
    X_w: np.ndarray  # (3,) m
    obs: dict = field(default_factory=dict)  # kf_id -> (2,) uv
    factors: dict = field(default_factory=dict)  # kf_id -> GenericProjectionFactorCal3_S2 (cached)
    map_prior: object = None  # PriorFactorPoint3 of a re-activated map point (relocalisation), else None

    @property
    def min_views(self) -> int:
        """Observations it needs to stay in the window (a re-activated map point is held by its prior)."""
        return 1 if self.map_prior is not None else 2


class MapState:
    """Keyframes, landmarks and observations of the window, the final keyframe poses and the map points."""

    def __init__(self) -> None:
        self.history: dict[int, tuple[int, np.ndarray]] = {}  # kf_id -> (ts, final T_w_b) of every keyframe
        self.map_points: dict[int, np.ndarray] = {}  # landmarks that left the window (final positions)
        self.landmarks: dict[int, Landmark] = {}
        self.clear_window()

    def clear_window(self) -> None:
        """Forget the window; landmarks seen twice or more become map points, ``history`` stays."""
        for j, lm in self.landmarks.items():
            if len(lm.obs) >= 2:
                self.map_points[j] = lm.X_w.copy()
        self.keyframes: dict[int, Keyframe] = {}  # active and anchor keyframes
        self.active: list[int] = []
        self.anchors: list[int] = []
        self.landmarks: dict[int, Landmark] = {}
        self.kf_obs: dict[int, set] = {}  # kf_id -> landmark ids it observes

    # ------------------------------------------------------------------ read interface
    @property
    def latest(self) -> Keyframe:
        return self.keyframes[self.active[-1]]

    def window_ids(self) -> list[int]:
        """Ids of the active keyframes, oldest first (a copy)."""
        return list(self.active)

    def has_keyframe(self, kf_id: int) -> bool:
        """Whether ``kf_id`` is in the window (active or anchor)."""
        return kf_id in self.keyframes

    def keyframe(self, kf_id: int) -> Keyframe:
        """The window's keyframe ``kf_id`` (active or anchor); KeyError when it is not in the window."""
        return self.keyframes[kf_id]

    @property
    def n_landmarks(self) -> int:
        """Landmarks in the window."""
        return len(self.landmarks)

    def is_landmark(self, lm_id: int) -> bool:
        """Whether track ``lm_id`` is a landmark of the window."""
        return int(lm_id) in self.landmarks

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

    def covisible_keyframes(self, kf_id: int, n: int) -> list[int]:
        """The ``n`` active keyframes sharing most landmarks with ``kf_id`` (itself excluded), best first."""
        mine = self.kf_obs.get(kf_id, set())
        scores = [(len(mine & self.kf_obs[k]), k) for k in self.active if k != kf_id]
        scores.sort(key=lambda s: (-s[0], -s[1]))
        return [k for s, k in scores[:n] if s > 0]

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

    def landmark_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The window's landmarks: ids (N,), positions (N, 3)."""
        ids = np.fromiter(self.landmarks.keys(), dtype=np.int64, count=len(self.landmarks))
        return ids, np.array([self.landmarks[int(j)].X_w for j in ids]).reshape(-1, 3)

    def map_point_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The map points that left the window: ids (N,), positions (N, 3), in insertion order."""
        ids = np.fromiter(self.map_points.keys(), dtype=np.int64, count=len(self.map_points))
        return ids, np.array([self.map_points[int(j)] for j in ids]).reshape(-1, 3)

    def all_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Every landmark estimate (map and window): ids (N,), positions (N, 3)."""
        pts = dict(self.map_points)
        for j, lm in self.landmarks.items():
            if len(lm.obs) >= 2:
                pts[j] = lm.X_w
        ids = np.array(sorted(pts), dtype=np.int64)
        return ids, np.array([pts[int(j)] for j in ids]).reshape(-1, 3)

    def reprojection_errors(self, K, T_c_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All observations of the window in a pinhole camera ``K = (fx, fy, cx, cy)`` mounted at ``T_c_b``:
        (kf ids (M,), landmark ids (M,), errors (M,) px, depths (M,) m)."""
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
        uniq, inv = np.unique(kfs_a, return_inverse=True)
        T_c_w = np.stack([T_c_b @ inv_T(self.keyframes[int(k)].T_w_b) for k in uniq])[inv]  # (M, 4, 4)
        p_c = np.einsum("mij,mj->mi", T_c_w[:, :3, :3], np.array(Xs)) + T_c_w[:, :3, 3]
        uv_hat, z = project_pinhole(K, p_c, min_abs_depth=1e-9)
        err = np.linalg.norm(uv_hat - np.array(uvs), axis=1)
        return kfs_a, np.array(lms, dtype=np.int64), err, z

    # ------------------------------------------------------------------ edits
    def insert_keyframe(self, kf: Keyframe) -> None:
        """A new active keyframe (newest)."""
        self.keyframes[kf.kf_id] = kf
        self.active.append(kf.kf_id)
        self.kf_obs[kf.kf_id] = set()
        self.history[kf.kf_id] = (kf.ts, kf.T_w_b.copy())

    def delete_landmark(self, lm_id: int) -> None:
        """Remove a landmark and its observations from the window."""
        lm = self.landmarks.pop(int(lm_id))
        for k in lm.obs:
            self.kf_obs.get(k, set()).discard(int(lm_id))

    def remove_observation(self, kf_id: int, lm_id: int) -> None:
        """Remove keyframe ``kf_id``'s observation of landmark ``lm_id`` (the landmark stays)."""
        lm = self.landmarks[lm_id]
        lm.obs.pop(kf_id, None)
        lm.factors.pop(kf_id, None)
        self.kf_obs[kf_id].discard(lm_id)

    def forget_keyframe(self, k: int) -> None:
        """Remove a keyframe's observations and state (its final pose stays in ``history``)."""
        for j in self.kf_obs.pop(k, set()):
            lm = self.landmarks.get(j)
            if lm is not None:
                lm.obs.pop(k, None)
                lm.factors.pop(k, None)
        self.keyframes.pop(k, None)

    def freeze_landmarks(self) -> None:
        """Landmarks no longer seen by any active keyframe move to the map (their estimate is final)."""
        active = set(self.active)
        gone = [j for j, lm in self.landmarks.items() if not any(k in active for k in lm.obs)]
        for j in gone:
            lm = self.landmarks[j]
            if len(lm.obs) >= 2:
                self.map_points[j] = lm.X_w.copy()
            self.delete_landmark(j)

    def move_landmarks(self, corr: dict[int, np.ndarray]) -> None:
        """Landmarks follow the world-frame correction ``corr[k]`` of their newest observing keyframe
        (re-activated map points stay)."""
        for lm in self.landmarks.values():
            if lm.map_prior is None and lm.obs:
                C = corr.get(max(lm.obs))
                if C is not None:
                    lm.X_w = lm.X_w @ C[:3, :3].T + C[:3, 3]
