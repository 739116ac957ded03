"""ROS bags (ROS1, ROS2 sqlite3 and mcap) read back as the ASL sequence they were written from, image decoders,
and the bag errors."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags")
sim_euroc = pytest.importorskip("sim.euroc")

from runtime.io.bag import BagFormatError, BagTopics, image_from_msg, read_bag  # noqa: E402
from runtime.io.euroc import read_euroc  # noqa: E402
from runtime.io.sequence import open_sequence  # noqa: E402
from sim.bag import GT_TOPIC, write_bag  # noqa: E402


@pytest.fixture(scope="module")
def asl(tmp_path_factory):
    """3 s textured sequence at quarter resolution (188x120), noisy IMU (float64 values that must survive)."""
    out = tmp_path_factory.mktemp("asl") / "seq"
    return sim_euroc.write_euroc_sequence(
        out, "textured", duration=3.0, seed=5, progress=False, scale=0.25, realism=False
    )


@pytest.fixture(scope="module", params=["bag", "ros2", "mcap"])
def bag(request, asl, tmp_path_factory):
    d = tmp_path_factory.mktemp(f"bag_{request.param}")
    name = "seq.bag" if request.param == "bag" else "seq"
    return write_bag(asl, d / name, request.param, calib_dir=d / "calib"), d / "calib"


def test_bag_reads_back_bit_identical_to_the_asl_folder(asl, bag):
    path, calib = bag
    a, b = read_euroc(asl), read_bag(path, calib)
    assert b.camera == a.camera and np.array_equal(b.T_b_c, a.T_b_c) and b.cam_rate_hz == a.cam_rate_hz
    assert np.array_equal(b.frame_ts, a.frame_ts) and np.array_equal(b.imu_ts, a.imu_ts)
    assert np.array_equal(b.gyro, a.gyro) and np.array_equal(b.accel, a.accel)
    assert b.topics.gt == GT_TOPIC and np.array_equal(b.gt.ts, a.gt.ts)
    np.testing.assert_allclose(b.gt.T_w_b, a.gt.T_w_b, atol=1e-12)
    for i in (0, 1, 2, 7, 3, len(a) - 1, 0):  # forward (streamed) and backward (re-seek)
        assert np.array_equal(b.image(i), a.image(i)), i
    b.close()


def test_open_sequence_needs_calib_for_a_bag_and_names_missing_topics(bag):
    path, calib = bag
    with pytest.raises(ValueError, match="calib=DIR"):
        open_sequence(path)
    with pytest.raises(BagFormatError, match=r"no IMU topic '/imu1'.*/cam0/image_raw \(sensor_msgs/msg/Image\)"):
        read_bag(path, calib, BagTopics(imu="/imu1"))
    with pytest.raises(BagFormatError, match="has type sensor_msgs/msg/Imu, expected"):
        read_bag(path, calib, BagTopics(image="/imu0"))
    assert read_bag(path, calib, BagTopics(gt="none")).gt is None


def test_image_decoders_known_answers():
    img = np.arange(12 * 5, dtype=np.uint8).reshape(5, 12)
    padded = np.zeros((5, 16), np.uint8)
    padded[:, :12] = img
    msg = SimpleNamespace(height=5, width=12, step=16, encoding="mono8", is_bigendian=0, data=padded.ravel())
    assert np.array_equal(image_from_msg(msg, "sensor_msgs/msg/Image"), img)
    v16 = img.astype(np.uint16) * 256 + 7
    for big in (0, 1):
        raw = v16.astype(">u2" if big else "<u2").view(np.uint8).ravel()
        msg = SimpleNamespace(height=5, width=12, step=24, encoding="mono16", is_bigendian=big, data=raw)
        assert np.array_equal(image_from_msg(msg, "sensor_msgs/msg/Image"), img)
    rgb = np.stack([img, img, img], -1)
    msg = SimpleNamespace(height=5, width=12, step=36, encoding="rgb8", is_bigendian=0, data=rgb.ravel())
    assert np.array_equal(image_from_msg(msg, "sensor_msgs/msg/Image"), img)
    png = cv2.imencode(".png", img)[1].ravel()
    comp = SimpleNamespace(format="png", data=png)
    assert np.array_equal(image_from_msg(comp, "sensor_msgs/msg/CompressedImage"), img)
    msg = SimpleNamespace(height=5, width=12, step=12, encoding="bayer_rggb8", is_bigendian=0, data=img.ravel())
    with pytest.raises(ValueError, match="bayer_rggb8"):
        image_from_msg(msg, "sensor_msgs/msg/Image")


def test_ground_truth_from_transform_stamped_and_pose_stamped():
    from runtime.io.bag import _ground_truth, _pose_from_msg

    v = lambda **k: SimpleNamespace(**k)  # noqa: E731
    q = v(x=0.0, y=0.0, z=np.sin(np.pi / 4), w=np.cos(np.pi / 4))  # 90 deg about z
    tf = v(transform=v(translation=v(x=1.0, y=2.0, z=3.0), rotation=q))
    ps = v(pose=v(position=v(x=1.0, y=2.0, z=3.0), orientation=q))
    p1, q1 = _pose_from_msg(tf, "geometry_msgs/msg/TransformStamped")
    p2, q2 = _pose_from_msg(ps, "geometry_msgs/msg/PoseStamped")
    assert np.array_equal(p1, p2) and np.array_equal(q1, q2) and p1.tolist() == [1.0, 2.0, 3.0]
    gt = _ground_truth(np.array([0, 1_000_000_000]), np.stack([p1, p1 + [0.5, 0, 0]]), np.stack([q1, q1]))
    np.testing.assert_allclose(gt.T_w_b[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(gt.v_w[0], [0.5, 0, 0])
    np.testing.assert_allclose(gt.q_wxyz[0], [q.w, 0, 0, q.z])
    with pytest.raises(BagFormatError, match="norm"):
        _ground_truth(np.array([0, 1]), np.zeros((2, 3)), np.array([[0, 0, 0, 2.0], [0, 0, 0, 1.0]]))
