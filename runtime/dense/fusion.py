"""Fused dense map of a whole run: an uncertainty-weighted voxel point map with normals.

:class:`VoxelMap` integrates keyframe depth maps (network resolution, pinhole network camera) one at a time:

* each depth map goes through the uncertainty filter of :class:`runtime.dense.config.DenseMapConfig`
  (:func:`runtime.dense.map.uncertainty_mask`) and is back-projected and moved to the world with ``T_w_c``;
* each pixel's normal (:func:`depth_normals`) is the cross product of its back-projected neighbours' central
  differences, facing the camera, rotated to the world; pixels next to a depth jump get none;
* each point has the weight ``1 / B^2`` of its predicted Laplace scale ``B`` [m] (``provider.uncertainty``,
  clamped below at ``min_uncertainty``), or 1 without uncertainty (ground truth, interpolated points);
* per voxel of edge ``voxel`` [m] the map keeps the sums of weight, weighted position, weighted colour and
  weighted normal, and the number of keyframes that saw it. The sums are rows of arrays that grow by doubling;
  a voxel's row is found by its int64 key in a sorted index, or among the newest rows (sorted per call), which
  are merged into the index every :data:`TAIL_MAX` new voxels (about 90 bytes per occupied voxel, whatever the
  number of keyframes; an integration costs O(pixels) plus the amortised merges).

:meth:`VoxelMap.points` returns the weighted mean position, colour and unit normal of each voxel (seen by at
least ``min_keyframes`` keyframes); :func:`write_fused_map` writes them as ``dense_map.ply`` (x y z, nx ny nz,
red green blue, and ``keyframes``: how many keyframes saw the voxel, ushort, to filter by support), atomically.
A keyframe id is integrated once: a second call with the same id is refused.

Measured (``benchmarks/bench_dense_map.py``, ``benchmarks/results/dense_map.json``): fed the true depth, the
fusion is within 5 cm of the ground truth for 96-100 % of its points; fed the network's depth, the map's
accuracy is that of the network (its points lie as far from the surface as its depth errors).

In ``dit-slam dense=true`` (:class:`runtime.dense.mapper.DenseMapper`) every keyframe is integrated when it
leaves the window (final code, final pose) and those still in it at the end, so the map covers the run.

:func:`surface_metrics` scores a map against a ground-truth cloud: accuracy (fraction of map points within
``threshold`` of the ground truth, mean and median distance) and completeness (fraction of ground-truth points
within ``threshold`` of the map), with k-d trees both ways (``benchmarks/bench_dense_map.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from runtime.dense.config import DenseMapConfig
from runtime.dense.map import backproject, uncertainty_mask, voxel_downsample
from runtime.geometry import Camera
from runtime.io.ply import write_ply
from runtime.outputs import atomic_write

__all__ = [
    "depth_normals",
    "pixel_weights",
    "colour_image",
    "VoxelMap",
    "write_fused_map",
    "surface_metrics",
    "MAX_NORMAL_JUMP",
    "FINEST_VOXEL",
]

#: Largest relative depth step ``|z_neighbour - z| / z`` between a pixel and its four neighbours for which the
#: pixel gets a normal (a larger one is an occlusion edge, not a surface).
MAX_NORMAL_JUMP = 0.1
#: Voxel index range: keys pack three 21-bit indices (about +-20 km at 2 cm voxels).
_OFF = 1 << 20
#: Voxel edge [m] of the fused map when ``DenseMapConfig.voxel`` is 0.
FINEST_VOXEL = 0.01
#: New voxels looked up by sorting them per call before they are merged into the sorted index.
TAIL_MAX = 1 << 15


def depth_normals(depth: np.ndarray, camera: Camera, mask: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) of a depth map, facing the camera; NaN where undefined.

    The normal of pixel (u, v) is ``(P(u+1, v) - P(u-1, v)) x (P(u, v+1) - P(u, v-1))`` of the back-projected
    points ``P``, flipped towards the camera. It is undefined on the border, where the pixel or one of its four
    neighbours is invalid (outside ``mask``, non-positive or non-finite) and across depth jumps larger than
    :data:`MAX_NORMAL_JUMP` (relative).

    Args:
        depth: (H, W) z-depth [m]; camera: the pinhole camera of the map (W x H); mask: (H, W) bool of pixels
            to use (default: all valid depths).

    >>> cam = Camera(2.0, 2.0, 1.5, 1.5, 4, 4)
    >>> depth_normals(np.full((4, 4), 3.0), cam)[1, 1].tolist()   # a fronto-parallel plane faces the camera
    [0.0, 0.0, -1.0]
    """
    d = np.asarray(depth, dtype=np.float64)
    H, W = d.shape
    if (camera.width, camera.height) != (W, H):
        raise ValueError(f"camera is {camera.width}x{camera.height}, depth map is {W}x{H}")
    ok = np.isfinite(d) & (d > 0)
    if mask is not None:
        ok &= np.asarray(mask, bool)
    z = np.where(ok, d, np.nan)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    P = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)
    out = np.full((H, W, 3), np.nan)
    if H < 3 or W < 3:
        return out
    c = z[1:-1, 1:-1]
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    n = np.cross(du, dv)
    with np.errstate(invalid="ignore"):
        jump = np.maximum.reduce(
            [np.abs(z[1:-1, 2:] - c), np.abs(z[1:-1, :-2] - c), np.abs(z[2:, 1:-1] - c), np.abs(z[:-2, 1:-1] - c)]
        )
        good = np.isfinite(n).all(-1) & (jump <= MAX_NORMAL_JUMP * c)
        norm = np.linalg.norm(n, axis=-1)
        good &= norm > 0
        n = n / np.where(good, norm, 1.0)[..., None]
        facing = np.sum(n * P[1:-1, 1:-1], -1) > 0  # pointing away from the camera: flip
    n[facing] *= -1.0
    n[~good] = np.nan
    out[1:-1, 1:-1] = n + 0.0  # no -0.0
    return out


