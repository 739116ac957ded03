"""ROS bags as sequences: ROS1 ``.bag`` files, ROS2 bag folders (``.db3`` or ``.mcap`` storage), read with
``rosbags`` (pure Python, no ROS install).

Topics (:class:`BagTopics`, EuRoC's names by default): ``sensor_msgs/Image`` or ``CompressedImage`` on the image
topic, ``sensor_msgs/Imu`` on the IMU topic, and, when present, ``geometry_msgs/PoseStamped`` or
``TransformStamped`` ground truth of the body. The calibration comes from ``calib=DIR``
(:func:`runtime.io.calib.read_calibration`: EuRoC ``sensor.yaml`` files or Kalibr yaml files), since bags carry
none.

Timestamps are the messages' ``header.stamp`` (EuRoC's bags stamp them as its ASL CSVs), not the recording time.
IMU and ground truth are read into memory on opening (12k IMU samples per minute at 200 Hz); images are not:
:meth:`BagSequence.image` streams them from the bag in order (a jump back re-seeks by recording time). Images are
decoded here (``mono8``, ``mono16``, ``8UC1``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8`` and compressed PNG/JPEG)
to grey uint8, as :meth:`runtime.io.euroc.EurocSequence.image` returns them.
Bad input raises :class:`BagFormatError` (a ``ValueError``) naming the bag, the topic and the problem.
"""

from __future__ import annotations

import logging
import struct
import threading
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from runtime.geometry import Camera, quat_xyzw_to_R
from runtime.io.calib import Calibration, read_calibration
from runtime.io.euroc import GroundTruth
from runtime.io.sensor_yaml import ImuParams

log = logging.getLogger(__name__)

__all__ = ["BagFormatError", "BagTopics", "BagSequence", "read_bag", "is_bag", "image_from_msg"]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
IMU_TYPE = "sensor_msgs/msg/Imu"
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped")
_CHANNELS = {
    "rgb8": (3, cv2.COLOR_RGB2GRAY),
    "bgr8": (3, cv2.COLOR_BGR2GRAY),
    "8UC3": (3, cv2.COLOR_BGR2GRAY),
    "rgba8": (4, cv2.COLOR_RGBA2GRAY),
    "bgra8": (4, cv2.COLOR_BGRA2GRAY),
    "8UC4": (4, cv2.COLOR_BGRA2GRAY),
}


class BagFormatError(ValueError):
    """A bag cannot be read as a sequence; the message names the bag, the topic and the problem."""


@dataclass(frozen=True)
class BagTopics:
    """Which topics hold the sequence. ``image`` / ``imu`` None: Kalibr's ``rostopic`` where the calibration
    names one, else EuRoC's ``/cam0/image_raw`` and ``/imu0``. ``gt``: a topic, ``"auto"`` (the one
    ``PoseStamped`` / ``TransformStamped`` topic, if any) or ``"none"``."""

    image: str | None = None
    imu: str | None = None
    gt: str | None = "auto"


def is_bag(path: str | Path) -> bool:
    """True for a ROS1 ``.bag`` file, a ``.mcap`` / ``.db3`` file or a ROS2 bag folder (``metadata.yaml``)."""
    p = Path(path)
    return p.suffix in (".bag", ".mcap", ".db3") or (p.is_dir() and (p / "metadata.yaml").is_file())


