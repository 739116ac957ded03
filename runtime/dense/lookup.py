"""Lookups in network-resolution maps: bilinear interpolation at fixed pixels and the depth-edge test.

Pixels are network pixels ``(u, v) = (column, row)``, looked up on the valid square ``[0, W-1] x [0, H-1]``.
A depth at an occlusion edge belongs to either surface and the bilinear gradient across the edge is metres per
pixel: a residual looked up there is an outlier whose Jacobian is wrong in direction (a Huber kernel bounds its
residual, not its Jacobian), so the depth factors drop such rows (:func:`depth_edge_ratio`, ``edge_rel``).

A factor needs a keyframe's depth at a few hundred pixels, not the whole map: :class:`MapExpansion` holds the
decoder's first-order expansion ``D0 + J0 dc`` and evaluates it only at the pixels looked up (the same numbers as
looking up the map ``D0 + J0 dc``, at a fraction of the cost).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "inside_image",
    "Bilinear",
    "bilinear",
    "MapExpansion",
    "as_expansion",
    "depth_edge_ratio",
    "off_depth_edges",
]


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
        u, v = uv[:, 0], uv[:, 1]
        finite = np.isfinite(u) & np.isfinite(v)
        with np.errstate(invalid="ignore"):
            self.inside = finite & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
        if not finite.all():
            u, v = np.where(finite, u, 0.0), np.where(finite, v, 0.0)
        u = np.minimum(np.maximum(u, 0.0), W - 1.0)
        v = np.minimum(np.maximum(v, 0.0), H - 1.0)
        x0 = np.minimum(u.astype(np.int64), W - 2)  # floor: u >= 0
        y0 = np.minimum(v.astype(np.int64), H - 2)
        self.fu = fu = u - x0  # (N,) in [0, 1]
        self.fv = fv = v - y0
        i00 = y0 * W + x0
        self.idx = np.stack([i00, i00 + 1, i00 + W, i00 + W + 1], -1)  # (N, 4) flat indices: 00, 10, 01, 11
        self.w = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], -1)  # (N, 4)
        self.memo: tuple | None = None  # a MapExpansion's D0 and J0 at these pixels (MapExpansion.sample)

    def _corners(self, img: np.ndarray) -> np.ndarray:
        img = np.asarray(img)
        if img.shape[:2] != self.shape:
            raise ValueError(f"map has shape {img.shape[:2]}, the lookup was built for {self.shape}")
        flat = img.reshape(self.shape[0] * self.shape[1], -1)
        return flat[self.idx].astype(np.float64)  # (N, 4, C)

    def interp(self, corners: np.ndarray) -> np.ndarray:
        """Interpolated values from the values at the four corners: (N, 4) -> (N,), (N, 4, C) -> (N, C)."""
        if corners.ndim == 2:
            return np.einsum("nk,nk->n", self.w, corners)
        return np.einsum("nk,nkc->nc", self.w, corners)

    def grad(self, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The bilinear interpolant's derivatives ``d/du``, ``d/dv`` (N,) from the corner values (N, 4)."""
        c, fu, fv = corners, self.fu, self.fv
        du = (1 - fv) * (c[:, 1] - c[:, 0]) + fv * (c[:, 3] - c[:, 2])
        dv = (1 - fu) * (c[:, 2] - c[:, 0]) + fu * (c[:, 3] - c[:, 1])
        return du, dv

    def sample(self, img: np.ndarray) -> np.ndarray:
        """Values at the pixels: (N,) for an (H, W) map, (N, C) for (H, W, C)."""
        out = self.interp(self._corners(img))
        return out[:, 0] if np.asarray(img).ndim == 2 else out

    def sample_grad(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Values (N,) of an (H, W) map and the bilinear interpolant's derivatives ``d/du``, ``d/dv`` (N,)."""
        c = self._corners(img)[:, :, 0]  # (N, 4)
        return (self.interp(c), *self.grad(c))


def bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, W) or (H, W, C) map at pixels (N, 2) (clamped to the image)."""
    return Bilinear(uv, np.asarray(img).shape[:2]).sample(img)


class MapExpansion:
    """A depth map ``D = D0 + J0 dc``, first order in the code offset ``dc`` from its expansion point, with the
    code Jacobian ``J0``, evaluated only at the pixels asked for (the map itself is never formed).

    Args:
        D0: (H, W) depth at the expansion point [m].
        J0: (H, W, C) its code Jacobian [m per code unit], or None (then the map is ``D0`` and has no Jacobian).
        dc: (C,) code offset from the expansion point, or None (the map is ``D0``).

    >>> D0, J0 = np.ones((3, 4)), np.full((3, 4, 2), 0.5)
    >>> MapExpansion(D0, J0, np.array([0.2, 0.4])).sample(Bilinear(np.array([[1.5, 0.5]]), (3, 4))).tolist()
    [1.3]
    """

    def __init__(self, D0: np.ndarray, J0: np.ndarray | None = None, dc: np.ndarray | None = None) -> None:
        D0 = np.asarray(D0)
        self.shape = D0.shape[:2]
        self.D0 = D0
        self._D0 = D0.reshape(-1)
        self.J0 = J0
        self._J0 = None if J0 is None else np.asarray(J0).reshape(self._D0.size, -1)
        self.dc = None
        if dc is not None and np.any(dc):
            if J0 is None:
                raise ValueError("a code offset needs the code Jacobian J0")
            self.dc = np.asarray(dc, dtype=np.float64)

    def _gather(self, flat: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """``D0`` (M,) and, when asked, the rows of ``J0`` (M, C) at flat pixel indices (M,), as float64."""
        d0 = self._D0.take(flat).astype(np.float64, copy=False)
        j0 = self._J0.take(flat, axis=0).astype(np.float64, copy=False) if jacobian else None
        return d0, j0

    def at(self, idx: np.ndarray) -> np.ndarray:
        """Depth [m] at flat pixel indices ``idx`` (any shape) of the (H, W) map."""
        d, j0 = self._gather(np.asarray(idx).reshape(-1), self.dc is not None)
        if self.dc is not None:  # gathered rows, then one matrix-vector product (not a stack of small ones)
            d = d + j0 @ self.dc
        return d.reshape(np.shape(idx))

    def _check(self, lookup: Bilinear) -> None:
        if lookup.shape != self.shape:
            raise ValueError(f"map has shape {self.shape}, the lookup was built for {lookup.shape}")

    def _at_fixed(self, lookup: Bilinear) -> tuple[np.ndarray, np.ndarray | None]:
        """``D0`` (N,) and ``J0`` (N, C) interpolated at the lookup's pixels, kept on the lookup for as long as it
        is asked about this expansion point (a factor's fixed pixels, evaluated at many codes)."""
        self._check(lookup)
        memo = lookup.memo
        if memo is None or memo[0] is not self.D0 or memo[1] is not self.J0:
            d0, j0 = self._gather(lookup.idx.reshape(-1), self._J0 is not None)
            d0 = lookup.interp(d0.reshape(lookup.idx.shape))
            j0 = None if j0 is None else lookup.interp(j0.reshape(*lookup.idx.shape, -1))
            memo = lookup.memo = (self.D0, self.J0, d0, j0)
        return memo[2], memo[3]

    def sample(self, lookup: Bilinear) -> np.ndarray:
        """Depth (N,) [m] at the lookup's pixels."""
        d0, j0 = self._at_fixed(lookup)
        return d0 if self.dc is None else d0 + j0 @ self.dc

    def sample_grad(self, lookup: Bilinear) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depth (N,) at the lookup's pixels and the interpolant's derivatives ``d/du``, ``d/dv`` (N,)."""
        self._check(lookup)
        c = self.at(lookup.idx)
        return (lookup.interp(c), *lookup.grad(c))

    def sample_jacobian(self, lookup: Bilinear) -> np.ndarray:
        """Code Jacobian (N, C) of the depth at the lookup's pixels."""
        if self._J0 is None:
            raise ValueError("this expansion has no code Jacobian")
        return self._at_fixed(lookup)[1]


def as_expansion(depth: np.ndarray | MapExpansion, J: np.ndarray | None = None) -> MapExpansion:
    """``depth`` itself when it is a :class:`MapExpansion`, else the map ``depth`` (H, W) with Jacobian ``J``."""
    return depth if isinstance(depth, MapExpansion) else MapExpansion(depth, J)


def depth_edge_ratio(depth: np.ndarray | MapExpansion, uv: np.ndarray) -> np.ndarray:
    """Relative depth range ``(max - min) / min`` (N,) over the 3x3 pixels around each pixel ``uv`` (N, 2)
    (the nearest pixel and its neighbours, clamped to the image) of an (H, W) depth map (or expansion);
    ``inf`` where a depth there is not positive or not finite. Large on depth discontinuities, about
    ``2 tan(angle) / f`` on a plane seen at ``angle`` from face-on with focal length ``f`` [px].

    >>> D = np.ones((4, 6)); D[:, 3:] = 2.0                     # an edge between columns 2 and 3
    >>> depth_edge_ratio(D, np.array([[0.0, 1.0], [2.2, 1.0], [4.6, 2.0]])).tolist()
    [0.0, 1.0, 0.0]
    """
    e = as_expansion(depth)
    H, W = e.shape
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    u, v = uv[:, 0], uv[:, 1]
    if not (np.isfinite(u).all() and np.isfinite(v).all()):
        u, v = np.nan_to_num(u), np.nan_to_num(v)
    u = np.minimum(np.maximum(np.floor(u + 0.5), 0), W - 1).astype(np.int64)
    v = np.minimum(np.maximum(np.floor(v + 0.5), 0), H - 1).astype(np.int64)
    step = np.array([-1, 0, 1])
    cols = np.minimum(np.maximum(u[:, None] + step, 0), W - 1)  # (N, 3), clamped as a replicated border
    rows = np.minimum(np.maximum(v[:, None] + step, 0), H - 1)
    d = e.at((rows[:, :, None] * W + cols[:, None, :]).reshape(-1, 9))  # (N, 9)
    hi, lo = d.max(1), d.min(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = (hi - lo) / lo
    return np.where(np.isfinite(d).all(1) & (lo > 0), ratio, np.inf)


def off_depth_edges(depth: np.ndarray | MapExpansion, uv: np.ndarray, edge_rel: float | None) -> np.ndarray:
    """Mask (N,) of the pixels that pass the depth-edge test (all of them when ``edge_rel`` is None)."""
    if edge_rel is None:
        return np.ones(np.asarray(uv).reshape(-1, 2).shape[0], dtype=bool)
    return depth_edge_ratio(depth, uv) <= edge_rel
