"""EuRoC ASL reader: values, tolerance to real-dataset quirks, and one error per kind of bad input."""

from __future__ import annotations

import re
import shutil
import time
import warnings

import cv2
import numpy as np
import pytest

from runtime.geometry import so3_exp
from runtime.io import (
    IMU_COLUMNS,
    EurocFormatError,
    EurocWarning,
    load_sensor_yaml,
    read_euroc,
    read_euroc_csv,
)
from tests.io.fake_euroc import (
    EUROC_DIST,
    EUROC_IMU,
    EUROC_INTRINSICS,
    EUROC_T_BS,
    GT_HEADER,
    IMU_HEADER,
    T0,
    H,
    W,
    cam_yaml,
    imu_yaml,
)


def _raises(path, *extra):
    """pytest.raises(EurocFormatError) whose message has the file path and every ``extra`` fragment."""
    pattern = "".join(f"(?=.*{re.escape(str(x))})" for x in (path, *extra))
    return pytest.raises(EurocFormatError, match=re.compile(pattern, re.S))


# --------------------------------------------------------------------------- values
def test_reads_euroc_values(euroc):
    seq = read_euroc(euroc.root)
    cam = seq.camera
    assert cam.intrinsics == tuple(EUROC_INTRINSICS)
    assert cam.dist == tuple(EUROC_DIST)
    assert (cam.width, cam.height) == (752, 480)
    np.testing.assert_array_equal(seq.T_b_c, np.array(EUROC_T_BS))
    assert seq.cam_rate_hz == 20.0
    assert seq.imu.gyro_noise_density == EUROC_IMU["gyroscope_noise_density"]
    assert seq.imu.gyro_random_walk == EUROC_IMU["gyroscope_random_walk"]
    assert seq.imu.accel_noise_density == EUROC_IMU["accelerometer_noise_density"]
    assert seq.imu.accel_random_walk == EUROC_IMU["accelerometer_random_walk"]
    assert seq.imu.rate_hz == 200.0
    np.testing.assert_array_equal(seq.imu.T_b_s, np.eye(4))

    assert len(seq) == 4 and seq.frame_ts.dtype == np.int64
    np.testing.assert_array_equal(seq.frame_ts, euroc.frame_ts)
    assert seq.frame_ts[0] == T0  # int64 ns kept exactly (not through float64)
    assert [p.name for p in seq.frame_paths] == [f"{t}.png" for t in euroc.frame_ts]

    np.testing.assert_array_equal(seq.imu_ts, euroc.imu_ts)
    np.testing.assert_array_equal(seq.gyro, euroc.imu[:, :3])  # gyro columns first ...
    np.testing.assert_array_equal(seq.accel, euroc.imu[:, 3:])  # ... then accelerometer
    assert seq.imu_ts.dtype == np.int64

    gt = seq.gt
    np.testing.assert_array_equal(gt.ts, euroc.gt_ts)
    np.testing.assert_array_equal(gt.p_w_b, euroc.gt[:, 0:3])
    np.testing.assert_allclose(gt.q_wxyz, euroc.gt[:, 3:7], atol=1e-15)
    np.testing.assert_allclose(gt.T_w_b[:, :3, :3], euroc.gt_R, atol=1e-12)
    np.testing.assert_array_equal(gt.T_w_b[:, :3, 3], euroc.gt[:, 0:3])
    np.testing.assert_array_equal(gt.v_w, euroc.gt[:, 7:10])
    np.testing.assert_array_equal(gt.bg, euroc.gt[:, 10:13])
    np.testing.assert_array_equal(gt.ba, euroc.gt[:, 13:16])
    assert "frames=4" in repr(seq)


@pytest.mark.parametrize("cam_style", ["plain", "opencv", "opencv_matrix"])
@pytest.mark.parametrize("imu_style", ["plain", "opencv"])
def test_sensor_yaml_styles(euroc_factory, cam_style, imu_style):
    seq = read_euroc(
        euroc_factory(cam_style=cam_style, imu_style=imu_style, depth=False, other_sensors=False).root
    )
    assert seq.camera.intrinsics == tuple(EUROC_INTRINSICS)
    np.testing.assert_array_equal(seq.T_b_c, np.array(EUROC_T_BS))
    assert seq.imu.accel_noise_density == 2.0e-3


