"""benchmarks/peers/variants.py on a tiny EuRoC-layout folder: one file changed, the rest linked."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.peers.variants import make_variant

CAM = (
    "sensor_type: camera\nintrinsics: [461.0, 460.0, 366.0, 247.0] #fu, fv, cu, cv\n"
    "distortion_coefficients: [-0.1, 0.01, 0.0, 0.0]\n"
)


@pytest.fixture
def seq(tmp_path: Path) -> Path:
    root = tmp_path / "seq"
    for d in ("cam0/data", "imu0", "state_groundtruth_estimate0"):
        (root / "mav0" / d).mkdir(parents=True)
    (root / "mav0" / "cam0" / "sensor.yaml").write_text(CAM)
    (root / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n1000000000,a.png\n1050000000,b.png\n")
    ts = 1_000_000_000 + 5_000_000 * np.arange(4)
    imu = "#timestamp,wx,wy,wz,ax,ay,az\n" + "".join(f"{t},0.1,0.2,0.3,1.0,2.0,9.0\n" for t in ts)
    (root / "mav0" / "imu0" / "data.csv").write_text(imu)
    gt_ts = ts[::3]  # every third sample: the bias is interpolated in between
    gt = "#timestamp,p...\n" + "".join(
        f"{t},0,0,0,1,0,0,0,0,0,0,0.01,0.02,0.03,{0.1 * i},0.2,0.3\n" for i, t in enumerate(gt_ts)
    )
    (root / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text(gt)
    info = {"render_camera": [458.0, 457.0, 367.0, 248.0, -0.2, 0.07, 0.001, 0.0002], "time_offset_s": 0.003}
    (root / "sim_info.json").write_text(json.dumps(info))
    return root


def test_accel_bias_removed(seq, tmp_path):
    out = make_variant(seq, tmp_path / "v", "accel-bias-removed")
    imu = np.loadtxt(out / "mav0" / "imu0" / "data.csv", delimiter=",", comments="#")
    np.testing.assert_allclose(imu[:, 4], [1.0, 1.0 - 0.1 / 3, 1.0 - 0.2 / 3, 0.9])  # ax - ba_x(t), interpolated
    np.testing.assert_allclose(imu[:, 5:7], [[1.8, 8.7]] * 4)
    np.testing.assert_allclose(imu[:, 1:4], [[0.1, 0.2, 0.3]] * 4)  # the gyroscope untouched
    gt = np.loadtxt(out / "mav0" / "state_groundtruth_estimate0" / "data.csv", delimiter=",", comments="#")
    assert np.all(gt[:, 14:17] == 0.0) and np.allclose(gt[:, 11:14], [0.01, 0.02, 0.03])
    assert (out / "mav0" / "cam0").is_symlink() and (out / "mav0" / "imu0" / "data.csv").is_file()


def test_true_calibration_and_time(seq, tmp_path):
    out = make_variant(seq, tmp_path / "c", "true-calibration")
    text = (out / "mav0" / "cam0" / "sensor.yaml").read_text()
    assert "intrinsics: [458.0, 457.0, 367.0, 248.0]" in text and "[-0.2, 0.07, 0.001, 0.0002]" in text
    assert (out / "mav0" / "cam0" / "data").is_symlink() and (out / "mav0" / "imu0").is_symlink()
    assert (seq / "mav0" / "cam0" / "sensor.yaml").read_text() == CAM  # the source is untouched
    out = make_variant(seq, tmp_path / "t", "true-time")
    rows = (out / "mav0" / "cam0" / "data.csv").read_text().splitlines()
    assert rows == ["#timestamp [ns],filename", "1003000000,a.png", "1053000000,b.png"]
    with pytest.raises(FileExistsError):
        make_variant(seq, tmp_path / "t", "true-time")
    with pytest.raises(ValueError, match="unknown variant"):
        make_variant(seq, tmp_path / "x", "no-noise")