def _bag_path(path: Path) -> Path:
    """The path rosbags opens: the ``.bag`` file or the ROS2 folder (a ``.db3`` / ``.mcap`` file's folder)."""
    if not path.exists():
        raise BagFormatError(f"{path}: bag does not exist")
    if path.suffix in (".mcap", ".db3"):
        if not (path.parent / "metadata.yaml").is_file():
            raise BagFormatError(f"{path}: a ROS2 bag file needs its folder's metadata.yaml; give the bag folder")
        return path.parent
    return path


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # noqa: BLE001 - rosbags raises several unrelated types for a bad bag
        raise BagFormatError(f"{path}: cannot open as a ROS bag ({type(e).__name__}: {e})") from e
    return reader


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _raw_stamp_ns(raw, ros2: bool) -> int:
    """``header.stamp`` of a serialized message that starts with a ``std_msgs/Header`` (Image, CompressedImage),
    without decoding the rest. ROS1: ``uint32 seq, uint32 sec, uint32 nsec``; ROS2 CDR: a 4-byte encapsulation
    header (byte 1: 1 little-endian, 0 big-endian), then ``int32 sec, uint32 nanosec``."""
    if ros2:
        sec, nsec = struct.unpack_from("<iI" if raw[1] == 1 else ">iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec * 1_000_000_000 + nsec


def image_from_msg(msg, msgtype: str) -> np.ndarray:
    """Grey (H, W) uint8 image of a ``sensor_msgs/Image`` or ``CompressedImage`` message.

    16-bit images keep their high byte; colour images are converted with OpenCV's weights.

    Raises:
        ValueError: an unsupported encoding (named) or a buffer of the wrong size.
    """
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"cannot decode compressed image (format {msg.format!r})")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        return (img >> 8).astype(np.uint8) if img.dtype == np.uint16 else img
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding)
    buf = np.asarray(msg.data, dtype=np.uint8)
    if buf.size < h * step:
        raise ValueError(f"image data has {buf.size} bytes, expected height {h} x step {step} = {h * step}")
    rows = buf[: h * step].reshape(h, step)
    if enc in ("mono8", "8UC1"):
        return np.ascontiguousarray(rows[:, :w])
    if enc in ("mono16", "16UC1"):
        v = rows[:, : 2 * w].copy().view(">u2" if msg.is_bigendian else "<u2")
        return (v >> 8).astype(np.uint8)
    if enc in _CHANNELS:
        c, code = _CHANNELS[enc]
        return cv2.cvtColor(np.ascontiguousarray(rows[:, : c * w].reshape(h, w, c)), code)
    raise ValueError(f"image encoding {enc!r} is not supported (mono8, mono16, rgb8, bgr8, rgba8, bgra8)")


