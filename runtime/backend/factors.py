"""Factors and residuals of the sparse system (Eq. 9, 11-12), and the helpers later factors reuse.

* Reprojection (Eq. 9): GTSAM's built-in ``GenericProjectionFactorCal3_S2`` with ``body_P_sensor = T_b_c`` on
  undistorted pixels and a Huber kernel (C++: no Python call per factor during optimisation).
* Inertial (Eq. 11-12): GTSAM's ``CombinedImuFactor`` (see :mod:`runtime.backend.imu` for its parameters).
* Motion-only refinement of non-keyframes: a vectorised numpy Gauss-Newton over one pose (reprojection of
  fixed landmarks + the IMU-predicted pose as a prior) with analytic Jacobians (tested against numerical
  ones).
* :func:`custom_factor` wraps a numpy error function into a ``gtsam.CustomFactor`` and checks Jacobian shapes,
  the pattern for stacked Python factors (one factor per keyframe, many rows; PITFALLS.md: ~5 us per call).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from runtime.geometry import inv_T, project_pinhole, so3_exp, so3_log


# --------------------------------------------------------------------------- noise models
def huber_noise(sigmas: Sequence[float] | np.ndarray, k: float, scalar: bool = True):
    """Diagonal noise with a Huber kernel (threshold ``k`` in sigmas).

    ``scalar=True`` reweights each row alone (for stacked independent residuals, PITFALLS.md); ``False``
    weighs the whole factor by the norm of its whitened error (right for one 2-D reprojection).
    """
    import gtsam

    base = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))
    if k is None or k <= 0:
        return base
    M = gtsam.noiseModel.mEstimator
    est = M.Huber.Create(float(k), M.Base.ReweightScheme.Scalar) if scalar else M.Huber.Create(float(k))
    return gtsam.noiseModel.Robust.Create(est, base)


def pose_prior_noise_world(R_w_b: np.ndarray, rot_sigmas_w: np.ndarray, trans_sigma: float):
    """Pose3 prior noise with rotation sigmas given about the world axes (e.g. tight yaw, looser roll/pitch).

    GTSAM's Pose3 tangent is ``[omega_b, v_b]`` (body frame, right perturbation); a world-axis rotation error
    ``d_w`` is ``R^T d_w`` in the body, so the body covariance is ``R^T diag(s_w^2) R``.
    """
    import gtsam

    R = np.asarray(R_w_b, dtype=np.float64)
    cov = np.zeros((6, 6))
    cov[:3, :3] = R.T @ np.diag(np.asarray(rot_sigmas_w, dtype=np.float64) ** 2) @ R
    cov[3:, 3:] = np.eye(3) * trans_sigma**2
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def make_projection_factors(
    lm_keys: np.ndarray, pose_keys: np.ndarray, uv: np.ndarray, K, body_P_sensor, noise
) -> list:
    """Built-in reprojection factors (Eq. 9), one per observation.

    Args:
        lm_keys, pose_keys: (N,) gtsam keys of ``L(j)`` and ``X(i)``.
        uv: (N, 2) undistorted pixels (pinhole K).
        K: ``gtsam.Cal3_S2``; body_P_sensor: ``gtsam.Pose3`` of ``T_b_c``; noise: shared noise model.
    """
    import gtsam

    F = gtsam.GenericProjectionFactorCal3_S2
    uv = np.asarray(uv, dtype=np.float64)
    return [F(uv[n], noise, int(pose_keys[n]), int(lm_keys[n]), K, body_P_sensor) for n in range(uv.shape[0])]


def custom_factor(noise, keys: Sequence[int], error_fn: Callable, dims: Sequence[int], check: bool = True):
    """Wrap ``error_fn(values) -> (r (m,), [J_k (m, dims[k])] or None)`` as a ``gtsam.CustomFactor``.

    ``error_fn`` receives the ``gtsam.Values`` and a flag telling whether Jacobians are wanted; it returns the
    residual and the list of Jacobians in key order. The wrapper fills GTSAM's ``H`` in place (rebinding it is
    an error, PITFALLS.md) and, with ``check``, asserts each Jacobian's shape (a wrong shape is accepted
    silently by GTSAM and LM converges to a wrong answer).
    """
    import gtsam

    keys = [int(k) for k in keys]
    dims = [int(d) for d in dims]
    if len(keys) != len(dims):
        raise ValueError(f"custom_factor: {len(keys)} keys but {len(dims)} tangent dimensions")

    def _err(this, values, H):
        r, J = error_fn(values, H is not None)
        r = np.ascontiguousarray(r, dtype=np.float64).reshape(-1)
        if H is not None:
            if check:
                if len(J) != len(keys):
                    raise AssertionError(f"custom factor returned {len(J)} Jacobians for {len(keys)} keys")
                for k, (Jk, d) in enumerate(zip(J, dims, strict=False)):
                    if np.shape(Jk) != (r.size, d):
                        raise AssertionError(f"Jacobian {k} has shape {np.shape(Jk)}, expected {(r.size, d)}")
            for k, Jk in enumerate(J):
                H[k] = np.asarray(Jk, dtype=np.float64)
        return r

    return gtsam.CustomFactor(noise, keys, _err)


# --------------------------------------------------------------------------- reprojection in numpy
def project_body_points(
    T_w_b: np.ndarray, T_b_c: np.ndarray, X_w: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points into the camera of body pose ``T_w_b`` (Eq. 9 without the measurement).

    Args:
        T_w_b: (4, 4); T_b_c: (4, 4); X_w: (N, 3) m; K: (3, 3) pinhole intrinsics.

    Returns:
        uv (N, 2) pixels, p_c (N, 3) camera-frame points, p_b (N, 3) body-frame points.
    """
    T_b_w = inv_T(T_w_b)
    p_b = X_w @ T_b_w[:3, :3].T + T_b_w[:3, 3]
    T_c_b = inv_T(T_b_c)
    p_c = p_b @ T_c_b[:3, :3].T + T_c_b[:3, 3]
    uv, _ = project_pinhole((K[0, 0], K[1, 1], K[0, 2], K[1, 2]), p_c, min_abs_depth=1e-9)
    return uv, p_c, p_b


