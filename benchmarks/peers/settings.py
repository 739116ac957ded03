"""The peers' settings, written from a EuRoC-layout sequence's ``cam0/sensor.yaml`` and ``imu0/sensor.yaml``.

* ORB-SLAM3: its settings file (``File.version: "1.0"``, OpenCV YAML). ``IMU.T_b_c1`` is the pose of the camera in
  the body (IMU) frame, i.e. cam0's ``T_BS`` as EuRoC stores it (the direction ORB-SLAM3's own ``EuRoC.yaml``
  uses: same numbers). The IMU noises are the continuous-time densities of ``imu0/sensor.yaml`` in the same
  units ORB-SLAM3 reads (rad/s/sqrt(Hz), m/s^2/sqrt(Hz), and the random walks per sqrt(Hz)), optionally inflated
  by ``imu_noise_scale`` (a MAV's rotor vibration is far above the datasheet densities, see docs/PITFALLS.md).
* cuVSLAM (``dim_odom``): a plain dict with the pinhole intrinsics, the radial-tangential coefficients, the image
  size and ``T_b_c``, from which the runner builds ``dim_odom.CameraModel`` and the mount transform.

Only numpy and the project's ``sensor.yaml`` reader: tested without the peers installed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from runtime.io.sensor_yaml import read_camera_yaml, read_imu_yaml

__all__ = ["SensorSetup", "read_setup", "orbslam3_settings", "write_orbslam3_settings", "cuvslam_camera"]

#: ORB-SLAM3's settings for EuRoC's 752x480 camera (its own EuRoC.yaml): features and FAST thresholds.
ORB_DEFAULTS = {
    "ORBextractor.nFeatures": 1000,
    "ORBextractor.scaleFactor": 1.2,
    "ORBextractor.nLevels": 8,
    "ORBextractor.iniThFAST": 20,
    "ORBextractor.minThFAST": 7,
}


class SensorSetup:
    """cam0 and imu0 calibration of one sequence, as the peers need it.

    Attributes:
        fx, fy, cx, cy: pinhole intrinsics [px]; dist: (k1, k2, p1, p2) radial-tangential.
        width, height: image size [px]; cam_rate_hz: camera rate [Hz].
        T_b_c: (4, 4) cam0 pose in the body (IMU) frame (cam0 ``T_BS``).
        gyro_noise, gyro_walk, accel_noise, accel_walk: imu0 densities (continuous time); imu_rate_hz: [Hz].
    """

    def __init__(self, cam_yaml: Path, imu_yaml: Path | None):
        cam, self.T_b_c, self.cam_rate_hz = read_camera_yaml(cam_yaml)
        self.fx, self.fy, self.cx, self.cy = cam.fx, cam.fy, cam.cx, cam.cy
        self.dist = tuple(float(d) for d in cam.dist)
        self.width, self.height = int(cam.width), int(cam.height)
        self.has_imu = imu_yaml is not None
        if imu_yaml is not None:
            imu = read_imu_yaml(imu_yaml)
            if not np.allclose(imu.T_b_s, np.eye(4), atol=1e-9):
                # EuRoC's body frame is the IMU: T_b_c is then the camera in the IMU frame, as ORB-SLAM3 wants it
                self.T_b_c = np.linalg.inv(imu.T_b_s) @ self.T_b_c
            self.gyro_noise, self.gyro_walk = imu.gyro_noise_density, imu.gyro_random_walk
            self.accel_noise, self.accel_walk = imu.accel_noise_density, imu.accel_random_walk
            self.imu_rate_hz = imu.rate_hz


def read_setup(seq_root: str | Path) -> SensorSetup:
    """Calibration of the EuRoC-layout sequence at ``seq_root`` (the folder holding ``mav0``, or ``mav0``)."""
    root = Path(seq_root)
    mav0 = root if root.name == "mav0" else root / "mav0"
    cam_yaml = mav0 / "cam0" / "sensor.yaml"
    if not cam_yaml.is_file():
        raise FileNotFoundError(f"{cam_yaml}: no cam0 calibration (expected a EuRoC-layout sequence)")
    imu_yaml = mav0 / "imu0" / "sensor.yaml"
    return SensorSetup(cam_yaml, imu_yaml if imu_yaml.is_file() else None)


def _fmt(x) -> str:
    if isinstance(x, str):
        return f'"{x}"'
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        return str(int(x))
    return repr(float(x))


def orbslam3_settings(
    setup: SensorSetup, inertial: bool, imu_noise_scale: float = 1.0, n_features: int | None = None
) -> dict:
    """ORB-SLAM3's settings as an ordered mapping ``key -> value`` (``IMU.T_b_c1`` a (4, 4) array)."""
    s: dict = {
        "File.version": "1.0",
        "Camera.type": "PinHole",
        "Camera1.fx": setup.fx,
        "Camera1.fy": setup.fy,
        "Camera1.cx": setup.cx,
        "Camera1.cy": setup.cy,
        "Camera1.k1": setup.dist[0],
        "Camera1.k2": setup.dist[1],
        "Camera1.p1": setup.dist[2],
        "Camera1.p2": setup.dist[3],
        "Camera.width": setup.width,
        "Camera.height": setup.height,
        "Camera.fps": int(round(setup.cam_rate_hz)),
        "Camera.RGB": 1,
    }
    if inertial:
        if not setup.has_imu:
            raise ValueError("monocular-inertial settings need imu0/sensor.yaml")
        k = float(imu_noise_scale)
        s.update(
            {
                "IMU.T_b_c1": np.asarray(setup.T_b_c, dtype=np.float64),
                "IMU.InsertKFsWhenLost": 0,
                "IMU.NoiseGyro": k * setup.gyro_noise,
                "IMU.NoiseAcc": k * setup.accel_noise,
                "IMU.GyroWalk": k * setup.gyro_walk,
                "IMU.AccWalk": k * setup.accel_walk,
                "IMU.Frequency": float(setup.imu_rate_hz),
            }
        )
    s.update(ORB_DEFAULTS)
    if n_features is not None:
        s["ORBextractor.nFeatures"] = int(n_features)
    s.update(
        {
            "Viewer.KeyFrameSize": 0.05,
            "Viewer.KeyFrameLineWidth": 1.0,
            "Viewer.GraphLineWidth": 0.9,
            "Viewer.PointSize": 2.0,
            "Viewer.CameraSize": 0.08,
            "Viewer.CameraLineWidth": 3.0,
            "Viewer.ViewpointX": 0.0,
            "Viewer.ViewpointY": -0.7,
            "Viewer.ViewpointZ": -1.8,
            "Viewer.ViewpointF": 500.0,
        }
    )
    return s


