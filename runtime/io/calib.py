"""Camera-IMU calibration from a folder: EuRoC ``sensor.yaml`` files or Kalibr's ``camchain.yaml`` + ``imu.yaml``.

Accepted layouts of ``calib=DIR`` (the first that matches wins):

* EuRoC / ASL: ``DIR/mav0/cam0/sensor.yaml`` and ``DIR/mav0/imu0/sensor.yaml`` (or ``DIR/cam0``, ``DIR/imu0``);
* Kalibr: ``DIR/camchain.yaml`` (else the one ``*camchain*.yaml``, e.g. ``camchain-imucam-<bag>.yaml``) and
  ``DIR/imu.yaml`` (else the one ``imu*.yaml``), as Kalibr writes them (``cam0: {T_cam_imu, intrinsics, ...}``,
  ``imu0: {accelerometer_noise_density, ...}``) or as its input files (flat ``imu.yaml``).

Conventions (``runtime/geometry.py``): body = IMU frame unless Kalibr's ``T_i_b`` says otherwise; Kalibr's
``T_cam_imu`` maps IMU points into the camera, so ``T_b_c = T_b_i @ inv(T_cam_imu)``; ``timeshift_cam_imu`` [s]
is Kalibr's ``t_imu = t_cam + shift`` and becomes :attr:`Calibration.time_shift_ns`.
Bad input raises :class:`runtime.io.asl_format.EurocFormatError` naming the file and key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.geometry import Camera
from runtime.io.asl_format import EurocFormatError
from runtime.io.sensor_yaml import ImuParams, load_sensor_yaml, read_camera_yaml, read_imu_yaml, sensor_float

__all__ = ["Calibration", "read_calibration", "read_kalibr"]

_DISTORTIONS = {"radtan": "radtan", "radial-tangential": "radtan", "equidistant": "equidistant", "none": "radtan"}
_IMU_KEYS = (
    "gyroscope_noise_density",
    "gyroscope_random_walk",
    "accelerometer_noise_density",
    "accelerometer_random_walk",
)


@dataclass(frozen=True, eq=False)
class Calibration:
    """What a sequence needs besides its samples.

    Attributes:
        camera: cam0 model (radial-tangential or equidistant).
        T_b_c: (4, 4) cam0 pose in the body frame.
        imu: IMU noise model, rate and ``T_b_s``.
        cam_rate_hz: nominal camera rate [Hz], or None where the files do not say (Kalibr).
        time_shift_ns: add to camera timestamps to get IMU time (Kalibr ``timeshift_cam_imu``; 0 for EuRoC).
        image_topic, imu_topic: Kalibr's ``rostopic`` entries, or None.
        source: the file(s) read, for messages.
    """

    camera: Camera
    T_b_c: np.ndarray
    imu: ImuParams
    cam_rate_hz: float | None = None
    time_shift_ns: int = 0
    image_topic: str | None = None
    imu_topic: str | None = None
    source: str = ""


def read_calibration(calib_dir: str | Path) -> Calibration:
    """Read ``calib=DIR`` (EuRoC ``sensor.yaml`` files or Kalibr yaml files, see the module docstring).

    Raises:
        EurocFormatError: the folder holds neither layout, or a file is malformed (the message names it).
    """
    d = Path(calib_dir).expanduser()
    if not d.is_dir():
        raise EurocFormatError(f"{d}: calibration folder does not exist (calib=DIR)")
    for base in (d / "mav0", d):
        cam_y, imu_y = base / "cam0" / "sensor.yaml", base / "imu0" / "sensor.yaml"
        if cam_y.is_file() and imu_y.is_file():
            camera, T_b_c, rate = read_camera_yaml(cam_y)
            return Calibration(camera, T_b_c, read_imu_yaml(imu_y), rate, source=f"{cam_y}, {imu_y}")
    camchain = _one(d, "camchain.yaml", "*camchain*.yaml")
    imu_yaml = _one(d, "imu.yaml", "imu*.yaml")
    if camchain is None or imu_yaml is None:
        raise EurocFormatError(
            f"{d}: no calibration found: expected mav0/cam0/sensor.yaml + mav0/imu0/sensor.yaml (EuRoC) or "
            "camchain.yaml + imu.yaml (Kalibr)"
        )
    return read_kalibr(camchain, imu_yaml)


def _one(d: Path, name: str, pattern: str) -> Path | None:
    if (d / name).is_file():
        return d / name
    found = sorted(p for p in d.glob(pattern) if p.is_file())
    if len(found) > 1:
        raise EurocFormatError(f"{d}: several files match {pattern} ({', '.join(p.name for p in found)}); keep one")
    return found[0] if found else None


def _rigid(value, key: str, path: Path) -> np.ndarray:
    """A 4x4 rigid transform written as 4 rows of 4 numbers (Kalibr's style)."""
    try:
        T = np.array([[float(x) for x in row] for row in value], dtype=np.float64)
    except (TypeError, ValueError):
        raise EurocFormatError(f"{path}: '{key}' must be 4 rows of 4 numbers, got {value!r}") from None
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise EurocFormatError(f"{path}: '{key}' must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9) or np.abs(R @ R.T - np.eye(3)).max() > 1e-5:
        raise EurocFormatError(f"{path}: '{key}' is not a rigid transform (rotation block or last row)")
    return T


def _numbers(d: dict, key: str, n: int, path: Path) -> list[float]:
    v = d.get(key)
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise EurocFormatError(f"{path}: '{key}' must be a list of {n} numbers, got {v!r}")
    return [sensor_float(x, f"{key}[{j}]", path) for j, x in enumerate(v)]


def _kalibr_camera(path: Path) -> tuple[Camera, np.ndarray, float, str | None]:
    """cam0 of a Kalibr camchain: camera, ``T_i_c``, time shift [s], rostopic."""
    chain = load_sensor_yaml(path)
    c = chain.get("cam0")
    if not isinstance(c, dict):
        raise EurocFormatError(f"{path}: missing key 'cam0' (a Kalibr camchain)")
    model = str(c.get("camera_model", "pinhole")).lower()
    if model != "pinhole":
        raise EurocFormatError(f"{path}: cam0 camera_model '{model}' is not supported (only 'pinhole')")
    dmodel = str(c.get("distortion_model", "radtan")).lower()
    if dmodel not in _DISTORTIONS:
        raise EurocFormatError(f"{path}: cam0 distortion_model '{dmodel}' is not supported (radtan, equidistant)")
    fx, fy, cx, cy = _numbers(c, "intrinsics", 4, path)
    w, h = _numbers(c, "resolution", 2, path)
    dist = [0.0] * 4 if dmodel == "none" else _numbers(c, "distortion_coeffs", 4, path)
    if fx <= 0 or fy <= 0 or w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise EurocFormatError(f"{path}: cam0 intrinsics {[fx, fy, cx, cy]} / resolution {[w, h]} are invalid")
    if "T_cam_imu" not in c:
        raise EurocFormatError(f"{path}: missing key 'cam0.T_cam_imu' (run Kalibr's camera-IMU calibration)")
    T_c_i = _rigid(c["T_cam_imu"], "cam0.T_cam_imu", path)
    shift = sensor_float(c.get("timeshift_cam_imu", 0.0), "cam0.timeshift_cam_imu", path)
    cam = Camera(fx, fy, cx, cy, int(w), int(h), tuple(dist), _DISTORTIONS[dmodel])
    topic = c.get("rostopic")
    return cam, np.linalg.inv(T_c_i), shift, (str(topic) if topic else None)


def read_kalibr(camchain: str | Path, imu_yaml: str | Path) -> Calibration:
    """Read Kalibr's ``camchain.yaml`` (cam0) and ``imu.yaml`` (imu0, or a flat IMU file)."""
    camchain, imu_yaml = Path(camchain), Path(imu_yaml)
    cam, T_i_c, shift, cam_topic = _kalibr_camera(camchain)
    d = load_sensor_yaml(imu_yaml)
    if isinstance(d.get("imu0"), dict):
        d = d["imu0"]
    vals = {}
    for key in _IMU_KEYS:
        if key not in d:
            raise EurocFormatError(f"{imu_yaml}: missing key '{key}'")
        vals[key] = sensor_float(d[key], key, imu_yaml)
        if vals[key] < 0:
            raise EurocFormatError(f"{imu_yaml}: '{key}' must not be negative, got {vals[key]}")
    if "update_rate" not in d and "rate_hz" not in d:
        raise EurocFormatError(f"{imu_yaml}: missing key 'update_rate' (IMU rate [Hz])")
    rate = sensor_float(d.get("update_rate", d.get("rate_hz")), "update_rate", imu_yaml)
    if rate <= 0:
        raise EurocFormatError(f"{imu_yaml}: 'update_rate' must be positive, got {rate}")
    T_b_i = np.linalg.inv(_rigid(d["T_i_b"], "T_i_b", imu_yaml)) if "T_i_b" in d else np.eye(4)
    imu = ImuParams(
        gyro_noise_density=vals["gyroscope_noise_density"],
        gyro_random_walk=vals["gyroscope_random_walk"],
        accel_noise_density=vals["accelerometer_noise_density"],
        accel_random_walk=vals["accelerometer_random_walk"],
        rate_hz=rate,
        T_b_s=T_b_i,
    )
    topic = d.get("rostopic")
    return Calibration(
        camera=cam,
        T_b_c=T_b_i @ T_i_c,
        imu=imu,
        cam_rate_hz=None,
        time_shift_ns=int(round(shift * 1e9)),
        image_topic=cam_topic,
        imu_topic=str(topic) if topic else None,
        source=f"{camchain}, {imu_yaml}",
    )