def test_plain_pyyaml_rejects_opencv_header_but_we_accept_it(tmp_path):
    import yaml

    p = tmp_path / "sensor.yaml"
    p.write_text(cam_yaml("opencv"))
    with pytest.raises(yaml.YAMLError):
        yaml.safe_load(p.read_text())
    assert load_sensor_yaml(p)["resolution"] == [752, 480]


def test_root_may_be_mav0(euroc):
    seq = read_euroc(euroc.mav0)
    assert seq.root == euroc.root and seq.mav0 == euroc.mav0
    assert len(seq) == 4


def test_other_sensor_folders_are_ignored(euroc):
    assert (euroc.mav0 / "cam1").is_dir() and (
        euroc.mav0 / "leica0"
    ).is_dir()  # both are invalid for our reader
    seq = read_euroc(euroc.root)
    assert all(p.parent.parent.name == "cam0" for p in seq.frame_paths)


# --------------------------------------------------------------------------- images and depth
def test_images_are_read_lazily_and_exactly(euroc, monkeypatch):
    calls = []
    real = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda *a, **k: calls.append(a) or real(*a, **k))
    seq = read_euroc(euroc.root)
    assert calls == []  # nothing decoded while reading the sequence
    for i in (0, 3, -1):
        img = seq.image(i)
        assert img.dtype == np.uint8 and img.shape == (H, W)
        np.testing.assert_array_equal(img, euroc.images[i])
    assert len(calls) == 3
    with pytest.raises(IndexError):
        seq.image(4)


def test_depth_is_metres(euroc):
    seq = read_euroc(euroc.root)
    assert seq.has_depth and seq.depth_scale == 5000.0
    d = seq.depth(2)
    assert d.dtype == np.float32 and d.shape == (H, W)
    np.testing.assert_allclose(d, euroc.depth_raw[2].astype(np.float64) / 5000.0, rtol=1e-6)
    assert d.min() == 0.0  # 0 stays invalid


def test_no_depth_folder(euroc_factory):
    seq = read_euroc(euroc_factory(depth=False).root)
    assert not seq.has_depth and seq.depth(0) is None


def test_missing_image_warns_and_is_skipped(euroc):
    gone = euroc.mav0 / f"cam0/data/{euroc.frame_ts[1]}.png"
    gone.unlink()
    with pytest.warns(EurocWarning, match=re.escape(str(gone))):
        seq = read_euroc(euroc.root)
    assert len(seq) == 3
    np.testing.assert_array_equal(seq.frame_ts, euroc.frame_ts[[0, 2, 3]])
    np.testing.assert_array_equal(seq.image(1), euroc.images[2])
    np.testing.assert_array_equal(
        seq.depth(1), euroc.depth_raw[2] / np.float32(5000.0)
    )  # depth matched by ts


def test_frames_without_depth_png_return_none(euroc):
    gone = euroc.mav0 / f"depth0/data/{euroc.frame_ts[3]}.png"
    gone.unlink()
    with pytest.warns(EurocWarning, match=re.escape(str(gone))):
        seq = read_euroc(euroc.root)
    assert seq.depth(3) is None and seq.depth(0) is not None


def test_no_warning_on_a_clean_sequence(euroc):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_euroc(euroc.root)


# --------------------------------------------------------------------------- ground truth
def test_quaternion_order_is_wxyz(euroc):
    """Hand-written GT rows: 90 deg about z is q = (w, x, y, z) = (cos 45, 0, 0, sin 45)."""
    c = np.sqrt(0.5)
    rows = [
        f"{T0},0,0,0,1,0,0,0,0,0,0,0,0,0,0,0,0",
        f"{T0 + 10_000_000},1,2,3,{c},0,0,{c},0.5,0,0,0.01,0.02,0.03,0.1,0.2,0.3",
    ]
    euroc.write_lines("state_groundtruth_estimate0/data.csv", [GT_HEADER, *rows])
    seq = read_euroc(euroc.root)
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(seq.gt.T_w_b[1][:3, :3], Rz90, atol=1e-15)
    np.testing.assert_allclose(seq.gt.T_w_b[1] @ [1, 0, 0, 1], [1, 3, 3, 1], atol=1e-15)  # x_b -> y_w, + p
    np.testing.assert_array_equal(seq.gt.v_w[1], [0.5, 0, 0])
    np.testing.assert_array_equal(seq.gt.bg[1], [0.01, 0.02, 0.03])
    np.testing.assert_array_equal(seq.gt.ba[1], [0.1, 0.2, 0.3])

    # interpolation: position linear, rotation by slerp (a quarter of the way = 22.5 deg about z)
    T = seq.gt_pose_at(T0 + 2_500_000)
    np.testing.assert_allclose(T[:3, :3], so3_exp([0, 0, np.pi / 8]), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.25, 0.5, 0.75], atol=1e-12)
    np.testing.assert_allclose(seq.gt_pose_at(T0 + 10_000_000), seq.gt.T_w_b[1], atol=1e-15)
    np.testing.assert_allclose(seq.gt_pose_at(T0), np.eye(4), atol=1e-15)
    Ts = seq.gt_pose_at(np.array([T0, T0 + 5_000_000, T0 + 10_000_000]))
    assert Ts.shape == (3, 4, 4)
    np.testing.assert_allclose(Ts[1, :3, :3], so3_exp([0, 0, np.pi / 4]), atol=1e-12)


