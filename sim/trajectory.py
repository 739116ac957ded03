"""Smooth MAV-like camera trajectories inside a scene's free region, deterministic by seed.

Camera position and yaw / pitch / roll are sums of sines times a C-infinity envelope ``e(t)`` that is exactly
0 during the initial rest (``t < t_rest``) and rises to 1 over ``t_ramp`` seconds, so the whole path is
C-infinity and starts with ``t_rest`` seconds at rest. The camera looks roughly horizontally (small pitch and
roll):

    R_w_c = Rz(yaw) @ Ry(pitch) @ Rx(roll) @ R_LEVEL  (R_LEVEL: optical axis along world +x, image x: -y)

Amplitudes are fitted so that the camera stays inside the scene's free region (``scene.clearance`` from every
surface), the speed stays below ``max_speed`` and the angular rate below ``max_rate``.

``whitewall``: after some exploration the camera blends (C-infinity window of ``t_blend`` seconds) into a
hover 1.35-1.6 m in front of the textureless wall ``x = Lx``, looking at it for ``hold`` seconds,
then blends back; :attr:`Trajectory.window` is that hold interval.

Body poses follow from cam0's ``T_b_c``: ``R_w_b = R_w_c @ R_b_c.T``, ``p_w_b = p_w_c - R_w_b @ t_b_c``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.scenes import Scene

__all__ = ["R_LEVEL", "Trajectory", "make_trajectory", "smooth_step", "euler_to_R_w_c"]

#: Camera orientation at yaw = pitch = roll = 0: columns are the camera x (right), y (down), z (optical axis)
#: in the world: x_c = -y_w, y_c = -z_w, z_c = +x_w.
R_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def smooth_step(x: np.ndarray) -> np.ndarray:
    """C-infinity step: 0 for x <= 0, 1 for x >= 1, ``f(x) / (f(x) + f(1 - x))`` with ``f(x) = exp(-1/x)``.

    >>> smooth_step(np.array([-1.0, 0.0, 0.5, 1.0])).tolist()
    [0.0, 0.0, 0.5, 1.0]
    """
    x = np.asarray(x, dtype=np.float64)
    a = np.where(x > 0, np.exp(-1.0 / np.where(x > 0, x, 1.0)), 0.0)
    b = np.where(x < 1, np.exp(-1.0 / np.where(x < 1, 1.0 - x, 1.0)), 0.0)
    return a / (a + b)


def euler_to_R_w_c(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll) @ R_LEVEL`` for arrays of angles (N,) [rad] -> (N, 3, 3).

    Positive pitch tilts the optical axis down, positive yaw turns it from +x towards +y.
    """
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    one, zero = np.ones_like(cy), np.zeros_like(cy)
    Rz = np.stack(
        [np.stack([cy, -sy, zero], -1), np.stack([sy, cy, zero], -1), np.stack([zero, zero, one], -1)], -2
    )
    Ry = np.stack(
        [np.stack([cp, zero, sp], -1), np.stack([zero, one, zero], -1), np.stack([-sp, zero, cp], -1)], -2
    )
    Rx = np.stack(
        [np.stack([one, zero, zero], -1), np.stack([zero, cr, -sr], -1), np.stack([zero, sr, cr], -1)], -2
    )
    return Rz @ Ry @ Rx @ R_LEVEL


