"""Depth residuals of the dense system as vectorised GTSAM factors (Sec. 5.2-5.3, Eq. 13-17).

* **Geometric depth residual (Eq. 13)**, one stacked factor per code keyframe ``k`` (or per chunk of its
  landmarks): for each landmark ``j`` observed in ``k`` at the network pixel ``(p, q)`` (a fixed measurement),
  ``r_kj = [T_c_w x_j]_z - D_k(c_k)[p, q]`` with ``T_c_w = inv(T_w_b T_b_c)``. Keys ``X(k), C(k)`` and the
  ``L(j)`` (or only ``X(k), C(k)`` with the landmarks held fixed, the paper's "fixed sparse map points").
* **Depth consistency residual (Eq. 14)**, one stacked factor per pair ``(k1, k2)`` of code keyframes: the
  sampled pixels ``P2`` of ``k2`` (Sec. 5.2, :mod:`runtime.sampling`) are back-projected with ``d_k2(P2)``,
  moved into ``k1``'s camera, projected to ``P1``, and ``r = d_k1(P1) - z_in_k1``. Keys ``X(k1), X(k2),
  C(k1), C(k2)``.

Conventions:

* Depth maps, their code Jacobians ``J`` (H, W, C) (Eq. 17, finite differences) and the uncertainty ``B``
  (H, W) come from a provider with :class:`runtime.network.KeyframeDepth`'s interface
  (:class:`DepthProvider`), all at network resolution; pixels are network pixels ``(u, v) = (column,
  row)``, looked up by bilinear interpolation on the valid square ``[0, W-1] x [0, H-1]``.
* Pose Jacobians are with respect to GTSAM's ``Pose3`` retraction ``T_w_b <- T_w_b Exp([omega, v])`` (right
  perturbation, rotation first), landmark ones with respect to ``x_w + delta``, code ones with respect to
  ``c + delta`` (GTSAM ``Vector``).
* **Sigma from the uncertainty map**: the network is trained with the L1/Laplace likelihood of Eq. 6, whose
  scale ``B`` gives a standard deviation ``sqrt(2) * B``. A row's sigma is ``sigma_per_b * B`` (default
  ``sqrt(2)``), floored at ``min_sigma``. For Eq. 14 the variance is propagated to first order from both maps,
  ``s1^2 + (dr/dd2)^2 s2^2`` (``dr/dd2`` includes the image gradient of ``d_k1`` at ``P1``; ``"z"`` uses only
  ``dz1/dd2``). GTSAM noise models are constant, so these sigmas are evaluated once, at the values the factor
  is built with (rebuild the factors when the window is re-optimised).
* **Robust kernel**: Huber per row (``mEstimator.Huber`` with ``ReweightScheme.Scalar``; GTSAM then reweights
  each row on its own whitened residual and ``factor.error`` is the sum of per-row Huber losses). Eq. 15 puts
  Huber on Eq. 13 and none on Eq. 14; both thresholds are configurable.
* **Points that leave the image** (Eq. 14): a sample whose back-projected depth is not positive, that lands
  behind (or closer than ``min_depth`` to) ``k1``'s camera, or that projects outside ``k1``'s network image
  gets a zero residual and zero Jacobian rows at that evaluation. The row count of a factor never changes, the
  rows just go silent (they come back if the point re-enters). As in direct methods, a point with a large
  residual can lower the cost by leaving the view; between overlapping keyframes whose poses are also held by
  the reprojection and IMU factors this is a small effect (freezing the validity mask at build time is the
  alternative should it show up).
* **Depth edges** (``edge_rel``): a row whose depth lookup sits on a depth discontinuity is not used. The
  depth at an occlusion edge belongs to either surface, and the bilinear gradient across the edge (Eq. 14's
  ``d_k1`` at ``P1``) is metres per pixel: such a row is a large outlier whose Jacobian is wrong in direction,
  and a Huber kernel bounds its residual's pull but not its Jacobian's size. The test
  (:func:`depth_edge_ratio`): over the 3x3 pixels around the lookup, ``(max - min) / min > edge_rel``.
  Eq. 13 drops such observations when the factors are built; Eq. 14 drops such samples of ``k2`` when the
  factor is built and, at each evaluation, silences rows whose ``P1`` lands on an edge of ``d_k1`` (as for
  leaving the image). Measured with the rendered depth at the true poses (textured, 60 s, 84 pairs of frames
  6-15 apart, 300 samples each): 0.35 % of Eq. 14 rows were off by more than 5 cm, up to 1 m; with
  ``edge_rel=0.05`` 1.1 % of the rows were dropped and 0.04 % stayed above 5 cm.

Speed: the error functions are numpy over all rows (no Python loop per point); reading the landmarks of a
factor from ``gtsam.Values`` is one ``atPoint3`` call per landmark (~0.7 us each). A Python factor costs about
0.1 ms per call whatever its size (numpy overheads), so one factor per landmark is slow; but stacking all of a
keyframe's landmarks in one factor makes them one clique for GTSAM's elimination (it does not see that the
rows are independent). :func:`make_geometric_depth_factors` therefore splits a keyframe's landmarks into
chunks (``chunk_size``). Measured on a 10-keyframe window (800 landmarks, 6261 reprojection factors, 5 code
keyframes with 150 landmarks each and 4 consistency pairs of 600 samples; 2 shared cores), one linearisation
plus elimination took 30 ms without depth factors, 38 ms with fixed landmarks, 45 ms with chunks of 32,
120 ms with chunks of 1 (Python calls) and 118 ms with one stacked factor per keyframe (fill-in).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from runtime.backend.factors import custom_factor
from runtime.geometry import inv_T

__all__ = [
    "SIGMA_PER_LAPLACE_B",
    "DepthProvider",
    "DepthFactorConfig",
    "Bilinear",
    "bilinear",
    "inside_image",
    "depth_sigma",
    "depth_edge_ratio",
    "geometric_residuals",
    "ConsistencyResult",
    "consistency_residuals",
    "consistency_sigmas",
    "make_geometric_depth_factors",
    "make_consistency_factor",
]

#: Standard deviation of a Laplace distribution per unit of its scale ``B`` (variance ``2 B^2``).
SIGMA_PER_LAPLACE_B = math.sqrt(2.0)


class DepthProvider(Protocol):
    """What the factors need from a keyframe's network (as :class:`runtime.network.KeyframeDepth`).

    Attributes:
        uncertainty: (H, W) Laplace scale ``B`` [m] of the prediction, > 0.
    """

    uncertainty: np.ndarray

    def depth(self, code: np.ndarray) -> np.ndarray:
        """Depth (H, W) [m] decoded from ``code`` (C,)."""
        ...

    def jacobian(self, code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) [m] and ``dD/dc`` (H, W, C) [m per code unit] at ``code``."""
        ...


