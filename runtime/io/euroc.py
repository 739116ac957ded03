"""Reader of the EuRoC ASL dataset layout (real EuRoC MAV sequences and ``sim/`` output).

Layout read here (everything else under ``mav0``, e.g. ``cam1``, ``leica0``, ``pointcloud0``, is ignored)::

    <root>/mav0/cam0/data.csv                      #timestamp [ns],filename
    <root>/mav0/cam0/data/<timestamp>.png          8-bit grey, distorted (radial-tangential)
    <root>/mav0/cam0/sensor.yaml                   intrinsics, distortion, resolution, rate_hz, T_BS
    <root>/mav0/imu0/data.csv                      #timestamp [ns],w_RS_S_x..z [rad s^-1],a_RS_S_x..z [m s^-2]
    <root>/mav0/imu0/sensor.yaml                   noise densities, random walks, rate_hz, T_BS
    <root>/mav0/state_groundtruth_estimate0/data.csv   (optional) p, q (w,x,y,z), v, b_w, b_a of the body
    <root>/mav0/depth0/{data.csv,data/*.png,sensor.yaml}  (optional, written by sim/) uint16 depth * 5000

Files are accepted as the real datasets ship them: ``sensor.yaml`` with or without OpenCV's
``%YAML:1.0`` first line (and ``!!opencv-matrix`` tags), ``#`` comment lines in the CSVs, CRLF line ends,
``data.csv`` rows whose image is missing (warned about with :class:`EurocWarning` and skipped), ground truth
covering only part of the images.
Bad input raises :class:`EurocFormatError` (a ``ValueError``) naming the file, the line and the problem.

Conventions (``runtime/geometry.py``): timestamps int64 ns; ``T_b_c`` is cam0's ``T_BS`` (body = IMU frame);
ground truth is ``T_w_b`` of the body; EuRoC quaternions are ``(w, x, y, z)``.
"""

from __future__ import annotations

import logging
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from runtime.geometry import Camera, interpolate_poses, quat_wxyz_to_R
from runtime.io.asl_format import EurocFormatError, EurocWarning, read_text
from runtime.io.sensor_yaml import ImuParams, load_sensor_yaml, read_camera_yaml, read_imu_yaml, sensor_float

log = logging.getLogger(__name__)

__all__ = [
    "EurocFormatError",
    "EurocWarning",
    "ImuParams",
    "GroundTruth",
    "EurocSequence",
    "read_euroc",
    "read_euroc_csv",
    "load_sensor_yaml",
    "read_camera_yaml",
    "read_imu_yaml",
    "read_groundtruth",
    "IMU_COLUMNS",
    "GT_COLUMNS",
    "DEPTH_SCALE",
]

