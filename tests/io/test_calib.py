"""Calibration folders: Kalibr's camchain.yaml + imu.yaml (output and input styles) and EuRoC sensor.yaml files,
including the equidistant (fisheye) model."""

import numpy as np
import pytest

from runtime.io.asl_format import EurocFormatError
from runtime.io.calib import read_calibration

# TUM-VI's camchain (cam0 only), as Kalibr writes it
CAMCHAIN = """cam0:
  T_cam_imu:
  - [-0.9995250378696743, 0.029615343885863205, -0.008522328211654736, 0.04727988224914392]
  - [0.0075019185074052044, -0.03439736061393144, -0.9993800792498829, -0.047443232143367084]
  - [-0.02989013031643309, -0.998969345370175, 0.03415885127385616, -0.0681999605066297]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182]
  distortion_model: equidistant
  intrinsics: [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504]
  resolution: [512, 512]
  rostopic: /cam0/image_raw
  timeshift_cam_imu: 0.001
"""
IMU_OUT = """imu0:
  T_i_b:
  - [1.0, 0.0, 0.0, 0.0]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  accelerometer_noise_density: 0.0028
  accelerometer_random_walk: 0.00086
  gyroscope_noise_density: 0.00016
  gyroscope_random_walk: 2.2e-05
  model: calibrated
  rostopic: /imu0
  time_offset: 0.0
  update_rate: 200.0
"""
IMU_FLAT = """accelerometer_noise_density: 0.0028
accelerometer_random_walk: 0.00086
gyroscope_noise_density: 0.00016
gyroscope_random_walk: 2.2e-05
rostopic: /imu1
update_rate: 250.0
"""


def test_kalibr_output_files(tmp_path):
    (tmp_path / "camchain-imucam-dataset.yaml").write_text(CAMCHAIN)
    (tmp_path / "imu.yaml").write_text(IMU_OUT)
    cal = read_calibration(tmp_path)
    c = cal.camera
    assert c.model == "equidistant" and (c.width, c.height) == (512, 512) and c.fx == pytest.approx(190.9784771)
    assert c.dist[3] == pytest.approx(0.00020293673591811182)
    T_c_i = np.array([[float(x) for x in r.split("[")[1].rstrip("]").split(",")] for r in CAMCHAIN.splitlines()[2:6]])
    np.testing.assert_allclose(cal.T_b_c @ T_c_i, np.eye(4), atol=1e-12)  # T_b_c = inv(T_cam_imu)
    assert cal.time_shift_ns == 1_000_000 and cal.cam_rate_hz is None
    assert (cal.image_topic, cal.imu_topic) == ("/cam0/image_raw", "/imu0")
    assert cal.imu.rate_hz == 200.0 and cal.imu.accel_noise_density == 0.0028 and cal.imu.gyro_random_walk == 2.2e-5


def test_kalibr_flat_imu_file_and_body_frame(tmp_path):
    (tmp_path / "camchain.yaml").write_text(CAMCHAIN)
    (tmp_path / "imu.yaml").write_text(IMU_FLAT)
    cal = read_calibration(tmp_path)
    assert cal.imu.rate_hz == 250.0 and cal.imu_topic == "/imu1" and np.array_equal(cal.imu.T_b_s, np.eye(4))


def test_kalibr_errors_name_file_and_key(tmp_path):
    (tmp_path / "camchain.yaml").write_text(CAMCHAIN.replace("equidistant", "fov"))
    (tmp_path / "imu.yaml").write_text(IMU_FLAT)
    with pytest.raises(EurocFormatError, match="camchain.yaml: cam0 distortion_model 'fov'"):
        read_calibration(tmp_path)
    (tmp_path / "camchain.yaml").write_text(CAMCHAIN)
    (tmp_path / "imu.yaml").write_text(IMU_FLAT.replace("update_rate: 250.0\n", ""))
    with pytest.raises(EurocFormatError, match="imu.yaml: missing key 'update_rate'"):
        read_calibration(tmp_path)
    with pytest.raises(EurocFormatError, match="no calibration found"):
        empty = tmp_path / "empty"
        empty.mkdir()
        read_calibration(empty)


def test_euroc_sensor_yaml_folder_with_equidistant_model(euroc, tmp_path):
    cal = read_calibration(euroc.root)
    assert cal.camera.model == "radtan" and cal.cam_rate_hz == 20.0 and cal.time_shift_ns == 0
    y = euroc.root / "mav0" / "cam0" / "sensor.yaml"
    text = y.read_text()
    y.write_text(text.replace("radial-tangential", "equidistant"))
    assert read_calibration(euroc.root).camera.model == "equidistant"


def test_open_sequence_takes_kalibr_calibration_for_an_asl_folder(euroc, tmp_path):
    from runtime.io.sequence import PinholeView, open_sequence

    kal = tmp_path / "kalibr"
    kal.mkdir()
    plain = open_sequence(euroc.root)
    (kal / "camchain.yaml").write_text(CAMCHAIN.replace("[512, 512]", f"[{plain.camera.width}, {plain.camera.height}]"))
    (kal / "imu.yaml").write_text(IMU_OUT)
    seq = open_sequence(euroc.root, kal)
    assert isinstance(seq, PinholeView) and seq.fisheye.model == "equidistant" and seq.imu.rate_hz == 200.0
    assert np.array_equal(seq.frame_ts, plain.frame_ts + 1_000_000)  # Kalibr's timeshift_cam_imu
    assert seq.image(0).shape == plain.image(0).shape
