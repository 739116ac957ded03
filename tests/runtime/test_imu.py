"""IMU stream, preintegration parameters and propagation against exact synthetic motion."""

import logging

import gtsam
import numpy as np
import pytest

from runtime.backend.imu import (
    ImuNoiseConfig,
    ImuStream,
    integrate,
    integrate_rotation,
    make_bias,
    preintegration_params,
    propagate,
)
from runtime.geometry import pose_error, so3_log
from tests.runtime.synth import ImuNoise, Motion, make_imu


@pytest.fixture(scope="module")
def motion_imu():
    m = Motion(seed=3, t_rest=0.5, t_ramp=0.5)
    ts, g, a = make_imu(m, 4.0, t0_ns=0)
    return m, ImuStream(ts, g, a, 200.0)


def test_numpy_and_gtsam_propagation_match_ground_truth_on_noiseless_data(motion_imu):
    m, imu = motion_imu
    t0, t1 = 1.5, 2.5  # 1 s of motion, several tenths of a metre and rad
    T0 = m.body(t0)[0]
    v0 = m.velocity(t0)[0]
    T1 = m.body(t1)[0]
    v1 = m.velocity(t1)[0]
    g, a, dt = imu.segment(int(t0 * 1e9), int(t1 * 1e9))
    assert dt.sum() == pytest.approx(t1 - t0, abs=1e-12)
    R, p, v = propagate(T0[:3, :3], T0[:3, 3], v0, g, a, dt)
    assert np.linalg.norm(T1[:3, 3] - T0[:3, 3]) > 0.2  # the motion is not trivial
    assert np.linalg.norm(p - T1[:3, 3]) < 1e-3  # m
    assert np.degrees(np.linalg.norm(so3_log(R.T @ T1[:3, :3]))) < 0.01
    assert np.linalg.norm(v - v1) < 2e-3
    pim = gtsam.PreintegratedCombinedMeasurements(preintegration_params(ImuNoise()), make_bias(np.zeros(6)))
    integrate(pim, g, a, dt)
    nav = pim.predict(gtsam.NavState(gtsam.Pose3(T0), v0), make_bias(np.zeros(6)))
    dp, dr = pose_error(nav.pose().matrix(), T1)
    assert dp < 1e-3 and np.degrees(dr) < 0.01
    assert np.linalg.norm(nav.velocity() - v1) < 2e-3


def test_rotation_integration_matches_relative_rotation(motion_imu):
    m, imu = motion_imu
    g, _, dt = imu.segment(int(1.2e9), int(1.25e9))
    R = integrate_rotation(g, dt)
    R_true = m.body(1.2)[0][:3, :3].T @ m.body(1.25)[0][:3, :3]
    assert np.linalg.norm(so3_log(R.T @ R_true)) < 1e-6


def test_segment_zero_order_hold_pieces():
    ts = np.array([0, 5, 10, 15, 20], dtype=np.int64) * 1_000_000
    gyro = np.arange(15, dtype=float).reshape(5, 3)
    imu = ImuStream(ts, gyro, gyro + 100, 200.0)
    g, a, dt = imu.segment(7_000_000, 16_000_000)  # [7, 10) uses sample 1, [10, 15) sample 2, [15, 16) sample 3
    assert np.allclose(dt, [0.003, 0.005, 0.001])
    assert np.allclose(g[:, 0], [3, 6, 9])
    assert np.allclose(a[:, 0], [103, 106, 109])
    g, a, dt = imu.segment(7_000_000, 7_000_000)
    assert dt.size == 0


def test_nan_rows_are_dropped_and_gaps_reported(caplog):
    ts = np.arange(0, 400, dtype=np.int64) * 5_000_000
    gyro = np.zeros((400, 3))
    acc = np.tile([0.0, 0.0, 9.81], (400, 1))
    gyro[10] = np.nan
    keep = np.ones(400, bool)
    keep[100:200] = False  # 0.5 s gap
    with caplog.at_level(logging.WARNING):
        imu = ImuStream(ts[keep], gyro[keep], acc[keep], 200.0)
    assert imu.dropped_ts.tolist() == [ts[10]]
    assert len(imu.gaps) == 1 and imu.gaps[0] == (int(ts[99]), int(ts[200]))
    assert "non-finite" in caplog.text and "gap of 0.505 s" in caplog.text
    assert imu.gap_in(int(ts[90]), int(ts[210])) == pytest.approx(0.505)
    g, a, dt = imu.segment(int(ts[90]), int(ts[210]))  # integration goes on across the gap
    assert dt.sum() == pytest.approx(0.6) and np.isfinite(g).all()


def test_bad_inputs_raise_naming_the_value():
    with pytest.raises(ValueError, match="not strictly increasing"):
        ImuStream(np.array([0, 5, 5]), np.zeros((3, 3)), np.zeros((3, 3)), 200.0)
    with pytest.raises(ValueError, match="rate_hz"):
        ImuStream(np.array([0, 5]), np.zeros((2, 3)), np.zeros((2, 3)), 0.0)

    class Bad(ImuNoise):
        pass

    bad = Bad()
    bad.accel_random_walk = -1.0
    with pytest.raises(ValueError, match="accel_random_walk"):
        preintegration_params(bad)


def test_preintegration_params_are_densities_squared():
    p = preintegration_params(ImuNoise(), ImuNoiseConfig(noise_scale=2.0))
    assert np.allclose(p.getGyroscopeCovariance(), (2 * 1.6968e-4) ** 2 * np.eye(3))
    assert np.allclose(p.getBiasAccCovariance(), 3.0e-3**2 * np.eye(3))
    assert np.allclose(p.n_gravity, [0, 0, -9.81])


def test_backward_propagation_inverts_forward():
    from runtime.backend.imu import propagate
    from runtime.geometry import so3_exp

    rng = np.random.default_rng(0)
    gyro, acc, dt = rng.normal(0, 0.5, (40, 3)), rng.normal(0, 2.0, (40, 3)) + [0, 0, 9.81], np.full(40, 0.005)
    R0, p0, v0 = so3_exp(np.array([0.1, 0.2, -0.3])), np.array([1.0, 2.0, 3.0]), np.array([0.5, -0.2, 0.1])
    bg, ba = np.array([0.01, 0.0, -0.02]), np.array([0.05, -0.03, 0.02])
    R1, p1, v1 = propagate(R0, p0, v0, gyro, acc, dt, bg=bg, ba=ba)
    R, p, v = propagate(R1, p1, v1, gyro, acc, dt, bg=bg, ba=ba, backward=True)
    assert np.allclose(R, R0, atol=1e-12) and np.allclose(p, p0, atol=1e-10) and np.allclose(v, v0, atol=1e-10)
