"""The project's conventions, written once (DESIGN.md sec. 3).

* ``T_a_b`` is a 4x4 float64 matrix mapping a point from frame b to frame a: ``p_a = T_a_b @ p_b``.
* World ``w`` is gravity aligned, z up, gravity ``(0, 0, -9.81)`` m/s^2.
* Body ``b`` is the IMU frame; camera ``c`` is OpenCV optical (x right, y down, z forward).
* Quaternions are named by their order: EuRoC CSVs store ``w, x, y, z``, TUM files ``x, y, z, w``.
* Pixels are ``(u, v) = (column, row)``; depth is metric z in the camera frame, float32, 0 = invalid.

Every other module imports these helpers instead of re-deriving them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

GRAVITY = 9.81
GRAVITY_W = np.array([0.0, 0.0, -GRAVITY])  # m/s^2 in the world frame
NS_PER_S = 1_000_000_000  # timestamps are int64 nanoseconds


def ns_to_s(t_ns):
    """Nanoseconds (int or array) to float seconds.

    >>> ns_to_s(1_500_000_000)
    1.5
    """
    return np.asarray(t_ns) * 1e-9 if np.ndim(t_ns) else float(t_ns) * 1e-9


def s_to_ns(t_s) -> int:
    """Seconds (float) to integer nanoseconds, truncated toward zero (a duration, as ``int(t_s * 1e9)``).

    >>> s_to_ns(0.25)
    250000000
    """
    return int(float(t_s) * NS_PER_S)


# --------------------------------------------------------------------------- SO(3) / SE(3)
def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(a) @ b == np.cross(a, b)``. Shape (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, dtype=np.float64)
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (..., 3) [rad] -> rotation matrix (..., 3, 3).

    >>> np.allclose(so3_exp(np.array([0, 0, np.pi / 2])) @ [1, 0, 0], [0, 1, 0])
    True
    """
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    W = skew(w)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    return np.eye(3) + a * W + b * (W @ W)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`so3_exp` for a single rotation (3, 3) -> (3,), angle in [0, pi]."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-8:
        return 0.5 * v
    if np.pi - theta < 1e-5:  # near pi: axis from the symmetric part
        M = (R + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(M)))
        axis = M[:, i] / np.sqrt(M[i, i])
        if np.dot(axis, v) < 0:
            axis = -axis
        return axis * theta
    return v * theta / (2.0 * np.sin(theta))


def rotation_angle(R: np.ndarray) -> float:
    """Angle [rad] of a rotation matrix."""
    return float(np.linalg.norm(so3_log(R)))


