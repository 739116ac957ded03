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

__all__ = [
    "ImuNoise",
    "EUROC_ADIS16448",
    "so3_log_batch",
    "synthesize_imu",
    "add_imu_noise",
    "Vibration",
    "ImuErrors",
    "FLIGHT_IMU",
    "HANDHELD_IMU",
    "rotor_vibration",
    "instantaneous_imu",
    "add_imu_errors",
]


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
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)  # sin(th) n
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
        raise ValueError(f"need R_w_b (N+1, 3, 3) and v_w (N+1, 3) with N >= 1, got {R_w_b.shape} and {v_w.shape}")
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


# --------------------------------------------------------------------------- realistic IMU errors
@dataclass(frozen=True)
class Vibration:
    """Rotor vibration added to the IMU: two narrow bands over a broadband floor, per axis.

    The defaults follow EuRoC's ADIS16448 on the MAV resting with its rotors on (V1_01_easy): per-axis
    standard deviation gyro 0.017-0.043 rad/s, accel 0.21-0.58 m/s^2, peaks near 17 Hz and 70-72 Hz.

    Attributes:
        gyro_std: (3,) per-axis standard deviation of the gyro vibration [rad/s].
        accel_std: (3,) per-axis standard deviation of the accelerometer vibration [m/s^2].
        peaks_hz: centre frequencies of the narrow bands [Hz].
        bandwidth_hz: -3 dB width of each band [Hz].
        peak_share: share of the variance in each band; the rest is the white broadband floor.
    """

    gyro_std: tuple[float, float, float] = (0.030, 0.041, 0.019)
    accel_std: tuple[float, float, float] = (0.55, 0.34, 0.23)
    peaks_hz: tuple[float, ...] = (17.0, 71.0)
    bandwidth_hz: tuple[float, ...] = (1.5, 2.5)
    peak_share: tuple[float, ...] = (0.3, 0.4)

    def __post_init__(self):
        if not (len(self.peaks_hz) == len(self.bandwidth_hz) == len(self.peak_share)):
            raise ValueError("Vibration: peaks_hz, bandwidth_hz and peak_share need the same length")
        if sum(self.peak_share) > 1.0 or min(self.peak_share, default=0.0) < 0:
            raise ValueError(f"Vibration: peak shares must be >= 0 and sum to <= 1, got {self.peak_share}")


@dataclass(frozen=True)
class ImuErrors:
    """Errors of a real MEMS IMU beyond the white noise and bias random walk of :class:`ImuNoise`.

    Attributes:
        gyro_bias_max: turn-on gyro bias, uniform in [-max, max] per axis [rad/s].
        accel_bias_max: turn-on accelerometer bias, uniform in [-max, max] per axis [m/s^2].
        vibration: rotor vibration, or None.
        scale_sigma: per-axis scale-factor error (standard deviation, e.g. 0.003 = 0.3 %).
        misalign_sigma: axis misalignment (standard deviation of the off-diagonal terms) [rad].
    """

    gyro_bias_max: float = 0.1
    accel_bias_max: float = 0.2
    vibration: Vibration | None = Vibration()
    scale_sigma: float = 0.0
    misalign_sigma: float = 0.0


#: The errors a realistic flight sequence gets (rotors on from the first sample).
FLIGHT_IMU = ImuErrors()
#: Hand-held: no rotors.
HANDHELD_IMU = ImuErrors(vibration=None)


