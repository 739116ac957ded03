"""Analytic depth providers with :class:`runtime.network.KeyframeDepth`'s interface, and a small scene."""

from __future__ import annotations

import numpy as np

from runtime.geometry import make_T, so3_exp
from tests.runtime.synth import EUROC_T_BS

T_B_C = EUROC_T_BS


def smooth_bases(C: int, H: int, W: int, seed: int = 0, amplitude: float = 0.1) -> np.ndarray:
    """C smooth maps (C, H, W): random low-frequency cosines with values in about [-amplitude, amplitude]."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    out = np.empty((C, H, W))
    for i in range(C):
        ku, kv = rng.uniform(0.5, 2.0, 2) * np.pi / np.array([W, H])
        pu, pv = rng.uniform(0, 2 * np.pi, 2)
        out[i] = amplitude * np.cos(ku * u + pu) * np.cos(kv * v + pv)
    return out


def dct_bases(C: int, H: int, W: int, amplitude: float = 0.1) -> np.ndarray:
    """The first C 2D DCT-II modes (C, H, W) (constant, then low frequencies), peak value ``amplitude``:
    orthogonal, so every code direction moves the depth map by a comparable amount."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    modes = sorted(((a, b) for a in range(4) for b in range(4)), key=lambda m: (m[0] + m[1], m))[:C]
    return np.stack(
        [amplitude * np.cos(np.pi * a * (u + 0.5) / W) * np.cos(np.pi * b * (v + 0.5) / H) for a, b in modes]
    )


class LinearDepth:
    """``D(c) = D0 + sum_i c_i B_i``; exact Jacobian ``J = B`` (H, W, C)."""

    def __init__(self, D0: np.ndarray, bases: np.ndarray, uncertainty: np.ndarray | None = None):
        self.D0 = np.asarray(D0, np.float64)
        self.bases = np.asarray(bases, np.float64)
        self.code_dim = self.bases.shape[0]
        self.J = np.ascontiguousarray(self.bases.transpose(1, 2, 0))
        self.uncertainty = np.full(self.D0.shape, 0.02) if uncertainty is None else uncertainty
        self.depth_calls = 0
        self.jacobian_calls = 0

    def depth(self, code):
        self.depth_calls += 1
        return self.D0 + np.tensordot(np.asarray(code, np.float64), self.bases, 1)

    def jacobian(self, code):
        self.jacobian_calls += 1
        return self.depth(code), self.J


class ExpDepth:
    """Smooth nonlinear ``D(c) = D0 * exp(sum_i c_i B_i)``; ``J = D(c) * B`` (H, W, C)."""

    def __init__(self, D0: np.ndarray, bases: np.ndarray, uncertainty: np.ndarray | None = None):
        self.D0 = np.asarray(D0, np.float64)
        self.bases = np.asarray(bases, np.float64)
        self.code_dim = self.bases.shape[0]
        self.uncertainty = np.full(self.D0.shape, 0.02) if uncertainty is None else uncertainty

    def depth(self, code):
        return self.D0 * np.exp(np.tensordot(np.asarray(code, np.float64), self.bases, 1))

    def jacobian(self, code):
        d = self.depth(code)
        return d, d[..., None] * self.bases.transpose(1, 2, 0)


def network_K(H: int, W: int, f_ratio: float = 0.8) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a pinhole network camera of W x H pixels."""
    return (f_ratio * W, f_ratio * W, (W - 1) / 2.0, (H - 1) / 2.0)


def body_pose(rotvec_w=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """T_w_b whose camera (through T_B_C) is at ``t`` and looks along world +x, turned by ``rotvec_w`` [rad]
    (a rotation vector about the world axes: z is yaw)."""
    # camera looking along world +x: x_c = -y_w, y_c = -z_w, z_c = x_w
    R_w_c = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R_w_c = so3_exp(np.asarray(rotvec_w, np.float64)) @ R_w_c
    T_w_c = make_T(R_w_c, t)
    return T_w_c @ np.linalg.inv(T_B_C)


def plane_depth(T_w_b: np.ndarray, K, shape, plane_x: float) -> np.ndarray:
    """Depth (H, W) [m] of the wall ``x_w = plane_x`` seen by the network camera of body pose T_w_b."""
    H, W = shape
    fx, fy, cx, cy = K
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    T_w_c = T_w_b @ T_B_C
    d_w = rays @ T_w_c[:3, :3].T
    o = T_w_c[:3, 3]
    return (plane_x - o[0]) / d_w[..., 0]
