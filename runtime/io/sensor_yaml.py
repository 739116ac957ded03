"""ASL ``sensor.yaml`` files (EuRoC's cam0 and imu0 calibration): the camera model, ``T_BS`` and the IMU noise.

Accepted as the real datasets ship them: with or without OpenCV's ``%YAML:1.0`` first line and
``!!opencv-matrix`` tags. Bad input raises :class:`runtime.io.asl_format.EurocFormatError` naming the file and key.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from runtime.geometry import Camera
from runtime.io.asl_format import EurocFormatError, read_text


@dataclass(frozen=True, eq=False)
class ImuParams:
    """IMU noise model from ``imu0/sensor.yaml`` (continuous-time densities, as GTSAM expects them squared).

    Attributes:
        gyro_noise_density: gyroscope white noise [rad / s / sqrt(Hz)].
        gyro_random_walk: gyroscope bias random walk [rad / s^2 / sqrt(Hz)].
        accel_noise_density: accelerometer white noise [m / s^2 / sqrt(Hz)].
        accel_random_walk: accelerometer bias random walk [m / s^3 / sqrt(Hz)].
        rate_hz: nominal sample rate [Hz].
        T_b_s: (4, 4) pose of the IMU sensor in the body frame (identity for EuRoC: body = IMU).
    """

    gyro_noise_density: float
    gyro_random_walk: float
    accel_noise_density: float
    accel_random_walk: float
    rate_hz: float
    T_b_s: np.ndarray = field(default_factory=lambda: np.eye(4))


class _OpenCvYamlLoader(yaml.SafeLoader):
    """SafeLoader that also reads OpenCV's ``!!opencv-matrix`` mappings."""


def _construct_opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node):
    return loader.construct_mapping(node, deep=True)


_OpenCvYamlLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _construct_opencv_matrix)


def load_sensor_yaml(path: str | Path) -> dict:
    """Load an ASL ``sensor.yaml``; accepts OpenCV's ``%YAML:1.0`` first line and ``!!opencv-matrix`` tags.

    Raises:
        EurocFormatError: missing file, invalid YAML, or not a mapping.
    """
    path = Path(path)
    text = read_text(path)
    lines = text.splitlines()
    # PyYAML rejects OpenCV's "%YAML:1.0" directive (and YAML 1.0 itself): drop any leading %YAML line.
    first = next((j for j, ln in enumerate(lines) if ln.strip()), None)
    if first is not None and lines[first].lstrip().startswith("%YAML"):
        del lines[first]
    try:
        data = yaml.load("\n".join(lines), Loader=_OpenCvYamlLoader)
    except yaml.YAMLError as e:
        raise EurocFormatError(f"{path}: invalid YAML ({e})") from e
    if not isinstance(data, dict):
        raise EurocFormatError(f"{path}: expected a YAML mapping, got {type(data).__name__}")
    return data


def sensor_float(value, key: str, path: Path) -> float:
    try:
        x = float(value)  # PyYAML leaves e.g. "1e-3" (no dot) as a string: float() reads it
    except (TypeError, ValueError):
        raise EurocFormatError(f"{path}: '{key}' must be a number, got {value!r}") from None
    if not np.isfinite(x):
        raise EurocFormatError(f"{path}: '{key}' is not finite ({value!r})")
    return x


def _require(data: dict, key: str, path: Path):
    if key not in data:
        raise EurocFormatError(f"{path}: missing key '{key}'")
    return data[key]


def _float_list(data: dict, key: str, n: int | Sequence[int], path: Path) -> list[float]:
    value = _require(data, key, path)
    ns = (n,) if isinstance(n, int) else tuple(n)
    if not isinstance(value, (list, tuple)) or len(value) not in ns:
        raise EurocFormatError(f"{path}: '{key}' must be a list of {' or '.join(map(str, ns))} numbers, got {value!r}")
    return [sensor_float(v, f"{key}[{j}]", path) for j, v in enumerate(value)]