def pixel_weights(uncertainty: np.ndarray | None, shape: tuple[int, int], min_uncertainty: float) -> np.ndarray:
    """(H, W) fusion weights ``1 / B^2`` of a Laplace-scale map ``B`` [m] clamped below at ``min_uncertainty``,
    or ones without uncertainty (ground truth, interpolated points)."""
    if uncertainty is None:
        return np.ones(shape)
    return 1.0 / np.maximum(np.asarray(uncertainty, np.float64), min_uncertainty) ** 2


def colour_image(image: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) float64 colours of a grey or RGB uint8 image of size ``shape`` (None: grey 128)."""
    if image is None:
        return np.full((*shape, 3), 128.0)
    img = np.asarray(image)
    if img.shape[:2] != tuple(shape) or img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise ValueError(f"image must be uint8 with size {tuple(shape)}, got {img.dtype} {img.shape}")
    c = img.astype(np.float64)
    return np.repeat(c[..., None], 3, -1) if c.ndim == 2 else c[..., :3]


class VoxelMap:
    """Uncertainty-weighted voxel point map with colours, normals and keyframe counts (module doc).

    Args:
        voxel: voxel edge [m] (> 0).
        min_uncertainty: smallest Laplace scale ``B`` [m] used in the weight ``1 / B^2``.

    >>> from runtime.geometry import Camera
    >>> m = VoxelMap(0.05)
    >>> cam = Camera(4.0, 4.0, 1.5, 1.5, 4, 4)
    >>> m.integrate(0, np.full((4, 4), 2.0), np.eye(4), cam)   # 16 points of a plane at z = 2 m
    16
    >>> xyz, rgb, nrm, count = m.points()
    >>> len(m), float(xyz[:, 2].mean()), float(nrm[:, 2].min())
    (16, 2.0, -1.0)
    """

    def __init__(self, voxel: float, min_uncertainty: float = 1e-3) -> None:
        if not voxel > 0:
            raise ValueError(f"voxel={voxel}: must be > 0")
        if not min_uncertainty > 0:
            raise ValueError(f"min_uncertainty={min_uncertainty}: must be > 0")
        self.voxel = float(voxel)
        self.min_uncertainty = float(min_uncertainty)
        self._n = 0  # voxels (rows in use)
        self.key = np.zeros(0, np.int64)  # voxel key of each row
        self.w = np.zeros(0)  # sum of weights
        self.wp = np.zeros((0, 3))  # sum of weight * position [m]
        self.wc = np.zeros((0, 3), np.float32)  # sum of weight * colour
        self.wn = np.zeros((0, 3), np.float32)  # sum of weight * unit normal
        self.n_kf = np.zeros(0, np.int32)  # keyframes that saw the voxel
        self._skeys = np.zeros(0, np.int64)  # sorted index: keys ...
        self._srows = np.zeros(0, np.int64)  # ... and their rows
        self._n_indexed = 0  # rows below are in the sorted index, the others (the newest) are not
        self.keyframes: list[int] = []  # integrated keyframe ids, in order
        self._ids: set[int] = set()

    @classmethod
    def from_config(cls, cfg: DenseMapConfig) -> VoxelMap:
        """The map of ``cfg.voxel`` (:data:`FINEST_VOXEL` when it is 0, i.e. no downsampling)."""
        return cls(cfg.voxel or FINEST_VOXEL)

    def __len__(self) -> int:
        return self._n

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._ids

    def integrate(
        self,
        kf_id: int,
        depth: np.ndarray,
        T_w_c: np.ndarray,
        camera: Camera,
        uncertainty: np.ndarray | None = None,
        image: np.ndarray | None = None,
        cfg: DenseMapConfig | None = None,
    ) -> int:
        """Integrate one keyframe's depth map; returns the number of points fused.

        Args:
            kf_id: the keyframe (each is integrated once; a second call raises ValueError).
            depth: (H, W) z-depth [m] at network resolution; T_w_c: (4, 4) camera-to-world.
            camera: the network camera (pinhole, W x H).
            uncertainty: (H, W) Laplace scale ``B`` [m]: filter and weights ``1 / B^2`` (None: weight 1).
            image: (H, W) grey or (H, W, 3) RGB uint8 at network resolution (None: grey 128).
            cfg: the filter and stride (:class:`DenseMapConfig`; its ``voxel`` is not used here).
        """
        kf_id = int(kf_id)
        if kf_id in self._ids:
            raise ValueError(f"keyframe {kf_id} is already in the fused map")
        cfg = cfg or DenseMapConfig()
        d = np.asarray(depth, dtype=np.float64)
        mask = uncertainty_mask(d, uncertainty, cfg)
        p_c, uv = backproject(d, camera, mask, cfg.stride)
        iu, iv = uv[:, 0].astype(np.int64), uv[:, 1].astype(np.int64)
        n_c = depth_normals(d, camera, mask)[iv, iu]
        w = pixel_weights(uncertainty, d.shape, self.min_uncertainty)[iv, iu]
        rgb = colour_image(image, d.shape)[iv, iu]
        T = np.asarray(T_w_c, np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_w_c must be (4, 4), got {T.shape}")
        self._add(p_c @ T[:3, :3].T + T[:3, 3], w, rgb, n_c @ T[:3, :3].T)
        self.keyframes.append(kf_id)
        self._ids.add(kf_id)
        return int(len(p_c))

    def _key(self, p: np.ndarray) -> np.ndarray:
        idx = np.floor(p / self.voxel).astype(np.int64)
        if idx.size and (np.abs(idx).max() >= _OFF):
            raise ValueError(f"points beyond {_OFF * self.voxel:.0f} m from the origin cannot be fused")
        idx += _OFF
        return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]

    def _add(self, p: np.ndarray, w: np.ndarray, rgb: np.ndarray, n: np.ndarray) -> None:
        """Accumulate one keyframe's world points (N, 3), weights (N,), colours (N, 3), normals (N, 3; NaN =
        none) into the voxels."""
        if len(p) == 0:
            return
        keys, inv = np.unique(self._key(p), return_inverse=True)
        inv = inv.reshape(-1)
        has_n = np.isfinite(n).all(-1)
        wn_pt = np.where(has_n[:, None], n, 0.0) * w[:, None]

        def per_voxel(x: np.ndarray) -> np.ndarray:
            return np.stack([np.bincount(inv, weights=x[:, i], minlength=keys.size) for i in range(3)], -1)

        sw = np.bincount(inv, weights=w, minlength=keys.size)
        swp, swc, swn = per_voxel(p * w[:, None]), per_voxel(rgb * w[:, None]), per_voxel(wn_pt)
        rows = self._rows(keys)
        self.w[rows] += sw  # rows are unique: plain fancy-index updates
        self.wp[rows] += swp
        self.wc[rows] += swc.astype(np.float32)
        self.wn[rows] += swn.astype(np.float32)
        self.n_kf[rows] += 1

    def _rows(self, keys: np.ndarray) -> np.ndarray:
        """Rows (M,) of unique voxel keys (M,); new voxels get new zero rows."""
        rows = np.full(keys.size, -1, np.int64)
        if self._skeys.size:
            pos = np.minimum(np.searchsorted(self._skeys, keys), self._skeys.size - 1)
            hit = self._skeys[pos] == keys
            rows[hit] = self._srows[pos[hit]]
        miss = np.flatnonzero(rows < 0)
        t0 = self._n_indexed
        if miss.size and self._n > t0:  # the newest voxels, not yet in the index
            order = np.argsort(self.key[t0 : self._n])
            tail = self.key[t0 : self._n][order]
            pos = np.minimum(np.searchsorted(tail, keys[miss]), tail.size - 1)
            hit = tail[pos] == keys[miss]
            rows[miss[hit]] = t0 + order[pos[hit]]
        new = np.flatnonzero(rows < 0)
        if new.size:
            start = self._n
            self._reserve(start + new.size)
            rows[new] = np.arange(start, start + new.size)
            self.key[start : start + new.size] = keys[new]
            self._n += int(new.size)
            if self._n - self._n_indexed > TAIL_MAX:
                self._merge_tail()
        return rows

    def _reserve(self, n: int) -> None:
        """Capacity for ``n`` rows (doubling; new rows are zero)."""
        cap = self.key.shape[0]
        if n <= cap:
            return
        cap = max(n, 2 * cap, 1024)
        for name in ("key", "w", "wp", "wc", "wn", "n_kf"):
            old = getattr(self, name)
            arr = np.zeros((cap, *old.shape[1:]), old.dtype)
            arr[: self._n] = old[: self._n]
            setattr(self, name, arr)

    def _merge_tail(self) -> None:
        tail = self.key[self._n_indexed : self._n]
        order = np.argsort(tail)
        pos = np.searchsorted(self._skeys, tail[order])
        self._skeys = np.insert(self._skeys, pos, tail[order])
        self._srows = np.insert(self._srows, pos, self._n_indexed + order)
        self._n_indexed = self._n

    def points(self, min_keyframes: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The map: per voxel seen by at least ``min_keyframes`` keyframes, in the order voxels were first seen.

        Returns:
            xyz (M, 3) weighted mean positions [m], rgb (M, 3) uint8 weighted mean colours, normals (M, 3) unit
            (zero where no observation had a normal), count (M,) keyframes that saw the voxel.
        """
        n = self._n
        keep = self.n_kf[:n] >= int(min_keyframes)
        rows = slice(None) if keep.all() else keep  # a view of the rows, not a copy, when all are kept
        w = self.w[:n][rows][:, None]
        xyz = self.wp[:n][rows] / w
        c = self.wc[:n][rows] / w  # float64; rounded and clipped in place (a map can hold millions of voxels)
        rgb = np.clip(np.rint(c, out=c), 0, 255, out=c).astype(np.uint8)
        del c
        nrm = self.wn[:n][rows].astype(np.float64)
        norm = np.sqrt(np.add.reduce(nrm * nrm, axis=1, keepdims=True))  # as np.linalg.norm(nrm, axis=1)
        has = norm > 0
        np.divide(nrm, np.where(has, norm, 1.0), out=nrm)
        nrm[~has[:, 0]] = 0.0  # no normal: zero (+0.0)
        return xyz, rgb, nrm, self.n_kf[:n][rows].copy()


