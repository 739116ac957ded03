"""Trajectories of the realistic presets: a MAV flight, a hand-held walk-through and a tabletop scan.

- ``flight``: 1-3 s resting on the floor (rotors on: the IMU vibrates, see :mod:`sim.imu`), a smooth take-off to
  the middle of the hall, then EuRoC-like motion: sums of sines up to about 2 m/s and 1.5 rad/s, the camera
  roughly level with pitch / roll sways. Smooth (C-infinity) throughout.
- ``handheld``: moving from the first sample on (no still period), up to about 1.2 m/s and 1.2 rad/s.
- ``tabletop``: moving from the first sample, on a sphere section about 0.4-1 m around the table centre, looking at
  points of the table: the objects stay 0.2-1.5 m away.

The classes share :class:`sim.trajectory.Trajectory`'s interface (``camera_pose``, ``camera_T``, ``body_pose``,
``body_velocity``, ``t_rest``, ``window``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.scenes import Scene
from sim.trajectory import PoseCurve, camera_rates, euler_to_R_w_c, sines, smooth_step

__all__ = ["MotionTrajectory", "make_motion_trajectory", "look_at"]


def look_at(p: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera orientations R_w_c (N, 3, 3) at ``p`` (N, 3) looking at ``target`` (N, 3), image x level."""
    z = target - p
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], -1)


@dataclass
class MotionTrajectory(PoseCurve):
    """A smooth camera trajectory of a realistic preset (all parameters fixed; evaluate at any time).

    Attributes:
        kind: ``flight``, ``handheld`` or ``tabletop``.
        duration: length [s].
        t_rest: still for t <= t_rest [s] (flight only; 0 otherwise).
        t_takeoff: length of the climb from the floor (flight) [s].
        p_ground: (3,) camera position while resting on the floor (flight) [m].
        center: (3,) centre of the motion (flight, handheld: position offset origin; tabletop: the target) [m].
        pos: (amp, freq, phase) (3, K) sines of the position (flight / handheld) or of (azimuth, elevation,
            radius) (tabletop).
        ang: (amp, freq, phase) (3, K) sines of (yaw, pitch, roll) (flight / handheld) or of the look-at point
            offset [m] (tabletop).
        yaw0: base yaw (flight / handheld) or azimuth (tabletop) [rad].
        base: (elevation [rad], radius [m]) of the tabletop sphere section.
        t_ramp: exploration envelope rise after take-off [s].
    """

    kind: str
    duration: float
    t_rest: float
    t_takeoff: float
    p_ground: np.ndarray
    center: np.ndarray
    pos: tuple[np.ndarray, np.ndarray, np.ndarray]
    ang: tuple[np.ndarray, np.ndarray, np.ndarray]
    yaw0: float
    base: tuple[float, float] = (0.0, 0.0)
    t_ramp: float = 2.0
    window = None
    t_offset: float = 0.0

    def camera_pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera orientation and position at times ``t`` (N,) [s] -> R_w_c (N, 3, 3), p_w_c (N, 3) [m]."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        if self.kind == "tabletop":
            tau = t + self.t_offset
            s = sines(tau, *self.pos)
            az = self.yaw0 + s[:, 0]
            el = self.base[0] + s[:, 1]
            r = self.base[1] + s[:, 2]
            d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
            p = self.center + r[:, None] * d
            target = self.center + sines(tau, *self.ang)
            return look_at(p, target), p
        if self.kind == "flight":
            tau = t - self.t_rest
            lift = smooth_step(tau / self.t_takeoff)[:, None]
            e = smooth_step((tau - 0.5 * self.t_takeoff) / self.t_ramp)[:, None]
            p = self.p_ground + lift * (self.center - self.p_ground) + e * sines(tau, *self.pos)
            a = np.array([self.yaw0, 0.0, 0.0]) + e * sines(tau, *self.ang)
        else:  # handheld: in motion from the first sample
            tau = t + self.t_offset
            p = self.center + sines(tau, *self.pos)
            a = np.array([self.yaw0, 0.0, 0.0]) + sines(tau, *self.ang)
        return euler_to_R_w_c(a[:, 0], a[:, 1], a[:, 2]), p


def _random_sines(rng, K, freq_lo, freq_hi, target):
    freq = rng.uniform(freq_lo, freq_hi, (3, K))
    phase = rng.uniform(0.0, 2 * np.pi, (3, K))
    amp = rng.uniform(0.3, 1.0, (3, K)) * rng.choice([-1.0, 1.0], (3, K))
    amp *= (np.asarray(target) / np.sum(np.abs(amp) * freq, 1))[:, None]
    return amp, freq, phase


def _fit_into(amp, freq, phase, tau, extent):
    """Shrink the per-axis amplitudes so that the sines' range fits ``extent`` (3,); returns (lo, hi) ranges."""
    S = sines(tau, amp, freq, phase)
    lo, hi = S.min(0), S.max(0)
    shrink = np.minimum(1.0, extent / np.maximum(hi - lo, 1e-9))
    amp *= shrink[:, None]
    return lo * shrink, hi * shrink


