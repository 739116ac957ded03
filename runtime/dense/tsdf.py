"""Truncated signed distance volume of a run's keyframe depth maps, and its triangle mesh (surface nets).

:class:`TsdfVolume` integrates keyframe depth maps (network resolution, pinhole network camera, ``T_w_c``) one at
a time, as :class:`runtime.dense.fusion.VoxelMap` does with points:

* each depth map goes through the uncertainty filter of :class:`runtime.dense.config.DenseMapConfig`
  (:func:`runtime.dense.map.uncertainty_mask`); each pixel weighs ``1 / B^2`` (its Laplace scale ``B`` [m],
  clamped below at ``min_uncertainty``), or 1 without uncertainty;
* **sparse storage**: voxels of edge ``voxel`` [m] live in blocks of :data:`BLOCK`\\ ^3, allocated only where a
  depth's truncation band ``[d - trunc, d + trunc]`` along a pixel's ray passes, and found by their int64 key in
  a sorted index. A voxel holds its truncated signed distance (float32, in units of ``trunc``), its weight
  (float32) and its colour (3 x uint8, the weighted mean): **11 bytes per allocated voxel** (704 bytes a block,
  plus 24 bytes of key and index), whatever the scene's bounding box or the number of keyframes;
* **projective update**: every voxel of the blocks the depth map touches is projected into the keyframe; its
  signed distance is ``d(u, v) - z``, positive in front of the surface (the camera side), with ``d`` bilinear
  over the kept pixels of the four around ``(u, v)`` (weights renormalised: real depth maps are speckled, and
  only 16 % of the 2 x 2 quads of ``rgbd_real/realsense_box`` at 128 x 128 are whole; the nearest pixel's depth
  put a tilted wall half a voxel off at the image border). A voxel is left alone (unobserved) where its
  nearest pixel is not kept (extrapolating half a pixel past a sphere's silhouette moved its surface out by
  0.2 voxel on average), where the kept ones differ by more than :data:`runtime.dense.fusion.MAX_NORMAL_JUMP`
  (relative: an occlusion edge), or when it lies more than ``trunc`` behind the surface; the others take
  ``min(sdf / trunc, 1)`` into their weighted running mean with the nearest pixel's weight.

:meth:`TsdfVolume.mesh` extracts the zero level set with naive surface nets (no tables, no new dependency):
a cell (the cube of 8 neighbouring voxel centres) whose 8 corners all have weight > 0 and which has a measured
sign change on one of its 12 edges gets one vertex, the mean of its edge crossings (linear interpolation of the
distance); each measured sign-changing edge shared by 4 such cells gives a quad, two triangles, wound so that
their normal points from the negative to the positive side, i.e. towards the cameras that saw the surface.
A sign change counts as measured only when neither end is truncated (``|tsdf| < 1``): between a truncated
``+1`` and a ``-1`` (the free space in front of an occluding edge and the band behind it) the surface could lie
anywhere. No geometry is made in unobserved space. No component is dropped: in ``dit-slam``'s mesh of
``textured`` the components under 100 faces hold 0.5 % of the faces and are as accurate as the rest. Vertex
normals are the distance's gradient in their cell, colours the interpolated corner colours at the crossings.

Measured (``tests/dense/test_tsdf.py``; ``benchmarks/bench_dense_map.py``, ``benchmarks/results/dense_map.json``,
5 cm threshold, mesh scored by points sampled on its triangles, 4 cm voxels, 12 cm truncation):

* known surfaces rendered from known poses: a wall within 0.02 voxel; a sphere seen from 8 poses around it within
  0.07 voxel on average (95 % within 0.2 voxel, the worst at the rim of the seen band, seen only at grazing angles);
* exact depth: the rendered depth at ``dit-slam``'s keyframe poses gives a mesh with accuracy 0.98-1.00 and
  completeness 0.93-0.98 (synthetic ``handheld``, ``textured``); the recorded depth of ``rgbd_real`` at its
  poses 0.99-1.00 and 0.71-0.76 (SUN3D) or 0.46 (``realsense_box``: a speckled depth, holes leave cells with an
  unobserved corner);
* the network's depth: ``dit-slam``'s ``dense_mesh.ply`` reaches accuracy 0.09-0.27 and completeness 0.21-0.36,
  below its point map (0.18-0.33, 0.63-0.83): keyframes' depth errors (RMSE 0.1-0.2 m) exceed the truncation, so
  their surfaces do not average into one; ``1 / B^2`` against uniform weights changes the real rows by < 0.01;
* cost at 128 x 128: 13-67 ms a keyframe in the benchmark, 69-116 ms on ``dit-slam``'s network thread (a loaded
  2-core machine); extracting the mesh 0.4-2.6 s at the end of a 30 s run; 1.3-6.4 MB of blocks for a 30 s run.

This module never imports torch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from runtime.dense.config import DenseMapConfig
from runtime.dense.fusion import MAX_NORMAL_JUMP, colour_image, pixel_weights
from runtime.dense.map import uncertainty_mask
from runtime.geometry import Camera
from runtime.io.ply import write_ply
from runtime.outputs import atomic_write

__all__ = ["BLOCK", "TsdfVolume", "Mesh", "write_mesh_ply", "sample_mesh"]

#: Voxels per block edge (blocks of ``BLOCK ** 3`` voxels are the unit of allocation).
BLOCK = 4
_NV = BLOCK**3
#: Voxel index range: keys pack three 21-bit indices (about +-40 km at 4 cm voxels).
_OFF = 1 << 20
#: Blocks updated per vectorised step of an integration (half a million voxels: bounds its temporary memory).
_CHUNK = 8192
#: Local voxel offsets (512, 3) of a block, in key order.
_LOCAL = np.stack(np.meshgrid(*[np.arange(BLOCK)] * 3, indexing="ij"), -1).reshape(-1, 3)
#: The 8 corners (dx, dy, dz) of a cell: corner c has bit 0 = x, bit 1 = y, bit 2 = z.
_CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)
#: The 12 edges (c0, c1) of a cell, c1 = c0 with one bit set.
_EDGES = np.array([(c, c | (1 << a)) for a in range(3) for c in range(8) if not c & (1 << a)], np.int64)

Mesh = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # vertices, faces, colours, normals


def _pack(idx: np.ndarray) -> np.ndarray:
    """Keys (N,) int64 of integer indices (N, 3), each within +-2^20."""
    idx = np.asarray(idx, np.int64) + _OFF
    return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]


def _unpack(key: np.ndarray) -> np.ndarray:
    mask = (1 << 21) - 1
    return np.stack([(key >> 42) & mask, (key >> 21) & mask, key & mask], -1) - _OFF


def _offset_key(d: tuple[int, int, int] | np.ndarray) -> int:
    """The key difference of an index step ``d`` (keys add like indices while no field overflows)."""
    return (int(d[0]) << 42) + (int(d[1]) << 21) + int(d[2])


def _find(sorted_keys: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Positions of keys ``q`` in ``sorted_keys``; -1 where absent."""
    if sorted_keys.size == 0:
        return np.full(q.shape, -1, np.int64)
    pos = np.minimum(np.searchsorted(sorted_keys, q), sorted_keys.size - 1)
    return np.where(sorted_keys[pos] == q, pos, -1)