def _pose_from_msg(msg, msgtype: str) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), quaternion (x, y, z, w)) of a PoseStamped or TransformStamped."""
    if msgtype.endswith("TransformStamped"):
        t, q = msg.transform.translation, msg.transform.rotation
    else:
        t, q = msg.pose.position, msg.pose.orientation
    return np.array([t.x, t.y, t.z]), np.array([q.x, q.y, q.z, q.w])


def _connection(reader, path: Path, topic: str, types: tuple[str, ...], what: str):
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in reader.connections)) or "none"
        raise BagFormatError(f"{path}: no {what} topic {topic!r}; the bag has: {have}")
    bad = [c.msgtype for c in conns if c.msgtype not in types]
    if bad:
        raise BagFormatError(f"{path}: topic {topic!r} has type {bad[0]}, expected {' or '.join(types)}")
    return conns


def _gt_connections(reader, path: Path, gt: str | None):
    if gt in (None, "", "none"):
        return []
    if gt != "auto":
        return _connection(reader, path, gt, POSE_TYPES, "ground-truth")
    topics = sorted({c.topic for c in reader.connections if c.msgtype in POSE_TYPES})
    if len(topics) > 1:
        log.warning("%s: several pose topics %s; ground truth from %s (set topics.gt)", path, topics, topics[0])
    return [c for c in reader.connections if topics and c.topic == topics[0]]


@dataclass(eq=False)
class BagSequence:
    """A bag read as a sequence with the attributes of :class:`runtime.io.euroc.EurocSequence`.

    Attributes:
        root: the bag (file or ROS2 folder).
        camera, T_b_c, cam_rate_hz, imu: from the calibration folder (the rate from the frames when Kalibr's).
        frame_ts: (N,) int64 image stamps [ns] in IMU time (Kalibr's time shift added), strictly increasing.
        imu_ts, gyro, accel: IMU samples (int64 ns, rad/s, m/s^2).
        gt: body ground truth from the pose topic, or None (velocity by finite differences, biases NaN).
        topics: the topics read.
    """

    root: Path
    camera: Camera
    T_b_c: np.ndarray
    cam_rate_hz: float
    frame_ts: np.ndarray
    imu_ts: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    imu: ImuParams
    topics: BagTopics
    gt: GroundTruth | None = None
    _bag_ts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    _stream: dict = field(default_factory=dict, repr=False)

    has_depth = False

    def __len__(self) -> int:
        return int(self.frame_ts.shape[0])

    def __repr__(self) -> str:
        gt = "none" if self.gt is None else len(self.gt)
        return (
            f"BagSequence(root={str(self.root)!r}, frames={len(self)}, imu={self.imu_ts.shape[0]}, gt={gt}, "
            f"camera={self.camera.width}x{self.camera.height} {self.camera.model})"
        )

    def depth(self, i: int) -> None:
        """Bags carry no ground-truth depth."""
        return None

    def gt_pose_at(self, ts_ns):
        if self.gt is None:
            raise ValueError(f"{self.root}: bag has no ground-truth pose topic")
        return self.gt.pose_at(ts_ns)

    def image(self, i: int) -> np.ndarray:
        """Grey image of frame ``i`` (H, W) uint8; sequential reads stream, others re-seek."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        i = int(i) % n
        s = self._stream
        if s.get("thread") != threading.get_ident() or s.get("next") != i:
            self._seek(i)
        conn, raw = next(s["it"])
        s["next"] = i + 1
        try:
            img = image_from_msg(s["reader"].deserialize(raw, conn.msgtype), conn.msgtype)
        except Exception as e:  # noqa: BLE001 - name the frame whatever failed in decoding
            raise BagFormatError(f"{self.root}: topic {self.topics.image!r}, frame {i}: {e}") from e
        if (img.shape[1], img.shape[0]) != (self.camera.width, self.camera.height):
            raise BagFormatError(
                f"{self.root}: topic {self.topics.image!r}, frame {i}: image is {img.shape[1]}x{img.shape[0]} but "
                f"the calibration says {self.camera.width}x{self.camera.height}"
            )
        return img

    def _seek(self, i: int) -> None:
        """(Re)open the image stream at frame ``i`` in this thread (sqlite connections stay in their thread)."""
        s = self._stream
        if s.get("thread") != threading.get_ident():
            self.close()
            s["reader"] = _open_reader(self.root)
            s["thread"] = threading.get_ident()
            s["conns"] = _connection(s["reader"], self.root, self.topics.image, IMAGE_TYPES, "image")
        t = int(self._bag_ts[i])
        skip = i - int(np.searchsorted(self._bag_ts, t, "left"))  # earlier frames recorded at the same time
        s["it"] = ((c, raw) for c, _, raw in s["reader"].messages(connections=s["conns"], start=t))
        for _ in range(skip):
            next(s["it"])

    def close(self) -> None:
        """Close the image stream (reopened on the next :meth:`image`)."""
        reader = self._stream.pop("reader", None)
        self._stream.clear()
        if reader is not None:
            reader.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass


def read_bag(path: str | Path, calib: str | Path | Calibration, topics: BagTopics | None = None) -> BagSequence:
    """Open a bag as a sequence: one pass reads the image stamps, the IMU and the ground truth.

    Args:
        path: ROS1 ``.bag`` file, ROS2 bag folder, or a ``.db3`` / ``.mcap`` file inside one.
        calib: the calibration folder (``calib=DIR``) or a read :class:`Calibration`.
        topics: which topics (default: Kalibr's rostopics, else EuRoC's names; ground truth found by type).

    Raises:
        BagFormatError: no such topic (the bag's topics are listed), wrong message type, non-increasing stamps.
        EurocFormatError: a bad calibration file.

    Example:
        >>> seq = read_bag("MH_01_easy.bag", calib="MH_01_easy")  # doctest: +SKIP
    """
    path = _bag_path(Path(path).expanduser())
    cal = calib if isinstance(calib, Calibration) else read_calibration(calib)
    t = topics or BagTopics()
    t = BagTopics(t.image or cal.image_topic or "/cam0/image_raw", t.imu or cal.imu_topic or "/imu0", t.gt)
    reader = _open_reader(path)
    try:
        img_c = _connection(reader, path, t.image, IMAGE_TYPES, "image")
        imu_c = _connection(reader, path, t.imu, (IMU_TYPE,), "IMU")
        gt_c = _gt_connections(reader, path, t.gt)
        data = _scan(reader, path, img_c, imu_c, gt_c)
    finally:
        reader.close()
    frame_ts, bag_ts, imu_ts, imu_v, gt_ts, gt_p, gt_q = data
    for name, ts in (("image " + t.image, frame_ts), ("IMU " + t.imu, imu_ts), ("ground-truth", gt_ts)):
        bad = np.flatnonzero(np.diff(ts) <= 0)
        if bad.size:
            j = int(bad[0])
            raise BagFormatError(f"{path}: {name} stamps not strictly increasing ({ts[j + 1]} ns after {ts[j]} ns)")
    if frame_ts.size == 0 or imu_ts.size < 2:
        raise BagFormatError(f"{path}: {frame_ts.size} images on {t.image!r}, {imu_ts.size} IMU samples on {t.imu!r}")
    rate = cal.cam_rate_hz or (1e9 / float(np.median(np.diff(frame_ts))) if frame_ts.size > 1 else 1.0)
    gt = _ground_truth(gt_ts, gt_p, gt_q) if gt_ts.size >= 2 else None
    if gt_c and gt is None:
        log.warning("%s: ground-truth topic %r has fewer than 2 poses; no ground truth", path, gt_c[0].topic)
    seq = BagSequence(
        root=path,
        camera=cal.camera,
        T_b_c=cal.T_b_c,
        cam_rate_hz=float(rate),
        frame_ts=frame_ts + np.int64(cal.time_shift_ns),
        imu_ts=imu_ts,
        gyro=imu_v[:, :3].copy(),
        accel=imu_v[:, 3:].copy(),
        imu=cal.imu,
        topics=BagTopics(t.image, t.imu, gt_c[0].topic if gt_c else "none"),
        gt=gt,
        _bag_ts=bag_ts,
    )
    log.info("read %r", seq)
    return seq


def _scan(reader, path: Path, img_c, imu_c, gt_c):
    """One pass over the bag: image stamps and recording times, IMU rows, ground-truth poses."""
    img_ids, imu_ids = {id(c) for c in img_c}, {id(c) for c in imu_c}
    f_ts, b_ts, i_ts, i_v, g_ts, g_p, g_q = [], [], [], [], [], [], []
    for conn, t_bag, raw in reader.messages(connections=[*img_c, *imu_c, *gt_c]):
        if id(conn) in img_ids:  # the stamp only: images are decoded when read
            if len(raw) < 12:
                raise BagFormatError(f"{path}: topic {conn.topic!r}: a message of {len(raw)} bytes has no header")
            f_ts.append(_raw_stamp_ns(raw, reader.is2))
            b_ts.append(t_bag)
            continue
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as e:  # noqa: BLE001
            raise BagFormatError(f"{path}: topic {conn.topic!r}: cannot decode a {conn.msgtype} ({e})") from e
        if id(conn) in imu_ids:
            w, a = msg.angular_velocity, msg.linear_acceleration
            i_ts.append(_stamp_ns(msg.header))
            i_v.append((w.x, w.y, w.z, a.x, a.y, a.z))
        else:
            p, q = _pose_from_msg(msg, conn.msgtype)
            g_ts.append(_stamp_ns(msg.header))
            g_p.append(p)
            g_q.append(q)
    i64 = lambda x: np.asarray(x, dtype=np.int64)  # noqa: E731
    return (
        i64(f_ts),
        i64(b_ts),
        i64(i_ts),
        np.asarray(i_v, dtype=np.float64).reshape(-1, 6),
        i64(g_ts),
        np.asarray(g_p, dtype=np.float64).reshape(-1, 3),
        np.asarray(g_q, dtype=np.float64).reshape(-1, 4),
    )


def _ground_truth(ts: np.ndarray, p: np.ndarray, q_xyzw: np.ndarray) -> GroundTruth:
    norm = np.linalg.norm(q_xyzw, axis=1)
    if np.any(np.abs(norm - 1.0) > 1e-2):
        j = int(np.argmax(np.abs(norm - 1.0)))
        raise BagFormatError(f"ground-truth pose at {ts[j]} ns has a quaternion of norm {norm[j]:.6f}, not 1")
    q_xyzw = q_xyzw / norm[:, None]
    T = np.zeros((len(ts), 4, 4))
    T[:, :3, :3] = quat_xyzw_to_R(q_xyzw)
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    v = np.gradient(p, ts.astype(np.float64) * 1e-9, axis=0)
    q_wxyz = np.concatenate([q_xyzw[:, 3:], q_xyzw[:, :3]], 1)
    nan = np.full((len(ts), 3), np.nan)
    return GroundTruth(ts=ts, p_w_b=p, q_wxyz=q_wxyz, T_w_b=T, v_w=v, bg=nan, ba=nan.copy())
