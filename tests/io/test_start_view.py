"""``StartView``: a sequence as a recording started later (``dit-slam start_s=``)."""

from types import SimpleNamespace

import numpy as np
import pytest

from runtime.io.sequence import CameraView, StartView


def _seq(n=10, rate_hz=10.0, imu_hz=200.0):
    """A stand-in sequence: frames every 0.1 s from t0, IMU at 200 Hz from t0, image i filled with i."""
    t0 = 1_000_000_000
    frame_ts = t0 + np.round(np.arange(n) / rate_hz * 1e9).astype(np.int64)
    imu_ts = t0 + np.round(np.arange(int(n / rate_hz * imu_hz)) / imu_hz * 1e9).astype(np.int64)
    gyro = np.arange(imu_ts.size, dtype=float)[:, None] * np.ones(3)
    return SimpleNamespace(
        frame_ts=frame_ts,
        frame_paths=[f"f{i}.png" for i in range(n)],
        imu_ts=imu_ts,
        gyro=gyro,
        accel=-gyro,
        gt="the ground truth",
        image=lambda i: np.full((2, 3), i, np.uint8),
        depth=lambda i: np.full((2, 3), 10.0 * i),
    )


def test_frames_from_the_first_at_or_after_the_start_and_the_imu_after_the_last_frame_left_out():
    seq = _seq()
    v = StartView(seq, 0.25)
    assert v.start_index == 3 and len(v) == 7
    np.testing.assert_array_equal(v.frame_ts, seq.frame_ts[3:])
    assert v.frame_paths == ["f3.png", "f4.png", "f5.png", "f6.png", "f7.png", "f8.png", "f9.png"]
    assert int(v.image(0)[0, 0]) == 3 and int(v.image(6)[0, 0]) == 9 and float(v.depth(1)[0, 0]) == 40.0
    # IMU: every sample after frame 2 (0.2 s) and none at or before it
    assert v.imu_ts[0] > seq.frame_ts[2] and v.imu_ts[0] - seq.frame_ts[2] <= 5_000_000
    np.testing.assert_array_equal(v.imu_ts, seq.imu_ts[seq.imu_ts > seq.frame_ts[2]])
    np.testing.assert_array_equal(v.gyro, seq.gyro[seq.imu_ts > seq.frame_ts[2]])
    np.testing.assert_array_equal(v.accel, -v.gyro)
    assert v.gt == "the ground truth"  # the rest is the wrapped sequence's
    with pytest.raises(IndexError):
        v.image(7)


def test_a_start_on_a_frame_stamp_keeps_that_frame_and_zero_keeps_everything():
    seq = _seq()
    assert StartView(seq, 0.3).start_index == 3
    v = StartView(seq, 0.0)
    assert v.start_index == 0 and len(v) == 10 and v.imu_ts.size == seq.imu_ts.size


@pytest.mark.parametrize(
    "start, message",
    [
        (-1.0, "expected seconds >= 0"),
        (float("nan"), "expected seconds >= 0"),
        (0.9, "leaves 1 of"),
        (0.95, "leaves 0 of"),
    ],
)
def test_bad_starts_are_refused(start, message):
    with pytest.raises(ValueError, match=message):
        StartView(_seq(), start)


def test_a_camera_view_over_a_start_view_keeps_the_start():
    v = CameraView(StartView(_seq(), 0.5), camera="refined")
    assert v.camera == "refined" and len(v) == 5 and v.start_s == 0.5 and int(v.image(0)[0, 0]) == 5
