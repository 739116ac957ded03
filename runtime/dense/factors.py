"""Depth residuals of the dense system as vectorised GTSAM factors (Sec. 5.2-5.3, Eq. 13-17).

* **Geometric depth residual (Eq. 13)**, stacked factors per code keyframe ``k`` (chunks of its landmarks):
  for each landmark ``j`` observed in ``k`` at the network pixel ``(p, q)`` (a fixed measurement),
  ``r_kj = [T_c_w x_j]_z - D_k(c_k)[p, q]`` with ``T_c_w = inv(T_w_b T_b_c)``. Keys ``X(k), C(k), L(j)...``.
* **Depth consistency residual (Eq. 14)**, one stacked factor per pair ``(k1, k2)`` of code keyframes: the
  sampled pixels ``P2`` of ``k2`` (Sec. 5.2, :mod:`runtime.dense.sampling`) are back-projected with ``d_k2(P2)``,
  moved into ``k1``'s camera, projected to ``P1``, and ``r = d_k1(P1) - z_in_k1``. Keys ``X(k1), X(k2),
  C(k1), C(k2)``.

Conventions:

* Depth maps, their code Jacobians ``J`` (H, W, C) (Eq. 17, finite differences) and the uncertainty ``B``
  (H, W) come from a :class:`DepthProvider`, all at network resolution; pixels are network pixels, looked up
  bilinearly (:mod:`runtime.dense.lookup`).
* Pose Jacobians are with respect to GTSAM's ``Pose3`` retraction ``T_w_b <- T_w_b Exp([omega, v])`` (right
  perturbation, rotation first), landmark ones with respect to ``x_w + delta``, code ones with respect to
  ``c + delta`` (GTSAM ``Vector``).
* **Sigma from the uncertainty map**: the network is trained with the L1/Laplace likelihood of Eq. 6, whose
  scale ``B`` gives a standard deviation ``sqrt(2) * B``. A row's sigma is ``sigma_per_b * B``, floored at
  ``min_sigma``. For Eq. 14 the variance is propagated to first order from both maps,
  ``s1^2 + (dr/dd2)^2 s2^2`` (``dr/dd2`` includes the image gradient of ``d_k1`` at ``P1``; ``"z"`` uses only
  ``dz1/dd2``). GTSAM noise models are constant, so these sigmas are evaluated once, at the values the factor
  is built with (the factors are rebuilt at each optimisation).
* **Robust kernel**: Huber per row (``mEstimator.Huber`` with ``ReweightScheme.Scalar``; GTSAM then reweights
  each row on its own whitened residual and ``factor.error`` is the sum of per-row Huber losses).
* **Points that leave the image** (Eq. 14): a sample whose back-projected depth is not positive, that lands
  behind (or closer than ``min_depth`` to) ``k1``'s camera, or that projects outside ``k1``'s network image
  gets a zero residual and zero Jacobian rows at that evaluation. The row count of a factor never changes, the
  rows just go silent (they come back if the point re-enters).
* **Depth edges** (``edge_rel``, :func:`runtime.dense.lookup.depth_edge_ratio`): Eq. 13 drops observations on
  a depth edge when the factors are built; Eq. 14 drops such samples of ``k2`` when the factor is built and,
  at each evaluation, silences rows whose ``P1`` lands on an edge of ``d_k1`` (as for leaving the image).

Speed: the error functions are numpy over all rows (no Python loop per point). A Python factor costs about
0.1 ms per call whatever its size, so one factor per landmark is slow; one factor per keyframe makes all its
landmarks one clique for GTSAM's elimination (fill-in). Eq. 13 therefore takes chunks of ``chunk_size``
landmarks. A factor evaluates its keyframes' depth only at its pixels (:func:`provider_expansion`,
:class:`runtime.dense.lookup.MapExpansion`): with the linearised decoder no depth map is formed during LM.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from runtime.backend.factors import custom_factor
from runtime.dense.config import DepthFactorConfig
from runtime.dense.lookup import Bilinear, MapExpansion, as_expansion, inside_image, off_depth_edges
from runtime.geometry import inv_T, project_pinhole

__all__ = [
    "DepthProvider",
    "provider_expansion",
    "depth_sigma",
    "geometric_residuals",
    "make_geometric_depth_factors",
    "ConsistencyResult",
    "pixel_rays",
    "consistency_residuals",
    "consistency_sigmas",
    "make_consistency_factor",
]


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


def depth_sigma(uncertainty_at: np.ndarray, cfg: DepthFactorConfig) -> np.ndarray:
    """Row sigmas [m] from the predicted Laplace scale ``B`` [m] at the rows' pixels: ``max(k B, floor)``."""
    b = np.asarray(uncertainty_at, dtype=np.float64)
    b = np.where(np.isfinite(b), b, np.inf)
    return np.maximum(cfg.sigma_per_b * b, cfg.min_sigma)


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