def _resonator(n: int, dt: float, f0: float, bw: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance narrow-band noise (AR(2) resonator at ``f0`` Hz, width ``bw`` Hz): (n,) float64."""
    from scipy.signal import lfilter

    r = np.exp(-np.pi * bw * dt)
    a1, a2 = -2.0 * r * np.cos(2.0 * np.pi * f0 * dt), r * r
    var = (1.0 + a2) / ((1.0 - a2) * ((1.0 + a2) ** 2 - a1 * a1))  # stationary variance for unit drive
    burn = int(np.ceil(5.0 / (np.pi * bw * dt)))  # transients decay by e^-5
    e = rng.standard_normal(n + burn)
    return lfilter([1.0], [1.0, a1, a2], e)[burn:] / np.sqrt(var)


def rotor_vibration(n: int, dt: float, rng: np.random.Generator, vib: Vibration) -> tuple[np.ndarray, np.ndarray]:
    """Gyro and accelerometer vibration (n, 3) each [rad/s, m/s^2]: narrow bands plus a white floor.

    Each axis of each sensor gets its own independent bands with the shares of ``vib``; a band above the
    Nyquist frequency ``1 / (2 dt)`` is folded into the floor.
    """
    out = []
    for std in (vib.gyro_std, vib.accel_std):
        x = np.zeros((n, 3))
        for ax in range(3):
            floor = 1.0
            for f0, bw, share in zip(vib.peaks_hz, vib.bandwidth_hz, vib.peak_share, strict=True):
                if f0 < 0.5 / dt - bw:
                    x[:, ax] += np.sqrt(share) * _resonator(n, dt, f0, bw, rng)
                    floor -= share
            x[:, ax] += np.sqrt(max(floor, 0.0)) * rng.standard_normal(n)
            x[:, ax] *= std[ax]
        out.append(x)
    return out[0], out[1]


def instantaneous_imu(pose_fn, t: np.ndarray, h: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Instantaneous angular rate and specific force of a smooth body trajectory.

    Args:
        pose_fn: ``t (N,) -> (R_w_b (N, 3, 3), p_w_b (N, 3))``, smooth in t.
        t: (N,) sample times [s].
        h: finite-difference step [s] (4th order in h for the acceleration, 2nd order for the rate).

    Returns:
        ``(gyro, accel)``: (N, 3) body-frame rate [rad/s] and specific force ``R^T (a_w - g_w)`` [m/s^2].
    """
    t = np.asarray(t, dtype=np.float64)
    R_m, _ = pose_fn(t - h)
    R_p, _ = pose_fn(t + h)
    R_0, p0 = pose_fn(t)
    R_0t = np.swapaxes(R_0, -1, -2)
    gyro = (so3_log_batch(R_0t @ R_p) - so3_log_batch(R_0t @ R_m)) / (2.0 * h)  # body frame at t, O(h^2)
    p = {k: pose_fn(t + k * h)[1] for k in (-2, -1, 1, 2)}
    a_w = (-p[2] + 16.0 * p[1] - 30.0 * p0 + 16.0 * p[-1] - p[-2]) / (12.0 * h * h)
    accel = np.einsum("nji,nj->ni", R_0, a_w - GRAVITY_W)
    return gyro, accel


def add_imu_errors(
    gyro: np.ndarray,
    accel: np.ndarray,
    dt: float,
    rng: np.random.Generator,
    noise: ImuNoise = EUROC_ADIS16448,
    errors: ImuErrors = FLIGHT_IMU,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Measured samples of a real IMU: scale / misalignment, turn-on bias + random walk, vibration, white noise.

    ``meas = M true + b + vibration + white``; ``M = I + diag(scale) + misalignment`` (identity by default).
    The returned biases are what a ground truth would hold (vibration is not a bias).

    Returns:
        ``(gyro_meas, accel_meas, bg, ba)``: (N, 3) each.
    """
    n = gyro.shape[0]
    mats = []
    for _ in range(2):
        M = np.eye(3)
        if errors.scale_sigma > 0:
            M += np.diag(rng.normal(0.0, errors.scale_sigma, 3))
        if errors.misalign_sigma > 0:
            off = rng.normal(0.0, errors.misalign_sigma, (3, 3))
            M += off - np.diag(np.diag(off))
        mats.append(M)
    bg0 = rng.uniform(-errors.gyro_bias_max, errors.gyro_bias_max, 3)
    ba0 = rng.uniform(-errors.accel_bias_max, errors.accel_bias_max, 3)
    steps_g = noise.gyro_random_walk * np.sqrt(dt) * rng.standard_normal((n, 3))
    steps_a = noise.accel_random_walk * np.sqrt(dt) * rng.standard_normal((n, 3))
    steps_g[0] = steps_a[0] = 0.0
    bg = bg0 + np.cumsum(steps_g, axis=0)
    ba = ba0 + np.cumsum(steps_a, axis=0)
    if errors.vibration is not None:
        vg, va = rotor_vibration(n, dt, rng, errors.vibration)
    else:
        vg = va = np.zeros((n, 3))
    wg = noise.gyro_noise_density / np.sqrt(dt) * rng.standard_normal((n, 3))
    wa = noise.accel_noise_density / np.sqrt(dt) * rng.standard_normal((n, 3))
    g = gyro @ mats[0].T + bg + vg + wg
    a = accel @ mats[1].T + ba + va + wa
    return g, a, bg, ba