def orbslam3_yaml(settings: dict) -> str:
    """The OpenCV-YAML text of :func:`orbslam3_settings` (``%YAML:1.0``, ``!!opencv-matrix`` for matrices)."""
    lines = ["%YAML:1.0", ""]
    for key, val in settings.items():
        if isinstance(val, np.ndarray):
            rows, cols = val.shape
            data = ", ".join(repr(float(v)) for v in val.reshape(-1))
            lines += [f"{key}: !!opencv-matrix", f"  rows: {rows}", f"  cols: {cols}", "  dt: f", f"  data: [{data}]"]
        else:
            lines.append(f"{key}: {_fmt(val)}")
    return "\n".join(lines) + "\n"


def write_orbslam3_settings(seq_root: str | Path, path: str | Path, inertial: bool, **kw) -> Path:
    """Write ORB-SLAM3's settings for the sequence at ``seq_root`` to ``path``; returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(orbslam3_yaml(orbslam3_settings(read_setup(seq_root), inertial, **kw)))
    return path


def cuvslam_camera(setup: SensorSetup) -> dict:
    """cuVSLAM's camera: ``{"width", "height", "fx", "fy", "cx", "cy", "distortion": "brown"|"pinhole",
    "coeffs": [k1, k2, p1, p2], "T_b_c": (4, 4) list}``."""
    brown = any(abs(d) > 0 for d in setup.dist)
    return {
        "width": setup.width,
        "height": setup.height,
        "fx": setup.fx,
        "fy": setup.fy,
        "cx": setup.cx,
        "cy": setup.cy,
        "distortion": "brown" if brown else "pinhole",
        "coeffs": list(setup.dist),
        "T_b_c": np.asarray(setup.T_b_c).tolist(),
    }
