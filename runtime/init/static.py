"""Static visual-inertial initialisation: gravity direction and gyroscope bias from a period at rest.

While the sensor rests, the accelerometer measures ``f_b = -R_w_b^T g_w`` (plus bias, noise and vibration) and
the gyroscope its bias. Averaging over about one second gives roll and pitch of ``R_w_b`` (yaw is unobservable
and set to 0), the gyroscope bias, and the accelerometer bias along gravity (its other components are
unobservable at rest and set to 0). Velocity is zero and the position is the origin.

The rule for "at rest" (:func:`imu_rest_stats`, used by the initialiser and by the zero-velocity test of the
running system) is the one of OpenVINS and ORB-SLAM3: image motion first, the IMU second.

* The tracked features have not moved: median displacement over the window below ``flow_max_px`` (1 px).
  Frames that do not yet cover the window (just after a restart), or tracks that do not survive it, count as
  motion (:meth:`runtime.init.runner.InitRunner._flow`); only a view with too few tracks leaves it to the IMU.
* The IMU's *low-frequency* content is quiet. Rotor vibration (tens to hundreds of Hz) is far above any
  motion's band, so the samples are averaged in blocks of ``block_s`` (50 ms) and the spread of the block means
  is tested: below ``gyro_std_max`` (0.03 rad/s) and ``accel_std_max`` (0.3 m/s^2) per axis, and
  ``| |mean f| - g |`` below ``gravity_tol`` (0.5 m/s^2). A raw-sample test cannot work on a MAV: at rest
  with its rotors on, EuRoC-like vibration gives a raw gyro std of 0.04 rad/s and a raw accel std of
  0.5 m/s^2, the same as flight; the block means give 0.008-0.013 rad/s and 0.11-0.17 m/s^2 at rest against
  0.10-0.18 rad/s and 0.37-0.61 m/s^2 in flight (simulated ``flight`` preset and MH_05 excerpt, 1 s windows).

The measured noise level (from the samples' second differences, :func:`_white_sigma`) is reported with the
result: the system raises the IMU noise densities to it when the sensor is noisier than its ``sensor.yaml`` says.

When the IMU decides alone (a view with nothing to track), passing those thresholds is not enough: an IMU cannot
tell constant velocity from rest, and slow motion can stay under them (a hand-held camera gliding at 0.15-0.41 m/s
did, ``handheld`` seed 188, and its start diverged). Its slow content must then be at its noise level: the block
means' spread at most ``imu_alone_ratio_max`` (2.0) times what white noise of the measured level gives them
(``sigma / sqrt(samples per block)``). Measured on 1 s windows: at rest 0.7-1.4 (MAV vibration: simulated
``flight`` and the MH_05 excerpt with a still period), under 1.8 for white noise; moving windows that pass the
thresholds 10.6 or more on ``handheld``, 3.0 or more on ``tabletop``. Under rotor vibration the test is weaker: on
``flight`` 36 of 119 such moving windows pass it too, on ``whitewall`` 66 of 75. (Refusing every IMU-only start
instead cost 4-72 mm on a bare view at rest, which must then wait for motion; reports/ablations.md.)

When the rule fails for ``report_after_s`` the sequence is reported as starting in motion, once, and the
dynamic initialiser (:mod:`runtime.init.dynamic`) takes over.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from runtime.geometry import GRAVITY, ns_to_s

log = logging.getLogger(__name__)


@dataclass
class InitConfig:
    """Thresholds of the static initialisation (see the module doc for the rule)."""

    still_duration_s: float = 1.0  # how long the sensor must rest
    block_s: float = 0.05  # s, IMU samples averaged per block (longer than the vibration's period)
    gyro_std_max: float = 0.03  # rad/s, per-axis spread of the block means over the window
    accel_std_max: float = 0.3  # m/s^2, per-axis spread of the block means over the window
    gravity_tol: float = 0.5  # m/s^2, | |mean f| - g | bound
    flow_max_px: float = 1.0  # median feature displacement over the window (when features are given)
    imu_alone_ratio_max: float = 2.0  # without image evidence: block-mean spread over its white-noise level
    report_after_s: float = 1.5  # report "not still" once this long after the first sample


@dataclass
class RestStats:
    """Low-frequency spread and noise level of an IMU window (see :func:`imu_rest_stats`)."""

    gyro_std: float  # rad/s, largest per-axis spread of the block means
    accel_std: float  # m/s^2
    gravity_err: float  # m/s^2, | |mean f| - g |
    gyro_noise: float  # rad/s, per-sample noise (white noise + vibration) from the second differences
    accel_noise: float  # m/s^2
    gyro_ratio: float  # gyro_std over what white noise of level gyro_noise gives the block means (1 at rest)
    accel_ratio: float  # the same for the accelerometer


def _white_sigma(x: np.ndarray) -> float:
    """Per-sample sigma of white noise on samples ``x`` (K, 3), K >= 3: RMS second difference over sqrt(6)."""
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return float(np.sqrt(np.mean(d2**2) / 6.0))


def imu_rest_stats(ts: np.ndarray, gyro: np.ndarray, accel: np.ndarray, block_s: float, gravity: float) -> RestStats:
    """Statistics of the samples ``ts`` (ns), ``gyro``, ``accel`` (K, 3) for the rest test.

    The samples are cut into blocks of ``block_s`` (at least 2 samples each); the spread of the block means
    measures motion. The noise level is the RMS of the samples' second differences over sqrt(6), the sigma of white
    noise: motion, smooth at the IMU's rate, drops out of them. So does vibration far below the Nyquist rate (a band
    at f keeps 16 sin^4(pi f / rate) / 6 of its variance: 1 % at 17 Hz, 170 % at 71 Hz for 200 Hz). (The spread about
    the block means, used before, counted the motion inside a block: x4.3 on an exact gyro turning in place;
    reports/ablations.md.)
    """
    k = gyro.shape[0]
    span = ns_to_s(ts[-1] - ts[0]) if k > 1 else 0.0
    rate = (k - 1) / span if span > 0 else 1.0
    n = max(2, int(round(block_s * rate)))
    nb = k // n
    if nb < 2:
        raise ValueError(f"{k} IMU samples: fewer than 2 blocks of {n}")
    g = gyro[: nb * n].reshape(nb, n, 3)
    a = accel[: nb * n].reshape(nb, n, 3)
    gm, am = g.mean(1), a.mean(1)
    g_std, a_std = float(np.max(gm.std(0))), float(np.max(am.std(0)))
    g_noise, a_noise = _white_sigma(gyro), _white_sigma(accel)
    return RestStats(
        gyro_std=g_std,
        accel_std=a_std,
        gravity_err=abs(float(np.linalg.norm(accel.mean(0))) - gravity),
        gyro_noise=g_noise,
        accel_noise=a_noise,
        gyro_ratio=g_std / max(g_noise / np.sqrt(n), 1e-12),
        accel_ratio=a_std / max(a_noise / np.sqrt(n), 1e-12),
    )


@dataclass
class InitResult:
    """Initial state at time ``ts`` (ns)."""

    ts: int
    R_w_b: np.ndarray  # (3, 3)
    p_w: np.ndarray  # (3,)
    v_w: np.ndarray  # (3,)
    bias: np.ndarray  # (6,) [ba, bg] (GTSAM order)
    method: str = "static"  # static | dynamic
    info: dict = field(default_factory=dict)  # how it was decided (for metrics.json and the log)
    noise: tuple[float, float] | None = None  # measured per-sample gyro [rad/s] and accel [m/s^2] noise level

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
            flow_px: median displacement [px] of tracked features across the same window (None: IMU only;
                inf: the images show motion).

        Returns:
            The initial state at ``ts_now`` when the window is still, else None.
        """
        c = self.cfg
        if self.t_first is None:
            self.t_first = int(imu_ts[0]) if imu_ts.size else ts_now
        span = ns_to_s(imu_ts[-1] - imu_ts[0]) if imu_ts.size > 1 else 0.0
        if imu_ts.size < 10 or span < 0.9 * c.still_duration_s:
            return None
        st = imu_rest_stats(imu_ts, gyro, accel, c.block_s, self.gravity)
        still = st.gyro_std < c.gyro_std_max and st.accel_std < c.accel_std_max and st.gravity_err < c.gravity_tol
        noise_ratio = max(st.gyro_ratio, st.accel_ratio)
        if flow_px is not None:
            still = still and flow_px < c.flow_max_px
        else:  # the IMU decides alone: its slow content must be at its noise level, not only below the thresholds
            still = still and noise_ratio < c.imu_alone_ratio_max
        self.last_stats = {
            "gyro_std": st.gyro_std,
            "accel_std": st.accel_std,
            "gravity_err": st.gravity_err,
            "flow_px": flow_px,
            "noise_ratio": noise_ratio,
        }
        if not still:
            if not self.reported_moving and ns_to_s(ts_now - self.t_first) >= c.report_after_s:
                self.reported_moving = True
                log.warning(
                    "t=%.3f s: the sequence is not at rest (low-frequency gyro spread %.4f rad/s, accel spread "
                    "%.3f m/s^2, |g| error %.3f m/s^2, flow %s px): initialising in motion",
                    ns_to_s(ts_now),
                    st.gyro_std,
                    st.accel_std,
                    st.gravity_err,
                    "n/a" if flow_px is None else f"{flow_px:.2f}",
                )
            return None
        f_mean = accel.mean(0)
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
            info={k: (None if v is None else round(float(v), 5)) for k, v in self.last_stats.items()},
            noise=(st.gyro_noise, st.accel_noise),
        )
