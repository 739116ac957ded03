"""Realistic IMU errors: rotor vibration level and spectrum, instantaneous samples, turn-on biases."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import welch

from runtime.geometry import GRAVITY_W, so3_exp
from sim.imu import FLIGHT_IMU, ImuErrors, Vibration, add_imu_errors, instantaneous_imu, rotor_vibration


def test_vibration_level_and_peaks():
    vib = Vibration()
    rng = np.random.default_rng(0)
    g, a = rotor_vibration(200 * 60, 0.005, rng, vib)
    np.testing.assert_allclose(g.std(0), vib.gyro_std, rtol=0.1)
    np.testing.assert_allclose(a.std(0), vib.accel_std, rtol=0.1)
    f, p = welch(a[:, 0], fs=200.0, nperseg=512)
    for f0 in vib.peaks_hz:  # the bands stand well above the floor
        band = np.abs(f - f0) < 1.0
        floor = (np.abs(f - f0) > 8.0) & (f > 5) & (f < 95)
        assert p[band].max() > 5 * np.median(p[floor])
    assert np.all(np.abs(g.mean(0)) < 0.1 * np.asarray(vib.gyro_std))  # zero mean


def test_instantaneous_imu_constant_twist():
    """Body spinning at w about its z axis while going round a circle: rate and specific force known."""
    w, r = 0.8, 1.5

    def pose(t):
        R = np.stack([so3_exp(np.array([0.0, 0.0, w * ti])) for ti in t])
        p = np.stack([r * np.cos(w * t), r * np.sin(w * t), np.zeros_like(t)], -1)
        return R, p

    t = np.linspace(0.0, 3.0, 7)
    gyro, accel = instantaneous_imu(pose, t)
    np.testing.assert_allclose(gyro, np.tile([0.0, 0.0, w], (7, 1)), atol=1e-7)
    # centripetal acceleration -w^2 r towards the centre: in the body frame (rotating with the radius) -x
    np.testing.assert_allclose(accel, np.tile([-w * w * r, 0.0, -GRAVITY_W[2]], (7, 1)), atol=1e-5)


def test_turn_on_bias_and_errors():
    n, dt = 2000, 0.005
    zeros = np.zeros((n, 3))
    g, a, bg, ba = add_imu_errors(zeros, zeros, dt, np.random.default_rng(1), errors=FLIGHT_IMU)
    assert np.all(np.abs(bg[0]) <= 0.1) and np.all(np.abs(ba[0]) <= 0.2)
    assert np.abs(bg[0]).max() > 0.01  # realistic magnitudes, not the old 2e-3 spread
    np.testing.assert_allclose((g - bg).std(0), Vibration().gyro_std, rtol=0.2)
    # scale errors act on the true signal
    true = np.tile([0.0, 0.0, 9.81], (n, 1))
    err = ImuErrors(vibration=None, gyro_bias_max=0.0, accel_bias_max=0.0, scale_sigma=0.01)
    _, a2, _, ba2 = add_imu_errors(zeros, true, dt, np.random.default_rng(2), errors=err)
    scale = np.mean(a2[:, 2] - ba2[:, 2]) / 9.81
    assert scale != pytest.approx(1.0, abs=1e-4) and abs(scale - 1.0) < 0.05
