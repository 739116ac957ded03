"""Readers and writers of the real data formats (EuRoC ASL, ROS bags, Kalibr calibration, TUM trajectories, PLY,
NYU Depth v2); :func:`open_sequence` opens an ASL folder or a bag.

Quaternion orders are converted here and nowhere else: EuRoC CSVs are ``(w, x, y, z)``, TUM files
``(x, y, z, w)``; everything returned uses the conventions of :mod:`runtime.geometry`.
"""

from runtime.io.bag import BagFormatError, BagSequence, BagTopics, read_bag
from runtime.io.calib import Calibration, read_calibration, read_kalibr
from runtime.io.euroc import (
    DEPTH_SCALE,
    GT_COLUMNS,
    IMU_COLUMNS,
    EurocFormatError,
    EurocSequence,
    EurocWarning,
    GroundTruth,
    ImuParams,
    load_sensor_yaml,
    read_camera_yaml,
    read_euroc,
    read_euroc_csv,
    read_groundtruth,
    read_imu_yaml,
)
from runtime.io.nyu import NYU_HW, NyuFormatError, NyuLabeledMat, list_nyu_h5, read_nyu_h5, read_nyu_split
from runtime.io.ply import PlyFormatError, read_ply, read_ply_faces, read_ply_normals, read_ply_vertex, write_ply
from runtime.io.sequence import CameraView, PinholeView, open_sequence
from runtime.io.tum import TumFormatError, read_tum, write_tum

__all__ = [
    "BagFormatError",
    "BagSequence",
    "BagTopics",
    "read_bag",
    "Calibration",
    "read_calibration",
    "read_kalibr",
    "CameraView",
    "PinholeView",
    "open_sequence",
    "DEPTH_SCALE",
    "GT_COLUMNS",
    "IMU_COLUMNS",
    "EurocFormatError",
    "EurocSequence",
    "EurocWarning",
    "GroundTruth",
    "ImuParams",
    "load_sensor_yaml",
    "read_camera_yaml",
    "read_euroc",
    "read_euroc_csv",
    "read_groundtruth",
    "read_imu_yaml",
    "NYU_HW",
    "NyuFormatError",
    "NyuLabeledMat",
    "list_nyu_h5",
    "read_nyu_h5",
    "read_nyu_split",
    "PlyFormatError",
    "read_ply",
    "read_ply_faces",
    "read_ply_normals",
    "read_ply_vertex",
    "write_ply",
    "TumFormatError",
    "read_tum",
    "write_tum",
]
