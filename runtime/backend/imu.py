"""IMU handling: cleaned sample stream, zero-order-hold segments, GTSAM preintegration, numpy propagation.

Frames: samples are expressed in the body frame ``b`` (the IMU frame; EuRoC's imu0 ``T_BS`` is the identity,
any other ``T_b_s`` rotates the samples into ``b``). The gyroscope gives ``omega_b`` [rad/s], the
accelerometer
the specific force ``f_b = R_w_b^T (a_w - g_w)`` [m/s^2]. World ``w`` is z up with ``g_w = (0, 0, -9.81)``.

Integration convention (GTSAM's and the simulator's): sample ``k`` holds over ``[t_k, t_{k+1})``
(zero-order hold); a frame interval ``[t0, t1)`` is cut at every sample time inside it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from runtime.geometry import GRAVITY, GRAVITY_W, ns_to_s, so3_exp

log = logging.getLogger(__name__)


@dataclass
class ImuNoiseConfig:
    """Multipliers applied to the sensor.yaml densities (1.0 = as calibrated).

    Real datasets usually need the random walks inflated (unmodelled temperature drift, vibration);
    the simulator is exact, so 1.0 is right there.
    """

    noise_scale: float = 1.0  # white-noise densities (gyro, accel); the floor when adapt_noise is on
    walk_scale: float = 1.0  # bias random walks
    integration_sigma: float = 1e-4  # [m/s^2 * sqrt(s)... ] position integration noise (GTSAM's integrationCovariance)
    gravity: float = GRAVITY
    gap_factor: float = 4.0  # an interval longer than gap_factor / rate is logged as a gap
    adapt_noise: bool = True  # raise the white-noise densities to the level measured at initialisation
    max_noise_scale: float = 5.0  # bound on that raise (raw spread overstates narrow-band vibration's effect)


def preintegration_params(imu, cfg: ImuNoiseConfig | None = None, scales: tuple[float, float] | None = None):
    """``gtsam.PreintegrationCombinedParams`` from the io ``ImuParams`` (continuous-time densities).

    Args:
        imu: object with ``gyro_noise_density`` [rad/s/sqrt(Hz)], ``gyro_random_walk`` [rad/s^2/sqrt(Hz)],
            ``accel_noise_density`` [m/s^2/sqrt(Hz)], ``accel_random_walk`` [m/s^3/sqrt(Hz)].
        cfg: noise multipliers.
        scales: (gyro, accel) white-noise multipliers in place of ``cfg.noise_scale`` (e.g. measured).

    Returns:
        Parameters with gravity ``(0, 0, -g)`` (``MakeSharedU``); covariances are densities squared (GTSAM
        divides
        by dt itself).
    """
    import gtsam

    cfg = cfg or ImuNoiseConfig()
    for name in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density", "accel_random_walk"):
        val = float(getattr(imu, name))
        if not np.isfinite(val) or val <= 0:
            raise ValueError(f"IMU parameter {name}={val!r} must be a positive finite number")
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(cfg.gravity)
    I3 = np.eye(3)
    sg, sa = scales if scales is not None else (cfg.noise_scale, cfg.noise_scale)
    p.setGyroscopeCovariance((sg * imu.gyro_noise_density) ** 2 * I3)
    p.setAccelerometerCovariance((sa * imu.accel_noise_density) ** 2 * I3)
    p.setIntegrationCovariance(cfg.integration_sigma**2 * I3)
    p.setBiasOmegaCovariance((cfg.walk_scale * imu.gyro_random_walk) ** 2 * I3)
    p.setBiasAccCovariance((cfg.walk_scale * imu.accel_random_walk) ** 2 * I3)
    return p


def make_bias(bias: np.ndarray):
    """6-vector ``[ba (3), bg (3)]`` (GTSAM's order: accelerometer first) -> ``imuBias.ConstantBias``."""
    import gtsam

    b = np.asarray(bias, dtype=np.float64).reshape(6)
    return gtsam.imuBias.ConstantBias(b[:3], b[3:])


class ImuStream:
    """Cleaned IMU samples in the body frame, with zero-order-hold segment extraction.

    Rows with a non-finite value are dropped (and logged with their timestamps); intervals longer than
    ``gap_factor / rate_hz`` are logged as gaps. Integration across a gap holds the last valid sample.

    Args:
        ts: (M,) int64 ns, strictly increasing.
        gyro: (M, 3) rad/s in the sensor frame s.
        accel: (M, 3) m/s^2 (specific force) in the sensor frame s.
        rate_hz: nominal sample rate.
        T_b_s: (4, 4) sensor-to-body transform (rotation used; a lever arm is ignored with a warning).
    """

    def __init__(
        self,
        ts: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        rate_hz: float,
        T_b_s: np.ndarray | None = None,
        gap_factor: float = 4.0,
    ) -> None:
        ts = np.asarray(ts, dtype=np.int64)
        gyro = np.asarray(gyro, dtype=np.float64)
        accel = np.asarray(accel, dtype=np.float64)
        if ts.ndim != 1 or gyro.shape != (ts.size, 3) or accel.shape != (ts.size, 3):
            raise ValueError(f"IMU arrays disagree: ts {ts.shape}, gyro {gyro.shape}, accel {accel.shape}")
        if not np.isfinite(rate_hz) or rate_hz <= 0:
            raise ValueError(f"IMU rate_hz={rate_hz!r} must be positive")
        good = np.isfinite(gyro).all(1) & np.isfinite(accel).all(1)
        self.dropped_ts = ts[~good]
        if self.dropped_ts.size:
            log.warning(
                "IMU: dropped %d non-finite samples (first at t=%.3f s)",
                self.dropped_ts.size,
                ns_to_s(self.dropped_ts[0]),
            )
        ts, gyro, accel = ts[good], gyro[good], accel[good]
        if ts.size < 2:
            raise ValueError(f"IMU stream has {ts.size} valid samples; at least 2 are needed")
        if np.any(np.diff(ts) <= 0):
            i = int(np.argmax(np.diff(ts) <= 0))
            raise ValueError(f"IMU timestamps not strictly increasing at row {i + 1} (t={ts[i + 1]} ns)")
        if T_b_s is not None:
            T_b_s = np.asarray(T_b_s, dtype=np.float64)
            R = T_b_s[:3, :3]
            if not np.allclose(R, np.eye(3), atol=1e-9):
                gyro = gyro @ R.T
                accel = accel @ R.T
            if np.linalg.norm(T_b_s[:3, 3]) > 1e-3:
                log.warning("IMU: T_b_s has a lever arm of %.3f m, ignored", np.linalg.norm(T_b_s[:3, 3]))
        self.ts, self.gyro, self.accel = ts, gyro, accel
        self.rate_hz = float(rate_hz)
        self.gap_ns = int(gap_factor * 1e9 / rate_hz)
        dts = np.diff(ts)
        gap_idx = np.nonzero(dts > self.gap_ns)[0]
        self.gaps = [(int(ts[i]), int(ts[i + 1])) for i in gap_idx]  # (start, end) ns
        for a, b in self.gaps[:20]:
            log.warning("IMU: gap of %.3f s at t=%.3f s (holding the last sample)", ns_to_s(b - a), ns_to_s(a))
        if len(self.gaps) > 20:
            log.warning("IMU: %d more gaps not listed", len(self.gaps) - 20)

    @classmethod
    def from_sequence(cls, seq, gap_factor: float = 4.0) -> ImuStream:
        """Build from an io ``EurocSequence`` (``imu_ts``, ``gyro``, ``accel``, ``imu``)."""
        return cls(seq.imu_ts, seq.gyro, seq.accel, seq.imu.rate_hz, getattr(seq.imu, "T_b_s", None), gap_factor)

    @property
    def t_start(self) -> int:
        return int(self.ts[0])

    @property
    def t_end(self) -> int:
        return int(self.ts[-1])

    def gap_in(self, t0: int, t1: int) -> float:
        """Longest interval [s] between consecutive samples from the last one at or before ``t0`` to the last
        one at or before ``t1``: non-zero once samples resume after a gap that overlaps ``[t0, t1]``."""
        i0 = max(int(np.searchsorted(self.ts, t0, "right")) - 1, 0)
        i1 = int(np.searchsorted(self.ts, t1, "right"))
        seg = self.ts[i0:i1]
        return float(ns_to_s(np.max(np.diff(seg)))) if seg.size > 1 else 0.0

    def segment(self, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Zero-order-hold pieces covering ``[t0, t1)``.

        Args:
            t0, t1: ns, ``t1 >= t0``.

        Returns:
            gyro (K, 3) rad/s, accel (K, 3) m/s^2, dt (K,) s with ``dt.sum() == (t1 - t0) * 1e-9``. Each piece
            uses
            the latest sample at or before its start (the first sample before the stream begins).
        """
        if t1 < t0:
            raise ValueError(f"segment end {t1} before start {t0}")
        if t1 == t0:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        i0 = int(np.searchsorted(self.ts, t0, "right"))
        i1 = int(np.searchsorted(self.ts, t1, "left"))
        knots = np.concatenate([[t0], self.ts[i0:i1], [t1]]).astype(np.int64)
        src = np.concatenate([[max(i0 - 1, 0)], np.arange(i0, i1)])
        dt = ns_to_s(np.diff(knots))
        keep = dt > 0
        return self.gyro[src][keep], self.accel[src][keep], dt[keep]

    def since_last(self, t: int) -> float:
        """Seconds from the last sample at or before ``t`` to ``t`` (inf before the first sample)."""
        i = int(np.searchsorted(self.ts, t, "right")) - 1
        return float(ns_to_s(t - self.ts[i])) if i >= 0 else float("inf")

    def window(self, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raw samples with ``t0 <= ts < t1``: (ts, gyro, accel)."""
        i0 = int(np.searchsorted(self.ts, t0, "left"))
        i1 = int(np.searchsorted(self.ts, t1, "left"))
        return self.ts[i0:i1], self.gyro[i0:i1], self.accel[i0:i1]


def integrate(pim, gyro: np.ndarray, accel: np.ndarray, dt: np.ndarray) -> None:
    """Feed ZOH pieces (from :meth:`ImuStream.segment`) into a GTSAM preintegrator (in place)."""
    for k in range(dt.shape[0]):  # ~10 samples per camera frame; GTSAM has no batch call
        pim.integrateMeasurement(accel[k], gyro[k], float(dt[k]))


def propagate(
    R_w_b: np.ndarray,
    p_w: np.ndarray,
    v_w: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    dt: np.ndarray,
    bg: np.ndarray | None = None,
    ba: np.ndarray | None = None,
    g_w: np.ndarray = GRAVITY_W,
    backward: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy strapdown integration with the same discretisation as GTSAM's preintegration.

    ``p += v dt + a dt^2 / 2``, ``v += a dt`` with ``a = R (f - ba) + g``, then ``R <- R Exp((w - bg) dt)``;
    ``backward``: the exact inverse, the state at the start of the pieces from the state at their end.

    Args:
        R_w_b: (3, 3), p_w: (3,) m, v_w: (3,) m/s: start state.
        gyro, accel: (K, 3) body-frame samples; dt: (K,) s.
        bg, ba: gyro / accel biases (3,).

    Returns:
        (R_w_b, p_w, v_w) at the end.
    """
    R = np.array(R_w_b, dtype=np.float64)
    p = np.array(p_w, dtype=np.float64)
    v = np.array(v_w, dtype=np.float64)
    bg = np.zeros(3) if bg is None else np.asarray(bg, dtype=np.float64)
    ba = np.zeros(3) if ba is None else np.asarray(ba, dtype=np.float64)
    dR = so3_exp((gyro - bg) * dt[:, None])  # (K, 3, 3)
    if backward:
        for k in range(dt.shape[0] - 1, -1, -1):
            R = R @ dR[k].T
            a = R @ (accel[k] - ba) + g_w
            v = v - a * dt[k]
            p = p - v * dt[k] - 0.5 * a * dt[k] ** 2
        return R, p, v
    for k in range(dt.shape[0]):
        a = R @ (accel[k] - ba) + g_w
        p = p + v * dt[k] + 0.5 * a * dt[k] ** 2
        v = v + a * dt[k]
        R = R @ dR[k]
    return R, p, v


def integrate_rotation(gyro: np.ndarray, dt: np.ndarray, bg: np.ndarray | None = None) -> np.ndarray:
    """``R_b0_b1`` (3, 3) from gyro pieces (K, 3) rad/s and dt (K,) s, bias-corrected."""
    bg = np.zeros(3) if bg is None else np.asarray(bg, dtype=np.float64)
    R = np.eye(3)
    for dR in so3_exp((gyro - bg) * dt[:, None]):
        R = R @ dR
    return R
