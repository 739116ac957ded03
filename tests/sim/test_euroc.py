"""EuRoC-layout sequences from sim/, read back with the independent reader runtime.io.euroc."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from runtime.geometry import inv_T, rotation_angle, transform
from runtime.io.euroc import read_euroc
from sim.euroc import EUROC_CAM0, EUROC_T_B_C0, simulate_sequence
from sim.imu import EUROC_ADIS16448
from tests.sim.conftest import MOVING


def test_layout_and_sensors(exact_seq):
    mav0 = exact_seq / "mav0"
    assert (mav0 / "cam0" / "sensor.yaml").read_text().splitlines()[0] == "%YAML:1.0"
    seq = read_euroc(exact_seq)
    cam = seq.camera
    assert (cam.width, cam.height) == (752, 480)
    assert cam.intrinsics == (458.654, 457.296, 367.215, 248.375)
    assert cam.dist == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    np.testing.assert_array_equal(seq.T_b_c, EUROC_T_B_C0)
    assert seq.cam_rate_hz == 20 and seq.imu.rate_hz == 200
    assert seq.imu.gyro_noise_density == 1.6968e-4 and seq.imu.gyro_random_walk == 1.9393e-5
    assert seq.imu.accel_noise_density == 2.0e-3 and seq.imu.accel_random_walk == 3.0e-3
    np.testing.assert_array_equal(seq.imu.T_b_s, np.eye(4))
    # one clock: 200 Hz IMU and ground truth, every 10th sample a frame (20 Hz), 4.5 s
    assert len(seq.imu_ts) == 900 and len(seq) == 90
    assert np.all(np.diff(seq.imu_ts) == 5_000_000)
    np.testing.assert_array_equal(seq.gt.ts, seq.imu_ts)
    np.testing.assert_array_equal(seq.frame_ts, seq.imu_ts[::10])
    img, depth = seq.image(10), seq.depth(10)
    assert img.dtype == np.uint8 and img.shape == (480, 752)
    assert depth.dtype == np.float32 and depth.shape == (480, 752)
    assert seq.has_depth and 0.4 < depth.min() and depth.max() < 8.0
    assert img.std() > 10  # textured, not blank
    np.testing.assert_array_equal(seq.gt.bg, 0.0)  # imu_noise=False: zero biases
    np.testing.assert_array_equal(seq.gt.ba, 0.0)


def _preintegrate(seq, i: int, j: int):
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(9.81)
    pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
    for k in range(i, j):
        dt = (seq.imu_ts[k + 1] - seq.imu_ts[k]) * 1e-9
        pim.integrateMeasurement(seq.accel[k], seq.gyro[k], dt)
    state_i = gtsam.NavState(gtsam.Pose3(seq.gt.T_w_b[i]), seq.gt.v_w[i])
    return pim.predict(state_i, gtsam.imuBias.ConstantBias())


@pytest.mark.parametrize("i", [0, MOVING[0]])
def test_gtsam_preintegration_reproduces_ground_truth(exact_seq, i):
    """Integrating 1 s of IMU with GTSAM predicts the GT state 1 s later to < 1 mm, < 0.01 deg, < 1 mm/s."""
    seq = read_euroc(exact_seq)
    j = i + 200
    if i > 0:  # a moving second, not the rest
        speed = np.linalg.norm(seq.gt.v_w[i:j], axis=1)
        assert speed.max() > 0.1
        assert rotation_angle(seq.gt.T_w_b[i][:3, :3].T @ seq.gt.T_w_b[j][:3, :3]) > np.radians(2)
    pred = _preintegrate(seq, i, j)
    T_pred = pred.pose().matrix()
    T_gt = seq.gt.T_w_b[j]
    rel_pred = inv_T(seq.gt.T_w_b[i]) @ T_pred
    rel_gt = inv_T(seq.gt.T_w_b[i]) @ T_gt
    assert np.linalg.norm(rel_pred[:3, 3] - rel_gt[:3, 3]) < 1e-3
    assert np.degrees(rotation_angle(rel_pred[:3, :3].T @ rel_gt[:3, :3])) < 0.01
    assert np.linalg.norm(pred.velocity() - seq.gt.v_w[j]) < 1e-3


@pytest.mark.parametrize("k", [70, 85])
def test_depth_reprojects_into_next_frame(exact_seq, k):
    """GT depth of frame k, moved by the GT poses and T_BS into frame k+1, matches frame k+1's depth."""
    seq = read_euroc(exact_seq)
    cam, T_b_c = seq.camera, seq.T_b_c
    d0, d1 = seq.depth(k), seq.depth(k + 1)
    T_w_c0 = seq.gt_pose_at(seq.frame_ts[k]) @ T_b_c
    T_w_c1 = seq.gt_pose_at(seq.frame_ts[k + 1]) @ T_b_c
    assert np.linalg.norm(T_w_c0[:3, 3] - T_w_c1[:3, 3]) > 5e-3  # the camera moved
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    p_c0 = cam.unproject(np.stack([u, v], -1).astype(np.float64), d0).reshape(-1, 3)
    p_c1 = transform(inv_T(T_w_c1) @ T_w_c0, p_c0)
    uv, ok = cam.project(p_c1)
    ok &= cam.in_image(uv)
    assert ok.mean() > 0.8
    ui = np.rint(uv[ok]).astype(int)
    z_obs = d1[ui[:, 1], ui[:, 0]]
    rel = np.abs(p_c1[ok, 2] - z_obs) / z_obs
    assert np.median(rel) < 0.01
    assert np.mean(rel < 0.01) > 0.9
    # and a wrong T_BS (identity) does not agree as well: the check is sensitive to it
    p_bad = transform(inv_T(seq.gt_pose_at(seq.frame_ts[k + 1])) @ seq.gt_pose_at(seq.frame_ts[k]), p_c0)
    uvb, okb = cam.project(p_bad)
    okb &= cam.in_image(uvb)
    ub = np.rint(uvb[okb]).astype(int)
    relb = np.abs(p_bad[okb, 2] - d1[ub[:, 1], ub[:, 0]]) / d1[ub[:, 1], ub[:, 0]]
    assert np.mean(relb < 0.01) < np.mean(rel < 0.01)


