"""Lookups in network-resolution maps: bilinear interpolation at fixed pixels and the depth-edge test.

Pixels are network pixels ``(u, v) = (column, row)``, looked up on the valid square ``[0, W-1] x [0, H-1]``.
A depth at an occlusion edge belongs to either surface and the bilinear gradient across the edge is metres per
pixel: a residual looked up there is an outlier whose Jacobian is wrong in direction (a Huber kernel bounds its
residual, not its Jacobian), so the depth factors drop such rows (:func:`depth_edge_ratio`, ``edge_rel``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["inside_image", "Bilinear", "bilinear", "depth_edge_ratio", "off_depth_edges"]


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
    import cv2

    D = np.asarray(depth, dtype=np.float64)
    H, W = D.shape[:2]
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    u = np.clip(np.floor(np.nan_to_num(uv[:, 0]) + 0.5), 0, W - 1).astype(np.int64)
    v = np.clip(np.floor(np.nan_to_num(uv[:, 1]) + 0.5), 0, H - 1).astype(np.int64)
    # 3x3 max and min over the whole map (the border replicated, as clamping the neighbours): a few cv2 passes
    # cost less than nine gathers at the pixels; an invalid depth anywhere in the 3x3 gives inf
    k = np.ones((3, 3), np.uint8)
    valid = np.isfinite(D) & (D > 0)
    if valid.all():  # the usual case: a decoded depth map
        hi = cv2.dilate(D, k, borderType=cv2.BORDER_REPLICATE)[v, u]
        lo = cv2.erode(D, k, borderType=cv2.BORDER_REPLICATE)[v, u]
        return (hi - lo) / lo
    Dv = np.where(valid, D, 1.0)
    hi = cv2.dilate(Dv, k, borderType=cv2.BORDER_REPLICATE)[v, u]
    lo = cv2.erode(Dv, k, borderType=cv2.BORDER_REPLICATE)[v, u]
    near_bad = cv2.dilate((~valid).astype(np.uint8), k, borderType=cv2.BORDER_REPLICATE)[v, u] > 0
    return np.where(near_bad, np.inf, (hi - lo) / lo)


def off_depth_edges(depth: np.ndarray, uv: np.ndarray, edge_rel: float | None) -> np.ndarray:
    """Mask (N,) of the pixels that pass the depth-edge test (all of them when ``edge_rel`` is None)."""
    if edge_rel is None:
        return np.ones(np.asarray(uv).reshape(-1, 2).shape[0], dtype=bool)
    return depth_edge_ratio(depth, uv) <= edge_rel