def test_gt_pose_at_sign_flipped_quaternion_takes_short_path(euroc):
    """q and -q are the same rotation; slerp must not go the long way round between them."""
    c, s = np.cos(np.pi / 8), np.sin(np.pi / 8)  # 45 deg about z
    rows = [
        f"{T0},0,0,0,1,0,0,0,0,0,0,0,0,0,0,0,0",
        f"{T0 + 10_000_000},0,0,0,{-c},0,0,{-s},0,0,0,0,0,0,0,0,0",
    ]
    euroc.write_lines("state_groundtruth_estimate0/data.csv", [GT_HEADER, *rows])
    seq = read_euroc(euroc.root)
    np.testing.assert_allclose(seq.gt_pose_at(T0 + 5_000_000)[:3, :3], so3_exp([0, 0, np.pi / 8]), atol=1e-12)


def test_gt_interpolation_matches_samples_and_is_rigid(euroc):
    seq = read_euroc(euroc.root)
    Ts = seq.gt_pose_at(euroc.gt_ts)
    np.testing.assert_allclose(Ts, seq.gt.T_w_b, atol=1e-12)
    mid = seq.gt_pose_at(euroc.gt_ts[:-1] + 2_500_000)
    R = mid[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(mid[:, :3, 3], 0.5 * (euroc.gt[:-1, :3] + euroc.gt[1:, :3]), atol=1e-12)


def test_gt_shorter_than_images(euroc_factory):
    """GT starting after the first frame and ending before the last is accepted; queries outside raise."""
    fake = euroc_factory(gt_span=(60_000_000, 110_000_000))  # frames at 0, 50, 100, 150 ms
    seq = read_euroc(fake.root)
    inside = seq.gt.covers(seq.frame_ts)
    np.testing.assert_array_equal(inside, [False, False, True, False])
    assert seq.gt_pose_at(seq.frame_ts[2]).shape == (4, 4)
    for i in (0, 1, 3):
        with pytest.raises(ValueError, match=f"{seq.frame_ts[i]} ns is outside the ground-truth range"):
            seq.gt_pose_at(seq.frame_ts[i])
    with pytest.raises(ValueError, match="integer nanoseconds"):
        seq.gt_pose_at(float(seq.frame_ts[2]))


def test_sequence_without_ground_truth(euroc):
    shutil.rmtree(euroc.mav0 / "state_groundtruth_estimate0")
    seq = read_euroc(euroc.root)
    assert seq.gt is None
    with pytest.raises(ValueError, match="no ground truth"):
        seq.gt_pose_at(T0)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "rel",
    [
        "cam0/data.csv",
        "cam0/sensor.yaml",
        "imu0/data.csv",
        "imu0/sensor.yaml",
        "state_groundtruth_estimate0/data.csv",
        "depth0/data.csv",
    ],
)
def test_missing_file(euroc, rel):
    euroc.path(rel).unlink()
    with _raises(euroc.path(rel), "missing file"):
        read_euroc(euroc.root)


@pytest.mark.parametrize("rel", ["cam0", "cam0/data", "imu0"])
def test_missing_folder(euroc, rel):
    shutil.rmtree(euroc.path(rel))
    with _raises(euroc.path(rel), "missing folder"):
        read_euroc(euroc.root)


def test_missing_imu_names_dit_sim_imu_when_there_is_a_ground_truth(euroc):
    shutil.rmtree(euroc.path("imu0"))
    with _raises(euroc.path("imu0"), "dit-sim imu source="):
        read_euroc(euroc.root)
    euroc.path("state_groundtruth_estimate0/data.csv").unlink()
    with pytest.raises(EurocFormatError, match="no ground truth") as e:
        read_euroc(euroc.root)
    assert "dit-sim imu" not in str(e.value)