#: Column names of ``imu0/data.csv`` (gyro first, then accelerometer), units stripped.
IMU_COLUMNS = ("timestamp", "w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
#: Column names of ``state_groundtruth_estimate0/data.csv``, units stripped.
GT_COLUMNS = (
    "timestamp",
    "p_RS_R_x",
    "p_RS_R_y",
    "p_RS_R_z",
    "q_RS_w",
    "q_RS_x",
    "q_RS_y",
    "q_RS_z",
    "v_RS_R_x",
    "v_RS_R_y",
    "v_RS_R_z",
    "b_w_RS_S_x",
    "b_w_RS_S_y",
    "b_w_RS_S_z",
    "b_a_RS_S_x",
    "b_a_RS_S_y",
    "b_a_RS_S_z",
)
#: The header lines EuRoC writes above ``imu0/data.csv`` and ``state_groundtruth_estimate0/data.csv`` (units in
#: brackets); the reader matches columns by name with the units stripped, writers use these.
IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
#: EuRoC MAV cam0 (MT9M034) calibration as its ``sensor.yaml`` ships it: intrinsics [fu, fv, cu, cv],
#: radial-tangential distortion, 752x480; the simulator writes it and the tests use it.
EUROC_CAM0 = Camera(
    458.654, 457.296, 367.215, 248.375, 752, 480, (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
)
#: EuRoC cam0 ``T_BS``: pose of cam0 in the body (IMU) frame.
EUROC_T_B_C0 = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
#: Default ``depth0`` PNG scale: value = depth_m * DEPTH_SCALE (TUM RGB-D convention), 0 = invalid.
DEPTH_SCALE = 5000.0

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_DIGITS = re.compile(r"\d+")


# --------------------------------------------------------------------------- data classes
@dataclass(eq=False)
class GroundTruth:
    """Body (IMU) trajectory from ``state_groundtruth_estimate0/data.csv``.

    Attributes:
        ts: (K,) int64 timestamps [ns], strictly increasing.
        p_w_b: (K, 3) body position in the world [m].
        q_wxyz: (K, 4) unit quaternions ``(w, x, y, z)`` of ``R_w_b`` (normalised on read).
        T_w_b: (K, 4, 4) body poses.
        v_w: (K, 3) body velocity in the world [m/s].
        bg: (K, 3) gyroscope bias [rad/s].
        ba: (K, 3) accelerometer bias [m/s^2].
    """

    ts: np.ndarray
    p_w_b: np.ndarray
    q_wxyz: np.ndarray
    T_w_b: np.ndarray
    v_w: np.ndarray
    bg: np.ndarray
    ba: np.ndarray

    def __len__(self) -> int:
        return int(self.ts.shape[0])

    def __repr__(self) -> str:
        return f"GroundTruth({len(self)} states, {self.ts[0]}..{self.ts[-1]} ns)"

    def covers(self, ts_ns: np.ndarray | int) -> np.ndarray:
        """Boolean mask: which timestamps [ns] lie in ``[ts[0], ts[-1]]`` (where :meth:`pose_at` works)."""
        t = np.asarray(ts_ns)
        return (t >= self.ts[0]) & (t <= self.ts[-1])

    def pose_at(self, ts_ns: np.ndarray | int) -> np.ndarray:
        """Interpolated body pose ``T_w_b`` at time(s) ``ts_ns``.

        Position is interpolated linearly and rotation by slerp between the two enclosing ground-truth states.

        Args:
            ts_ns: int timestamp [ns] or (N,) integer array.

        Returns:
            (4, 4) float64 for a scalar, (N, 4, 4) for an array.

        Raises:
            ValueError: a timestamp outside ``[ts[0], ts[-1]]`` or a non-integer timestamp.
        """
        t = np.asarray(ts_ns)
        if t.dtype.kind not in "iu":
            raise ValueError(f"ground-truth timestamps must be integer nanoseconds, got dtype {t.dtype}")
        scalar = t.ndim == 0
        t = np.atleast_1d(t).astype(np.int64)
        outside = ~self.covers(t)
        if outside.any():
            bad = int(t[np.flatnonzero(outside)[0]])
            raise ValueError(
                f"timestamp {bad} ns is outside the ground-truth range [{self.ts[0]}, {self.ts[-1]}] ns "
                f"({int(outside.sum())} of {t.size} queried timestamps outside)"
            )
        out, _ = interpolate_poses(t, self.ts, self.T_w_b)
        return out[0] if scalar else out


@dataclass(eq=False)
class EurocSequence:
    """One EuRoC-layout sequence; images and depth maps are read lazily, everything else is in memory.

    Attributes:
        root: folder that contains ``mav0``.
        camera: cam0 model (distorted pinhole + radial-tangential, from ``cam0/sensor.yaml``).
        T_b_c: (4, 4) cam0 pose in the body (IMU) frame, cam0 ``T_BS``.
        cam_rate_hz: nominal camera rate [Hz].
        frame_ts: (N,) int64 frame timestamps [ns] (only frames whose PNG exists).
        frame_paths: N paths of the cam0 PNGs.
        imu_ts: (M,) int64 IMU timestamps [ns].
        gyro: (M, 3) angular velocity [rad/s] in the IMU frame.
        accel: (M, 3) specific force [m/s^2] in the IMU frame.
        imu: noise model and ``T_b_s`` from ``imu0/sensor.yaml``.
        gt: ground truth of the body, or None when the sequence has none.
        depth_scale: PNG value per metre of ``depth0`` (5000 unless its sensor.yaml says otherwise).
    """

    root: Path
    camera: Camera
    T_b_c: np.ndarray
    cam_rate_hz: float
    frame_ts: np.ndarray
    frame_paths: list[Path]
    imu_ts: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    imu: ImuParams
    gt: GroundTruth | None = None
    depth_scale: float = DEPTH_SCALE
    _depth_paths: dict[int, Path] | None = field(default=None, repr=False)

    @property
    def mav0(self) -> Path:
        return self.root / "mav0"

    @property
    def has_depth(self) -> bool:
        """True when the sequence has a ``depth0`` folder (ground-truth depth written by ``sim/``)."""
        return self._depth_paths is not None

    def __len__(self) -> int:
        return int(self.frame_ts.shape[0])

    def __repr__(self) -> str:
        gt = "none" if self.gt is None else len(self.gt)
        depth = "none" if self._depth_paths is None else len(self._depth_paths)
        return (
            f"EurocSequence(root={str(self.root)!r}, frames={len(self)}, imu={self.imu_ts.shape[0]}, "
            f"gt={gt}, "
            f"depth={depth}, camera={self.camera.width}x{self.camera.height})"
        )

    def _check_index(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        return int(i) % n

    def image(self, i: int) -> np.ndarray:
        """Grey image of frame ``i``: (H, W) uint8, distorted as recorded; raises if unreadable/mis-sized."""
        i = self._check_index(i)
        path = self.frame_paths[i]
        img = _imread(path, cv2.IMREAD_GRAYSCALE)
        _check_size(img, self.camera, path, "cam0/sensor.yaml")
        return img

    def depth(self, i: int) -> np.ndarray | None:
        """Ground-truth depth of frame ``i``: (H, W) float32 z in cam0 [m], 0 = invalid; None if absent."""
        i = self._check_index(i)
        if self._depth_paths is None:
            return None
        path = self._depth_paths.get(int(self.frame_ts[i]))
        if path is None:
            return None
        raw = _imread(path, cv2.IMREAD_UNCHANGED)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise EurocFormatError(
                f"{path}: depth PNG must be single-channel uint16, got {raw.dtype} with shape {raw.shape}"
            )
        _check_size(raw, self.camera, path, "cam0/sensor.yaml")
        return raw.astype(np.float32) / np.float32(self.depth_scale)

    def gt_pose_at(self, ts_ns: np.ndarray | int) -> np.ndarray:
        """Interpolated ground-truth ``T_w_b`` at ``ts_ns`` (see :meth:`GroundTruth.pose_at`)."""
        if self.gt is None:
            raise ValueError(f"{self.mav0}: sequence has no ground truth (state_groundtruth_estimate0)")
        return self.gt.pose_at(ts_ns)


# --------------------------------------------------------------------------- files
def _imread(path: Path, flags: int) -> np.ndarray:
    try:
        img = cv2.imread(str(path), flags)
    except cv2.error as e:  # pragma: no cover - cv2 usually returns None instead
        raise EurocFormatError(f"{path}: cannot decode image ({e})") from e
    if img is None:
        if not Path(path).is_file():
            raise EurocFormatError(f"{path}: image file is missing")
        raise EurocFormatError(f"{path}: cannot decode image (corrupt or not an image file)")
    return img


def _check_size(img: np.ndarray, cam: Camera, path: Path, source: str) -> None:
    h, w = img.shape[:2]
    if (w, h) != (cam.width, cam.height):
        raise EurocFormatError(
            f"{path}: image is {w}x{h} (width x height) but {source} resolution is {cam.width}x{cam.height}"
        )


def _png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk without decoding; None if the file is not a PNG."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _norm_name(name: str) -> str:
    """'#timestamp [ns]' / ' w_RS_S_x [rad s^-1]' -> 'timestamp' / 'w_rs_s_x'."""
    return re.sub(r"\[.*?\]", "", name).strip().lstrip("#").strip().lower()


def _data_lines(path: Path) -> tuple[list[str], np.ndarray, list[str]]:
    """Non-empty, non-comment lines of a CSV, their 1-based line numbers, and the comment lines."""
    text = read_text(path)
    rows: list[str] = []
    numbers: list[int] = []
    comments: list[str] = []
    for j, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            comments.append(s)
            continue
        rows.append(s)
        numbers.append(j)
    return rows, np.asarray(numbers, dtype=np.int64), comments


def _check_header(path: Path, comments: list[str], columns: Sequence[str]) -> None:
    """A header naming the expected columns in another order (e.g. accel before gyro) is an error."""
    want = [c.lower() for c in columns]
    for c in comments[:1]:
        got = [_norm_name(x) for x in c.split(",")]
        if len(got) == len(want) and got != want and sorted(got) == sorted(want):
            raise EurocFormatError(f"{path}: header columns {got} are not in the expected order {want}")


def _bad_row(path: Path, rows: list[str], numbers: np.ndarray, columns: Sequence[str]) -> EurocFormatError:
    """Find the first malformed row (slow path, only after the fast parser failed) and describe it."""
    for s, ln in zip(rows, numbers, strict=True):
        parts = s.split(",")
        if len(parts) != len(columns):
            return EurocFormatError(f"{path}: line {ln}: expected {len(columns)} columns, got {len(parts)}: {s!r}")
        if not _DIGITS.fullmatch(parts[0].strip()):
            return EurocFormatError(f"{path}: line {ln}: timestamp {parts[0]!r} is not an integer [ns]")
        for name, p in zip(columns[1:], parts[1:], strict=True):
            try:
                float(p)
            except ValueError:
                return EurocFormatError(f"{path}: line {ln}: column '{name}' value {p!r} is not a number")
    return EurocFormatError(f"{path}: cannot parse")  # pragma: no cover


def _check_increasing(path: Path, ts: np.ndarray, numbers: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(ts) <= 0)
    if bad.size:
        j = int(bad[0])
        raise EurocFormatError(
            f"{path}: line {numbers[j + 1]}: timestamps not strictly increasing "
            f"({ts[j + 1]} ns after {ts[j]} ns on line {numbers[j]})"
        )


def read_euroc_csv(path: str | Path, columns: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a numeric ASL CSV (int timestamp [ns] then floats) with numpy, checking every row.

    Args:
        path: the CSV file; ``#`` lines and blank lines are skipped.
        columns: expected column names (timestamp first), used for the column count and messages.

    Returns:
        ts (N,) int64 [ns], strictly increasing; values (N, len(columns) - 1) float64, all finite;
        line numbers (N,) int64 of the rows in the file.

    Raises:
        EurocFormatError: missing file, no rows, malformed row, NaN/inf value, or non-increasing timestamps,
        naming the file and the line (and column).
    """
    path = Path(path)
    rows, numbers, comments = _data_lines(path)
    _check_header(path, comments, columns)
    if not rows:
        raise EurocFormatError(f"{path}: no data rows")
    ncol = len(columns)
    commas = np.fromiter((s.count(",") for s in rows), dtype=np.int64, count=len(rows))
    if (commas != ncol - 1).any():
        raise _bad_row(path, rows, numbers, columns)
    try:
        ts = np.loadtxt(rows, delimiter=",", dtype=np.int64, usecols=0, ndmin=1)
        vals = np.loadtxt(rows, delimiter=",", dtype=np.float64, usecols=range(1, ncol), ndmin=2)
    except ValueError:
        raise _bad_row(path, rows, numbers, columns) from None
    if (ts < 0).any():
        j = int(np.flatnonzero(ts < 0)[0])
        raise EurocFormatError(f"{path}: line {numbers[j]}: negative timestamp {ts[j]}")
    bad = ~np.isfinite(vals)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise EurocFormatError(
            f"{path}: line {numbers[r]}: column '{columns[c + 1]}' is {vals[r, c]} (NaN/inf values are not allowed)"
        )
    _check_increasing(path, ts, numbers)
    return ts, vals, numbers


def _read_file_list(path: Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """``#timestamp [ns],filename`` CSV -> (ts int64 (N,), filenames, line numbers)."""
    rows, numbers, _ = _data_lines(path)
    if not rows:
        raise EurocFormatError(f"{path}: no data rows")
    ts = np.empty(len(rows), dtype=np.int64)
    names: list[str] = []
    for j, (s, ln) in enumerate(zip(rows, numbers, strict=True)):
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 2:
            raise EurocFormatError(f"{path}: line {ln}: expected 2 columns (timestamp, filename), got {len(parts)}")
        if not _DIGITS.fullmatch(parts[0]):
            raise EurocFormatError(f"{path}: line {ln}: timestamp {parts[0]!r} is not an integer [ns]")
        if not parts[1] or "/" in parts[1] or "\\" in parts[1]:
            raise EurocFormatError(f"{path}: line {ln}: bad filename {parts[1]!r}")
        ts[j] = int(parts[0])
        names.append(parts[1])
    _check_increasing(path, ts, numbers)
    return ts, names, numbers


def _existing(path_csv: Path, data_dir: Path, ts: np.ndarray, names: list[str]) -> tuple[np.ndarray, list[Path]]:
    """Keep the rows whose file exists in ``data_dir``; warn (naming the files) about the others."""
    if not data_dir.is_dir():
        raise EurocFormatError(f"{data_dir}: missing folder (images listed in {path_csv})")
    present = {p.name for p in data_dir.iterdir()}
    keep = np.fromiter((n in present for n in names), dtype=bool, count=len(names))
    if not keep.all():
        missing = [str(data_dir / n) for n, k in zip(names, keep, strict=True) if not k]
        shown = ", ".join(missing[:5]) + (f", ... ({len(missing) - 5} more)" if len(missing) > 5 else "")
        msg = f"{path_csv}: {len(missing)} of {len(names)} rows name files that do not exist, skipped: {shown}"
        warnings.warn(msg, EurocWarning, stacklevel=3)
    return ts[keep], [data_dir / n for n, k in zip(names, keep, strict=True) if k]


def read_groundtruth(path: str | Path) -> GroundTruth:
    """Read ``state_groundtruth_estimate0/data.csv`` (17 columns, quaternion ``w, x, y, z``)."""
    path = Path(path)
    ts, v, numbers = read_euroc_csv(path, GT_COLUMNS)
    q = v[:, 3:7]
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-2)
    if bad.size:
        j = int(bad[0])
        raise EurocFormatError(f"{path}: line {numbers[j]}: quaternion (w,x,y,z) has norm {norm[j]:.6f}, not 1")
    q = q / norm[:, None]
    p = v[:, 0:3].copy()
    T = np.zeros((len(ts), 4, 4))
    T[:, :3, :3] = quat_wxyz_to_R(q)
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return GroundTruth(
        ts=ts, p_w_b=p, q_wxyz=q, T_w_b=T, v_w=v[:, 7:10].copy(), bg=v[:, 10:13].copy(), ba=v[:, 13:16].copy()
    )


def _find_mav0(root: Path) -> tuple[Path, Path]:
    if not root.is_dir():
        raise EurocFormatError(f"{root}: missing folder (EuRoC sequence root)")
    if (root / "mav0").is_dir():
        return root, root / "mav0"
    if root.name == "mav0" or (root / "cam0").is_dir():
        return root.parent, root
    raise EurocFormatError(f"{root}: missing folder 'mav0' (expected {root}/mav0/cam0, imu0, ...)")


def read_euroc(root: str | Path) -> EurocSequence:
    """Read an EuRoC ASL sequence (metadata, IMU and ground truth now; images lazily).

    Args:
        root: the folder that contains ``mav0``, or ``mav0`` itself.

    Returns:
        The sequence. Frames whose PNG is missing are skipped with an :class:`EurocWarning`. The first frame's
        PNG header is checked against cam0's resolution now; every image again when it is read.

    Raises:
        EurocFormatError: a required file or folder is missing or malformed (the message names it).

    Example:
        >>> seq = read_euroc("data/MH_01_easy")  # doctest: +SKIP
        >>> img = seq.image(0); T_w_b = seq.gt_pose_at(seq.frame_ts[100])  # doctest: +SKIP
    """
    root, mav0 = _find_mav0(Path(root))
    cam_dir, imu_dir, gt_dir = mav0 / "cam0", mav0 / "imu0", mav0 / "state_groundtruth_estimate0"
    if not cam_dir.is_dir():
        raise EurocFormatError(f"{cam_dir}: missing folder")
    if not imu_dir.is_dir():
        if (gt_dir / "data.csv").is_file():
            hint = f"; it has a ground truth: `dit-sim imu source={root} out=DIR` writes a copy with an IMU fit to it"
        else:
            hint = "; it has no ground truth to synthesise one from"
        raise EurocFormatError(f"{imu_dir}: missing folder (the system is visual-inertial{hint})")

    camera, T_b_c, cam_rate = read_camera_yaml(cam_dir / "sensor.yaml")
    ts_all, names, _ = _read_file_list(cam_dir / "data.csv")
    frame_ts, frame_paths = _existing(cam_dir / "data.csv", cam_dir / "data", ts_all, names)
    if not frame_paths:
        raise EurocFormatError(f"{cam_dir / 'data.csv'}: none of the {len(names)} listed images exist")
    size = _png_size(frame_paths[0])
    if size is not None and size != (camera.width, camera.height):
        raise EurocFormatError(
            f"{frame_paths[0]}: image is {size[0]}x{size[1]} (width x height) but {cam_dir / 'sensor.yaml'} "
            f"resolution is {camera.width}x{camera.height}"
        )

    imu = read_imu_yaml(imu_dir / "sensor.yaml")
    imu_ts, iv, _ = read_euroc_csv(imu_dir / "data.csv", IMU_COLUMNS)

    gt = None
    if gt_dir.is_dir():
        gt = read_groundtruth(gt_dir / "data.csv")
    else:
        log.info("%s: no state_groundtruth_estimate0, sequence has no ground truth", mav0)

    depth_paths = None
    depth_scale = DEPTH_SCALE
    depth_dir = mav0 / "depth0"
    if depth_dir.is_dir():
        if (depth_dir / "sensor.yaml").is_file():
            dy = load_sensor_yaml(depth_dir / "sensor.yaml")
            if "depth_scale" in dy:
                depth_scale = sensor_float(dy["depth_scale"], "depth_scale", depth_dir / "sensor.yaml")
                if depth_scale <= 0:
                    raise EurocFormatError(f"{depth_dir / 'sensor.yaml'}: depth_scale must be positive")
        dts, dnames, _ = _read_file_list(depth_dir / "data.csv")
        dts, dpaths = _existing(depth_dir / "data.csv", depth_dir / "data", dts, dnames)
        depth_paths = {int(t): p for t, p in zip(dts, dpaths, strict=True)}

    seq = EurocSequence(
        root=root,
        camera=camera,
        T_b_c=T_b_c,
        cam_rate_hz=cam_rate,
        frame_ts=frame_ts,
        frame_paths=frame_paths,
        imu_ts=imu_ts,
        gyro=iv[:, 0:3].copy(),
        accel=iv[:, 3:6].copy(),
        imu=imu,
        gt=gt,
        depth_scale=depth_scale,
        _depth_paths=depth_paths,
    )
    log.info("read %r", seq)
    return seq