def _reproject(
    T_w_b: np.ndarray, X_w: np.ndarray, uv: np.ndarray, K: np.ndarray, T_c_b: np.ndarray, jacobian: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Shared kernel: residuals (N, 2), their pose Jacobian (N, 2, 6) or None, camera depths (N,)."""
    R, t = T_w_b[:3, :3], T_w_b[:3, 3]
    R_cb, t_cb = T_c_b[:3, :3], T_c_b[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p_b = (X_w - t) @ R  # R^T (X - t)
    p_c = p_b @ R_cb.T + t_cb
    z = np.where(np.abs(p_c[:, 2]) > 1e-9, p_c[:, 2], 1e-9)
    r = uv - np.stack([fx * p_c[:, 0] / z + cx, fy * p_c[:, 1] / z + cy], -1)
    if not jacobian:
        return r, None, p_c[:, 2]
    N = X_w.shape[0]
    A = np.zeros((N, 2, 3))  # d uv / d p_c
    A[:, 0, 0] = fx / z
    A[:, 0, 2] = -fx * p_c[:, 0] / z**2
    A[:, 1, 1] = fy / z
    A[:, 1, 2] = -fy * p_c[:, 1] / z**2
    A = A @ R_cb  # d uv / d p_b
    # p_b(xi) = Exp(xi)^-1 p_b0  =>  d p_b / d omega = [p_b]_x, d p_b / d v = -I; columns of A [p_b]_x:
    px, py, pz = p_b[:, 0:1], p_b[:, 1:2], p_b[:, 2:3]
    J = np.empty((N, 2, 6))
    J[:, :, 0] = A[:, :, 1] * pz - A[:, :, 2] * py
    J[:, :, 1] = A[:, :, 2] * px - A[:, :, 0] * pz
    J[:, :, 2] = A[:, :, 0] * py - A[:, :, 1] * px
    J[:, :, 3:] = -A
    return r, -J, p_c[:, 2]  # residual = uv - projection


def reprojection_residuals(
    T_w_b: np.ndarray,
    T_b_c: np.ndarray,
    X_w: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    jacobian: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Residuals ``uv - Pi(T_b_c^-1 T_w_b^-1 X)`` (N, 2) and, optionally, their Jacobian (N, 2, 6).

    The Jacobian is with respect to GTSAM's Pose3 retraction of the body pose,
    ``T_w_b <- T_w_b Exp([omega, v])`` (rotation first, right perturbation).
    """
    r, J, _ = _reproject(T_w_b, np.asarray(X_w, dtype=np.float64), uv, K, inv_T(T_b_c), jacobian)
    return r, J


def pose_prior_residual(T: np.ndarray, T_prior: np.ndarray) -> np.ndarray:
    """``Log(T_prior^-1 T)`` in GTSAM's ``[omega, v]`` order, with the translation part ``R_p^T (t - t_p)``.

    This is the residual GN uses for the pose prior (exact in rotation; its Jacobian is taken as identity,
    right for small errors, which is what a prior around a good prediction sees).
    """
    E = inv_T(T_prior) @ T
    return np.concatenate([so3_log(E[:3, :3]), E[:3, 3]])


def retract_pose(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T Exp(xi)`` with ``xi = [omega, v]``; the translation increment is applied in the body frame
    (first-order SE(3) retraction as GTSAM's ``Pose3.retract`` in its default chart)."""
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ so3_exp(xi[:3])
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ xi[3:]
    return out


def refine_pose(
    T_init: np.ndarray,
    X_w: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    T_b_c: np.ndarray,
    T_prior: np.ndarray | None = None,
    prior_sigmas: np.ndarray | None = None,
    pixel_sigma: float = 1.0,
    huber_k: float = 2.0,
    iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Motion-only refinement of a body pose against fixed landmarks (vectorised Gauss-Newton, Huber IRLS).

    Args:
        T_init: (4, 4) initial ``T_w_b`` (usually the IMU prediction).
        X_w: (N, 3) landmark positions; uv: (N, 2) their undistorted pixel observations.
        K: (3, 3); T_b_c: (4, 4).
        T_prior, prior_sigmas: optional pose prior (6 sigmas, ``[rot rad, trans m]``).
        pixel_sigma: px; huber_k: threshold in sigmas.

    Returns:
        refined ``T_w_b`` (4, 4), inlier mask (N,) (error below ``3 * huber_k`` sigmas at the end),
        final residual norms (N,) [px].
    """
    T = np.array(T_init, dtype=np.float64)
    N = X_w.shape[0]
    if N == 0:
        return T, np.zeros(0, bool), np.zeros(0)
    w_prior = None if T_prior is None else 1.0 / np.asarray(prior_sigmas, dtype=np.float64) ** 2
    T_c_b = inv_T(T_b_c)
    for it in range(iterations + 1):
        r, J, zc = _reproject(T, X_w, uv, K, T_c_b, jacobian=it < iterations)
        err = np.linalg.norm(r, axis=1)
        if it == iterations:
            break
        e = err / pixel_sigma
        w = np.where(e <= huber_k, 1.0, huber_k / np.maximum(e, 1e-12)) / pixel_sigma**2
        w = np.where(zc > 0.05, w, 0.0)  # points behind the camera get no weight
        Jf = J.reshape(2 * N, 6)
        wf = np.repeat(w, 2)
        H = Jf.T @ (Jf * wf[:, None])
        g = Jf.T @ (wf * r.reshape(-1))
        if w_prior is not None:
            H += np.diag(w_prior)
            g += w_prior * pose_prior_residual(T, T_prior)  # rp(xi) ~ rp + xi
        H += 1e-9 * np.eye(6)
        dx = -np.linalg.solve(H, g)  # r(xi) ~ r + J xi  ->  (J^T W J) xi = -J^T W r
        T = retract_pose(T, dx)
        if np.linalg.norm(dx) < 1e-7:
            iterations = it + 1  # one more pass computes the final residuals
    inl = (err < 3.0 * huber_k * pixel_sigma) & (zc > 0.05)
    return T, inl, err


# --------------------------------------------------------------------------- Jacobian checks
def numerical_jacobians(factor, values, eps: float = 1e-6) -> list[np.ndarray]:
    """Central differences of ``factor.unwhitenedError`` along each key's tangent (``Values.retract``).

    Returns one (m, d_k) matrix per key of the factor, in key order. Use it to check every custom factor's
    analytic Jacobians (PITFALLS.md: a wrong Jacobian is accepted silently by GTSAM).
    """
    import gtsam

    zero = values.zeroVectors()
    all_keys = list(values.keys())
    dims = {k: zero.at(k).shape[0] for k in all_keys}
    out = []
    for key in factor.keys():
        cols = []
        for i in range(dims[key]):
            errs = []
            for s in (+1.0, -1.0):
                vv = gtsam.VectorValues()
                for k in all_keys:
                    d = np.zeros(dims[k])
                    if k == key:
                        d[i] = s * eps
                    vv.insert(k, d)
                errs.append(np.asarray(factor.unwhitenedError(values.retract(vv)), dtype=np.float64))
            cols.append((errs[0] - errs[1]) / (2 * eps))
        out.append(np.stack(cols, 1))
    return out


def analytic_jacobians(factor, values) -> list[np.ndarray]:
    """The Jacobians GTSAM linearises a factor with (per key, in key order), unwhitened.

    The factor's noise model must be isotropic/diagonal without a robust kernel for the unwhitening to be
    exact (tests build factors with ``noiseModel.Unit``).
    """
    jf = factor.linearize(values)
    A, _ = jf.jacobian()
    nm = factor.noiseModel()
    sig = np.asarray(nm.sigmas(), dtype=np.float64) if hasattr(nm, "sigmas") else np.ones(A.shape[0])
    A = A * sig[:, None]
    out, c = [], 0
    zero = values.zeroVectors()
    for key in factor.keys():
        d = zero.at(key).shape[0]
        out.append(A[:, c : c + d])
        c += d
    assert c == A.shape[1], "Jacobian columns do not add up to the keys' dimensions"
    return out
