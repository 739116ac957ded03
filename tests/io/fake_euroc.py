"""A tiny EuRoC ASL sequence written by hand (independent of sim/), for runtime.io tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from runtime.geometry import R_to_quat_wxyz, so3_exp
from runtime.io.euroc import GT_HEADER, IMU_HEADER

# Real EuRoC values (shared/PITFALLS.md, "Formats").
EUROC_INTRINSICS = [458.654, 457.296, 367.215, 248.375]
EUROC_DIST = [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
EUROC_T_BS = [
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
]
EUROC_IMU = dict(
    gyroscope_noise_density=1.6968e-04,
    gyroscope_random_walk=1.9393e-05,
    accelerometer_noise_density=2.0e-3,
    accelerometer_random_walk=3.0e-3,
)
T0 = 1403636579763555584  # first cam0 timestamp of MH_01_easy [ns]
W, H = 752, 480


def _flat(T) -> str:
    return ", ".join(repr(float(x)) for x in np.asarray(T).ravel())


def cam_yaml(style: str = "opencv", resolution=(W, H)) -> str:
    """cam0 sensor.yaml as EuRoC ships it; ``opencv`` adds ``%YAML:1.0``, ``opencv_matrix`` also the tag."""
    head = "%YAML:1.0\n" if style in ("opencv", "opencv_matrix") else ""
    tag = " !!opencv-matrix" if style == "opencv_matrix" else ""
    return (
        f"{head}# General sensor definitions.\nsensor_type: camera\ncomment: VI-Sensor cam0 (MT9M034)\n\n"
        f"# Sensor extrinsics wrt. the body-frame.\nT_BS:{tag}\n  cols: 4\n  rows: 4\n"
        f"  data: [{_flat(EUROC_T_BS)}]\n\n"
        f"# Camera specific definitions.\nrate_hz: 20\nresolution: [{resolution[0]}, {resolution[1]}]\n"
        "camera_model: pinhole\n"
        "intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        "distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]\n"
    )


def imu_yaml(style: str = "plain") -> str:
    head = "%YAML:1.0\n" if style in ("opencv", "opencv_matrix") else ""
    return (
        f"{head}#Default imu sensor yaml file\nsensor_type: imu\ncomment: VI-Sensor IMU (ADIS16448)\n\n"
        "T_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0,\n         0.0, 1.0, 0.0, 0.0,\n"
        "         0.0, 0.0, 1.0, 0.0,\n         0.0, 0.0, 0.0, 1.0]\nrate_hz: 200\n\n"
        "# inertial sensor noise model parameters (static)\n"
        'gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )\n'
        "gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )\n"
        'accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]  ( accel "white noise" )\n'
        "accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )\n"
    )


@dataclass
class FakeEuroc:
    """What the fixture wrote, to compare against what the reader returns."""

    root: Path
    mav0: Path
    frame_ts: np.ndarray
    images: list[np.ndarray]
    depth_raw: list[np.ndarray]
    imu_ts: np.ndarray
    imu: np.ndarray  # (M, 6) gyro, accel
    gt_ts: np.ndarray
    gt: np.ndarray  # (K, 16) p, q(wxyz), v, bg, ba
    gt_R: np.ndarray  # (K, 3, 3)

    def path(self, rel: str) -> Path:
        return self.mav0 / rel

    def lines(self, rel: str) -> list[str]:
        return self.path(rel).read_text().splitlines()

    def write_lines(self, rel: str, lines: list[str]) -> None:
        self.path(rel).write_text("\n".join(lines) + "\n")


def make_euroc(
    root: Path,
    n_frames: int = 4,
    cam_style: str = "opencv",
    imu_style: str = "plain",
    depth: bool = True,
    gt_span: tuple[int, int] | None = None,
    other_sensors: bool = True,
    seed: int = 0,
) -> FakeEuroc:
    """Write a tiny EuRoC ASL sequence: ``n_frames`` 752x480 PNGs at 20 Hz, IMU at 200 Hz, GT at 200 Hz.

    ``gt_span = (start, end)`` in ns relative to the first frame sets the ground-truth coverage.
    """
    rng = np.random.default_rng(seed)
    mav0 = root / "mav0"
    for d in ("cam0/data", "imu0", "state_groundtruth_estimate0"):
        (mav0 / d).mkdir(parents=True, exist_ok=True)

    frame_ts = T0 + np.arange(n_frames, dtype=np.int64) * 50_000_000
    images = [rng.integers(0, 256, (H, W), dtype=np.uint8) for _ in range(n_frames)]
    for t, img in zip(frame_ts, images, strict=True):
        assert cv2.imwrite(str(mav0 / f"cam0/data/{t}.png"), img)
    (mav0 / "cam0/data.csv").write_text(
        "#timestamp [ns],filename\r\n"
        + "".join(f"{t},{t}.png\r\n" for t in frame_ts)  # CRLF like some copies
    )
    (mav0 / "cam0/sensor.yaml").write_text(cam_yaml(cam_style))

    imu_ts = np.arange(frame_ts[0] - 50_000_000, frame_ts[-1] + 50_000_001, 5_000_000, dtype=np.int64)
    imu = rng.normal(size=(len(imu_ts), 6))
    imu[:, 5] += 9.81
    (mav0 / "imu0/data.csv").write_text(
        IMU_HEADER
        + "\n"
        + "".join(
            f"{t}," + ",".join(repr(float(x)) for x in r) + "\n" for t, r in zip(imu_ts, imu, strict=True)
        )
    )
    (mav0 / "imu0/sensor.yaml").write_text(imu_yaml(imu_style))

    lo, hi = gt_span if gt_span is not None else (-50_000_000, int(frame_ts[-1] - frame_ts[0]) + 50_000_000)
    gt_ts = np.arange(frame_ts[0] + lo, frame_ts[0] + hi + 1, 5_000_000, dtype=np.int64)
    gt_R = so3_exp(rng.normal(scale=0.5, size=(len(gt_ts), 3)))
    q = R_to_quat_wxyz(gt_R)
    gt = np.concatenate([rng.normal(size=(len(gt_ts), 3)), q, rng.normal(size=(len(gt_ts), 9)) * 0.1], axis=1)
    (mav0 / "state_groundtruth_estimate0/data.csv").write_text(
        GT_HEADER
        + "\n"
        + "".join(
            f"{t}," + ",".join(repr(float(x)) for x in r) + "\n" for t, r in zip(gt_ts, gt, strict=True)
        )
    )

    depth_raw = []
    if depth:
        (mav0 / "depth0/data").mkdir(parents=True)
        depth_raw = [rng.integers(0, 20000, (H, W), dtype=np.uint16) for _ in range(n_frames)]
        for t, d in zip(frame_ts, depth_raw, strict=True):
            assert cv2.imwrite(str(mav0 / f"depth0/data/{t}.png"), d)
        (mav0 / "depth0/data.csv").write_text(
            "#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in frame_ts)
        )
        (mav0 / "depth0/sensor.yaml").write_text("sensor_type: depth\ndepth_scale: 5000.0\n")

    if other_sensors:  # present in real sequences, must be ignored (deliberately not valid for our reader)
        (mav0 / "cam1/data").mkdir(parents=True)
        (mav0 / "cam1/data.csv").write_text("this is not, a valid, cam0 file\n")
        (mav0 / "cam1/sensor.yaml").write_text("%YAML:1.0\n: broken yaml [\n")
        (mav0 / "leica0").mkdir()
        (mav0 / "leica0/data.csv").write_text(
            "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]\nx,y,z\n"
        )
        (mav0 / "body.yaml").write_text("comment: body\n")

    return FakeEuroc(root, mav0, frame_ts, images, depth_raw, imu_ts, imu, gt_ts, gt, gt_R)
