"""Feature-level synthetic data for the runtime tests (no rendering): a smooth body motion with exact IMU,
3D points on the walls of a room, and a fake tracker that returns their projections.

The IMU is sampled at the middle of each sample interval (``t_k + dt/2``) and labelled ``t_k``, so that
zero-order-hold integration over ``[t_k, t_k + dt)`` is second-order accurate: noiseless propagation then
matches the ground truth to well below a millimetre over seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.frontend.tracking import FrameFeatures
from runtime.geometry import GRAVITY_W, Camera, inv_T
from runtime.io.euroc import EUROC_CAM0 as EUROC_CAM
from runtime.io.euroc import EUROC_T_B_C0 as EUROC_T_BS

# camera at zero angles: optical axis along world +x, image x along -y, image y along -z
R_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass
class ImuNoise:
    gyro_noise_density: float = 1.6968e-4
    gyro_random_walk: float = 1.9393e-5
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    rate_hz: float = 200.0
    T_b_s: np.ndarray = None

    def __post_init__(self):
        if self.T_b_s is None:
            self.T_b_s = np.eye(4)


def _smooth_step(x):
    x = np.asarray(x, dtype=np.float64)
    a = np.where(x > 0, np.exp(-1.0 / np.where(x > 0, x, 1.0)), 0.0)
    b = np.where(x < 1, np.exp(-1.0 / np.where(x < 1, 1.0 - x, 1.0)), 0.0)
    return a / (a + b)


def _rot(yaw, pitch, roll):
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    o, z = np.ones_like(cy), np.zeros_like(cy)
    Rz = np.stack([np.stack([cy, -sy, z], -1), np.stack([sy, cy, z], -1), np.stack([z, z, o], -1)], -2)
    Ry = np.stack([np.stack([cp, z, sp], -1), np.stack([z, o, z], -1), np.stack([-sp, z, cp], -1)], -2)
    Rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cr, -sr], -1), np.stack([z, sr, cr], -1)], -2)
    return Rz @ Ry @ Rx


class Motion:
    """Smooth body motion: rest for ``t_rest`` s, then sums of sines (C-infinity envelope); with ``t_translate``
    later than ``t_rest`` the body only turns until then."""

    def __init__(
        self, t_rest=1.5, t_ramp=1.0, amp=0.6, rate=0.4, seed=0, T_b_c=EUROC_T_BS, still=False, t_translate=None
    ):
        rng = np.random.default_rng(seed)
        self.t_rest, self.t_ramp, self.still = t_rest, t_ramp, still
        self.t_translate = t_rest if t_translate is None else t_translate
        self.freq = rng.uniform(0.4, 1.0, (3, 2))
        self.phase = rng.uniform(0, 2 * np.pi, (3, 2))
        self.amp = amp * rng.uniform(0.5, 1.0, (3, 2)) * np.array([[1.0], [1.0], [0.3]])
        self.afreq = rng.uniform(0.3, 0.8, (3, 2))
        self.aphase = rng.uniform(0, 2 * np.pi, (3, 2))
        self.aamp = rate * rng.uniform(0.5, 1.0, (3, 2)) * np.array([[1.0], [0.2], [0.15]])
        self.T_b_c = T_b_c

    def _env(self, t):
        return _smooth_step((np.asarray(t) - self.t_rest) / self.t_ramp)

    def camera(self, t):
        """R_w_c (N, 3, 3), p_w_c (N, 3) at times t (N,) s."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        e = np.zeros_like(t) if self.still else self._env(t)
        e_p = np.zeros_like(t) if self.still else _smooth_step((t - self.t_translate) / self.t_ramp)
        tau = t - self.t_rest

        def s(A, F, P):
            return np.sum(A[None] * (np.sin(tau[:, None, None] * F[None] + P[None]) - np.sin(P)[None]), -1)

        p = e_p[:, None] * s(self.amp, self.freq, self.phase)
        ang = e[:, None] * s(self.aamp / self.afreq, self.afreq, self.aphase)
        R = _rot(ang[:, 0], ang[:, 1], ang[:, 2]) @ R_LEVEL
        return R, p

    def body(self, t):
        """T_w_b (N, 4, 4)."""
        R_w_c, p_w_c = self.camera(t)
        R_b_c, t_b_c = self.T_b_c[:3, :3], self.T_b_c[:3, 3]
        R_w_b = R_w_c @ R_b_c.T
        p_w_b = p_w_c - R_w_b @ t_b_c
        T = np.tile(np.eye(4), (len(p_w_b), 1, 1))
        T[:, :3, :3] = R_w_b
        T[:, :3, 3] = p_w_b
        return T

    def velocity(self, t, h=1e-4):
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return (self.body(t + h)[:, :3, 3] - self.body(t - h)[:, :3, 3]) / (2 * h)

    def imu(self, t, h=1e-4):
        """Exact body-frame gyro (N, 3) and specific force (N, 3) at times t."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        T0, Tp, Tm = self.body(t), self.body(t + h), self.body(t - h)
        dR = (Tp[:, :3, :3] - Tm[:, :3, :3]) / (2 * h)
        W = np.swapaxes(T0[:, :3, :3], -1, -2) @ dR
        gyro = np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], -1) / 2
        a_w = (Tp[:, :3, 3] - 2 * T0[:, :3, 3] + Tm[:, :3, 3]) / h**2
        f_b = np.einsum("nji,nj->ni", T0[:, :3, :3], a_w - GRAVITY_W)
        return gyro, f_b


def make_imu(motion: Motion, duration: float, rate=200.0, noise: ImuNoise | None = None, seed=0, t0_ns=10**9):
    """IMU samples (ts ns, gyro, accel), midpoint-sampled; with ``noise`` white noise and constant biases."""
    n = int(round(duration * rate)) + 1
    ts = t0_ns + np.round(np.arange(n) * 1e9 / rate).astype(np.int64)
    t_mid = (ts - t0_ns) * 1e-9 + 0.5 / rate
    gyro, acc = motion.imu(t_mid)
    if noise is not None:
        rng = np.random.default_rng(seed)
        gyro = gyro + rng.normal(0, noise.gyro_noise_density * np.sqrt(rate), gyro.shape) + 0.002
        acc = acc + rng.normal(0, noise.accel_noise_density * np.sqrt(rate), acc.shape) + 0.02
    return ts, gyro, acc


def room_points(n=3000, half=(4.0, 4.0), z=(-1.5, 2.5), seed=0):
    """Points on the four walls, floor and ceiling of a box room (N, 3)."""
    rng = np.random.default_rng(seed)
    pts = []
    hx, hy = half
    for _ in range(n):
        face = rng.integers(0, 6)
        u, v, w = rng.uniform(-hx, hx), rng.uniform(-hy, hy), rng.uniform(*z)
        pts.append([(hx, v, w), (-hx, v, w), (u, hy, w), (u, -hy, w), (u, v, z[0]), (u, v, z[1])][face])
    return np.array(pts, dtype=np.float64)


class FakeTracker:
    """Drop-in for :class:`FeatureTracker`: projections of known points (noise ``sigma_px``), unique ids."""

    def __init__(self, camera: Camera, T_b_c, points, motion: Motion, t0_ns, max_features=150, sigma_px=0.3, seed=0):
        self.camera, self.T_b_c, self.points, self.motion, self.t0 = camera, T_b_c, points, motion, t0_ns
        self.max_features, self.sigma = max_features, sigma_px
        self.rng = np.random.default_rng(seed)
        self.next_id = 0
        self.reset()
        self.blank = set()  # frame timestamps with no features (textureless)
        self.track_point = {}  # track id -> point index (for checks)

    @property
    def n_tracks(self):
        return int(self.ids.size)

    def reset(self):
        self.ids = np.zeros(0, np.int64)
        self.pidx = np.zeros(0, np.int64)
        self.uv = np.zeros((0, 2))

    def _visible(self, ts):
        T_w_b = self.motion.body((ts - self.t0) * 1e-9)[0]
        T_c_w = inv_T(T_w_b @ self.T_b_c)
        p_c = self.points @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        uv, ok = self.camera.project(p_c, 0.3)
        ok &= self.camera.in_image(uv, 15) & (p_c[:, 2] < 15)
        return uv, ok

    def _features(self, ts, flow=0.0):
        xn = self.camera.pixel_to_normalized(self.uv) if self.uv.shape[0] else np.zeros((0, 2))
        uv_u = np.stack([self.camera.fx * xn[:, 0] + self.camera.cx, self.camera.fy * xn[:, 1] + self.camera.cy], -1)
        return FrameFeatures(ts, self.ids.copy(), self.uv.copy(), xn, uv_u, flow, 0, 0)

    def current(self, ts):
        return self._features(ts)

    def track(self, ts, image, R_b0_b1=None):
        if ts in self.blank:
            self.reset()
            return self._features(ts)
        uv, ok = self._visible(ts)
        keep = ok[self.pidx]
        old = self.uv[keep]
        self.ids, self.pidx = self.ids[keep], self.pidx[keep]
        self.uv = uv[self.pidx] + self.rng.normal(0, self.sigma, (self.ids.size, 2))
        flow = float(np.median(np.linalg.norm(self.uv - old, axis=1))) if self.ids.size else 0.0
        return self._features(ts, flow)

    def replenish(self, ts, image):
        if ts in self.blank:
            return self._features(ts)
        need = self.max_features - self.ids.size
        if need > 0:
            uv, ok = self._visible(ts)
            ok[self.pidx] = False
            cand = np.nonzero(ok)[0]
            if cand.size:
                pick = self.rng.choice(cand, size=min(need, cand.size), replace=False)
                new_ids = np.arange(self.next_id, self.next_id + pick.size)
                self.next_id += pick.size
                self.track_point.update(zip(new_ids.tolist(), pick.tolist(), strict=False))
                self.ids = np.concatenate([self.ids, new_ids])
                self.pidx = np.concatenate([self.pidx, pick])
                self.uv = np.concatenate([self.uv, uv[pick] + self.rng.normal(0, self.sigma, (pick.size, 2))])
        return self._features(ts)

    def rename(self, old, new):
        """As ``FeatureTracker.rename``: returns the mask of the pairs applied (here all of them)."""
        old, new = np.asarray(old, np.int64).reshape(-1), np.asarray(new, np.int64).reshape(-1)
        m = dict(zip(old.tolist(), new.tolist(), strict=True))
        self.ids = np.array([m.get(int(j), int(j)) for j in self.ids], dtype=np.int64)
        return np.ones(old.size, dtype=bool)

    def drop(self, ids):
        keep = ~np.isin(self.ids, ids)
        self.ids, self.pidx, self.uv = self.ids[keep], self.pidx[keep], self.uv[keep]


__all__ = ["Motion", "make_imu", "room_points", "FakeTracker", "EUROC_T_BS", "EUROC_CAM", "ImuNoise"]