@dataclass(frozen=True)
class DepthFactorConfig:
    """Settings of the depth factors.

    Attributes:
        sigma_per_b: standard deviation per unit of the predicted Laplace scale ``B`` (``sqrt(2)``: Laplace).
        min_sigma: floor on a row's sigma [m] (a tiny predicted ``B`` must not make a row rigid).
        geo_huber_k: Huber threshold of Eq. 13 in sigmas (None or <= 0: no robust kernel).
        consis_huber_k: Huber threshold of Eq. 14 in sigmas (None: none, as Eq. 15).
        consis_covariance: ``"full"`` (``dr/dd2``, with the image gradient of ``d_k1``) or ``"z"``
            (``dz/dd2`` only).
        chunk_size: landmarks per geometric factor when the landmarks are variables (0: one factor per
            keyframe).
        geo_eff_rows, consis_eff_rows: effective number of independent rows of one keyframe's Eq. 13 rows and
            of one pair's Eq. 14 rows (None: every row independent). A depth map's error is a smooth field
            (the decoder spans it with a few code directions), so hundreds of rows on one map are not
            hundreds of independent measurements; with ``n`` rows the sigmas are scaled by
            ``sqrt(max(n / eff_rows, 1))`` (:func:`correlation_inflation`), which gives the rows together the
            information of ``eff_rows`` independent ones.
        min_depth: smallest depth [m] in ``k1`` for a consistency sample to count.
        edge_rel: depth-edge test of both residuals (module doc, :func:`depth_edge_ratio`); None: off.
        consis_offset: an Eq. 14 pair's rows carry a common depth offset as a nuisance (eliminated: its
            weighted mean over the valid rows is taken out of the residuals and their Jacobians), so that the
            pair constrains the shape its two depth maps agree on, not their absolute depth (a per-map bias of
            the network). Codes' Eq. 14 factors only (not the fixed-depth ones of the coast bridge).
        check_shapes: assert every Jacobian's shape at each linearisation (cheap; GTSAM accepts wrong shapes).
    """

    sigma_per_b: float = SIGMA_PER_LAPLACE_B
    min_sigma: float = 0.01
    geo_huber_k: float | None = 1.5
    consis_huber_k: float | None = None
    consis_covariance: str = "full"
    chunk_size: int = 32
    min_depth: float = 0.05
    check_shapes: bool = True
    geo_eff_rows: float | None = None
    consis_eff_rows: float | None = None
    edge_rel: float | None = None
    consis_offset: bool = False

    def __post_init__(self) -> None:
        if self.edge_rel is not None and not self.edge_rel > 0:
            raise ValueError(f"edge_rel={self.edge_rel}: must be > 0 (or None: no depth-edge test)")
        if not self.sigma_per_b > 0:
            raise ValueError(f"sigma_per_b={self.sigma_per_b}: must be > 0")
        if not self.min_sigma > 0:
            raise ValueError(f"min_sigma={self.min_sigma}: must be > 0")
        if self.consis_covariance not in ("full", "z"):
            raise ValueError(f"consis_covariance={self.consis_covariance!r}: expected 'full' or 'z'")
        if self.chunk_size < 0:
            raise ValueError(f"chunk_size={self.chunk_size}: must be >= 0")
        for name in ("geo_eff_rows", "consis_eff_rows"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"{name}={v}: must be > 0 (or None)")