def _matrix4(data: dict, key: str, path: Path) -> np.ndarray:
    """A rigid 4x4 transform stored as ``{rows: 4, cols: 4, data: [16 numbers, row-major]}``."""
    m = _require(data, key, path)
    if not isinstance(m, dict):
        raise EurocFormatError(f"{path}: '{key}' must be a mapping with rows, cols, data; got {m!r}")
    rows, cols = (int(sensor_float(_require(m, k, path), f"{key}.{k}", path)) for k in ("rows", "cols"))
    if (rows, cols) != (4, 4):
        raise EurocFormatError(f"{path}: '{key}' must be 4x4, got rows={rows} cols={cols}")
    vals = _float_list(m, "data", 16, path)
    T = np.asarray(vals, dtype=np.float64).reshape(4, 4)  # row-major
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise EurocFormatError(f"{path}: '{key}' last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > 1e-5 or np.linalg.det(R) < 0:
        raise EurocFormatError(
            f"{path}: '{key}' rotation is not a rotation (|R R^T - I| = {err:.2e}, det = {np.linalg.det(R):.6f})"
        )
    return T


def read_camera_yaml(path: str | Path) -> tuple[Camera, np.ndarray, float]:
    """Read cam0's ``sensor.yaml``.

    Returns:
        camera (pinhole + radtan, size from ``resolution`` [w, h]; the optional ``line_delay_s`` of a rolling
        shutter, seconds between rows with the middle row at the stamp), ``T_b_c`` (4, 4) from ``T_BS``,
        ``rate_hz``.

    Raises:
        EurocFormatError: missing keys, wrong lengths, unsupported camera or distortion model.
    """
    path = Path(path)
    d = load_sensor_yaml(path)
    model = str(d.get("camera_model", "pinhole")).lower()
    if model != "pinhole":
        raise EurocFormatError(f"{path}: camera_model '{model}' is not supported (only 'pinhole')")
    dmodel = str(d.get("distortion_model", "radial-tangential")).lower()
    if dmodel not in ("radial-tangential", "radtan", "plumb_bob", "none", "equidistant"):
        raise EurocFormatError(
            f"{path}: distortion_model '{dmodel}' is not supported "
            "(radial-tangential k1, k2, p1, p2 or equidistant k1, k2, k3, k4)"
        )
    fx, fy, cx, cy = _float_list(d, "intrinsics", 4, path)
    if fx <= 0 or fy <= 0:
        raise EurocFormatError(f"{path}: focal lengths must be positive, got fu={fx}, fv={fy}")
    if dmodel == "none" and "distortion_coefficients" not in d:
        dist = [0.0, 0.0, 0.0, 0.0]
    else:
        dist = _float_list(d, "distortion_coefficients", 4 if dmodel == "equidistant" else (4, 5), path)
        if len(dist) == 5:  # plumb_bob k1, k2, p1, p2, k3: only k3 = 0 is representable
            if dist[4] != 0.0:
                raise EurocFormatError(f"{path}: distortion_coefficients k3={dist[4]} is not supported (must be 0)")
            dist = dist[:4]
    w, h = _float_list(d, "resolution", 2, path)
    if w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise EurocFormatError(f"{path}: resolution must be two positive integers [width, height], got {[w, h]}")
    rate = sensor_float(_require(d, "rate_hz", path), "rate_hz", path)
    if rate <= 0:
        raise EurocFormatError(f"{path}: rate_hz must be positive, got {rate}")
    T_b_c = _matrix4(d, "T_BS", path)
    model = "equidistant" if dmodel == "equidistant" else "radtan"
    line_delay = sensor_float(d.get("line_delay_s", 0.0), "line_delay_s", path)
    if line_delay < 0:
        raise EurocFormatError(f"{path}: line_delay_s must be >= 0 (0 = global shutter), got {line_delay}")
    cam = Camera(fx, fy, cx, cy, int(w), int(h), (dist[0], dist[1], dist[2], dist[3]), model, line_delay)
    return cam, T_b_c, rate


def read_imu_yaml(path: str | Path) -> ImuParams:
    """Read imu0's ``sensor.yaml`` (noise densities, random walks, ``rate_hz``, ``T_BS``)."""
    path = Path(path)
    d = load_sensor_yaml(path)
    vals = {}
    for key in (
        "gyroscope_noise_density",
        "gyroscope_random_walk",
        "accelerometer_noise_density",
        "accelerometer_random_walk",
        "rate_hz",
    ):
        vals[key] = sensor_float(_require(d, key, path), key, path)
        if vals[key] < 0 or (key == "rate_hz" and vals[key] == 0):
            raise EurocFormatError(f"{path}: '{key}' must be positive, got {vals[key]}")
    T_b_s = _matrix4(d, "T_BS", path) if "T_BS" in d else np.eye(4)
    return ImuParams(
        gyro_noise_density=vals["gyroscope_noise_density"],
        gyro_random_walk=vals["gyroscope_random_walk"],
        accel_noise_density=vals["accelerometer_noise_density"],
        accel_random_walk=vals["accelerometer_random_walk"],
        rate_hz=vals["rate_hz"],
        T_b_s=T_b_s,
    )
