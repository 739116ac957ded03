"""The depth codes of the map, refined at fixed poses when a keyframe leaves the window (Eq. 14, Sec. 5.2).

The window's Eq. 14 factors serve the poses. Their row sigmas are 16x the network's own Laplace sigma
(:class:`runtime.dense.config.DepthFactorConfig`), because stronger depth factors pulled the trajectory, and they
pair only the newest code keyframe with the others. The codes they leave move a keyframe's depth by under 1 %
(the depth metrics of ``metrics.json``; ``reports/ablations.md``, "The map's depth codes").

The map can ask more of the codes, because here the poses are given. When a keyframe leaves the window,
:func:`refine_codes` fits the codes of the keyframe and of its most co-visible keyframes jointly. The fit uses
Eq. 14 on every ordered pair of the group, at the window's current poses, with the ``N(0, I)`` code prior (scaled
by ``code_prior_sigma``). Each keyframe's depth is its first-order expansion
(:class:`runtime.dense.linearized.LinearizedDepth`), so no decoder runs during the fit. Only the leaving
keyframe's code is kept; it is the code that keyframe's dense-map depth and its depth metrics use. The neighbours'
window codes are left as they are: the trajectory never sees this fit.

The fit is Levenberg-Marquardt with Huber weights (iteratively reweighted) on the whitened rows. A step is kept
only when it lowers the robust cost.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from runtime.dense.config import DepthFactorConfig
from runtime.dense.factors import consistency_residuals, consistency_sigmas, pixel_rays
from runtime.dense.lookup import Bilinear

__all__ = ["refine_codes"]


def _huber_weights(z: np.ndarray, k: float | None) -> np.ndarray:
    """IRLS weights of the Huber loss on whitened residuals ``z`` (1 inside ``k``, ``k / |z|`` outside)."""
    if k is None or k <= 0:
        return np.ones_like(z)
    a = np.abs(z)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _huber_cost(z: np.ndarray, k: float | None) -> float:
    if k is None or k <= 0:
        return float(0.5 * (z**2).sum())
    a = np.abs(z)
    return float(np.where(a <= k, 0.5 * a**2, k * a - 0.5 * k * k).sum())


def refine_codes(
    providers: Sequence,
    codes: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    samples_uv: Sequence[np.ndarray],
    T_b_c: np.ndarray,
    K: Sequence[float],
    cfg: DepthFactorConfig,
    code_prior_sigma: float = 1.0,
    iterations: int = 2,
) -> tuple[list[np.ndarray], dict]:
    """Jointly fit the codes of a group of keyframes to Eq. 14 on all ordered pairs, poses held fixed.

    Args:
        providers: each keyframe's depth provider with ``expansion(code)`` (a
            :class:`runtime.dense.linearized.LinearizedDepth`) and ``uncertainty`` (H, W), same network size.
        codes: start codes (C,) of each keyframe.
        poses: (4, 4) body poses ``T_w_b`` of each keyframe (held fixed).
        samples_uv: (S_i, 2) network pixels of each keyframe warped into the others.
        T_b_c: (4, 4) camera-to-body; K: ``(fx, fy, cx, cy)`` of the network camera.
        cfg: the row sigmas (``sigma_per_b``, ``min_sigma``, ``consis_covariance``), the robust kernel
            (``consis_huber_k``) and the validity tests (``min_depth``, ``edge_rel``).
        code_prior_sigma: sigma of each code's ``N(0, I)`` prior.
        iterations: Levenberg-Marquardt iterations.

    Returns:
        ``(codes, info)``: the fitted codes (C,) float64 of each keyframe, and ``{"cost": [start, end],
        "rows": valid rows at the end, "iterations": steps taken}``.
    """
    n = len(providers)
    if not (n == len(codes) == len(poses) == len(samples_uv)) or n < 2:
        raise ValueError(f"refine_codes: needs 2 or more keyframes with a code, pose and samples each, got {n}")
    if not code_prior_sigma > 0 or iterations < 0:
        raise ValueError(f"refine_codes: code_prior_sigma={code_prior_sigma} must be > 0, iterations >= 0")
    C = int(np.asarray(codes[0]).size)
    shape = np.asarray(providers[0].uncertainty).shape[:2]
    lookups, rays, b_at = [], [], []
    for p, uv in zip(providers, samples_uv, strict=True):
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        lk = Bilinear(uv, shape)
        lookups.append(lk)
        rays.append(pixel_rays(uv, K))
        b_at.append(lk.sample(np.asarray(p.uncertainty, np.float64)))
    pairs = [(a, b) for a in range(n) for b in range(n) if a != b]  # samples of b warped into a
    k_h = cfg.consis_huber_k

    def evaluate(c: np.ndarray, jac: bool, sig: dict | None):
        exp = [p.expansion(c[i * C : (i + 1) * C]) for i, p in enumerate(providers)]
        zs, Js, sigs, rows = [], [], {}, 0
        for a, b in pairs:
            res = consistency_residuals(
                poses[a], poses[b], T_b_c, K, lookups[b], rays[b], exp[a], exp[b],
                min_depth=cfg.min_depth, edge_rel=cfg.edge_rel, jacobians=jac, pose_jacobians=False,
            )  # fmt: skip
            s = sig[(a, b)] if sig is not None else consistency_sigmas(res, providers[a].uncertainty, b_at[b], cfg)
            sigs[(a, b)] = s
            zs.append(res.r / s)
            rows += int(res.valid.sum())
            if jac:
                J = np.zeros((len(s), n * C))
                J[:, a * C : (a + 1) * C] = res.jacobians[2] / s[:, None]
                J[:, b * C : (b + 1) * C] = res.jacobians[3] / s[:, None]
                Js.append(J)
        z = np.concatenate(zs)
        return z, (np.concatenate(Js) if jac else None), sigs, rows

    def cost(z: np.ndarray, c: np.ndarray) -> float:
        return _huber_cost(z, k_h) + 0.5 * float(c @ c) / code_prior_sigma**2

    c = np.concatenate([np.asarray(x, np.float64).reshape(C) for x in codes])
    z, J, sig, rows = evaluate(c, True, None)  # sigmas evaluated once, at the start values (as the factors)
    e = e0 = cost(z, c)
    lam, steps = None, 0
    prior_info = np.eye(n * C) / code_prior_sigma**2
    for _ in range(iterations):
        w = _huber_weights(z, k_h)
        H = J.T @ (w[:, None] * J) + prior_info
        g = -(J.T @ (w * z)) - prior_info @ c
        if lam is None:
            lam = 1e-3 * float(np.trace(H)) / H.shape[0]
        for _ in range(4):  # raise the damping until a step lowers the cost
            cand = c + np.linalg.solve(H + lam * np.eye(H.shape[0]), g)
            zc, Jc, _, rc = evaluate(cand, True, sig)  # the Jacobian of the next iteration, if it is kept
            ec = cost(zc, cand)
            if ec < e:
                c, z, J, e, rows, lam = cand, zc, Jc, ec, rc, lam / 3.0
                steps += 1
                break
            lam *= 10.0
        else:
            break
    out = [c[i * C : (i + 1) * C].copy() for i in range(n)]
    return out, {"cost": [e0, e], "rows": rows, "iterations": steps}