_BRANCH = {"flight": 1, "handheld": 2, "tabletop": 3}  # seed-sequence branch per preset


def make_motion_trajectory(scene: Scene, duration: float, seed: int, preset: str) -> MotionTrajectory:
    """Random trajectory of ``preset`` (``flight``, ``handheld``, ``tabletop``) in ``scene``.

    Args:
        scene: the room (its free region bounds the positions after take-off).
        duration: length [s].
        seed: same seed, same trajectory.
        preset: the preset.

    Returns:
        The :class:`MotionTrajectory`.
    """
    if preset not in _BRANCH:
        raise ValueError(f"unknown motion preset {preset!r}; expected flight, handheld or tabletop")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x30710, _BRANCH[preset]]))
    lo, hi = scene.free_lo, scene.free_hi
    tau = np.arange(-2.0, duration + 2.05, 0.02)
    if preset == "flight":
        t_rest = float(rng.uniform(1.0, 3.0))
        pos = _random_sines(rng, 3, 0.25, 0.9, [1.3, 1.3, 0.3])
        ang = _random_sines(rng, 3, 0.15, 0.8, [0.9, 0.25, 0.2])
        ang[0][1:] = np.clip(ang[0][1:], -0.15, 0.15)
        ext = (hi - lo) * 0.98
        target = np.array([1.3, 1.3, 0.3])
        for _ in range(4):  # fit into the free region, then speed up (higher frequencies) back to the target
            s_lo, s_hi = _fit_into(*pos, tau, ext)
            pos[1][:] *= np.clip(target / np.sum(np.abs(pos[0]) * pos[1], 1), 1.0, 2.5 / pos[1].max(1))[:, None]
        s_lo, s_hi = _fit_into(*pos, tau, ext)
        center = lo - s_lo + rng.uniform(0, 1, 3) * np.maximum((hi - s_hi) - (lo - s_lo), 0.0)
        p_ground = np.array([center[0], center[1], 0.25])
        traj = MotionTrajectory(
            "flight", float(duration), t_rest, 2.5, p_ground, center, pos, ang, float(rng.uniform(-np.pi, np.pi))
        )
        max_speed, max_rate = 2.0, 1.5
    elif preset == "handheld":
        pos = _random_sines(rng, 3, 0.3, 1.2, [0.8, 0.8, 0.25])
        ang = _random_sines(rng, 3, 0.2, 1.0, [0.7, 0.3, 0.15])
        ext = (hi - lo) * 0.98
        s_lo, s_hi = _fit_into(*pos, tau, ext)
        center = lo - s_lo + rng.uniform(0, 1, 3) * np.maximum((hi - s_hi) - (lo - s_lo), 0.0)
        traj = MotionTrajectory(
            "handheld",
            float(duration),
            0.0,
            1.0,
            center.copy(),
            center,
            pos,
            ang,
            float(rng.uniform(-np.pi, np.pi)),
            t_offset=float(rng.uniform(0, 100)),
        )
        max_speed, max_rate = 1.2, 1.2
    elif preset == "tabletop":
        top = float(scene.hi[[i for i, n in enumerate(scene.names) if n == "table_top"][0], 2])
        center = np.array([scene.size[0] / 2, scene.size[1] / 2, top + 0.05])
        pos = _random_sines(rng, 3, 0.15, 0.6, [0.5, 0.15, 0.08])
        _fit_into(*pos, tau, np.array([2.5, 0.5, 0.3]))  # azimuth, elevation [rad], radius [m] spans
        ang = _random_sines(rng, 3, 0.2, 0.8, [0.08, 0.06, 0.02])
        _fit_into(*ang, tau, np.array([0.4, 0.25, 0.1]))  # look-at point offsets [m]
        traj = MotionTrajectory(
            "tabletop",
            float(duration),
            0.0,
            1.0,
            center.copy(),
            center,
            pos,
            ang,
            float(rng.uniform(-np.pi, np.pi)),
            base=(float(rng.uniform(0.6, 0.9)), float(rng.uniform(0.55, 0.7))),
            t_offset=float(rng.uniform(0, 100)),
        )
        max_speed, max_rate = 0.6, 1.0
    else:
        raise ValueError(f"unknown motion preset {preset!r}; expected flight, handheld or tabletop")
    if preset == "tabletop":  # keep 12 cm from every object: raise and widen the sphere section until it does
        tt = np.arange(0.0, duration + 0.05, 0.05)
        for _ in range(20):
            if scene.min_distance(traj.camera_pose(tt)[1]).min() >= 0.12:
                break
            traj.base = (min(traj.base[0] + 0.05, 1.3), traj.base[1] * 1.06)
    for _ in range(30):  # enforce the speed and rate bounds by shrinking the amplitudes
        v, w, _ = camera_rates(traj)
        if v <= max_speed and w <= max_rate:
            break
        if v > max_speed:
            traj.pos[0][:] *= 0.97 * max_speed / v
        if w > max_rate:
            traj.ang[0][:] *= 0.97 * max_rate / w
            if preset == "tabletop":
                traj.pos[0][:] *= 0.97 * max_rate / w
    return traj
