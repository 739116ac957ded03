"""IMU synthesis that GTSAM's preintegration reproduces exactly, and the EuRoC (ADIS16448) noise model.

Given body orientations ``R_k`` and velocities ``v_k`` sampled at ``t_k = k dt`` (k = 0..N), the measurement
``k`` holds over ``[t_k, t_k+1)`` (as GTSAM integrates it):

    gyro   w_k = Log(R_k^T R_k+1) / dt                            (body frame, rad/s)
    accel  a_k = R_k^T ((v_k+1 - v_k) / dt - g_w)                 (specific force, body frame, m/s^2)

and the ground-truth positions are the discrete ones, ``p_k+1 = p_k + v_k dt + 0.5 (v_k+1 - v_k) dt``. Then
``R_k+1 = R_k Exp(w_k dt)``, ``v_k+1 = v_k + g dt + R_k a_k dt`` and ``p_k+1 = p_k + v_k dt + 0.5 g dt^2 + 0.5
R_k a_k dt^2`` hold to rounding: exactly GTSAM's update with zero bias.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.geometry import GRAVITY_W

__all__ = ["ImuNoise", "EUROC_ADIS16448", "so3_log_batch", "synthesize_imu", "add_imu_noise"]


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities (as in EuRoC's ``imu0/sensor.yaml``) and initial-bias spreads.

    Attributes:
        gyro_noise_density: [rad / s / sqrt(Hz)].
        gyro_random_walk: [rad / s^2 / sqrt(Hz)].
        accel_noise_density: [m / s^2 / sqrt(Hz)].
        accel_random_walk: [m / s^3 / sqrt(Hz)].
        gyro_bias_init: standard deviation of the initial gyro bias per axis [rad/s].
        accel_bias_init: standard deviation of the initial accelerometer bias per axis [m/s^2].
    """

    gyro_noise_density: float = 1.6968e-4
    gyro_random_walk: float = 1.9393e-5
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    gyro_bias_init: float = 2e-3
    accel_bias_init: float = 2e-2


#: EuRoC's ADIS16448 numbers.
EUROC_ADIS16448 = ImuNoise()


def so3_log_batch(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotations (N, 3, 3), angles < pi - 1e-6 -> (N, 3) [rad]; exact for small angles."""
    R = np.asarray(R, dtype=np.float64)
    v = 0.5 * np.stack(
        [R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1
    )  # sin(th) n
    s = np.linalg.norm(v, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(s, c)
    if np.any(np.pi - theta < 1e-6):
        raise ValueError("so3_log_batch: a rotation angle is too close to pi (samples too far apart?)")
    small = s < 1e-12
    scale = np.where(small, 1.0, theta / np.where(small, 1.0, s))
    return v * scale[:, None]


def synthesize_imu(
    R_w_b: np.ndarray, v_w: np.ndarray, p0_w: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free IMU samples and the matching discrete positions.

    Args:
        R_w_b: (N+1, 3, 3) body orientations at ``t_k = k dt``.
        v_w: (N+1, 3) body velocities in the world [m/s].
        p0_w: (3,) body position at ``t_0`` [m].
        dt: sample period [s].

    Returns:
        ``(gyro, accel, p_w)``: (N, 3) rad/s and (N, 3) m/s^2 in the body frame (sample k holds over
        ``[t_k, t_k+1)``), and (N+1, 3) positions [m] (trapezoidal integration of ``v_w``).
    """
    R_w_b = np.asarray(R_w_b, dtype=np.float64)
    v_w = np.asarray(v_w, dtype=np.float64)
    if R_w_b.ndim != 3 or R_w_b.shape[1:] != (3, 3) or v_w.shape != (R_w_b.shape[0], 3) or R_w_b.shape[0] < 2:
        raise ValueError(
            f"need R_w_b (N+1, 3, 3) and v_w (N+1, 3) with N >= 1, got {R_w_b.shape} and {v_w.shape}"
        )
    if dt <= 0:
        raise ValueError(f"dt must be positive, got {dt}")
    Rt = np.swapaxes(R_w_b[:-1], -1, -2)  # R_k^T
    gyro = so3_log_batch(Rt @ R_w_b[1:]) / dt
    dv = np.diff(v_w, axis=0)
    accel = (Rt @ (dv / dt - GRAVITY_W)[..., None])[..., 0]
    steps = v_w[:-1] * dt + 0.5 * dv * dt
    p0_w = np.asarray(p0_w, np.float64).reshape(1, 3)
    p_w = np.concatenate([p0_w, p0_w + np.cumsum(steps, axis=0)], 0)
    return gyro, accel, p_w


def add_imu_noise(
    gyro: np.ndarray,
    accel: np.ndarray,
    dt: float,
    rng: np.random.Generator,
    noise: ImuNoise = EUROC_ADIS16448,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Add white noise and random-walk biases (discretised as GTSAM / Kalibr do).

    White noise ``sigma = density / sqrt(dt)``; biases ``b_k+1 = b_k + random_walk * sqrt(dt) * N(0, 1)``
    from a random initial bias.

    Args:
        gyro, accel: (N, 3) noise-free samples.
        dt: sample period [s].
        rng: seeded generator.
        noise: densities and initial-bias spreads.

    Returns:
        ``(gyro_meas, accel_meas, bg, ba)``: measured samples (N, 3) and the true biases (N, 3) added to them.
    """
    n = gyro.shape[0]
    bg0 = rng.normal(0.0, noise.gyro_bias_init, 3)
    ba0 = rng.normal(0.0, noise.accel_bias_init, 3)
    steps_g = noise.gyro_random_walk * np.sqrt(dt) * rng.standard_normal((n, 3))
    steps_a = noise.accel_random_walk * np.sqrt(dt) * rng.standard_normal((n, 3))
    steps_g[0] = steps_a[0] = 0.0
    bg = bg0 + np.cumsum(steps_g, axis=0)
    ba = ba0 + np.cumsum(steps_a, axis=0)
    wg = noise.gyro_noise_density / np.sqrt(dt) * rng.standard_normal((n, 3))
    wa = noise.accel_noise_density / np.sqrt(dt) * rng.standard_normal((n, 3))
    return gyro + bg + wg, accel + ba + wa, bg, ba
