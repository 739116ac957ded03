"""Static visual-inertial initialisation: gravity direction and gyroscope bias from a still period.

While the sensor rests, the accelerometer measures ``f_b = -R_w_b^T g_w`` (plus bias and noise) and the
gyroscope measures its bias. Averaging over about one second gives roll and pitch of ``R_w_b`` (yaw is
unobservable and set to 0), the gyroscope bias, and the accelerometer bias along gravity (its other components
are unobservable while still and set to 0). Velocity is zero and the position is the origin.

The sensor counts as still when the IMU samples of the last ``still_duration_s`` have small spread and the
tracked image features (when given) have not moved. If the sequence starts moving, this is reported once,
clearly, and initialisation keeps waiting for a still period (dynamic initialisation is not implemented).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from runtime.geometry import GRAVITY, ns_to_s

log = logging.getLogger(__name__)


@dataclass
class InitConfig:
    """Thresholds of the static initialisation."""

    still_duration_s: float = 1.0  # how long the sensor must rest
    gyro_std_max: float = 0.02  # rad/s, per-axis standard deviation over the window
    accel_std_max: float = 0.15  # m/s^2, per-axis standard deviation over the window
    gravity_tol: float = 0.5  # m/s^2, | |mean f| - g | bound
    flow_max_px: float = 1.0  # median feature displacement over the window (when features are given)
    report_after_s: float = 1.5  # report "not still" once this long after the first sample


@dataclass
class InitResult:
    """Initial state at time ``ts`` (ns)."""

    ts: int
    R_w_b: np.ndarray  # (3, 3)
    p_w: np.ndarray  # (3,)
    v_w: np.ndarray  # (3,)
    bias: np.ndarray  # (6,) [ba, bg] (GTSAM order)
    gyro_std: float  # rad/s over the window
    accel_std: float  # m/s^2 over the window

    @property
    def T_w_b(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R_w_b
        T[:3, 3] = self.p_w
        return T


def gravity_aligned_rotation(f_b: np.ndarray) -> np.ndarray:
    """``R_w_b`` with zero yaw whose world z axis is along the mean specific force ``f_b`` (3,) (up at rest).

    The result maps ``f_b / |f_b|`` to ``(0, 0, 1)``; among such rotations it is the one whose body x axis,
    projected on the horizontal plane, points along world x (yaw 0), or the minimal rotation if x is vertical.
    """
    z_b = np.asarray(f_b, dtype=np.float64)
    n = np.linalg.norm(z_b)
    if not np.isfinite(n) or n < 1e-6:
        raise ValueError(f"specific force {f_b} has no direction")
    z_b = z_b / n  # world z expressed in body
    x_b = np.array([1.0, 0.0, 0.0]) - z_b[0] * z_b  # body x minus its vertical part
    if np.linalg.norm(x_b) < 1e-3:
        x_b = np.array([0.0, 1.0, 0.0]) - z_b[1] * z_b
    x_b /= np.linalg.norm(x_b)
    y_b = np.cross(z_b, x_b)
    R_b_w = np.stack([x_b, y_b, z_b], 1)  # columns: world axes in body
    return R_b_w.T


class StaticInitializer:
    """Feed IMU windows (and optionally feature motion); gives an :class:`InitResult` once still for long."""

    def __init__(self, cfg: InitConfig | None = None, gravity: float = GRAVITY) -> None:
        self.cfg = cfg or InitConfig()
        self.gravity = gravity
        self.reported_moving = False
        self.t_first: int | None = None
        self.still_since: int | None = None
        self.last_stats: dict = {}

    def reset(self) -> None:
        self.still_since = None

    def check(
        self,
        ts_now: int,
        imu_ts: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
        flow_px: float | None = None,
    ) -> InitResult | None:
        """Decide at time ``ts_now`` from the IMU samples of the last ``still_duration_s``.

        Args:
            ts_now: ns, current camera time.
            imu_ts, gyro, accel: samples with ``ts_now - still_duration <= imu_ts < ts_now`` (body frame).
            flow_px: median displacement [px] of tracked features across the same window (None: IMU only).

        Returns:
            The initial state at ``ts_now`` when the window is still, else None.
        """
        c = self.cfg
        if self.t_first is None:
            self.t_first = int(imu_ts[0]) if imu_ts.size else ts_now
        span = ns_to_s(imu_ts[-1] - imu_ts[0]) if imu_ts.size > 1 else 0.0
        if imu_ts.size < 10 or span < 0.9 * c.still_duration_s:
            return None
        g_std = float(np.max(np.std(gyro, axis=0)))
        a_std = float(np.max(np.std(accel, axis=0)))
        f_mean = accel.mean(0)
        g_err = abs(float(np.linalg.norm(f_mean)) - self.gravity)
        still = g_std < c.gyro_std_max and a_std < c.accel_std_max and g_err < c.gravity_tol
        if flow_px is not None:
            still = still and flow_px < c.flow_max_px
        self.last_stats = {"gyro_std": g_std, "accel_std": a_std, "gravity_err": g_err, "flow_px": flow_px}
        if not still:
            if not self.reported_moving and ns_to_s(ts_now - self.t_first) >= c.report_after_s:
                self.reported_moving = True
                log.warning(
                    "t=%.3f s: the sequence is not still (gyro std %.4f rad/s, accel std %.3f m/s^2, "
                    "|g| error "
                    "%.3f m/s^2, flow %s px); static initialisation needs %.1f s at rest and keeps waiting "
                    "(dynamic initialisation is not implemented)",
                    ns_to_s(ts_now),
                    g_std,
                    a_std,
                    g_err,
                    "n/a" if flow_px is None else f"{flow_px:.2f}",
                    c.still_duration_s,
                )
            return None
        R_w_b = gravity_aligned_rotation(f_mean)
        bg = gyro.mean(0)
        n = f_mean / np.linalg.norm(f_mean)
        ba = (np.linalg.norm(f_mean) - self.gravity) * n  # only the component along gravity is observable
        return InitResult(
            ts=int(ts_now),
            R_w_b=R_w_b,
            p_w=np.zeros(3),
            v_w=np.zeros(3),
            bias=np.concatenate([ba, bg]),
            gyro_std=g_std,
            accel_std=a_std,
        )