class TsdfVolume:
    """Sparse, uncertainty-weighted TSDF with colours; :meth:`mesh` extracts its surface (module doc).

    Args:
        voxel: voxel edge [m] (> 0).
        trunc: truncation distance [m] (> ``voxel``; default 3 voxels).
        min_uncertainty: smallest Laplace scale ``B`` [m] used in the weight ``1 / B^2``.

    >>> vol = TsdfVolume(0.05)
    >>> cam = Camera(20.0, 20.0, 15.5, 15.5, 32, 32)
    >>> vol.integrate(0, np.full((32, 32), 2.0), np.eye(4), cam) > 0   # a plane at z = 2 m
    True
    >>> v, f, rgb, n = vol.mesh()
    >>> bool(np.allclose(v[:, 2], 2.0)), bool(np.allclose(n, [0.0, 0.0, -1.0])), len(f) > 0
    (True, True, True)
    """

    def __init__(self, voxel: float, trunc: float | None = None, min_uncertainty: float = 1e-3) -> None:
        if not voxel > 0:
            raise ValueError(f"voxel={voxel}: must be > 0")
        trunc = 3.0 * voxel if trunc is None else trunc
        if not trunc > voxel:
            raise ValueError(f"trunc={trunc}: must be > voxel={voxel} (a surface must cross two voxels' band)")
        if not min_uncertainty > 0:
            raise ValueError(f"min_uncertainty={min_uncertainty}: must be > 0")
        self.voxel = float(voxel)
        self.trunc = float(trunc)
        self.min_uncertainty = float(min_uncertainty)
        self._n = 0  # blocks in use (rows)
        self.block_key = np.zeros(0, np.int64)  # key of each row's block
        self.tsdf = np.zeros((0, _NV), np.float32)  # signed distance / trunc, in [-1, 1]
        self.weight = np.zeros((0, _NV), np.float32)  # sum of weights; 0 = unobserved
        self.rgb = np.zeros((0, _NV, 3), np.uint8)  # weighted mean colour
        self._skeys = np.zeros(0, np.int64)  # sorted index: block keys ...
        self._srows = np.zeros(0, np.int64)  # ... and their rows
        self.keyframes: list[int] = []
        self._ids: set[int] = set()

    @classmethod
    def from_config(cls, cfg: DenseMapConfig) -> TsdfVolume:
        """The volume of ``cfg.tsdf_voxel`` and ``cfg.tsdf_trunc``."""
        return cls(cfg.tsdf_voxel, cfg.tsdf_trunc)

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._ids

    @property
    def n_blocks(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes of the voxel blocks in use and their index."""
        per_block = self.tsdf.itemsize * _NV + self.weight.itemsize * _NV + 3 * _NV + 3 * 8
        return self._n * per_block

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
        """Integrate one keyframe's depth map; returns the number of voxels updated.

        Args:
            kf_id: the keyframe (each is integrated once; a second call raises ValueError).
            depth: (H, W) z-depth [m] at network resolution; T_w_c: (4, 4) camera-to-world.
            camera: the network camera (pinhole, W x H).
            uncertainty: (H, W) Laplace scale ``B`` [m]: filter and weights ``1 / B^2`` (None: weight 1).
            image: (H, W) grey or (H, W, 3) RGB uint8 at network resolution (None: grey 128).
            cfg: the uncertainty filter and depth range (:class:`DenseMapConfig`).
        """
        kf_id = int(kf_id)
        if kf_id in self._ids:
            raise ValueError(f"keyframe {kf_id} is already in the TSDF")
        cfg = cfg or DenseMapConfig()
        d = np.asarray(depth, np.float64)
        if d.ndim != 2 or (camera.width, camera.height) != (d.shape[1], d.shape[0]):
            raise ValueError(f"camera is {camera.width}x{camera.height}, depth map has shape {d.shape}")
        T = np.asarray(T_w_c, np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"T_w_c must be a finite (4, 4) matrix, got shape {T.shape}")
        mask = uncertainty_mask(d, uncertainty, cfg)
        w_pix = pixel_weights(uncertainty, d.shape, self.min_uncertainty).astype(np.float32)
        colour = colour_image(image, d.shape)
        rows = self._allocate(self._band_blocks(d, mask, camera, T))
        n = 0
        for s in range(0, rows.size, _CHUNK):
            n += self._update(rows[s : s + _CHUNK], d, mask, w_pix, colour, camera, T)
        self.keyframes.append(kf_id)
        self._ids.add(kf_id)
        return n

    def _band_blocks(self, d: np.ndarray, mask: np.ndarray, camera: Camera, T: np.ndarray) -> np.ndarray:
        """Unique keys of the blocks the truncation band of the kept pixels passes through."""
        v, u = np.nonzero(mask)
        if u.size == 0:
            return np.zeros(0, np.int64)
        z = d[v, u]
        ray = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.size)], -1)
        step = 0.5 * BLOCK * self.voxel / float(np.linalg.norm(ray, axis=1).max())  # half a block along any ray
        n = int(np.ceil(2.0 * self.trunc / step)) + 1
        keys = []
        for s in np.linspace(-self.trunc, self.trunc, n):
            p = ray * np.maximum(z + s, 0.0)[:, None] @ T[:3, :3].T + T[:3, 3]
            idx = np.floor(p / self.voxel).astype(np.int64)
            if np.abs(idx).max() >= _OFF - BLOCK:
                raise ValueError(f"points beyond {(_OFF - BLOCK) * self.voxel:.0f} m from the origin cannot be fused")
            keys.append(np.unique(_pack(idx // BLOCK)))
        return np.unique(np.concatenate(keys))

    def _allocate(self, keys: np.ndarray) -> np.ndarray:
        """Rows (M,) of unique block keys (M,); new blocks get new unobserved rows."""
        pos = _find(self._skeys, keys)
        rows = np.full(keys.size, -1, np.int64)
        rows[pos >= 0] = self._srows[pos[pos >= 0]]
        new = np.flatnonzero(rows < 0)
        if new.size:
            start = self._n
            self._reserve(start + new.size)
            rows[new] = np.arange(start, start + new.size)
            self.block_key[start : start + new.size] = keys[new]
            self._n += int(new.size)
            pos = np.searchsorted(self._skeys, keys[new])  # keys are sorted (np.unique)
            self._skeys = np.insert(self._skeys, pos, keys[new])
            self._srows = np.insert(self._srows, pos, rows[new])
        return rows

    def _reserve(self, n: int) -> None:
        """Capacity for ``n`` blocks (doubling; new blocks are unobserved)."""
        cap = self.block_key.shape[0]
        if n <= cap:
            return
        cap = max(n, 2 * cap, 64)
        for name in ("block_key", "tsdf", "weight", "rgb"):
            old = getattr(self, name)
            arr = np.zeros((cap, *old.shape[1:]), old.dtype)
            arr[: self._n] = old[: self._n]
            setattr(self, name, arr)

    def _update(self, rows, d, mask, w_pix, colour, camera: Camera, T: np.ndarray) -> int:
        """Projective update of every voxel of the blocks ``rows`` (module doc); returns the voxels updated."""
        H, W = d.shape
        R, t = T[:3, :3], T[:3, 3]
        origin_c = (_unpack(self.block_key[rows]) * (BLOCK * self.voxel) - t) @ R  # (R, 3) block corners
        local_c = ((_LOCAL + 0.5) * self.voxel) @ R  # (512, 3) voxel centres from the corner
        p_c = (origin_c[:, None, :] + local_c[None]).reshape(-1, 3)  # R^T (p_w - t), row = block * 512 + voxel
        sel, u, v = _project(p_c, camera, H, W)
        iu, iv = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
        # cheap cull first (most voxels of a block are far behind the band or off the kept pixels): the
        # interpolated depth is within MAX_NORMAL_JUMP of the nearest kept pixel's
        ok = mask[iv, iu] & ((1.0 + MAX_NORMAL_JUMP) * d[iv, iu] - p_c[sel, 2] >= -self.trunc)
        sel, u, v, iu, iv = sel[ok], u[ok], v[ok], iu[ok], iv[ok]
        dd, ok = _bilinear(d, mask, u, v, MAX_NORMAL_JUMP)
        ok[ok] = dd[ok] - p_c[sel[ok], 2] >= -self.trunc  # farther behind the surface: unobserved
        sel, iu, iv, sdf = sel[ok], iu[ok], iv[ok], dd[ok] - p_c[sel[ok], 2]
        b, loc = np.divmod(sel, _NV)
        b = rows[b]
        w_old = self.weight[b, loc].astype(np.float64)
        w_new = w_pix[iv, iu].astype(np.float64)
        w_sum = w_old + w_new
        f_new = np.minimum(sdf / self.trunc, 1.0)
        self.tsdf[b, loc] = (self.tsdf[b, loc] * w_old + f_new * w_new) / w_sum
        c_old = self.rgb[b, loc].astype(np.float64)
        c = (c_old * w_old[:, None] + colour[iv, iu] * w_new[:, None]) / w_sum[:, None]
        self.rgb[b, loc] = np.clip(np.rint(c), 0, 255).astype(np.uint8)
        self.weight[b, loc] = w_sum
        return int(sel.size)

    def voxels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The observed voxels (weight > 0), sorted by key: keys (N,), indices (N, 3), tsdf (N,), rgb (N, 3)."""
        b, loc = np.nonzero(self.weight[: self._n] > 0)
        idx = _unpack(self.block_key[b]) * BLOCK + _LOCAL[loc]
        keys = _pack(idx)
        order = np.argsort(keys)
        return keys[order], idx[order], self.tsdf[b, loc][order].astype(np.float64), self.rgb[b, loc][order]

    def mesh(self) -> Mesh:
        """The zero level set as a triangle mesh (naive surface nets, module doc).

        Returns:
            vertices (V, 3) float64 [m, world], faces (F, 3) int64 (counter-clockwise seen from the positive,
            observed free side), colours (V, 3) uint8, normals (V, 3) unit, pointing to the positive side.
        """
        keys, idx, f, rgb = self.voxels()
        cell_keys, vert, vcol, vnrm = self._cell_vertices(keys, idx, f, rgb)
        faces = self._faces(keys, f, cell_keys)
        used, faces = np.unique(faces, return_inverse=True)  # drop the vertices of no face
        faces = faces.reshape(-1, 3)
        return vert[used] * self.voxel, faces.astype(np.int64), vcol[used], vnrm[used]

    def _cell_vertices(self, keys, idx, f, rgb):
        """Cells (sorted keys of their lowest corner) with a measured sign change and 8 observed corners; each
        one's vertex [voxels], colour and unit normal."""
        near = np.flatnonzero(np.abs(f) < 1.0)
        cand = np.unique(np.concatenate([keys[near] - _offset_key(o) for o in _CORNERS]))
        corner = np.stack([_find(keys, cand + _offset_key(o)) for o in _CORNERS], -1)  # (M, 8)
        ok = (corner >= 0).all(1)
        cand, corner = cand[ok], corner[ok]
        fc = f[corner]  # (M, 8)
        fa, fb = fc[:, _EDGES[:, 0]], fc[:, _EDGES[:, 1]]  # (M, 12)
        cross = _measured_crossing(fa, fb)
        has = cross.any(1)
        cand, corner, fc, fa, fb, cross = cand[has], corner[has], fc[has], fa[has], fb[has], cross[has]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(cross, fa / (fa - fb), 0.0)  # (M, 12) in [0, 1]
        e0, e1 = _CORNERS[_EDGES[:, 0]], _CORNERS[_EDGES[:, 1]]  # (12, 3)
        pts = e0[None] + t[..., None] * (e1 - e0)[None]  # (M, 12, 3) in the cell
        n_cross = cross.sum(1)[:, None]
        local = (pts * cross[..., None]).sum(1) / n_cross
        c = rgb[corner].astype(np.float64)  # (M, 8, 3)
        ca, cb = c[:, _EDGES[:, 0]], c[:, _EDGES[:, 1]]
        col = ((ca + t[..., None] * (cb - ca)) * cross[..., None]).sum(1) / n_cross
        vert = _unpack(cand) + 0.5 + local
        grad = np.stack([(fc[:, _CORNERS[:, a] == 1] - fc[:, _CORNERS[:, a] == 0]).sum(1) for a in range(3)], -1)
        norm = np.linalg.norm(grad, axis=1, keepdims=True)
        nrm = np.where(norm > 0, grad / np.where(norm > 0, norm, 1.0), 0.0)
        return cand, vert, np.clip(np.rint(col), 0, 255).astype(np.uint8), nrm

    def _faces(self, keys, f, cell_keys) -> np.ndarray:
        """Two triangles (vertex ids = positions in ``cell_keys``) per measured sign-changing voxel edge whose 4
        cells all have a vertex; wound so that the normal points to the positive side."""
        tris = []
        for a in range(3):
            ea, eb, ec = (np.eye(3, dtype=np.int64)[(a + k) % 3] for k in range(3))
            j = _find(keys, keys + _offset_key(ea))
            i = np.flatnonzero(j >= 0)
            j = j[i]
            m = _measured_crossing(f[i], f[j])
            i, j = i[m], j[m]
            ring = [keys[i] - _offset_key(o) for o in (0 * ea, eb, eb + ec, ec)]  # the 4 cells around the edge
            q = np.stack([_find(cell_keys, r) for r in ring], -1)  # (E, 4)
            full = (q >= 0).all(1)
            q, flip = q[full], f[i][full] >= 0  # positive at the lower end: the positive side is -a
            q[flip] = q[flip][:, ::-1]
            tris += [q[:, [0, 1, 2]], q[:, [0, 2, 3]]]
        return np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)