def make_T(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """Build a 4x4 ``T_a_b`` from ``R_a_b`` (3, 3) and ``p_a`` of b's origin (3,)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4) without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ t[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def transform(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` (4, 4) to points ``p_b`` (..., 3) -> ``p_a`` (..., 3).

    >>> transform(make_T(t=[1, 2, 3]), np.zeros(3)).tolist()
    [1.0, 2.0, 3.0]
    """
    p_b = np.asarray(p_b, dtype=np.float64)
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def pose_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(translation error [m], rotation error [rad]) of ``inv(T_ref) @ T_est``."""
    E = inv_T(T_ref) @ T_est
    return float(np.linalg.norm(E[:3, 3])), rotation_angle(E[:3, :3])


# --------------------------------------------------------------------------- quaternions
def quat_wxyz_to_R(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) in EuRoC order ``(w, x, y, z)`` (..., 4) -> rotation matrices (..., 3, 3).

    The quaternion is normalised first; ``q`` and ``-q`` give the same rotation.
    """
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions ``(w, x, y, z)`` with ``w >= 0``."""
    R = np.asarray(R, dtype=np.float64)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    out = np.empty((R.shape[0], 4))
    for i, m in enumerate(R):  # Shepperd's method; branches per matrix (not a hot path)
        tr = np.trace(m)
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[i] = -q if q[0] < 0 else q
    return out.reshape(*shape, 4)


def quat_xyzw_to_R(q: np.ndarray) -> np.ndarray:
    """TUM order ``(x, y, z, w)`` (..., 4) -> rotation matrices (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    return quat_wxyz_to_R(np.concatenate([q[..., 3:4], q[..., :3]], -1))


def R_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> TUM order ``(x, y, z, w)`` with ``w >= 0``."""
    q = R_to_quat_wxyz(R)
    return np.concatenate([q[..., 1:], q[..., :1]], -1)


# --------------------------------------------------------------------------- gtsam
def to_pose3(T: np.ndarray):
    """4x4 ``T_a_b`` -> ``gtsam.Pose3`` (same frames)."""
    import gtsam

    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def from_pose3(pose) -> np.ndarray:
    """``gtsam.Pose3`` -> 4x4 float64 matrix."""
    return np.asarray(pose.matrix(), dtype=np.float64)


def pose_sigmas(rot_rad: float | np.ndarray, trans_m: float | np.ndarray) -> np.ndarray:
    """Sigmas in gtsam's Pose3 tangent order ``[rot(3), trans(3)]``."""
    return np.concatenate([np.broadcast_to(rot_rad, 3), np.broadcast_to(trans_m, 3)]).astype(np.float64)


# --------------------------------------------------------------------------- camera model
@dataclass(frozen=True)
class Camera:
    """Pinhole camera with lens distortion, as EuRoC's ``sensor.yaml`` and Kalibr's ``camchain.yaml`` give it.

    ``model`` names the distortion: ``"radtan"`` (radial-tangential / plumb bob, ``dist = (k1, k2, p1, p2)``) or
    ``"equidistant"`` (Kannala-Brandt fisheye as OpenCV's ``cv2.fisheye``, ``dist = (k1, k2, k3, k4)``: a ray at
    angle ``theta`` from the optical axis lands at radius ``theta (1 + k1 theta^2 + ... + k4 theta^8)`` on the
    normalised plane). Image size ``(width, height)`` in pixels. ``line_delay_s``: a rolling shutter's time between
    consecutive rows [s], the middle row read at the image's stamp (0: a global shutter; cam0 ``sensor.yaml``'s
    optional ``line_delay_s``).

    >>> fish = Camera(100, 100, 50, 40, 100, 80, (0.0, 0.0, 0.0, 0.0), "equidistant")
    >>> fish.project(np.array([1.0, 0.0, 1.0]))[0].round(6).tolist()  # 45 deg: radius pi/4 on the plane
    [128.539816, 40.0]
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    model: str = "radtan"
    line_delay_s: float = 0.0

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise ValueError(f"camera model {self.model!r} is not one of {CAMERA_MODELS}")
        if not self.line_delay_s >= 0.0:
            raise ValueError(f"camera line_delay_s={self.line_delay_s}: must be >= 0 (0 = global shutter)")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        return (self.fx, self.fy, self.cx, self.cy)

    @property
    def is_fisheye(self) -> bool:
        return self.model == "equidistant"

    @property
    def has_distortion(self) -> bool:
        """True unless pixels are pinhole pixels (an equidistant lens always distorts, even with k = 0)."""
        return self.is_fisheye or any(abs(d) > 0 for d in self.dist)

    def pinhole(self) -> Camera:
        """The same intrinsics without distortion (the camera of undistorted images)."""
        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    # ---- normalised plane <-> distorted normalised plane
    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Apply the lens distortion to normalised coordinates (..., 2) (rays ``[x, y, 1]``)."""
        if self.is_fisheye:
            r = np.hypot(xn[..., 0], xn[..., 1])
            return xn * _fisheye_scale(self.dist, r, np.arctan(r))[..., None]
        k1, k2, p1, p2 = self.dist
        x, y = xn[..., 0], xn[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], -1)

    def undistort_normalized(self, xd: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert :meth:`distort`: fixed-point iteration for radial-tangential (converges for EuRoC-like lenses),
        Newton on ``theta`` for equidistant. A fisheye ray at 90 deg or more from the axis has no point on the
        normalised plane: NaN."""
        xd = np.asarray(xd, dtype=np.float64)
        if not self.has_distortion:
            return xd.copy()
        if self.is_fisheye:
            return _fisheye_undistort(self.dist, xd)
        k1, k2, p1, p2 = self.dist
        x = xd.copy()
        for _ in range(iterations):
            u, v = x[..., 0], x[..., 1]
            r2 = u * u + v * v
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            dx = 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
            dy = p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
            x = np.stack([(xd[..., 0] - dx) / radial, (xd[..., 1] - dy) / radial], -1)
        return x

    # ---- 3D <-> pixels
    def project(self, p_c: np.ndarray, min_depth: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (..., 3) -> distorted pixels (..., 2) and a validity mask (z > min_depth).

        >>> cam = Camera(100, 100, 50, 40, 100, 80)
        >>> cam.project(np.array([0.0, 0.0, 2.0]))[0].tolist()
        [50.0, 40.0]
        """
        p_c = np.asarray(p_c, dtype=np.float64)
        z = p_c[..., 2]
        valid = z > min_depth
        zs = np.where(valid, z, 1.0)
        if self.is_fisheye:
            r = np.hypot(p_c[..., 0], p_c[..., 1])
            xd = p_c[..., :2] * _fisheye_scale(self.dist, r, np.arctan2(r, zs))[..., None]
        else:
            xn = p_c[..., :2] / zs[..., None]
            xd = self.distort(xn) if self.has_distortion else xn
        uv = np.stack([self.fx * xd[..., 0] + self.cx, self.fy * xd[..., 1] + self.cy], -1)
        return uv, valid

    def unproject(self, uv: np.ndarray, depth: np.ndarray | float) -> np.ndarray:
        """Distorted pixels (..., 2) and z-depth [m] (...) -> camera-frame points (..., 3)."""
        xn = self.pixel_to_normalized(uv)
        depth = np.asarray(depth, dtype=np.float64)
        return np.concatenate(
            [xn * depth[..., None], np.broadcast_to(depth[..., None], xn.shape[:-1] + (1,))], -1
        )

    def pixel_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (..., 2) -> undistorted normalised coordinates (..., 2)."""
        uv = np.asarray(uv, dtype=np.float64)
        xd = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], -1)
        return self.undistort_normalized(xd)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels -> pixels of the undistorted (pinhole, same K) image."""
        xn = self.pixel_to_normalized(uv)
        return np.stack([self.fx * xn[..., 0] + self.cx, self.fy * xn[..., 1] + self.cy], -1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        return (
            (uv[..., 0] >= margin)
            & (uv[..., 1] >= margin)
            & (uv[..., 0] <= self.width - 1 - margin)
            & (uv[..., 1] <= self.height - 1 - margin)
        )

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Maps for ``cv2.remap`` producing the undistorted image with the same K and size."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        xn = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy], -1)
        uv, _ = self.project(np.concatenate([xn, np.ones_like(u)[..., None]], -1))
        return uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32)

    def undistort_image(self, image: np.ndarray, interpolation: int | None = None) -> np.ndarray:
        """Resample a distorted image into the pinhole image with the same K (bilinear by default)."""
        import cv2

        if not self.has_distortion:
            return image
        mx, my = _cached_maps(self)
        interp = cv2.INTER_LINEAR if interpolation is None else interpolation
        return cv2.remap(image, mx, my, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


CAMERA_MODELS = ("radtan", "equidistant")


def _fisheye_scale(k, r: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``theta_d / r`` of the equidistant model (``r``: radius of the point or ray, ``theta``: its angle)."""
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
    small = r < 1e-12
    return np.where(small, 1.0, theta_d / np.where(small, 1.0, r))


def _fisheye_undistort(k, xd: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Distorted normalised (..., 2) -> normalised; Newton on ``theta(1 + k1 theta^2 + ...) = theta_d``."""
    theta_d = np.hypot(xd[..., 0], xd[..., 1])
    theta = np.clip(theta_d, 0.0, np.pi)
    for _ in range(iterations):
        t2 = theta * theta
        f = theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - theta_d
        df = 1.0 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        theta = theta - f / df
    small = theta_d < 1e-12
    scale = np.where(small, 1.0, np.tan(theta) / np.where(small, 1.0, theta_d))
    scale = np.where((theta >= np.pi / 2) | (theta < 0), np.nan, scale)
    return xd * scale[..., None]


_MAPS: dict[Camera, tuple[np.ndarray, np.ndarray]] = {}


def _cached_maps(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    if cam not in _MAPS:
        _MAPS[cam] = cam.undistort_maps()
    return _MAPS[cam]


# --------------------------------------------------------------------------- camera -> network
@dataclass(frozen=True)
class NetworkMapping:
    """The one mapping from (undistorted, pinhole) camera pixels to network pixels.

    Resize by ``scale`` so that the image covers ``(out_h, out_w)``, then centre-crop. A camera pixel
    ``(u, v)`` lands at ``(scale * (u + 0.5) - 0.5 - x0, scale * (v + 0.5) - 0.5 - y0)``; intrinsics map the
    same way, so a 3D point projects to the same network pixel through either path.

    >>> m = NetworkMapping.fit(640, 480, 224, 224)
    >>> m.out_size
    (224, 224)
    """

    in_w: int
    in_h: int
    out_w: int
    out_h: int
    scale: float = field(default=1.0)
    x0: float = field(default=0.0)
    y0: float = field(default=0.0)

    @staticmethod
    def fit(in_w: int, in_h: int, out_w: int, out_h: int) -> NetworkMapping:
        scale = max(out_w / in_w, out_h / in_h)
        rw, rh = in_w * scale, in_h * scale
        return NetworkMapping(in_w, in_h, out_w, out_h, scale, (rw - out_w) / 2.0, (rh - out_h) / 2.0)

    @property
    def out_size(self) -> tuple[int, int]:
        return (self.out_h, self.out_w)

    @property
    def resized_size(self) -> tuple[int, int]:
        """(width, height) of the image after resize, before the crop."""
        return (int(round(self.in_w * self.scale)), int(round(self.in_h * self.scale)))

    def points_to_network(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack(
            [
                self.scale * (uv[..., 0] + 0.5) - 0.5 - self.x0,
                self.scale * (uv[..., 1] + 0.5) - 0.5 - self.y0,
            ],
            -1,
        )

    def points_from_network(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack(
            [
                (uv[..., 0] + 0.5 + self.x0) / self.scale - 0.5,
                (uv[..., 1] + 0.5 + self.y0) / self.scale - 0.5,
            ],
            -1,
        )

    def camera(self, cam: Camera) -> Camera:
        """The pinhole camera of network images, given the (pinhole) camera of the input images."""
        if cam.width != self.in_w or cam.height != self.in_h:
            raise ValueError(f"camera is {cam.width}x{cam.height}, mapping expects {self.in_w}x{self.in_h}")
        s = self.scale
        return Camera(
            s * cam.fx,
            s * cam.fy,
            s * (cam.cx + 0.5) - 0.5 - self.x0,
            s * (cam.cy + 0.5) - 0.5 - self.y0,
            self.out_w,
            self.out_h,
        )

    def image_to_network(self, image: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Resize + centre-crop an image (H, W[, C]); ``nearest`` for depth maps (no mixing across edges)."""
        import cv2

        if image.shape[0] != self.in_h or image.shape[1] != self.in_w:
            raise ValueError(
                f"image is {image.shape[1]}x{image.shape[0]}, mapping expects {self.in_w}x{self.in_h}"
            )
        # An affine warp does resize and crop in one step with exactly the pixel mapping above.
        A = np.array(
            [
                [self.scale, 0.0, 0.5 * self.scale - 0.5 - self.x0],
                [0.0, self.scale, 0.5 * self.scale - 0.5 - self.y0],
            ]
        )
        interp = cv2.INTER_NEAREST if nearest else (cv2.INTER_AREA if self.scale < 1 else cv2.INTER_LINEAR)
        if interp == cv2.INTER_AREA:  # warpAffine has no area filter: resize, then crop by the same mapping
            rw, rh = self.resized_size
            resized = cv2.resize(image, (rw, rh), interpolation=cv2.INTER_AREA)
            sx, sy = self.scale * self.in_w / rw, self.scale * self.in_h / rh  # residual scale after rounding
            A = np.array([[sx, 0.0, 0.5 * sx - 0.5 - self.x0], [0.0, sy, 0.5 * sy - 0.5 - self.y0]])
            return cv2.warpAffine(resized, A, (self.out_w, self.out_h), flags=cv2.INTER_LINEAR)
        return cv2.warpAffine(
            image, A, (self.out_w, self.out_h), flags=interp, borderMode=cv2.BORDER_CONSTANT
        )


# --------------------------------------------------------------------------- projection and interpolation
def project_pinhole(K, p_c: np.ndarray, min_abs_depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection (no distortion) of camera-frame points.

    Args:
        K: ``(fx, fy, cx, cy)``.
        p_c: (N, 3) points in the camera frame [m].
        min_abs_depth: None: divide by z as it is (callers mask); else |z| is floored at this for the division.

    Returns:
        uv (N, 2) pixels ``(fx x / z + cx, fy y / z + cy)`` and z (N,) (unfloored).

    >>> project_pinhole((100.0, 100.0, 50.0, 40.0), np.array([[0.2, -0.4, 2.0]]))[0].tolist()
    [[60.0, 20.0]]
    """
    fx, fy, cx, cy = (float(k) for k in K)
    p_c = np.asarray(p_c, dtype=np.float64).reshape(-1, 3)
    z = p_c[:, 2]
    zs = z if min_abs_depth is None else np.where(np.abs(z) > min_abs_depth, z, min_abs_depth)
    return np.stack([fx * p_c[:, 0] / zs + cx, fy * p_c[:, 1] / zs + cy], -1), z


def blend_poses(T_a: np.ndarray, T_b: np.ndarray, w) -> np.ndarray:
    """Poses between ``T_a`` and ``T_b`` ((4, 4) or (N, 4, 4)) at fractions ``w`` (scalar or (N,)) in [0, 1]:
    position linear, rotation along the geodesic (slerp), ``R_a Exp(w Log(R_a^T R_b))``.

    >>> T = blend_poses(np.eye(4), make_T(so3_exp([0, 0, 1.0]), [2.0, 0, 0]), 0.5)
    >>> np.round(T[:3, 3], 6).tolist(), round(float(so3_log(T[:3, :3])[2]), 6)
    ([1.0, 0.0, 0.0], 0.5)
    """
    from scipy.spatial.transform import Rotation

    single = np.ndim(T_a) == 2
    Ta, Tb = np.asarray(T_a, np.float64).reshape(-1, 4, 4), np.asarray(T_b, np.float64).reshape(-1, 4, 4)
    w = np.broadcast_to(np.asarray(w, np.float64), (Ta.shape[0],))
    rel = Rotation.from_matrix(np.einsum("nji,njk->nik", Ta[:, :3, :3], Tb[:, :3, :3])).as_rotvec()
    out = np.tile(np.eye(4), (Ta.shape[0], 1, 1))
    out[:, :3, :3] = Ta[:, :3, :3] @ Rotation.from_rotvec(w[:, None] * rel).as_matrix()
    out[:, :3, 3] = (1 - w)[:, None] * Ta[:, :3, 3] + w[:, None] * Tb[:, :3, 3]
    return out[0] if single else out


def interpolate_poses(ts_query: np.ndarray, ts: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) at ``ts_query`` (ns) from a trajectory (``ts`` (K,) ns increasing, ``T`` (K, 4, 4)), and
    a mask (N,) of the queries inside ``[ts[0], ts[-1]]`` (the poses of the others are the identity).

    >>> T = np.stack([np.eye(4), make_T(t=[1.0, 0, 0])])
    >>> interpolate_poses(np.array([5, 20]), np.array([0, 10]), T)[0][:, 0, 3].tolist()
    [0.5, 0.0]
    """
    ts_query = np.asarray(ts_query, dtype=np.int64).reshape(-1)
    ts = np.asarray(ts, dtype=np.int64)
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    inside = (ts_query >= ts[0]) & (ts_query <= ts[-1])
    out = np.tile(np.eye(4), (ts_query.size, 1, 1))
    q = ts_query[inside]
    if q.size == 0:
        return out, inside
    if ts.size == 1:
        out[inside] = T[0]
        return out, inside
    i = np.clip(np.searchsorted(ts, q, side="right") - 1, 0, ts.size - 2)  # ts[i] <= q <= ts[i+1]
    a = (q - ts[i]).astype(np.float64) / (ts[i + 1] - ts[i]).astype(np.float64)
    out[inside] = blend_poses(T[i], T[i + 1], a)
    return out, inside