def test_missing_root_and_mav0(tmp_path):
    with _raises(tmp_path / "nope", "missing folder"):
        read_euroc(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with _raises(tmp_path / "empty", "mav0"):
        read_euroc(tmp_path / "empty")


def test_errors_are_value_errors():
    assert issubclass(EurocFormatError, ValueError)


def _edit_row(euroc, rel, row, fn):
    """Apply ``fn`` to the fields of data row ``row`` (0-based, after the header); returns its line number."""
    lines = euroc.lines(rel)
    parts = lines[row + 1].split(",")
    lines[row + 1] = ",".join(fn(parts))
    euroc.write_lines(rel, lines)
    return row + 2  # 1-based, header is line 1


def test_malformed_imu_value_names_line_and_column(euroc):
    ln = _edit_row(euroc, "imu0/data.csv", 6, lambda p: [*p[:4], "abc", *p[5:]])
    with _raises(euroc.path("imu0/data.csv"), f"line {ln}", "a_RS_S_x", "'abc'"):
        read_euroc(euroc.root)


def test_imu_row_with_missing_column(euroc):
    ln = _edit_row(euroc, "imu0/data.csv", 3, lambda p: p[:-1])
    with _raises(euroc.path("imu0/data.csv"), f"line {ln}", "expected 7 columns, got 6"):
        read_euroc(euroc.root)


def test_float_timestamp_is_malformed(euroc):
    ln = _edit_row(euroc, "imu0/data.csv", 2, lambda p: [p[0] + ".0", *p[1:]])
    with _raises(euroc.path("imu0/data.csv"), f"line {ln}", "not an integer"):
        read_euroc(euroc.root)


def test_malformed_cam_row(euroc):
    lines = euroc.lines("cam0/data.csv")
    lines[2] = lines[2].replace(",", ";")
    euroc.write_lines("cam0/data.csv", lines)
    with _raises(euroc.path("cam0/data.csv"), "line 3", "expected 2 columns"):
        read_euroc(euroc.root)


@pytest.mark.parametrize("rel", ["imu0/data.csv", "state_groundtruth_estimate0/data.csv", "cam0/data.csv"])
def test_non_monotonic_timestamps(euroc, rel):
    lines = euroc.lines(rel)
    lines[3], lines[4] = lines[4], lines[3]  # data rows 3 and 4 (file lines 4 and 5) swapped
    euroc.write_lines(rel, lines)
    with _raises(euroc.path(rel), "line 5", "not strictly increasing"):
        read_euroc(euroc.root)


def test_duplicate_timestamp_is_non_monotonic(euroc):
    lines = euroc.lines("imu0/data.csv")
    lines[8] = lines[7]
    euroc.write_lines("imu0/data.csv", lines)
    with _raises(euroc.path("imu0/data.csv"), "line 9", "not strictly increasing"):
        read_euroc(euroc.root)


@pytest.mark.parametrize(
    "rel,col,name", [("state_groundtruth_estimate0/data.csv", 5, "q_RS_x"), ("imu0/data.csv", 2, "w_RS_S_y")]
)
def test_nan_names_line_and_column(euroc, rel, col, name):
    ln = _edit_row(euroc, rel, 4, lambda p: [*p[:col], "nan", *p[col + 1 :]])
    with _raises(euroc.path(rel), f"line {ln}", f"'{name}'", "NaN"):
        read_euroc(euroc.root)


def test_accel_before_gyro_header_is_rejected(euroc):
    names = IMU_HEADER.split(",")
    lines = euroc.lines("imu0/data.csv")
    lines[0] = ",".join([names[0], *names[4:], *names[1:4]])
    euroc.write_lines("imu0/data.csv", lines)
    with _raises(euroc.path("imu0/data.csv"), "not in the expected order"):
        read_euroc(euroc.root)


def test_wrong_size_first_image_fails_at_read(euroc):
    p = euroc.mav0 / f"cam0/data/{euroc.frame_ts[0]}.png"
    cv2.imwrite(str(p), np.zeros((480, 640), np.uint8))
    with _raises(p, "640x480", "752x480"):
        read_euroc(euroc.root)


def test_wrong_size_later_image_fails_when_read(euroc):
    p = euroc.mav0 / f"cam0/data/{euroc.frame_ts[2]}.png"
    cv2.imwrite(str(p), np.zeros((240, 376), np.uint8))
    seq = read_euroc(euroc.root)
    seq.image(1)
    with _raises(p, "376x240", "752x480"):
        seq.image(2)


def test_wrong_resolution_in_yaml(euroc):
    euroc.path("cam0/sensor.yaml").write_text(cam_yaml(resolution=(640, 480)))
    with _raises(euroc.mav0 / f"cam0/data/{euroc.frame_ts[0]}.png", "752x480", "640x480"):
        read_euroc(euroc.root)


@pytest.mark.parametrize("kind", ["garbage", "truncated"])
def test_corrupt_png_names_file(euroc, kind):
    p = euroc.mav0 / f"cam0/data/{euroc.frame_ts[1]}.png"
    data = p.read_bytes()
    p.write_bytes(b"not a png at all" * 4 if kind == "garbage" else data[: len(data) // 3])
    seq = read_euroc(euroc.root)
    with _raises(p, "cannot decode"):
        seq.image(1)


def test_depth_png_of_wrong_type(euroc):
    p = euroc.mav0 / f"depth0/data/{euroc.frame_ts[0]}.png"
    cv2.imwrite(str(p), np.zeros((H, W), np.uint8))
    seq = read_euroc(euroc.root)
    with _raises(p, "uint16"):
        seq.depth(0)


@pytest.mark.parametrize(
    "edit,fragment",
    [
        (
            lambda s: s.replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", ""),
            "missing key 'intrinsics'",
        ),
        (lambda s: s.replace("[458.654, 457.296, 367.215, 248.375]", "[458.654, 457.296]"), "'intrinsics'"),
        (lambda s: s.replace("radial-tangential", "kannala-brandt"), "kannala-brandt"),
        (lambda s: s.replace("rows: 4", "rows: 3"), "4x4"),
        (lambda s: s.replace("0.0148655429818", "0.5"), "not a rotation"),
        (lambda s: s + "  bad: [\n", "invalid YAML"),
    ],
)
def test_bad_cam_yaml(euroc, edit, fragment):
    p = euroc.path("cam0/sensor.yaml")
    p.write_text(edit(p.read_text()))
    with _raises(p, fragment):
        read_euroc(euroc.root)


def test_bad_imu_yaml(euroc):
    p = euroc.path("imu0/sensor.yaml")
    p.write_text(imu_yaml().replace("gyroscope_random_walk: 1.9393e-05", "gyroscope_random_walk: lots"))
    with _raises(p, "gyroscope_random_walk", "'lots'"):
        read_euroc(euroc.root)


def test_yaml_float_without_dot_is_accepted(euroc):
    """PyYAML reads ``1e-3`` (no dot) as a string; the reader converts it."""
    p = euroc.path("imu0/sensor.yaml")
    p.write_text(imu_yaml().replace("2.0000e-3", "2e-3"))
    assert read_euroc(euroc.root).imu.accel_noise_density == 2e-3


def test_gt_quaternion_not_unit(euroc):
    ln = _edit_row(
        euroc, "state_groundtruth_estimate0/data.csv", 1, lambda p: [*p[:4], "0", "0", "0", "0", *p[8:]]
    )
    with _raises(euroc.path("state_groundtruth_estimate0/data.csv"), f"line {ln}", "norm"):
        read_euroc(euroc.root)


def test_empty_imu_file(euroc):
    euroc.write_lines("imu0/data.csv", [IMU_HEADER])
    with _raises(euroc.path("imu0/data.csv"), "no data rows"):
        read_euroc(euroc.root)


# --------------------------------------------------------------------------- speed
def test_imu_csv_of_30k_rows_is_parsed_exactly_and_fast(tmp_path):
    rng = np.random.default_rng(1)
    n = 30_000
    ts = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    v = rng.normal(size=(n, 6))
    p = tmp_path / "data.csv"
    p.write_text(
        IMU_HEADER
        + "\n"
        + "".join(f"{t}," + ",".join(repr(float(x)) for x in r) + "\n" for t, r in zip(ts, v, strict=True))
    )
    t = time.perf_counter()
    got_ts, got_v, lines = read_euroc_csv(p, IMU_COLUMNS)
    dt = time.perf_counter() - t
    np.testing.assert_array_equal(got_ts, ts)
    np.testing.assert_array_equal(got_v, v)
    assert lines[0] == 2 and lines[-1] == n + 1
    assert dt < 2.0, (
        f"parsing {n} IMU rows took {dt:.2f} s"
    )  # ~0.05 s measured; generous for a shared machine
