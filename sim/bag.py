"""Write an EuRoC-layout sequence as a ROS bag (ROS1 ``.bag``, ROS2 ``sqlite3`` or ``mcap``) with ``rosbags``.

Topics as EuRoC's bags name them: ``/cam0/image_raw`` (``sensor_msgs/Image``, ``mono8``), ``/imu0``
(``sensor_msgs/Imu``, no orientation: covariance[0] = -1), and the body ground truth on ``/ground_truth/pose``
(``geometry_msgs/PoseStamped``). Every message is recorded at its header stamp, in time order, so that the bag
read back (:func:`runtime.io.bag.read_bag`) gives the same samples, to the bit, as the ASL folder.
The calibration goes next to the bag as ``calib/mav0/{cam0,imu0}/sensor.yaml`` (bags carry none).
"""

from __future__ import annotations

import heapq
import shutil
from pathlib import Path

import cv2
import numpy as np

from runtime.geometry import R_to_quat_xyzw
from runtime.io.euroc import read_euroc

__all__ = ["BAG_FORMATS", "GT_TOPIC", "write_bag", "bag_name"]

BAG_FORMATS = ("bag", "ros2", "mcap")  # ROS1 .bag file, ROS2 folder with .db3, ROS2 folder with .mcap
GT_TOPIC = "/ground_truth/pose"


def bag_name(fmt: str) -> str:
    """File or folder name of the bag in a ``dit-sim euroc format=...`` output folder."""
    if fmt not in BAG_FORMATS:
        raise ValueError(f"format={fmt!r} is not one of asl, {', '.join(BAG_FORMATS)}")
    return "sequence.bag" if fmt == "bag" else "sequence"


class _Messages:
    """Message builders of one typestore (ROS1 headers carry ``seq``, ROS2 headers do not)."""

    def __init__(self, ros1: bool):
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.T = self.store.types

    def header(self, t_ns: int, frame: str, seq: int):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))
        H = self.T["std_msgs/msg/Header"]
        return H(seq=seq, stamp=stamp, frame_id=frame) if self.ros1 else H(stamp=stamp, frame_id=frame)

    def serialize(self, msg) -> bytes:
        if self.ros1:
            return self.store.serialize_ros1(msg, msg.__msgtype__)
        return self.store.serialize_cdr(msg, msg.__msgtype__)

    def image(self, t_ns: int, img: np.ndarray, seq: int):
        h, w = img.shape
        return self.T["sensor_msgs/msg/Image"](
            header=self.header(t_ns, "cam0", seq),
            height=h,
            width=w,
            encoding="mono8",
            is_bigendian=0,
            step=w,
            data=np.ascontiguousarray(img).reshape(-1),
        )

    def imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray, seq: int):
        V, Q = self.T["geometry_msgs/msg/Vector3"], self.T["geometry_msgs/msg/Quaternion"]
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(t_ns, "imu0", seq),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=no_orientation,
            angular_velocity=V(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V(x=float(accel[0]), y=float(accel[1]), z=float(accel[2])),
            linear_acceleration_covariance=np.zeros(9),
        )

    def pose(self, t_ns: int, T_w_b: np.ndarray, seq: int):
        q = R_to_quat_xyzw(T_w_b[:3, :3])
        P, Q = self.T["geometry_msgs/msg/Point"], self.T["geometry_msgs/msg/Quaternion"]
        pose = self.T["geometry_msgs/msg/Pose"](
            position=P(x=float(T_w_b[0, 3]), y=float(T_w_b[1, 3]), z=float(T_w_b[2, 3])),
            orientation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )
        return self.T["geometry_msgs/msg/PoseStamped"](header=self.header(t_ns, "world", seq), pose=pose)


def _writer(path: Path, fmt: str):
    if fmt == "bag":
        from rosbags.rosbag1 import Writer

        return Writer(path)
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    return Writer(path, version=9, storage_plugin=plugin)


def write_bag(asl_root: str | Path, out: str | Path, fmt: str = "bag", calib_dir: str | Path | None = None) -> Path:
    """Write the ASL sequence at ``asl_root`` as a bag at ``out`` (a ``.bag`` file or a ROS2 folder).

    Args:
        asl_root: an EuRoC-layout sequence (its ``mav0``).
        out: the bag to create (must not exist).
        fmt: ``bag`` (ROS1), ``ros2`` (sqlite3 ``.db3``) or ``mcap`` (ROS2 with MCAP storage).
        calib_dir: where to copy ``mav0/cam0/sensor.yaml`` and ``mav0/imu0/sensor.yaml`` (None: nowhere).

    Returns:
        ``out`` as a Path.
    """
    bag_name(fmt)
    seq = read_euroc(asl_root)
    out = Path(out)
    m = _Messages(ros1=fmt == "bag")
    # (stamp, order within a stamp, kind, index): IMU before an image of the same stamp, as a recorder sees them
    events = [
        heapq.merge(
            ((int(t), 0, "imu", k) for k, t in enumerate(seq.imu_ts)),
            ((int(t), 1, "img", k) for k, t in enumerate(seq.frame_ts)),
            ((int(t), 2, "gt", k) for k, t in enumerate(seq.gt.ts if seq.gt is not None else [])),
        )
    ]
    with _writer(out, fmt) as w:
        c_img = w.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=m.store)
        c_imu = w.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=m.store)
        c_gt = w.add_connection(GT_TOPIC, "geometry_msgs/msg/PoseStamped", typestore=m.store) if seq.gt else None
        for t, _, kind, k in events[0]:
            if kind == "imu":
                w.write(c_imu, t, m.serialize(m.imu(t, seq.gyro[k], seq.accel[k], k)))
            elif kind == "img":
                img = cv2.imread(str(seq.frame_paths[k]), cv2.IMREAD_GRAYSCALE)
                w.write(c_img, t, m.serialize(m.image(t, img, k)))
            else:
                w.write(c_gt, t, m.serialize(m.pose(t, seq.gt.T_w_b[k], k)))
    if calib_dir is not None:
        for sensor in ("cam0", "imu0"):
            dst = Path(calib_dir) / "mav0" / sensor
            dst.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(seq.mav0 / sensor / "sensor.yaml", dst / "sensor.yaml")
    return out


def write_bag_sequence(out: str | Path, fmt: str, **kw) -> Path:
    """``dit-sim euroc format=bag|ros2|mcap``: render the sequence (keywords of
    :func:`sim.euroc.write_euroc_sequence`) and write it into ``out`` as the bag :func:`bag_name` names, with
    ``calib/`` (its sensor.yaml files) and ``sim_info.json``; the ASL folder rendered on the way is removed, and so
    is the partial output of an interrupted or failed run (:func:`sim.output.sim_output`).

    Returns:
        The bag (``out/sequence.bag`` or the ROS2 folder ``out/sequence``).
    """
    import json

    from sim.euroc import write_euroc_sequence
    from sim.output import sim_output, write_info

    out = Path(out)
    name = bag_name(fmt)
    with sim_output(out, (name, "calib", "_asl"), "euroc", format=fmt):
        asl = write_euroc_sequence(out / "_asl", **kw)
        try:
            bag = write_bag(asl, out / name, fmt, calib_dir=out / "calib")
            info = json.loads((asl / "sim_info.json").read_text())
            info.update(format=fmt, bag=name, calib="calib", gt_topic=GT_TOPIC)
        finally:
            shutil.rmtree(asl)
        write_info(out, info)
    return bag