def write_fused_map(path: str | Path, xyz: np.ndarray, rgb: np.ndarray, normals: np.ndarray, count: np.ndarray) -> Path:
    """Write a fused map (the arrays of :meth:`VoxelMap.points`) as PLY with normals, colours and keyframe counts
    (property ``keyframes``, ushort; ``dense_map.ply`` when ``path`` is a folder), atomically
    (:func:`runtime.outputs.atomic_write`); returns the path."""
    path = Path(path)
    if path.suffix.lower() != ".ply":
        path = path / "dense_map.ply"
    support = {"keyframes": np.minimum(count, np.iinfo(np.uint16).max).astype(np.uint16)}
    return atomic_write(path, lambda tmp: write_ply(tmp, xyz, rgb, normals, support))


def surface_metrics(
    map_xyz: np.ndarray, gt_xyz: np.ndarray, threshold: float = 0.05, gt_voxel: float = 0.0
) -> dict[str, float]:
    """Accuracy and completeness of a map against a ground-truth surface cloud (same frame, metres).

    Args:
        map_xyz: (N, 3) map points; gt_xyz: (K, 3) ground-truth surface points.
        threshold: distance [m] within which a point counts (5 cm in the benchmark).
        gt_voxel: voxel-downsample the ground truth first [m] (0: as given).

    Returns:
        ``accuracy`` (fraction of map points within ``threshold`` of the ground truth), ``acc_mean_m``,
        ``acc_median_m`` (their distances), ``completeness`` (fraction of ground-truth points within
        ``threshold`` of the map), ``comp_mean_m``, ``comp_median_m``, ``n_map``, ``n_gt``. NaN when either
        cloud is empty.

    >>> g = np.random.default_rng(0).uniform(0, 1, (500, 3))
    >>> m = surface_metrics(g, g)
    >>> m["accuracy"], m["completeness"], m["acc_mean_m"]
    (1.0, 1.0, 0.0)
    """
    from scipy.spatial import cKDTree

    a = np.asarray(map_xyz, np.float64).reshape(-1, 3)
    g = np.asarray(gt_xyz, np.float64).reshape(-1, 3)
    if gt_voxel > 0:
        g, _ = voxel_downsample(g, gt_voxel)
    out = {"n_map": int(len(a)), "n_gt": int(len(g)), "threshold_m": float(threshold)}
    names = ("accuracy", "acc_mean_m", "acc_median_m", "completeness", "comp_mean_m", "comp_median_m")
    if len(a) == 0 or len(g) == 0:
        out.update({k: float("nan") for k in names})
        return out
    d_acc, _ = cKDTree(g).query(a, k=1)
    d_comp, _ = cKDTree(a).query(g, k=1)
    out.update(
        accuracy=float(np.mean(d_acc <= threshold)),
        acc_mean_m=float(np.mean(d_acc)),
        acc_median_m=float(np.median(d_acc)),
        completeness=float(np.mean(d_comp <= threshold)),
        comp_mean_m=float(np.mean(d_comp)),
        comp_median_m=float(np.median(d_comp)),
    )
    return out