# --------------------------------------------------------------------------- bilinear lookup
def inside_image(uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Mask (N,) of pixels ``uv`` (N, 2) on the interpolation square ``[0, W-1] x [0, H-1]`` of (H, W)."""
    uv = np.asarray(uv, dtype=np.float64)
    H, W = shape[:2]
    u, v = uv[..., 0], uv[..., 1]
    with np.errstate(invalid="ignore"):
        return np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)


class Bilinear:
    """Bilinear interpolation weights of fixed pixels, reusable across maps of one size.

    Pixels outside ``[0, W-1] x [0, H-1]`` are clamped onto it (``inside`` tells which ones were inside).

    Args:
        uv: (N, 2) pixels ``(u, v)``.
        shape: (H, W) of the maps, H, W >= 2.

    >>> img = np.arange(12, dtype=np.float32).reshape(3, 4)   # value = 4 v + u
    >>> Bilinear(np.array([[1.5, 0.5], [3.0, 2.0]]), img.shape).sample(img).tolist()
    [3.5, 11.0]
    """

    def __init__(self, uv: np.ndarray, shape: tuple[int, int]) -> None:
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        H, W = int(shape[0]), int(shape[1])
        if H < 2 or W < 2:
            raise ValueError(f"map shape {shape}: bilinear lookup needs H, W >= 2")
        self.shape = (H, W)
        self.inside = inside_image(uv, (H, W))
        u = np.clip(np.nan_to_num(uv[:, 0]), 0.0, W - 1.0)
        v = np.clip(np.nan_to_num(uv[:, 1]), 0.0, H - 1.0)
        x0 = np.minimum(np.floor(u).astype(np.int64), W - 2)
        y0 = np.minimum(np.floor(v).astype(np.int64), H - 2)
        self.fu = u - x0  # (N,) in [0, 1]
        self.fv = v - y0
        i00 = y0 * W + x0
        self.idx = np.stack([i00, i00 + 1, i00 + W, i00 + W + 1], -1)  # (N, 4) flat indices: 00, 10, 01, 11
        fu, fv = self.fu, self.fv
        self.w = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], -1)  # (N, 4)

    def _corners(self, img: np.ndarray) -> np.ndarray:
        img = np.asarray(img)
        if img.shape[:2] != self.shape:
            raise ValueError(f"map has shape {img.shape[:2]}, the lookup was built for {self.shape}")
        flat = img.reshape(self.shape[0] * self.shape[1], -1)
        return flat[self.idx].astype(np.float64)  # (N, 4, C)

    def sample(self, img: np.ndarray) -> np.ndarray:
        """Values at the pixels: (N,) for an (H, W) map, (N, C) for (H, W, C)."""
        out = np.einsum("nk,nkc->nc", self.w, self._corners(img))
        return out[:, 0] if np.asarray(img).ndim == 2 else out

    def sample_grad(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Values (N,) of an (H, W) map and the bilinear interpolant's derivatives ``d/du``, ``d/dv`` (N,)."""
        c = self._corners(img)[:, :, 0]  # (N, 4)
        val = np.einsum("nk,nk->n", self.w, c)
        fu, fv = self.fu, self.fv
        du = (1 - fv) * (c[:, 1] - c[:, 0]) + fv * (c[:, 3] - c[:, 2])
        dv = (1 - fu) * (c[:, 2] - c[:, 0]) + fu * (c[:, 3] - c[:, 1])
        return val, du, dv


def bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, W) or (H, W, C) map at pixels (N, 2) (clamped to the image)."""
    return Bilinear(uv, np.asarray(img).shape[:2]).sample(img)


def depth_edge_ratio(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Relative depth range ``(max - min) / min`` (N,) over the 3x3 pixels around each pixel ``uv`` (N, 2)
    (the nearest pixel and its neighbours, clamped to the image) of an (H, W) depth map; ``inf`` where a
    depth there is not positive or not finite. Large on depth discontinuities, about ``2 tan(angle) / f`` on
    a plane seen at ``angle`` from face-on with focal length ``f`` [px].

    >>> D = np.ones((4, 6)); D[:, 3:] = 2.0                     # an edge between columns 2 and 3
    >>> depth_edge_ratio(D, np.array([[0.0, 1.0], [2.2, 1.0], [4.6, 2.0]])).tolist()
    [0.0, 1.0, 0.0]
    """
    D = np.asarray(depth, dtype=np.float64)
    H, W = D.shape[:2]
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    u = np.clip(np.floor(np.nan_to_num(uv[:, 0]) + 0.5), 0, W - 1).astype(np.int64)
    v = np.clip(np.floor(np.nan_to_num(uv[:, 1]) + 0.5), 0, H - 1).astype(np.int64)
    d = np.stack(
        [D[np.clip(v + dy, 0, H - 1), np.clip(u + dx, 0, W - 1)] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], -1
    )
    lo = d.min(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = (d.max(-1) - lo) / lo
    return np.where(np.isfinite(d).all(-1) & (lo > 0), ratio, np.inf)


def _not_on_edge(depth: np.ndarray, uv: np.ndarray, edge_rel: float | None) -> np.ndarray:
    """Mask (N,) of the pixels that pass the depth-edge test (all of them when ``edge_rel`` is None)."""
    if edge_rel is None:
        return np.ones(np.asarray(uv).reshape(-1, 2).shape[0], dtype=bool)
    return depth_edge_ratio(depth, uv) <= edge_rel


def depth_sigma(uncertainty_at: np.ndarray, cfg: DepthFactorConfig) -> np.ndarray:
    """Row sigmas [m] from the predicted Laplace scale ``B`` [m] at the rows' pixels: ``max(k B, floor)``."""
    b = np.asarray(uncertainty_at, dtype=np.float64)
    b = np.where(np.isfinite(b), b, np.inf)
    return np.maximum(cfg.sigma_per_b * b, cfg.min_sigma)


def correlation_inflation(n_rows: int, eff_rows: float | None) -> float:
    """Sigma factor ``sqrt(max(n_rows / eff_rows, 1))`` that gives ``n_rows`` correlated rows the information
    of ``eff_rows`` independent ones (1 when ``eff_rows`` is None)."""
    if eff_rows is None:
        return 1.0
    return float(np.sqrt(max(n_rows / float(eff_rows), 1.0)))


def _noise(sigmas: np.ndarray, huber_k: float | None):
    import gtsam

    sigmas = np.asarray(sigmas, dtype=np.float64)
    if not np.all(np.isfinite(sigmas) & (sigmas > 0)):
        raise ValueError(f"depth sigmas must be finite and > 0, got min {sigmas.min()} max {sigmas.max()}")
    base = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    if huber_k is None or huber_k <= 0:
        return base
    M = gtsam.noiseModel.mEstimator
    return gtsam.noiseModel.Robust.Create(M.Huber.Create(float(huber_k), M.Base.ReweightScheme.Scalar), base)


def _check_T(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{name} must be a finite 4x4 transform, got shape {T.shape}")
    return T


# --------------------------------------------------------------------------- Eq. 13
def geometric_residuals(
    T_w_b: np.ndarray,
    T_b_c: np.ndarray,
    X_w: np.ndarray,
    lookup: Bilinear,
    depth: np.ndarray,
    J: np.ndarray | None = None,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
    """Geometric depth residuals (Eq. 13) ``r_j = [T_c_w x_j]_z - D[p_j, q_j]`` and their Jacobians.

    Args:
        T_w_b: (4, 4) body pose of the keyframe; T_b_c: (4, 4) camera-to-body.
        X_w: (M, 3) landmark positions in the world [m].
        lookup: bilinear weights of the M observed network pixels (fixed measurements).
        depth: (H, W) decoded depth [m] at the current code.
        J: (H, W, C) code Jacobian of the depth map; when given, the Jacobians are returned.

    Returns:
        r (M,) [m] and, with ``J``, ``(d r / d xi_pose (M, 6), d r / d x_j (M, 3), d r / d c (M, C))``
        (the landmark Jacobian row ``n`` is the derivative with respect to landmark ``n`` only).
    """
    T_w_c = T_w_b @ T_b_c
    T_c_w = inv_T(T_w_c)
    p_c = X_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]  # (M, 3)
    r = p_c[:, 2] - lookup.sample(depth)
    if J is None:
        return r, None
    M = X_w.shape[0]
    T_b_w = inv_T(T_w_b)
    p_b = X_w @ T_b_w[:3, :3].T + T_b_w[:3, 3]  # (M, 3)
    e = T_b_c[:3, :3][:, 2]  # row 2 of R_c_b: z of the camera in body axes
    # z(xi) = e . (Exp(xi)^-1 p_b) + t  ->  dz/domega = e . [p_b]_x = e x p_b, dz/dv = -e
    J_pose = np.concatenate([np.cross(e[None], p_b), np.broadcast_to(-e, (M, 3))], 1)
    J_lm = np.broadcast_to(T_c_w[2, :3], (M, 3)).copy()
    J_code = -lookup.sample(J)  # (M, C)
    return r, (J_pose, J_lm, J_code)


def make_geometric_depth_factors(
    pose_key: int,
    code_key: int,
    uv: np.ndarray,
    provider: DepthProvider,
    T_b_c: np.ndarray,
    landmark_keys: Sequence[int] | None = None,
    landmarks_w: np.ndarray | None = None,
    cfg: DepthFactorConfig | None = None,
    depth_map: np.ndarray | None = None,
) -> list:
    """Eq. 13 factors of one code keyframe.

    Give either ``landmark_keys`` (landmarks are graph variables ``L(j)``; the rows are split into factors
    of ``cfg.chunk_size`` landmarks, keys ``[pose_key, code_key, L...]``) or ``landmarks_w`` (fixed
    positions; one factor with keys ``[pose_key, code_key]``). Observations whose pixel is outside the
    network image are dropped (:func:`inside_image` tells which), and with ``cfg.edge_rel`` those on a depth
    edge of ``depth_map`` (module doc).

    Args:
        pose_key, code_key: keys of ``X(k)`` (Pose3 ``T_w_b``) and ``C(k)`` (Vector(C)).
        uv: (M, 2) network pixels where the landmarks were observed in keyframe k (from the undistorted
            observations: ``NetworkMapping.points_to_network(uv_undistorted)``).
        provider: depth, code Jacobian and uncertainty of keyframe k (:class:`DepthProvider`).
        T_b_c: (4, 4) camera-to-body.
        landmark_keys: (M,) distinct keys of ``L(j)`` (Point3 in the world), or None.
        landmarks_w: (M, 3) fixed landmark positions [m], or None.
        cfg: settings (sigma conversion, Huber, chunking, edge test).
        depth_map: (H, W) decoded depth at the keyframe's current code (needed with ``cfg.edge_rel``).

    Returns:
        list of ``gtsam.CustomFactor`` (empty when no observation is usable).
    """
    cfg = cfg or DepthFactorConfig()
    T_b_c = _check_T(T_b_c, "T_b_c")
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if (landmark_keys is None) == (landmarks_w is None):
        raise ValueError("give exactly one of landmark_keys (variables) and landmarks_w (fixed positions)")
    if landmark_keys is not None:
        lkeys = np.asarray([int(k) for k in landmark_keys], dtype=np.int64)
        if lkeys.shape != (uv.shape[0],):
            raise ValueError(f"{lkeys.size} landmark keys for {uv.shape[0]} pixels")
        if np.unique(lkeys).size != lkeys.size:
            raise ValueError("landmark_keys has duplicates (one observation per landmark and keyframe)")
    else:
        Xf = np.asarray(landmarks_w, dtype=np.float64)
        if Xf.shape != (uv.shape[0], 3) or not np.isfinite(Xf).all():
            raise ValueError(f"landmarks_w must be finite with shape {(uv.shape[0], 3)}, got {Xf.shape}")
    B = np.asarray(provider.uncertainty)
    shape = B.shape[:2]
    keep = inside_image(uv, shape)
    if cfg.edge_rel is not None:
        if depth_map is None:
            raise ValueError("cfg.edge_rel needs the depth map at the current code (depth_map)")
        if np.shape(depth_map)[:2] != shape:
            raise ValueError(f"depth_map has shape {np.shape(depth_map)}, the uncertainty map {shape}")
        keep &= _not_on_edge(depth_map, uv, cfg.edge_rel)
    if not keep.any():
        return []
    uv = uv[keep]
    lookup_all = Bilinear(uv, shape)
    sig_all = depth_sigma(lookup_all.sample(B), cfg) * correlation_inflation(uv.shape[0], cfg.geo_eff_rows)
    if landmarks_w is not None:
        return [_geometric_factor(pose_key, code_key, None, Xf[keep], lookup_all, sig_all, provider, T_b_c, cfg)]
    lkeys = lkeys[keep]
    n = lkeys.size
    step = n if cfg.chunk_size == 0 else cfg.chunk_size
    out = []
    for s in range(0, n, step):  # one factor per chunk (not per point)
        sl = slice(s, min(s + step, n))
        lk = Bilinear(uv[sl], shape)
        out.append(_geometric_factor(pose_key, code_key, lkeys[sl], None, lk, sig_all[sl], provider, T_b_c, cfg))
    return out


def _geometric_factor(pose_key, code_key, lkeys, X_fixed, lookup, sigmas, provider, T_b_c, cfg):
    def error_fn(values, want_jacobians: bool):
        T_w_b = values.atPose3(pose_key).matrix()
        code = np.asarray(values.atVector(code_key), dtype=np.float64)
        X_w = X_fixed if lkeys is None else np.array([values.atPoint3(int(k)) for k in lkeys]).reshape(-1, 3)
        if not want_jacobians:
            r, _ = geometric_residuals(T_w_b, T_b_c, X_w, lookup, provider.depth(code))
            return r, None
        depth, J = provider.jacobian(code)
        r, (J_pose, J_lm, J_code) = geometric_residuals(T_w_b, T_b_c, X_w, lookup, depth, J)
        Js = [J_pose, J_code]
        if lkeys is not None:
            M = r.size
            blocks = np.zeros((M, M, 3))  # landmark n only moves row n
            blocks[np.arange(M), np.arange(M)] = J_lm
            Js.extend(blocks.transpose(1, 0, 2))  # M blocks of (M, 3)
        return r, Js

    keys = [pose_key, code_key] + ([] if lkeys is None else [int(k) for k in lkeys])
    dims = [6, _code_dim(provider)] + ([] if lkeys is None else [3] * len(lkeys))
    return custom_factor(_noise(sigmas, cfg.geo_huber_k), keys, error_fn, dims, check=cfg.check_shapes)


def _code_dim(provider: DepthProvider) -> int:
    dim = getattr(getattr(provider, "net", None), "code_dim", None)
    if dim is None:
        dim = getattr(provider, "code_dim", None)
    if dim is None:
        raise ValueError("provider must expose its code dimension (provider.net.code_dim or provider.code_dim)")
    return int(dim)


# --------------------------------------------------------------------------- Eq. 14
@dataclass
class ConsistencyResult:
    """Residuals of Eq. 14 for S samples.

    Attributes:
        r: (S,) ``d_k1(P1) - z_in_k1`` [m], 0 where not ``valid``.
        valid: (S,) positive depth in k2, in front of k1 and inside k1's image.
        uv1: (S, 2) projections ``P1`` into k1's network image (meaningless where not valid).
        z1: (S,) depth of the warped points in k1 [m].
        dr_dd2: (S,) derivative of ``r`` with respect to ``d_k2(P2)`` (for the covariance), 0 where not valid.
        dz_dd2: (S,) derivative of ``z1`` with respect to ``d_k2(P2)``.
        jacobians: ``(dr/dxi_1 (S, 6), dr/dxi_2 (S, 6), dr/dc_1 (S, C), dr/dc_2 (S, C))`` (the code parts None
            for fixed depth maps) or None.
    """

    r: np.ndarray
    valid: np.ndarray
    uv1: np.ndarray
    z1: np.ndarray
    dr_dd2: np.ndarray
    dz_dd2: np.ndarray
    jacobians: tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None] | None


def consistency_residuals(
    T_w_b1: np.ndarray,
    T_w_b2: np.ndarray,
    T_b_c: np.ndarray,
    K: Sequence[float],
    lookup2: Bilinear,
    rays2: np.ndarray,
    depth1: np.ndarray,
    depth2: np.ndarray,
    J1: np.ndarray | None = None,
    J2: np.ndarray | None = None,
    min_depth: float = 0.05,
    pose_jacobians: bool = False,
    edge_rel: float | None = None,
) -> ConsistencyResult:
    """Depth consistency residuals (Eq. 14) of samples ``P2`` of keyframe k2 against keyframe k1.

    ``p_c2 = d_k2(P2) * rays2``; ``p_c1 = T_c1_c2 p_c2`` with ``T_c1_c2 = inv(T_w_b1 T_b_c) T_w_b2 T_b_c``;
    ``P1 = Pi_K(p_c1)``; ``r = d_k1(P1) - [p_c1]_z``.

    Args:
        T_w_b1, T_w_b2: (4, 4) body poses of k1 and k2; T_b_c: (4, 4).
        K: ``(fx, fy, cx, cy)`` of the network camera (pinhole, both keyframes).
        lookup2: bilinear weights of the S sample pixels ``P2`` in k2.
        rays2: (S, 3) ``K^-1 [u, v, 1]`` of the samples (z = 1).
        depth1, depth2: (H, W) decoded depth maps [m] of k1 and k2.
        J1, J2: (H, W, C) their code Jacobians; both or neither (then no Jacobians are computed).
        min_depth: smallest valid depth [m] in k1.
        pose_jacobians: without ``J1, J2``, the pose Jacobians all the same (the code ones are None: fixed
            depth maps).
        edge_rel: rows whose ``P1`` is on a depth edge of ``depth1`` (:func:`depth_edge_ratio`) are not
            valid; None: no test.

    Returns:
        :class:`ConsistencyResult`.
    """
    fx, fy, cx, cy = (float(k) for k in K)
    H, W = depth1.shape[:2]
    d2 = lookup2.sample(depth2)  # (S,)
    p_c2 = d2[:, None] * rays2  # (S, 3)
    T_c_b = inv_T(T_b_c)
    T_b1_b2 = inv_T(T_w_b1) @ T_w_b2
    T_c1_c2 = T_c_b @ T_b1_b2 @ T_b_c
    R12 = T_c1_c2[:3, :3]
    p_c1 = p_c2 @ R12.T + T_c1_c2[:3, 3]
    z1 = p_c1[:, 2]
    front = (d2 > 0) & (z1 > min_depth) & lookup2.inside
    zs = np.where(front, z1, 1.0)
    uv1 = np.stack([fx * p_c1[:, 0] / zs + cx, fy * p_c1[:, 1] / zs + cy], -1)
    lookup1 = Bilinear(uv1, (H, W))
    valid = front & lookup1.inside
    if edge_rel is not None:
        valid &= _not_on_edge(depth1, uv1, edge_rel)
    d1, gu, gv = lookup1.sample_grad(depth1)
    r = np.where(valid, d1 - z1, 0.0)
    # dr/dp_c1 = g^T dP1/dp_c1 - e3  (S, 3)
    a = np.stack([gu * fx / zs, gv * fy / zs, -(gu * fx * p_c1[:, 0] + gv * fy * p_c1[:, 1]) / zs**2 - 1.0], -1)
    a = np.where(valid[:, None], a, 0.0)
    dp_dd2 = rays2 @ R12.T  # (S, 3) d p_c1 / d d2
    dr_dd2 = np.einsum("si,si->s", a, dp_dd2)
    dz_dd2 = dp_dd2[:, 2]
    jac = None
    with_codes = J1 is not None and J2 is not None
    if with_codes or pose_jacobians:
        S = r.size
        R_c_b = T_c_b[:3, :3]
        T_b1_w = inv_T(T_w_b1)
        p_w = p_c2 @ (T_w_b2 @ T_b_c)[:3, :3].T + (T_w_b2 @ T_b_c)[:3, 3]
        p_b1 = p_w @ T_b1_w[:3, :3].T + T_b1_w[:3, 3]
        p_b2 = p_c2 @ T_b_c[:3, :3].T + T_b_c[:3, 3]
        b1 = a @ R_c_b  # dr/dp_b1 (S, 3)
        # p_b1(xi1) = Exp(xi1)^-1 p_b1: d/domega = [p_b1]_x, d/dv = -I
        J_x1 = np.concatenate([np.cross(b1, p_b1), -b1], 1)
        b2 = b1 @ T_b1_b2[:3, :3]  # dr/dp_b2
        # p_b1 = T_b1_b2 Exp(xi2) p_b2: d/domega = -R_b1_b2 [p_b2]_x, d/dv = R_b1_b2
        J_x2 = np.concatenate([np.cross(p_b2, b2), b2], 1)
        J_c1 = np.where(valid[:, None], lookup1.sample(J1), 0.0) if with_codes else None
        J_c2 = dr_dd2[:, None] * lookup2.sample(J2) if with_codes else None
        jac = (J_x1, J_x2, J_c1, J_c2)
        for Jk in jac:
            if Jk is not None and Jk.shape[0] != S:
                raise AssertionError(f"consistency Jacobian has {Jk.shape[0]} rows for {S} samples")
    return ConsistencyResult(r, valid, uv1, z1, dr_dd2, dz_dd2, jac)


def consistency_sigmas(
    res: ConsistencyResult, B1: np.ndarray, B2_at_samples: np.ndarray, cfg: DepthFactorConfig
) -> np.ndarray:
    """Row sigmas [m] of Eq. 14: ``sqrt(s1^2 + (dr/dd2)^2 s2^2)`` (``"z"``: ``dz/dd2`` instead), floored.

    ``s1`` is from ``B1`` (k1's uncertainty map) at ``P1``, ``s2`` from k2's at the samples; rows not valid
    now get ``s2``-based sigmas so that they are finite.
    """
    s2 = depth_sigma(B2_at_samples, cfg)
    s1 = depth_sigma(Bilinear(res.uv1, np.asarray(B1).shape[:2]).sample(B1), cfg)
    g = res.dr_dd2 if cfg.consis_covariance == "full" else res.dz_dd2
    var = np.where(res.valid, s1**2 + (g * s2) ** 2, 2.0 * s2**2)
    return np.maximum(np.sqrt(var), cfg.min_sigma)


def make_consistency_factor(
    pose_keys: tuple[int, int] | None,
    code_keys: tuple[int, int] | None,
    providers: tuple[DepthProvider, DepthProvider],
    uv2: np.ndarray,
    K: Sequence[float],
    T_b_c: np.ndarray,
    init_poses: tuple[np.ndarray, np.ndarray],
    init_codes: tuple[np.ndarray, np.ndarray],
    cfg: DepthFactorConfig | None = None,
):
    """Eq. 14 factor of the pair (k1, k2) on samples ``uv2`` of k2, keys ``[X(k1), X(k2), C(k1), C(k2)]``.

    Args:
        pose_keys: keys of ``X(k1)``, ``X(k2)``; code_keys: keys of ``C(k1)``, ``C(k2)``, or None: the codes
            stay at ``init_codes`` (fixed depth maps) and the factor's keys are ``[X(k1), X(k2)]``.
            ``pose_keys`` None (with code keys): the poses stay at ``init_poses`` and the keys are
            ``[C(k1), C(k2)]`` (Eq. 14 on the depth maps only; a diagnostic, the paper's factor has both).
        providers: depth providers of k1 and k2 (same network size).
        uv2: (S, 2) sampled network pixels of k2 (:func:`runtime.sampling.sample_consistency_pixels`).
        K: ``(fx, fy, cx, cy)`` of the network camera (e.g. ``NetworkMapping.camera(cam.pinhole())``).
        T_b_c: (4, 4) camera-to-body.
        init_poses: (4, 4) ``T_w_b`` of k1 and k2 and init_codes: (C,) codes at which the row sigmas are
            propagated (the values the graph is built with).
        cfg: settings.

    Returns:
        ``gtsam.CustomFactor`` with S rows (samples outside k2's image, and with ``cfg.edge_rel`` those on a
        depth edge of k2's map at ``init_codes``, are dropped first).
    """
    cfg = cfg or DepthFactorConfig()
    T_b_c = _check_T(T_b_c, "T_b_c")
    p1, p2 = providers
    B1, B2 = np.asarray(p1.uncertainty), np.asarray(p2.uncertainty)
    if B1.shape != B2.shape:
        raise ValueError(f"uncertainty maps differ in shape: {B1.shape} vs {B2.shape}")
    shape = B2.shape[:2]
    fx, fy, cx, cy = (float(k) for k in K)
    if not (fx > 0 and fy > 0):
        raise ValueError(f"K={tuple(K)}: focal lengths must be > 0")
    T1 = _check_T(init_poses[0], "init_poses[0]")
    T2 = _check_T(init_poses[1], "init_poses[1]")
    depths0 = (p1.depth(np.asarray(init_codes[0])), p2.depth(np.asarray(init_codes[1])))
    uv2 = np.asarray(uv2, dtype=np.float64).reshape(-1, 2)
    uv2 = uv2[inside_image(uv2, shape) & _not_on_edge(depths0[1], uv2, cfg.edge_rel)]
    if uv2.shape[0] == 0:
        raise ValueError("no consistency sample inside the image (and off depth edges)")
    lookup2 = Bilinear(uv2, shape)
    rays2 = np.stack([(uv2[:, 0] - cx) / fx, (uv2[:, 1] - cy) / fy, np.ones(uv2.shape[0])], -1)
    ekw = {"min_depth": cfg.min_depth, "edge_rel": cfg.edge_rel}
    res0 = consistency_residuals(T1, T2, T_b_c, K, lookup2, rays2, *depths0, **ekw)
    sigmas = consistency_sigmas(res0, B1, lookup2.sample(B2), cfg)
    sigmas = sigmas * correlation_inflation(int(res0.valid.sum()), cfg.consis_eff_rows)
    # with consis_offset, the weights of the coded factors' nuisance offset (fixed at build)
    offset_w = sigmas**-2.0 if cfg.consis_offset else None
    geometry = (T_b_c, K, lookup2, rays2)
    if pose_keys is None:
        if code_keys is None:
            raise ValueError("give pose_keys, code_keys or both")
        return _fixed_pose_consistency_factor(code_keys, providers, (T1, T2), geometry, sigmas, ekw, offset_w, cfg)
    kx1, kx2 = (int(k) for k in pose_keys)
    if code_keys is None:
        return _fixed_depth_consistency_factor((kx1, kx2), depths0, geometry, sigmas, ekw, cfg)
    kc1, kc2 = (int(k) for k in code_keys)
    if len({kx1, kx2, kc1, kc2}) != 4:
        raise ValueError(f"keys must be distinct, got {pose_keys}, {code_keys}")

    def error_fn(values, want_jacobians: bool):
        poses = (values.atPose3(kx1).matrix(), values.atPose3(kx2).matrix())
        codes = (values.atVector(kc1), values.atVector(kc2))
        r, jac = _coded_consistency(poses, codes, providers, geometry, ekw, offset_w, want_jacobians)
        return r, (list(jac) if want_jacobians else None)

    C1, C2 = _code_dim(p1), _code_dim(p2)
    return custom_factor(
        _noise(sigmas, cfg.consis_huber_k),
        [kx1, kx2, kc1, kc2],
        error_fn,
        [6, 6, C1, C2],
        check=cfg.check_shapes,
    )


def remove_weighted_offset(r: np.ndarray, jacobians, valid: np.ndarray, w: np.ndarray):
    """Eliminate a common offset ``b`` of the valid rows: ``r - b*`` with ``b* = sum(w r) / sum(w)`` over them
    (the least-squares offset at weights ``w``), and the Jacobians likewise (``b*`` is linear in ``r``); rows
    not valid stay 0. Returns ``(r, jacobians)`` (jacobians None stays None)."""
    wv = np.where(valid, w, 0.0)
    sw = wv.sum()
    if sw <= 0:
        return r, jacobians
    r = np.where(valid, r - (wv @ r) / sw, 0.0)
    if jacobians is not None:
        jacobians = tuple(
            None if J is None else np.where(valid[:, None], J - (wv @ J) / sw, 0.0) for J in jacobians
        )
    return r, jacobians


def _fixed_depth_consistency_factor(keys, depths, geometry, sigmas, ekw, cfg: DepthFactorConfig):
    """Eq. 14 with both depth maps fixed: keys ``[X(k1), X(k2)]`` (:func:`make_consistency_factor`; ``geometry``
    and ``ekw`` as in :func:`_coded_consistency`)."""
    kx1, kx2 = keys
    if kx1 == kx2:
        raise ValueError(f"keys must be distinct, got {keys}")
    d1, d2 = (np.asarray(d, np.float64) for d in depths)

    def error_fn(values, want_jacobians: bool):
        poses = (values.atPose3(kx1).matrix(), values.atPose3(kx2).matrix())
        res = consistency_residuals(*poses, *geometry, d1, d2, pose_jacobians=want_jacobians, **ekw)
        return res.r, (list(res.jacobians[:2]) if want_jacobians else None)

    return custom_factor(_noise(sigmas, cfg.consis_huber_k), [kx1, kx2], error_fn, [6, 6], check=cfg.check_shapes)


def _coded_consistency(poses, codes, providers, geometry, ekw, offset_w, want_jacobians: bool):
    """Eq. 14 residuals of two keyframes' decoded depth maps at ``codes`` and, with ``want_jacobians``, the
    Jacobians ``(J_x1, J_x2, J_c1, J_c2)`` (else None). ``geometry``: ``(T_b_c, K, lookup2, rays2)``; ``ekw``:
    ``min_depth``, ``edge_rel``; ``offset_w``: None, or the weights of :func:`remove_weighted_offset`."""
    p1, p2 = providers
    c1, c2 = (np.asarray(c, dtype=np.float64) for c in codes)
    if not want_jacobians:
        res = consistency_residuals(*poses, *geometry, p1.depth(c1), p2.depth(c2), **ekw)
    else:
        d1, J1 = p1.jacobian(c1)
        d2, J2 = p2.jacobian(c2)
        res = consistency_residuals(*poses, *geometry, d1, d2, J1, J2, **ekw)
    if offset_w is not None:
        return remove_weighted_offset(res.r, res.jacobians, res.valid, offset_w)
    return res.r, res.jacobians


def _fixed_pose_consistency_factor(keys, providers, poses, geometry, sigmas, ekw, offset_w, cfg):
    """Eq. 14 with both poses fixed: keys ``[C(k1), C(k2)]`` (:func:`make_consistency_factor`)."""
    kc1, kc2 = (int(k) for k in keys)
    if kc1 == kc2:
        raise ValueError(f"keys must be distinct, got {keys}")

    def error_fn(values, want_jacobians: bool):
        codes = (values.atVector(kc1), values.atVector(kc2))
        r, jac = _coded_consistency(poses, codes, providers, geometry, ekw, offset_w, want_jacobians)
        return r, (list(jac[2:]) if want_jacobians else None)

    return custom_factor(
        _noise(sigmas, cfg.consis_huber_k),
        [kc1, kc2],
        error_fn,
        [_code_dim(p) for p in providers],
        check=cfg.check_shapes,
    )
