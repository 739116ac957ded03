"""Trajectories and IMU synthesis: MAV-like bounds, rest, clearance, smoothness, exact discrete kinematics."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.geometry import GRAVITY_W, so3_exp
from sim.euroc import EUROC_T_B_C0, simulate_sequence
from sim.imu import so3_log_batch, synthesize_imu
from sim.trajectory import smooth_step, whitewall_min_duration


@pytest.mark.parametrize(
    "preset,duration,seed", [("textured", 40.0, 0), ("textured", 40.0, 7), ("whitewall", 30.0, 3)]
)
def test_mav_like_bounds_and_clearance(preset, duration, seed):
    d = simulate_sequence(preset, duration, seed, imu_noise=False)
    speed = np.linalg.norm(d.v_w, axis=1)
    rate = np.linalg.norm(d.gyro, axis=1)
    moving = slice(int(5.0 / 0.005), None)  # after rest + ramp
    assert speed.max() <= 1.05 and rate.max() <= 1.05
    assert speed[moving].mean() > 0.2 and rate.max() > 0.1
    # the camera never comes closer than 0.5 m to a surface (never inside a box)
    T_w_c = d.T_w_b(np.arange(len(d.ts))) @ EUROC_T_B_C0
    p_c = T_w_c[:, :3, 3]
    assert not d.scene.inside_box(p_c).any()
    assert d.scene.min_distance(p_c).min() >= 0.5 - 1e-9
    assert np.all(p_c > d.scene.lo[0]) and np.all(p_c < d.scene.hi[0])
    # looking roughly horizontally: optical axis within ~25 deg of the horizontal plane, small roll
    z_c = T_w_c[:, :3, 2]
    assert np.degrees(np.abs(np.arcsin(z_c[:, 2]))).max() < 25
    x_c = T_w_c[:, :3, 0]
    assert np.degrees(np.abs(np.arcsin(x_c[:, 2]))).max() < 15


def test_discrete_states_follow_smooth_path_and_are_c2():
    d = simulate_sequence("textured", 20.0, 5, imu_noise=False)
    t = np.arange(len(d.ts)) * 0.005
    _, p_smooth = d.trajectory.body_pose(t, EUROC_T_B_C0)
    assert np.abs(d.p_w_b - p_smooth).max() < 1e-5  # trapezoid GT stays within 10 um of the smooth path
    # C2: accelerometer (specific force) and gyro change smoothly between samples (bounded jerk)
    assert np.abs(np.diff(d.accel, axis=0)).max() < 0.05
    assert np.abs(np.diff(d.gyro, axis=0)).max() < 0.01


def test_synthesize_imu_known_answer():
    """Constant yaw rate and constant world acceleration: gyro = rate, accel = R^T (a - g) exactly."""
    dt, n, w = 0.005, 50, 0.3
    t = np.arange(n + 1) * dt
    R = so3_exp(np.stack([np.zeros_like(t), np.zeros_like(t), w * t], -1))
    a_w = np.array([0.2, -0.1, 0.05])
    v = t[:, None] * a_w
    gyro, accel, p = synthesize_imu(R, v, np.zeros(3), dt)
    np.testing.assert_allclose(gyro, np.tile([0.0, 0.0, w], (n, 1)), atol=1e-12)
    expect = np.einsum("nji,j->ni", R[:-1], a_w - GRAVITY_W)
    np.testing.assert_allclose(accel, expect, atol=1e-12)
    np.testing.assert_allclose(p, 0.5 * t[:, None] ** 2 * a_w, atol=1e-14)  # trapezoid exact for linear v


def test_so3_log_batch_inverts_exp():
    rng = np.random.default_rng(0)
    w = rng.normal(0, 0.5, (20, 3))
    w[0] = 0.0
    w[1] = [1e-9, 0, 0]
    np.testing.assert_allclose(so3_log_batch(so3_exp(w)), w, atol=1e-12)


def test_smooth_step_and_whitewall_duration_check():
    np.testing.assert_allclose(smooth_step(np.array([-1.0, 0.0, 0.5, 1.0, 2.0])), [0, 0, 0.5, 1, 1])
    with pytest.raises(ValueError, match="whitewall.*duration"):
        simulate_sequence("whitewall", whitewall_min_duration() - 1.0, 0, imu_noise=False)
    with pytest.raises(ValueError, match="preset"):
        simulate_sequence("dark", 5.0, 0)
    with pytest.raises(ValueError, match="duration"):
        simulate_sequence("textured", -1.0, 0)