def sines(tau: np.ndarray, amp: np.ndarray, freq: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """``sum_k amp_k (sin(freq_k tau + phase_k) - sin(phase_k))`` per row: (D, K) params, (N,) -> (N, D)."""
    arg = tau[:, None, None] * freq[None] + phase[None]  # (N, D, K)
    return np.sum(amp[None] * (np.sin(arg) - np.sin(phase)[None]), -1)


class PoseCurve:
    """Camera, body and velocity from a class's ``camera_pose(t) -> (R_w_c (N, 3, 3), p_w_c (N, 3))``."""

    def camera_T(self, t: np.ndarray) -> np.ndarray:
        """Camera poses ``T_w_c`` (N, 4, 4) at times ``t`` (N,) [s]."""
        R, p = self.camera_pose(t)
        T = np.zeros((R.shape[0], 4, 4))
        T[:, :3, :3] = R
        T[:, :3, 3] = p
        T[:, 3, 3] = 1.0
        return T

    def body_pose(self, t: np.ndarray, T_b_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body (IMU) orientation and position: R_w_b (N, 3, 3), p_w_b (N, 3) [m]."""
        R_w_c, p_w_c = self.camera_pose(t)
        R_b_c, t_b_c = T_b_c[:3, :3], T_b_c[:3, 3]
        R_w_b = R_w_c @ R_b_c.T
        return R_w_b, p_w_c - R_w_b @ t_b_c

    def body_velocity(self, t: np.ndarray, T_b_c: np.ndarray, h: float = 1e-3) -> np.ndarray:
        """Body velocity in the world (N, 3) [m/s] (4th-order central difference, error ~1e-10 m/s)."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        p = [self.body_pose(t + k * h, T_b_c)[1] for k in (-2, -1, 1, 2)]
        return (p[0] - 8.0 * p[1] + 8.0 * p[2] - p[3]) / (12.0 * h)


@dataclass
class Trajectory(PoseCurve):
    """A smooth camera trajectory (all parameters fixed; evaluate at any time).

    Attributes:
        duration: length [s]; poses are defined for any t, meaningful in [0, duration].
        t_rest: the camera is exactly still for t <= t_rest [s].
        t_ramp: length of the envelope's rise [s].
        p0: (3,) camera position during the rest [m].
        pos_amp, pos_freq, pos_phase: (3, K) sines of the position offset [m, rad/s, rad].
        yaw0: yaw during the rest [rad].
        ang_amp, ang_freq, ang_phase: (3, K) sines of (yaw, pitch, roll) offsets.
        window: (t0, t1) [s] of the white-wall hold, or None.
        hold: whitewall hover parameters (position (3,), sway amplitudes (3,), frequencies (3,)), or None.
        t_blend: length of the blends into and out of the hold [s].
    """

    duration: float
    t_rest: float
    t_ramp: float
    p0: np.ndarray
    pos_amp: np.ndarray
    pos_freq: np.ndarray
    pos_phase: np.ndarray
    yaw0: float
    ang_amp: np.ndarray
    ang_freq: np.ndarray
    ang_phase: np.ndarray
    window: tuple[float, float] | None = None
    hold: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    t_blend: float = 5.5

    def envelope(self, t: np.ndarray) -> np.ndarray:
        return smooth_step((np.asarray(t, dtype=np.float64) - self.t_rest) / self.t_ramp)

    def blend(self, t: np.ndarray) -> np.ndarray:
        """Weight of the white-wall hover (0 outside, 1 during :attr:`window`)."""
        t = np.asarray(t, dtype=np.float64)
        if self.window is None:
            return np.zeros_like(t)
        w0, w1 = self.window
        return smooth_step((t - (w0 - self.t_blend)) / self.t_blend) - smooth_step((t - w1) / self.t_blend)

    def _explore(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e = self.envelope(t)[:, None]
        tau = t - self.t_rest
        p = self.p0 + e * sines(tau, self.pos_amp, self.pos_freq, self.pos_phase)
        ang = np.array([self.yaw0, 0.0, 0.0]) + e * sines(tau, self.ang_amp, self.ang_freq, self.ang_phase)
        return p, ang

    def camera_pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera orientation and position at times ``t`` (N,) [s] -> R_w_c (N, 3, 3), p_w_c (N, 3) [m]."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        p, ang = self._explore(t)
        if self.hold is not None:
            w = self.blend(t)[:, None]
            c, amp, freq = self.hold
            s = np.sin(freq[None, :] * t[:, None])
            p_h = c + amp[None, :3] * s[:, :3]
            ang_h = amp[None, 3:] * s[:, 3:]
            p = (1.0 - w) * p + w * p_h
            ang = (1.0 - w) * ang + w * ang_h
        return euler_to_R_w_c(ang[:, 0], ang[:, 1], ang[:, 2]), p


def camera_rates(traj: PoseCurve, dt: float = 0.02) -> tuple[float, float, np.ndarray]:
    """(max speed [m/s], max angular rate [rad/s], positions (N, 3)) of the camera on a grid."""
    t = np.arange(0.0, traj.duration + dt, dt)
    R, p = traj.camera_pose(t)
    speed = np.linalg.norm(np.diff(p, axis=0), axis=-1) / dt
    rel = np.swapaxes(R[:-1], -1, -2) @ R[1:]
    ang = np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)) / dt
    return float(speed.max()), float(ang.max()), p


def whitewall_min_duration(
    t_rest: float = 2.5, t_ramp: float = 2.0, t_blend: float = 5.5, hold: float = 6.0
) -> float:
    """Shortest ``whitewall`` sequence [s]: rest, ramp, 1.5 s exploring, blend in, hold, blend out, 1 s."""
    return t_rest + t_ramp + 1.5 + 2 * t_blend + hold + 1.0


def make_trajectory(
    scene: Scene,
    duration: float,
    seed: int,
    preset: str = "textured",
    t_rest: float = 2.5,
    t_ramp: float = 2.0,
    max_speed: float = 1.0,
    max_rate: float = 1.0,
    hold: float = 6.0,
    t_blend: float = 5.5,
) -> Trajectory:
    """Random smooth trajectory inside ``scene.free_lo .. scene.free_hi``.

    Args:
        scene: the room (its free region bounds the camera positions).
        duration: sequence length [s] (> t_rest; ``whitewall`` needs :func:`whitewall_min_duration`).
        seed: same seed, same trajectory.
        preset: ``textured`` or ``whitewall``.
        t_rest: initial rest [s] (>= 2 for static initialisation).
        t_ramp: envelope rise time [s].
        max_speed: bound on the camera speed [m/s].
        max_rate: bound on the angular rate [rad/s].
        hold: white-wall hover length [s].
        t_blend: blend time into / out of the hover [s].

    Returns:
        The :class:`Trajectory`.
    """
    if duration <= t_rest:
        raise ValueError(f"duration {duration} s must exceed the rest period t_rest={t_rest} s")
    if preset not in ("textured", "whitewall"):
        raise ValueError(f"unknown preset {preset!r}; expected 'textured' or 'whitewall'")
    if preset == "whitewall":
        if not scene.whitewall:
            raise ValueError("preset 'whitewall' needs a scene built with preset='whitewall'")
        need = whitewall_min_duration(t_rest, t_ramp, t_blend, hold)
        if duration < need:
            raise ValueError(f"preset 'whitewall' needs duration >= {need:.1f} s, got {duration}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7EA1]))
    lo, hi = scene.free_lo, scene.free_hi
    K = 3
    pos_freq = rng.uniform(0.35, 1.3, (3, K))
    pos_phase = rng.uniform(0.0, 2 * np.pi, (3, K))
    pos_amp = rng.uniform(0.3, 1.0, (3, K)) * rng.choice([-1.0, 1.0], (3, K))
    speed_target = np.array([0.7, 0.7, 0.15])  # sum_k |a_k| w_k per axis [m/s]
    pos_amp *= (speed_target / np.sum(np.abs(pos_amp) * pos_freq, 1))[:, None]
    ang_freq = np.stack([rng.uniform(0.12, 0.5, K), rng.uniform(0.3, 1.0, K), rng.uniform(0.3, 1.0, K)])
    ang_phase = rng.uniform(0.0, 2 * np.pi, (3, K))
    ang_amp = rng.uniform(0.3, 1.0, (3, K)) * rng.choice([-1.0, 1.0], (3, K))
    rate_target = np.array([0.5, 0.1, 0.05])  # yaw, pitch, roll [rad/s]
    ang_amp *= (rate_target / np.sum(np.abs(ang_amp) * ang_freq, 1))[:, None]
    ang_cap = np.array([np.inf, 0.2, 0.08])  # |pitch|, |roll| offsets [rad]
    yaw0 = float(rng.uniform(-np.pi, np.pi))
    window = hold_params = None
    if preset == "whitewall":
        # explore looking at a side wall (yaw ~ +-pi/2, the bare wall x = Lx at most at the image border),
        # then turn by ~pi/2 to face the bare wall during the blend
        yaw0 = float(rng.choice([-1.0, 1.0]) * np.pi / 2 + rng.uniform(-0.2, 0.2))
        ang_cap[0] = 0.6
        t_a = max(t_rest + t_ramp + 1.5, 0.5 * (duration - 2 * t_blend - hold))
        window = (t_a + t_blend, t_a + t_blend + hold)
        Lx, Ly, Lz = scene.size
        c = np.array(
            [
                Lx - float(rng.uniform(1.35, 1.6)),
                Ly / 2 + float(rng.uniform(-0.3, 0.3)),
                np.clip(Lz / 2, lo[2], hi[2]),
            ]
        )
        amp = np.array([0.05, 0.2, 0.06, 0.08, 0.03, 0.0])  # x, y, z [m], yaw, pitch, roll [rad]
        freq = rng.uniform(0.35, 0.7, 6)
        hold_params = (c, amp, freq)

    tau = np.arange(0.0, duration - t_rest + 0.05, 0.02)
    # cap the angle offsets, then fit the position offsets into the free region
    A = sines(tau, ang_amp, ang_freq, ang_phase)
    ang_amp *= np.minimum(1.0, ang_cap / np.maximum(np.abs(A).max(0), 1e-9))[:, None]
    room = (hi - lo) * 0.98
    for it in range(
        4
    ):  # fit the offsets into the free region, then speed them up (higher frequencies) to target
        S = sines(tau, pos_amp, pos_freq, pos_phase)
        s_lo, s_hi = np.minimum(S.min(0), 0.0), np.maximum(S.max(0), 0.0)
        shrink = np.minimum(1.0, room / np.maximum(s_hi - s_lo, 1e-9))
        pos_amp *= shrink[:, None]
        s_lo, s_hi = s_lo * shrink, s_hi * shrink
        if it == 3:
            break
        speedup = np.clip(speed_target / np.sum(np.abs(pos_amp) * pos_freq, 1), 1.0, 4.0 / pos_freq.max(1))
        pos_freq *= speedup[:, None]
    p0 = lo - s_lo + rng.uniform(0.0, 1.0, 3) * np.maximum((hi - s_hi) - (lo - s_lo), 0.0)

    traj = Trajectory(
        float(duration),
        t_rest,
        t_ramp,
        p0,
        pos_amp,
        pos_freq,
        pos_phase,
        yaw0,
        ang_amp,
        ang_freq,
        ang_phase,
        window,
        hold_params,
        t_blend,
    )
    for _ in range(20):  # enforce the speed and rate bounds by shrinking the amplitudes
        v, w, _ = camera_rates(traj)
        if v <= max_speed and w <= max_rate:
            break
        if v > max_speed:
            traj.pos_amp = traj.pos_amp * (0.97 * max_speed / v)
        if w > max_rate:
            traj.ang_amp = traj.ang_amp * (0.97 * max_rate / w)
    else:
        raise RuntimeError(
            f"could not meet the speed / rate bounds for seed {seed} (speed {v:.2f}, rate {w:.2f})"
        )
    return traj
