"""Batched multi-view triangulation (linear DLT) with parallax, depth and reprojection checks.

All tracks are triangulated at once: observations are packed into (M, V) arrays with a mask, the DLT rows of
missing views are zero (they do not change the solution), and the smallest eigenvector of each 4x4 normal
matrix gives the point. Coordinates are taken relative to the mean camera centre for conditioning.

Each view's reprojection error passes a chi-square test (2 dof) at the stated ``pixel_sigma`` unless
``max_reproj_px`` gives an explicit bound. The sigma is the noise of an observation against a map on real images,
calibration and tracking drift included: ``benchmarks/bench_frontend.py`` triangulates the MH_05 excerpt's tracks
of 10 frames or more with the ground-truth poses and finds a robust sigma of 0.7-0.8 px (about 0.6 px once each
frame's pose is refined against the points; 0.46 px on the synthetic flight preset), hence 0.7 px and a bound of
2.1 px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.frontend.tracking import chi2_bound


@dataclass
class TriangulationConfig:
    """Acceptance checks for new landmarks."""

    min_parallax_deg: float = 2.0  # largest angle between any observing ray and the first one
    min_depth: float = 0.1  # m, in every observing camera
    max_depth: float = 40.0  # m
    pixel_sigma: float = 0.7  # px, noise of an observation on real images (bench_frontend.py)
    chi2_prob: float = 0.99  # acceptance probability of the per-view chi-square test (2 dof)
    max_reproj_px: float = 0.0  # explicit bound in every view [px, fx]; 0: the chi-square bound of pixel_sigma
    min_views: int = 2

    @property
    def reproj_bound_px(self) -> float:
        """The reprojection error [px] every view must stay under."""
        if self.max_reproj_px > 0:
            return self.max_reproj_px
        return chi2_bound(self.pixel_sigma, self.chi2_prob, 2)


def stack_views(T_w_c: np.ndarray, tracks: list[tuple[np.ndarray, np.ndarray]]):
    """The (M, V) arrays of :func:`triangulate` from tracks given as ``(frame indices (V_m,), xn (V_m, 2))`` into
    the poses ``T_w_c`` (F, 4, 4); each track's views fill its first ``V_m`` columns.

    Returns:
        ``(T, xn, mask)``: (M, V, 4, 4), (M, V, 2), (M, V) with V the longest track.

    >>> T, xn, mask = stack_views(np.tile(np.eye(4), (3, 1, 1)), [(np.array([0, 2]), np.ones((2, 2)))])
    >>> T.shape, xn.shape, mask.tolist()
    ((1, 2, 4, 4), (1, 2, 2), [[True, True]])
    """
    M, V = len(tracks), max((len(fr) for fr, _ in tracks), default=1)
    T = np.tile(np.eye(4), (M, V, 1, 1))
    xn, mask = np.zeros((M, V, 2)), np.zeros((M, V), bool)
    for m, (frames, x) in enumerate(tracks):
        T[m, : len(frames)], xn[m, : len(frames)], mask[m, : len(frames)] = T_w_c[frames], x, True
    return T, xn, mask


def triangulate(
    T_w_c: np.ndarray,
    xn: np.ndarray,
    mask: np.ndarray,
    focal: float = 1.0,
    cfg: TriangulationConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Triangulate M points from up to V views each.

    Args:
        T_w_c: (M, V, 4, 4) camera-to-world poses of each observation (any value where ``mask`` is False).
        xn: (M, V, 2) undistorted normalised image coordinates.
        mask: (M, V) bool, which observations exist.
        focal: focal length [px] to express the reprojection error in pixels.
        cfg: acceptance thresholds.

    Returns:
        X_w (M, 3) world points, ok (M,) bool (all checks passed), and diagnostics
        ``{"parallax_deg", "max_err_px", "min_depth"}`` (each (M,)).

    >>> T = np.tile(np.eye(4), (1, 2, 1, 1)); T[0, 1, 0, 3] = 1.0   # second camera 1 m to the right
    >>> X = np.array([0.2, -0.1, 4.0]); x0 = X[:2] / X[2]; x1 = (X[:2] - [1.0, 0.0]) / X[2]
    >>> P, ok, _ = triangulate(T, np.array([[x0, x1]]), np.ones((1, 2), bool), focal=500.0)
    >>> bool(ok[0]), np.allclose(P[0], X)
    (True, True)
    """
    cfg = cfg or TriangulationConfig()
    T_w_c = np.asarray(T_w_c, dtype=np.float64)
    xn = np.asarray(xn, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    M, V = mask.shape
    if T_w_c.shape != (M, V, 4, 4) or xn.shape != (M, V, 2):
        raise ValueError(
            f"triangulate: shapes T_w_c {T_w_c.shape}, xn {xn.shape}, mask {mask.shape} disagree"
        )
    if M == 0:
        return np.zeros((0, 3)), np.zeros(0, bool), {"parallax_deg": np.zeros(0), "max_err_px": np.zeros(0)}
    w = mask.astype(np.float64)
    centres = T_w_c[..., :3, 3]  # (M, V, 3)
    origin = (centres * w[..., None]).sum(1) / np.maximum(w.sum(1), 1)[:, None]  # (M, 3)
    R_c_w = np.swapaxes(T_w_c[..., :3, :3], -1, -2)  # (M, V, 3, 3)
    t_c = -np.einsum("mvij,mvj->mvi", R_c_w, centres - origin[:, None, :])  # camera from origin-centred world
    P = np.concatenate([R_c_w, t_c[..., None]], -1)  # (M, V, 3, 4)
    A = np.stack([xn[..., 0:1] * P[..., 2, :] - P[..., 0, :], xn[..., 1:2] * P[..., 2, :] - P[..., 1, :]], 2)
    A = A * w[..., None, None]  # (M, V, 2, 4), zero rows for missing views
    A = A.reshape(M, 2 * V, 4)
    # normalise rows so that near and far views weigh alike
    nrm = np.linalg.norm(A, axis=-1, keepdims=True)
    A = A / np.where(nrm > 0, nrm, 1.0)
    _, vecs = np.linalg.eigh(np.einsum("mki,mkj->mij", A, A))
    Xh = vecs[..., 0]  # (M, 4) smallest eigenvalue
    wh = Xh[:, 3]
    finite = np.abs(wh) > 1e-12
    Xl = Xh[:, :3] / np.where(finite, wh, 1.0)[:, None]
    X_w = Xl + origin
    # checks
    p_c = np.einsum("mvij,mvj->mvi", R_c_w, (Xl[:, None, :] - (centres - origin[:, None, :])))  # (M, V, 3)
    z = p_c[..., 2]
    zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
    err = np.linalg.norm(p_c[..., :2] / zs[..., None] - xn, axis=-1) * focal
    depth_ok = np.where(mask, (z > cfg.min_depth) & (z < cfg.max_depth), True).all(1)
    max_err = np.where(mask, err, 0.0).max(1)
    # parallax: the largest angle between the first observed ray and any other (world frame)
    rays = X_w[:, None, :] - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
    first = np.argmax(mask, axis=1)
    r0 = rays[np.arange(M), first]
    cosang = np.clip(np.einsum("mvi,mi->mv", rays, r0), -1.0, 1.0)
    parallax = np.degrees(np.where(mask, np.arccos(cosang), 0.0).max(1))
    ok = (
        finite
        & depth_ok
        & (max_err < cfg.reproj_bound_px)
        & (parallax > cfg.min_parallax_deg)
        & (mask.sum(1) >= cfg.min_views)
        & np.isfinite(X_w).all(1)
    )
    min_depth = np.where(mask, z, np.inf).min(1)
    return X_w, ok, {"parallax_deg": parallax, "max_err_px": max_err, "min_depth": min_depth}