def _code_dim(provider: DepthProvider) -> int:
    dim = getattr(getattr(provider, "net", None), "code_dim", None)
    if dim is None:
        dim = getattr(provider, "code_dim", None)
    if dim is None:
        raise ValueError("provider must expose its code dimension (provider.net.code_dim or provider.code_dim)")
    return int(dim)


def provider_expansion(provider: DepthProvider, code: np.ndarray, jacobian: bool) -> MapExpansion:
    """The provider's depth at ``code`` as a :class:`MapExpansion`: its own first-order expansion when it has
    one (:meth:`runtime.dense.linearized.LinearizedDepth.expansion`: no map is computed), else the map decoded at
    ``code`` (with its Jacobian when ``jacobian``)."""
    code = np.asarray(code, dtype=np.float64)
    expansion = getattr(provider, "expansion", None)
    if expansion is not None:
        return expansion(code)
    if jacobian:
        return MapExpansion(*provider.jacobian(code))
    return MapExpansion(provider.depth(code))


# --------------------------------------------------------------------------- Eq. 13
def geometric_residuals(
    T_w_b: np.ndarray,
    T_b_c: np.ndarray,
    X_w: np.ndarray,
    lookup: Bilinear,
    depth: np.ndarray | MapExpansion,
    J: np.ndarray | None = None,
    jacobians: bool | None = None,
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
    """Geometric depth residuals (Eq. 13) ``r_j = [T_c_w x_j]_z - D[p_j, q_j]`` and their Jacobians.

    Args:
        T_w_b: (4, 4) body pose of the keyframe; T_b_c: (4, 4) camera-to-body.
        X_w: (M, 3) landmark positions in the world [m].
        lookup: bilinear weights of the M observed network pixels (fixed measurements).
        depth: (H, W) decoded depth [m] at the current code, or its :class:`MapExpansion` (which carries ``J``).
        J: (H, W, C) code Jacobian of the depth map.
        jacobians: whether to return the Jacobians; None: when there is a code Jacobian.

    Returns:
        r (M,) [m] and, with ``jacobians``, ``(d r / d xi_pose (M, 6), d r / d x_j (M, 3), d r / d c (M, C))``
        (the landmark Jacobian row ``n`` is the derivative with respect to landmark ``n`` only).
    """
    dmap = as_expansion(depth, J)
    T_w_c = T_w_b @ T_b_c
    T_c_w = inv_T(T_w_c)
    p_c = X_w @ T_c_w[:3, :3].T + T_c_w[:3, 3]  # (M, 3)
    r = p_c[:, 2] - dmap.sample(lookup)
    if jacobians is None:
        jacobians = dmap.J0 is not None
    if not jacobians:
        return r, None
    M = X_w.shape[0]
    T_b_w = inv_T(T_w_b)
    p_b = X_w @ T_b_w[:3, :3].T + T_b_w[:3, 3]  # (M, 3)
    e = T_b_c[:3, :3][:, 2]  # row 2 of R_c_b: z of the camera in body axes
    # z(xi) = e . (Exp(xi)^-1 p_b) + t  ->  dz/domega = e . [p_b]_x = e x p_b, dz/dv = -e
    J_pose = np.concatenate([np.cross(e[None], p_b), np.broadcast_to(-e, (M, 3))], 1)
    J_lm = np.broadcast_to(T_c_w[2, :3], (M, 3)).copy()
    J_code = -dmap.sample_jacobian(lookup)  # (M, C)
    return r, (J_pose, J_lm, J_code)


def make_geometric_depth_factors(
    pose_key: int,
    code_key: int,
    uv: np.ndarray,
    provider: DepthProvider,
    T_b_c: np.ndarray,
    landmark_keys: Sequence[int],
    cfg: DepthFactorConfig | None = None,
    depth_map: np.ndarray | MapExpansion | None = None,
) -> list:
    """Eq. 13 factors of one code keyframe, the landmarks ``L(j)`` as graph variables.

    The rows are split into factors of ``cfg.chunk_size`` landmarks, keys ``[pose_key, code_key, L...]``.
    Observations whose pixel is outside the network image are dropped, and with ``cfg.edge_rel`` those on a
    depth edge of ``depth_map``.

    Args:
        pose_key, code_key: keys of ``X(k)`` (Pose3 ``T_w_b``) and ``C(k)`` (Vector(C)).
        uv: (M, 2) network pixels where the landmarks were observed in keyframe k (from the undistorted
            observations: ``NetworkMapping.points_to_network(uv_undistorted)``).
        provider: depth, code Jacobian and uncertainty of keyframe k (:class:`DepthProvider`).
        T_b_c: (4, 4) camera-to-body.
        landmark_keys: (M,) distinct keys of ``L(j)`` (Point3 in the world).
        cfg: settings (sigma conversion, Huber, chunking, edge test).
        depth_map: (H, W) decoded depth at the keyframe's current code, or its :class:`MapExpansion` (needed
            with ``cfg.edge_rel``).

    Returns:
        list of ``gtsam.CustomFactor`` (empty when no observation is usable).
    """
    cfg = cfg or DepthFactorConfig()
    T_b_c = _check_T(T_b_c, "T_b_c")
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if landmark_keys is None:
        raise ValueError("landmark_keys: the keys L(j) of the observed landmarks are needed")
    lkeys = np.asarray([int(k) for k in landmark_keys], dtype=np.int64)
    if lkeys.shape != (uv.shape[0],):
        raise ValueError(f"{lkeys.size} landmark keys for {uv.shape[0]} pixels")
    if np.unique(lkeys).size != lkeys.size:
        raise ValueError("landmark_keys has duplicates (one observation per landmark and keyframe)")
    B = np.asarray(provider.uncertainty)
    shape = B.shape[:2]
    keep = inside_image(uv, shape)
    if cfg.edge_rel is not None:
        if depth_map is None:
            raise ValueError("cfg.edge_rel needs the depth map at the current code (depth_map)")
        depth_map = as_expansion(depth_map)
        if depth_map.shape != shape:
            raise ValueError(f"depth_map has shape {depth_map.shape}, the uncertainty map {shape}")
        keep &= off_depth_edges(depth_map, uv, cfg.edge_rel)
    if not keep.any():
        return []
    uv = uv[keep]
    sig_all = depth_sigma(Bilinear(uv, shape).sample(B), cfg)
    lkeys = lkeys[keep]
    n = lkeys.size
    step = n if cfg.chunk_size == 0 else cfg.chunk_size
    out = []
    for s in range(0, n, step):  # one factor per chunk (not per point)
        sl = slice(s, min(s + step, n))
        lk = Bilinear(uv[sl], shape)
        out.append(_geometric_factor(pose_key, code_key, lkeys[sl], lk, sig_all[sl], provider, T_b_c, cfg))
    return out


def _geometric_factor(pose_key, code_key, lkeys, lookup, sigmas, provider, T_b_c, cfg):
    lkeys = [int(k) for k in lkeys]
    diag = np.arange(len(lkeys))

    def error_fn(values, want_jacobians: bool):
        T_w_b = values.atPose3(pose_key).matrix()
        code = np.asarray(values.atVector(code_key), dtype=np.float64)
        X_w = np.array([values.atPoint3(k) for k in lkeys]).reshape(-1, 3)
        e = provider_expansion(provider, code, want_jacobians)
        if not want_jacobians:
            return geometric_residuals(T_w_b, T_b_c, X_w, lookup, e, jacobians=False)[0], None
        r, (J_pose, J_lm, J_code) = geometric_residuals(T_w_b, T_b_c, X_w, lookup, e, jacobians=True)
        M = r.size
        blocks = np.zeros((M, M, 3))  # landmark n only moves row n
        blocks[diag, diag] = J_lm
        return r, [J_pose, J_code, *blocks.transpose(1, 0, 2)]  # M landmark blocks of (M, 3)

    keys = [pose_key, code_key] + lkeys
    dims = [6, _code_dim(provider)] + [3] * len(lkeys)
    return custom_factor(_noise(sigmas, cfg.geo_huber_k), keys, error_fn, dims, check=cfg.check_shapes)


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
        jacobians: ``(dr/dxi_1 (S, 6), dr/dxi_2 (S, 6), dr/dc_1 (S, C), dr/dc_2 (S, C))`` or None.
    """

    r: np.ndarray
    valid: np.ndarray
    uv1: np.ndarray
    z1: np.ndarray
    dr_dd2: np.ndarray
    dz_dd2: np.ndarray
    jacobians: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None


def pixel_rays(uv: np.ndarray, K: Sequence[float]) -> np.ndarray:
    """(S, 3) rays ``K^-1 [u, v, 1]`` (z = 1) of network pixels ``uv`` (S, 2), for :func:`consistency_residuals`.

    >>> pixel_rays(np.array([[12.0, 7.0]]), (10.0, 5.0, 2.0, 2.0)).tolist()
    [[1.0, 1.0, 1.0]]
    """
    fx, fy, cx, cy = (float(k) for k in K)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    return np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(uv.shape[0])], -1)


def consistency_residuals(
    T_w_b1: np.ndarray,
    T_w_b2: np.ndarray,
    T_b_c: np.ndarray,
    K: Sequence[float],
    lookup2: Bilinear,
    rays2: np.ndarray,
    depth1: np.ndarray | MapExpansion,
    depth2: np.ndarray | MapExpansion,
    J1: np.ndarray | None = None,
    J2: np.ndarray | None = None,
    min_depth: float = 0.05,
    edge_rel: float | None = None,
    jacobians: bool | None = None,
    pose_jacobians: bool = True,
) -> ConsistencyResult:
    """Depth consistency residuals (Eq. 14) of samples ``P2`` of keyframe k2 against keyframe k1.

    ``p_c2 = d_k2(P2) * rays2``; ``p_c1 = T_c1_c2 p_c2`` with ``T_c1_c2 = inv(T_w_b1 T_b_c) T_w_b2 T_b_c``;
    ``P1 = Pi_K(p_c1)``; ``r = d_k1(P1) - [p_c1]_z``.

    Args:
        T_w_b1, T_w_b2: (4, 4) body poses of k1 and k2; T_b_c: (4, 4).
        K: ``(fx, fy, cx, cy)`` of the network camera (pinhole, both keyframes).
        lookup2: bilinear weights of the S sample pixels ``P2`` in k2.
        rays2: (S, 3) ``K^-1 [u, v, 1]`` of the samples (z = 1).
        depth1, depth2: (H, W) decoded depth maps [m] of k1 and k2, or their :class:`MapExpansion` (which
            carry ``J1``, ``J2``).
        J1, J2: (H, W, C) their code Jacobians.
        min_depth: smallest valid depth [m] in k1.
        edge_rel: rows whose ``P1`` is on a depth edge of ``depth1`` are not valid; None: no test.
        jacobians: whether to compute the Jacobians; None: when both maps have code Jacobians.
        pose_jacobians: with ``jacobians``, also the pose Jacobians (False: ``None`` in their place, for a fit
            of the codes alone).

    Returns:
        :class:`ConsistencyResult`.
    """
    fx, fy, cx, cy = (float(k) for k in K)
    e1, e2 = as_expansion(depth1, J1), as_expansion(depth2, J2)
    H, W = e1.shape
    d2 = e2.sample(lookup2)  # (S,)
    p_c2 = d2[:, None] * rays2  # (S, 3)
    T_c_b = inv_T(T_b_c)
    T_b1_b2 = inv_T(T_w_b1) @ T_w_b2
    T_c1_c2 = T_c_b @ T_b1_b2 @ T_b_c
    R12 = T_c1_c2[:3, :3]
    p_c1 = p_c2 @ R12.T + T_c1_c2[:3, 3]
    z1 = p_c1[:, 2]
    front = (d2 > 0) & (z1 > min_depth) & lookup2.inside
    zs = np.where(front, z1, 1.0)
    uv1, _ = project_pinhole(K, np.concatenate([p_c1[:, :2], zs[:, None]], 1))
    lookup1 = Bilinear(uv1, (H, W))
    valid = front & lookup1.inside
    if edge_rel is not None:  # tested where the row is valid so far
        at = np.flatnonzero(valid)
        valid[at] = off_depth_edges(e1, uv1[at], edge_rel)
    d1, gu, gv = e1.sample_grad(lookup1)
    r = np.where(valid, d1 - z1, 0.0)
    # dr/dp_c1 = g^T dP1/dp_c1 - e3  (S, 3)
    a = np.stack([gu * fx / zs, gv * fy / zs, -(gu * fx * p_c1[:, 0] + gv * fy * p_c1[:, 1]) / zs**2 - 1.0], -1)
    a = np.where(valid[:, None], a, 0.0)
    dp_dd2 = rays2 @ R12.T  # (S, 3) d p_c1 / d d2
    dr_dd2 = np.einsum("si,si->s", a, dp_dd2)
    dz_dd2 = dp_dd2[:, 2]
    if jacobians is None:
        jacobians = e1.J0 is not None and e2.J0 is not None
    jac = None
    if jacobians:
        jac = _consistency_jacobians(
            T_w_b1, T_w_b2, T_b_c, p_c2, a, valid, dr_dd2, (lookup1, lookup2), (e1, e2), pose_jacobians
        )
    return ConsistencyResult(r, valid, uv1, z1, dr_dd2, dz_dd2, jac)


def _consistency_jacobians(T_w_b1, T_w_b2, T_b_c, p_c2, a, valid, dr_dd2, lookups, maps, poses=True):
    """``(J_x1, J_x2, J_c1, J_c2)`` of Eq. 14 from ``a = dr/dp_c1`` (S, 3) (:func:`consistency_residuals`);
    ``J_x1``, ``J_x2`` are None unless ``poses``."""
    lookup1, lookup2 = lookups
    e1, e2 = maps
    S = a.shape[0]
    J_c1 = np.where(valid[:, None], e1.sample_jacobian(lookup1), 0.0)
    J_c2 = dr_dd2[:, None] * e2.sample_jacobian(lookup2)
    if not poses:
        return None, None, J_c1, J_c2
    R_c_b = inv_T(T_b_c)[:3, :3]
    T_b1_w = inv_T(T_w_b1)
    T_b1_b2 = T_b1_w @ T_w_b2
    p_w = p_c2 @ (T_w_b2 @ T_b_c)[:3, :3].T + (T_w_b2 @ T_b_c)[:3, 3]
    p_b1 = p_w @ T_b1_w[:3, :3].T + T_b1_w[:3, 3]
    p_b2 = p_c2 @ T_b_c[:3, :3].T + T_b_c[:3, 3]
    b1 = a @ R_c_b  # dr/dp_b1 (S, 3)
    # p_b1(xi1) = Exp(xi1)^-1 p_b1: d/domega = [p_b1]_x, d/dv = -I
    J_x1 = np.concatenate([np.cross(b1, p_b1), -b1], 1)
    b2 = b1 @ T_b1_b2[:3, :3]  # dr/dp_b2
    # p_b1 = T_b1_b2 Exp(xi2) p_b2: d/domega = -R_b1_b2 [p_b2]_x, d/dv = R_b1_b2
    J_x2 = np.concatenate([np.cross(p_b2, b2), b2], 1)
    jac = (J_x1, J_x2, J_c1, J_c2)
    for Jk in jac:
        if Jk.shape[0] != S:
            raise AssertionError(f"consistency Jacobian has {Jk.shape[0]} rows for {S} samples")
    return jac


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
    pose_keys: tuple[int, int],
    code_keys: tuple[int, int],
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
        pose_keys: keys of ``X(k1)``, ``X(k2)``; code_keys: keys of ``C(k1)``, ``C(k2)``.
        providers: depth providers of k1 and k2 (same network size).
        uv2: (S, 2) sampled network pixels of k2 (:func:`runtime.dense.sampling.sample_consistency_pixels`).
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
    kx1, kx2 = (int(k) for k in pose_keys)
    kc1, kc2 = (int(k) for k in code_keys)
    if len({kx1, kx2, kc1, kc2}) != 4:
        raise ValueError(f"keys must be distinct, got {pose_keys}, {code_keys}")
    T1 = _check_T(init_poses[0], "init_poses[0]")
    T2 = _check_T(init_poses[1], "init_poses[1]")
    depths0 = (provider_expansion(p1, init_codes[0], False), provider_expansion(p2, init_codes[1], False))
    uv2 = np.asarray(uv2, dtype=np.float64).reshape(-1, 2)
    uv2 = uv2[inside_image(uv2, shape) & off_depth_edges(depths0[1], uv2, cfg.edge_rel)]
    if uv2.shape[0] == 0:
        raise ValueError("no consistency sample inside the image (and off depth edges)")
    lookup2 = Bilinear(uv2, shape)
    rays2 = pixel_rays(uv2, K)
    ekw = {"min_depth": cfg.min_depth, "edge_rel": cfg.edge_rel}
    res0 = consistency_residuals(T1, T2, T_b_c, K, lookup2, rays2, *depths0, jacobians=False, **ekw)
    sigmas = consistency_sigmas(res0, B1, lookup2.sample(B2), cfg)
    geometry = (T_b_c, K, lookup2, rays2)

    def error_fn(values, want_jacobians: bool):
        poses = (values.atPose3(kx1).matrix(), values.atPose3(kx2).matrix())
        c1, c2 = (np.asarray(values.atVector(k), dtype=np.float64) for k in (kc1, kc2))
        e1, e2 = provider_expansion(p1, c1, want_jacobians), provider_expansion(p2, c2, want_jacobians)
        res = consistency_residuals(*poses, *geometry, e1, e2, jacobians=want_jacobians, **ekw)
        return res.r, None if res.jacobians is None else list(res.jacobians)

    return custom_factor(
        _noise(sigmas, cfg.consis_huber_k),
        [kx1, kx2, kc1, kc2],
        error_fn,
        [6, 6, _code_dim(p1), _code_dim(p2)],
        check=cfg.check_shapes,
    )