def _measured_crossing(fa: np.ndarray, fb: np.ndarray) -> np.ndarray:
    """A sign change between two distances with neither end truncated (module doc)."""
    return ((fa >= 0) != (fb >= 0)) & (np.abs(fa) < 1.0) & (np.abs(fb) < 1.0)


def _project(p_c: np.ndarray, camera: Camera, H: int, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (M,) of the camera-frame points (N, 3) in front of the camera whose projection ``(u, v)`` (M,)
    lies among the pixel centres (bilinear interpolation possible)."""
    z = p_c[:, 2]
    front = np.flatnonzero(z > 1e-6)
    u = camera.fx * p_c[front, 0] / z[front] + camera.cx
    v = camera.fy * p_c[front, 1] / z[front] + camera.cy
    ok = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    return front[ok], u[ok], v[ok]


def _bilinear(img, mask, u, v, max_jump: float) -> tuple[np.ndarray, np.ndarray]:
    """Values (M,) of ``img`` at ``(u, v)`` inside the pixel centres: bilinear over the kept ones (``mask``) of
    the four pixels around, their weights renormalised; and where they are defined (M,) bool: the nearest pixel
    is kept (no growth into filtered-out pixels, e.g. past a silhouette) and the kept ones are within
    ``max_jump`` (relative) of each other (across an occlusion edge the depth is not interpolable and the voxel
    is left alone)."""
    H, W = img.shape
    u0 = np.minimum(np.floor(u).astype(np.int64), W - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), H - 2)
    a, b = u - u0, v - v0
    quad = np.stack([img[v0, u0], img[v0, u0 + 1], img[v0 + 1, u0], img[v0 + 1, u0 + 1]], -1).astype(np.float64)
    kept = np.stack([mask[v0, u0], mask[v0, u0 + 1], mask[v0 + 1, u0], mask[v0 + 1, u0 + 1]], -1)
    wq = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], -1) * kept
    w = wq.sum(1)
    ok = (w > 1e-9) & mask[np.rint(v).astype(np.int64), np.rint(u).astype(np.int64)]
    ok &= np.where(kept, quad, -np.inf).max(1) <= (1.0 + max_jump) * np.where(kept, quad, np.inf).min(1)
    return (quad * wq).sum(1) / np.where(ok, w, 1.0), ok


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, spacing: float, seed: int = 0) -> np.ndarray:
    """Points (N, 3) sampled uniformly on a triangle mesh's surface, about one per ``spacing^2`` of area (and at
    least one per triangle), for scoring the surface rather than its vertices."""
    if not spacing > 0:
        raise ValueError(f"spacing={spacing}: must be > 0")
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if f.size == 0:
        return np.zeros((0, 3))
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    n = np.maximum(1, np.rint(area / spacing**2).astype(np.int64))
    tri = np.repeat(np.arange(len(f)), n)
    rng = np.random.default_rng(seed)
    r1, r2 = rng.random(tri.size), rng.random(tri.size)
    s = np.sqrt(r1)
    w0, w1, w2 = 1 - s, s * (1 - r2), s * r2
    return w0[:, None] * a[tri] + w1[:, None] * b[tri] + w2[:, None] * c[tri]


def write_mesh_ply(
    path: str | Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    colours: np.ndarray | None = None,
    normals: np.ndarray | None = None,
) -> Path:
    """Write a triangle mesh as binary PLY (``dense_mesh.ply`` when ``path`` is a folder), atomically
    (:func:`runtime.outputs.atomic_write`); returns the path."""
    path = Path(path)
    if path.suffix.lower() != ".ply":
        path = path / "dense_mesh.ply"
    return atomic_write(path, lambda tmp: write_ply(tmp, vertices, colours, normals, faces=faces))