def test_rest_period_and_gravity(exact_seq):
    seq = read_euroc(exact_seq)
    rest = seq.imu_ts < seq.imu_ts[0] + 2_000_000_000  # first 2 s
    assert rest.sum() == 400
    np.testing.assert_allclose(seq.gt.v_w[rest], 0.0, atol=1e-9)
    np.testing.assert_allclose(seq.gt.p_w_b[rest], np.tile(seq.gt.p_w_b[0], (400, 1)), atol=1e-12)
    np.testing.assert_allclose(seq.gyro[rest], 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(seq.accel[rest], axis=1), 9.81, atol=1e-9)
    # the accelerometer reads -g rotated into the body frame: R_w_b a = (0, 0, 9.81)
    a_w = np.einsum("nij,nj->ni", seq.gt.T_w_b[rest][:, :3, :3], seq.accel[rest])
    np.testing.assert_allclose(a_w, np.tile([0.0, 0.0, 9.81], (400, 1)), atol=1e-9)
    # EuRoC-like mounting: camera looks horizontally, so the IMU x axis (~ camera -y) points up
    assert a_w.shape == (400, 3) and seq.accel[0, 0] > 9.0
    assert np.linalg.norm(seq.gt.v_w[-1]) > 0.05  # it moves afterwards


def test_textured_images_rich_in_corners(exact_seq):
    import cv2

    seq = read_euroc(exact_seq)
    fast = cv2.FastFeatureDetector_create(20)
    counts = [len(fast.detect(seq.image(k))) for k in (0, 45, 89)]
    assert min(counts) > 300, counts


def test_noisy_imu_carries_true_biases(noisy_small_seq):
    seq = read_euroc(noisy_small_seq)
    exact = simulate_sequence("textured", 3.0, 2, imu_noise=False)
    noisy = simulate_sequence("textured", 3.0, 2, imu_noise=True)
    # the CSVs hold exactly what was simulated (17 significant digits)
    np.testing.assert_array_equal(seq.gyro, noisy.gyro)
    np.testing.assert_array_equal(seq.gt.bg, noisy.bg)
    np.testing.assert_array_equal(seq.gt.ba, noisy.ba)
    # same trajectory as without noise; noise = bias + white noise of the ADIS16448 density
    np.testing.assert_array_equal(seq.gt.v_w, exact.v_w)
    dt = 0.005
    wg = seq.gyro - exact.gyro - seq.gt.bg
    wa = seq.accel - exact.accel - seq.gt.ba
    assert np.std(wg) == pytest.approx(EUROC_ADIS16448.gyro_noise_density / np.sqrt(dt), rel=0.1)
    assert np.std(wa) == pytest.approx(EUROC_ADIS16448.accel_noise_density / np.sqrt(dt), rel=0.1)
    assert np.all(np.abs(seq.gt.bg[0]) > 0) and np.all(np.abs(seq.gt.ba[0]) > 0)
    steps = np.diff(seq.gt.ba, axis=0)
    assert np.std(steps) == pytest.approx(EUROC_ADIS16448.accel_random_walk * np.sqrt(dt), rel=0.15)
    # scaled resolution keeps the model and scales the intrinsics
    assert (seq.camera.width, seq.camera.height) == (188, 120)
    assert seq.camera.fx == pytest.approx(EUROC_CAM0.fx / 4)
    assert seq.image(0).shape == (120, 188)
