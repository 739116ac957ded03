"""Map-point descriptors and matching: ORB descriptors per landmark, mutual-best and guided matching, the
candidate map points in view, and RANSAC PnP (used by :mod:`runtime.reloc.relocalizer`)."""

from __future__ import annotations

import cv2
import numpy as np

from runtime.geometry import project_pinhole

# popcount of a byte, for Hamming distances in numpy
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


class MapDescriptors:
    """ORB descriptors of landmarks, keyed by landmark id."""

    def __init__(self) -> None:
        self.orb = cv2.ORB_create(nfeatures=1, nlevels=1, edgeThreshold=19, patchSize=31)
        self.desc: dict[int, np.ndarray] = {}

    def describe(self, image: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ORB descriptors (N, 32) uint8 at pixels (N, 2) of ``image``; ``ok`` (N,) False near the border."""
        n = uv.shape[0]
        out = np.zeros((n, 32), np.uint8)
        ok = np.zeros(n, bool)
        if n == 0:
            return out, ok
        kps = [cv2.KeyPoint(float(u), float(v), 31.0, -1.0, 0.0, 0, int(i)) for i, (u, v) in enumerate(uv)]
        kps, des = self.orb.compute(image, kps)
        if des is None or not kps:
            return out, ok
        idx = np.array([k.class_id for k in kps], dtype=np.int64)
        out[idx] = des
        ok[idx] = True
        return out, ok

    def add(self, ids: np.ndarray, desc: np.ndarray, ok: np.ndarray) -> None:
        for j, d, g in zip(ids, desc, ok, strict=False):
            if g:
                self.desc[int(j)] = d

    def get(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Descriptors (N, 32) and a mask of the ids that have one."""
        out = np.zeros((len(ids), 32), np.uint8)
        ok = np.zeros(len(ids), bool)
        for n, j in enumerate(ids):
            d = self.desc.get(int(j))
            if d is not None:
                out[n] = d
                ok[n] = True
        return out, ok


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise Hamming distances between descriptor sets (F, 32) and (M, 32) uint8 -> (F, M) int."""
    x = np.bitwise_xor(a[:, None, :], b[None, :, :])
    return _POPCOUNT[x].sum(-1, dtype=np.int32)


def match(q: np.ndarray, t: np.ndarray, max_dist: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual-best matches with a ratio test: indices into ``q`` and ``t``."""
    if q.shape[0] == 0 or t.shape[0] < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    D = hamming(q, t)
    best = np.argmin(D, 1)
    d1 = D[np.arange(D.shape[0]), best]
    D2 = D.copy()
    D2[np.arange(D.shape[0]), best] = 1 << 20
    d2 = D2.min(1)
    back = np.argmin(D, 0)
    qi = np.nonzero((d1 <= max_dist) & (d1 < ratio * d2) & (back[best] == np.arange(D.shape[0])))[0]
    return qi, best[qi]


def guided_match(
    uv_map: np.ndarray,
    d_map: np.ndarray,
    uv_f: np.ndarray,
    d_f: np.ndarray,
    radius: float,
    max_dist: int,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match projected map points (M, 2) to features (F, 2) within ``radius`` px by descriptor distance.

    Each map point takes its best feature in the radius (ratio test against the second best there); a feature
    claimed by several map points goes to the closest descriptor. Returns indices into map points, features.
    """
    if uv_map.shape[0] == 0 or uv_f.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    near = np.linalg.norm(uv_map[:, None, :] - uv_f[None, :, :], axis=-1) < radius  # (M, F)
    mi, fi = np.nonzero(near)
    if mi.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    D = np.full(near.shape, 1 << 20, dtype=np.int64)
    D[mi, fi] = _POPCOUNT[np.bitwise_xor(d_map[mi], d_f[fi])].sum(-1)
    best = np.argmin(D, 1)
    d1 = D[np.arange(D.shape[0]), best]
    D[np.arange(D.shape[0]), best] = 1 << 20
    d2 = D.min(1)
    ok = (d1 <= max_dist) & ((d2 >= 1 << 20) | (d1 < ratio * d2))
    m_idx = np.nonzero(ok)[0]
    if m_idx.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    f_idx = best[m_idx]
    # one map point per feature: keep the lowest distance
    order = np.lexsort((d1[m_idx], f_idx))
    f_sorted = f_idx[order]
    first = np.r_[True, f_sorted[1:] != f_sorted[:-1]]
    keep = order[first]
    return m_idx[keep], f_idx[keep]


def candidates_in_view(
    T_w_c: np.ndarray,
    X_w: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    margin: float,
    max_depth: float,
) -> np.ndarray:
    """Mask of world points (N, 3) in front of the camera and inside its image enlarged by ``margin``."""
    if X_w.shape[0] == 0:
        return np.zeros(0, bool)
    T_c_w = np.linalg.inv(T_w_c)
    (u, v), z = _project(K, X_w @ T_c_w[:3, :3].T + T_c_w[:3, 3])
    mw, mh = margin * width, margin * height
    return (z > 0.1) & (z < max_depth) & (u > -mw) & (u < width + mw) & (v > -mh) & (v < height + mh)


def in_view(T_c_w: np.ndarray, X_w: np.ndarray, K, width: int, height: int, max_depth: float):
    """Pixels (N, 2) of world points (N, 3) in a camera at ``T_c_w`` and a mask of those in front of it (0.1 m
    to ``max_depth``) and inside its image."""
    (u, v), z = _project(K, X_w @ T_c_w[:3, :3].T + T_c_w[:3, 3])
    ok = (z > 0.1) & (z < max_depth) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return np.stack([u, v], -1), ok


def _project(K, p_c: np.ndarray):
    """``((u, v), z)`` of camera-frame points for the view tests (a point behind the camera is masked by z)."""
    uv, z = project_pinhole((K[0, 0], K[1, 1], K[0, 2], K[1, 2]), p_c, min_abs_depth=1e-6)
    return (uv[:, 0], uv[:, 1]), z


def pnp(X_w: np.ndarray, xn: np.ndarray, reproj_norm: float, seed: int = 0) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC PnP on normalised image coordinates (N, 2) of world points (N, 3).

    Returns:
        ``T_w_c`` (4, 4) or None, and the inlier mask (N,).
    """
    n = X_w.shape[0]
    inl = np.zeros(n, bool)
    if n < 6:
        return None, inl
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        X_w.astype(np.float64),
        xn.astype(np.float64),
        np.eye(3),
        None,
        iterationsCount=300,
        reprojectionError=reproj_norm,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or idx is None or len(idx) < 6:
        return None, inl
    inl[idx.reshape(-1)] = True
    # refine on the inliers
    ok, rvec, tvec = cv2.solvePnP(X_w[inl], xn[inl], np.eye(3), None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
    R, _ = cv2.Rodrigues(rvec)
    T_c_w = np.eye(4)
    T_c_w[:3, :3] = R
    T_c_w[:3, 3] = tvec.reshape(3)
    # final inlier set with the refined pose
    p = X_w @ R.T + tvec.reshape(3)
    err = np.linalg.norm(p[:, :2] / np.where(p[:, 2:] > 1e-6, p[:, 2:], 1e-6) - xn, axis=1)
    inl = (err < reproj_norm) & (p[:, 2] > 0)
    return np.linalg.inv(T_c_w), inl
