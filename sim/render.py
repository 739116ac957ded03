"""Vectorised ray casting of box scenes (numpy, float32, no per-pixel Python loops).

The per-pixel rays of the (distorted) camera are computed once: pixel ``(u, v)`` -> undistorted normalised
``(x, y)`` by :meth:`runtime.geometry.Camera.pixel_to_normalized`, ray ``[x, y, 1]`` in the camera frame, so
the ray parameter of a hit *is* its z-depth. Per frame the rays are rotated to the world, the room (seen from
inside) is hit by its exit slab, and every furniture box by the slab test, restricted to the pixel rectangle
its visible part can project to (screen-space culling from the box corners clipped at the camera plane). The
nearest hit gives depth and face; the face texture is looked up bilinearly and shaded by a per-face factor.
"""

from __future__ import annotations

import numpy as np

from runtime.geometry import Camera
from sim.scenes import FACE_UV_AXES, Scene

__all__ = ["Renderer", "camera_rays"]

_EDGES = np.array(
    [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]],
    dtype=np.int64,
)
_CORNER_BITS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64)  # (8, 3)


def camera_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates of every pixel of ``camera``.

    Args:
        camera: the (possibly distorted) camera; pixel centres are integer ``(u, v)`` as in
            ``Camera.project``.

    Returns:
        ``(x, y)``: two (H, W) float32 arrays; the ray of pixel ``(u, v)`` is ``[x[v, u], y[v, u], 1]`` in the
        camera frame.
    """
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
    xn = camera.pixel_to_normalized(np.stack([u, v], -1))
    if camera.has_distortion:  # check that the fixed-point undistortion converged everywhere
        uv, _ = camera.project(np.concatenate([xn, np.ones_like(u)[..., None]], -1))
        err = float(np.max(np.abs(uv - np.stack([u, v], -1))))
        if err > 1e-3:
            raise ValueError(f"camera undistortion did not converge (max reprojection error {err:.3g} px)")
    return xn[..., 0].astype(np.float32), xn[..., 1].astype(np.float32)


class Renderer:
    """Renders a :class:`~sim.scenes.Scene` through a :class:`~runtime.geometry.Camera`.

    Args:
        scene: the room.
        camera: intrinsics, distortion and image size.
    """

    def __init__(self, scene: Scene, camera: Camera):
        self.scene = scene
        self.camera = camera
        self.rx, self.ry = camera_rays(camera)  # (H, W) float32
        # conservative per-column x and per-row y ranges of the rays, for screen-space culling
        self.col_xmin, self.col_xmax = self.rx.min(0), self.rx.max(0)
        self.row_ymin, self.row_ymax = self.ry.min(1), self.ry.max(1)
        F = 6 * scene.n_boxes
        face = np.arange(F)
        box, axis = face // 6, (face % 6) // 2
        ua = np.array([FACE_UV_AXES[a][0] for a in axis])
        va = np.array([FACE_UV_AXES[a][1] for a in axis])
        self.face_u0 = scene.lo[box, ua].astype(np.float32)  # (F,) origin of the face's texture coordinates [m]
        self.face_v0 = scene.lo[box, va].astype(np.float32)
        self.shade = scene.shade.astype(np.float32)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.camera.height, self.camera.width)

    def _pixel_rect(self, lo: np.ndarray, hi: np.ndarray, R_c_w: np.ndarray, o: np.ndarray, near: float = 1e-3):
        """Pixel rectangle ``(v0, v1, u0, u1)`` (half-open) that can see box ``[lo, hi]``; None: invisible."""
        corners = lo + _CORNER_BITS * (hi - lo)  # (8, 3) world
        pc = (corners - o) @ R_c_w.T  # (8, 3) camera
        z = pc[:, 2]
        front = z >= near
        if not front.any():
            return None
        pts = [pc[front]]
        a, b = _EDGES[:, 0], _EDGES[:, 1]
        cross = front[a] != front[b]
        if cross.any():  # clip the box at the plane z = near: edge intersections are vertices of the visible part
            pa, pb = pc[a[cross]], pc[b[cross]]
            s = (near - pa[:, 2]) / (pb[:, 2] - pa[:, 2])
            pts.append(pa + s[:, None] * (pb - pa))
        p = np.concatenate(pts, 0)
        xn, yn = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        cols = np.flatnonzero((self.col_xmax >= xn.min()) & (self.col_xmin <= xn.max()))
        rows = np.flatnonzero((self.row_ymax >= yn.min()) & (self.row_ymin <= yn.max()))
        if cols.size == 0 or rows.size == 0:
            return None
        return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1

    def trace(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of every pixel's ray.

        Args:
            T_w_c: (4, 4) camera pose in the world.

        Returns:
            ``(depth, face)``: (H, W) float32 z-depth [m] of the hit (> 0) and (H, W) int32 face index.
        """
        T_w_c = np.asarray(T_w_c, dtype=np.float64)
        if T_w_c.shape != (4, 4) or not np.all(np.isfinite(T_w_c)):
            raise ValueError(f"T_w_c must be a finite 4x4 matrix, got shape {T_w_c.shape}")
        sc = self.scene
        R = T_w_c[:3, :3]
        o = T_w_c[:3, 3]
        if sc.inside_box(o):
            raise ValueError(f"camera position {o.tolist()} is inside a box or outside the room")
        f32 = np.float32
        # world ray directions (components), then their inverses for the slab test
        d = [f32(R[i, 0]) * self.rx + f32(R[i, 1]) * self.ry + f32(R[i, 2]) for i in range(3)]
        for di in d:  # avoid 0 * inf = nan in the slab test
            tiny = np.abs(di) < f32(1e-12)
            if tiny.any():
                di[tiny] = f32(1e-12)
        inv = [f32(1.0) / di for di in d]
        neg = [(di < 0).astype(np.int32) for di in d]  # 1 where the ray runs towards -axis

        # room, seen from inside: exit slab
        lo, hi = sc.lo[0], sc.hi[0]
        tmax = [np.maximum(f32(lo[i] - o[i]) * inv[i], f32(hi[i] - o[i]) * inv[i]) for i in range(3)]
        t = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
        ax = tmax[0] == t
        ay = ~ax & (tmax[1] == t)
        face = np.where(ax, 1 - neg[0], np.where(ay, 3 - neg[1], 5 - neg[2])).astype(np.int32)

        R_c_w = R.T
        for b in range(1, sc.n_boxes):
            rect = self._pixel_rect(sc.lo[b], sc.hi[b], R_c_w, o)
            if rect is None:
                continue
            v0, v1, u0, u1 = rect
            win = (slice(v0, v1), slice(u0, u1))
            lo, hi = sc.lo[b], sc.hi[b]
            tmin = []
            tfar = None
            for i in range(3):
                iv = inv[i][win]
                t1 = f32(lo[i] - o[i]) * iv
                t2 = f32(hi[i] - o[i]) * iv
                tmin.append(np.minimum(t1, t2))
                tm = np.maximum(t1, t2, out=t1)
                tfar = tm if tfar is None else np.minimum(tfar, tm, out=tfar)
            tnear = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
            tw = t[win]
            hit = (tnear <= tfar) & (tnear > 0) & (tnear < tw)
            if not hit.any():
                continue
            ax = tmin[0] == tnear
            ay = ~ax & (tmin[1] == tnear)
            base = 6 * b
            fb = np.where(ax, base + neg[0][win], np.where(ay, base + 2 + neg[1][win], base + 4 + neg[2][win]))
            np.copyto(tw, tnear, where=hit)
            np.copyto(face[win], fb, where=hit)
        return t, face

    def _surface(self, T_w_c: np.ndarray):
        """What the rays of one frame hit: depth (H, W), face per pixel (P,), hit points (3 arrays (P,)) and albedo
        (P, C)."""
        t, face = self.trace(T_w_c)
        o = np.asarray(T_w_c, dtype=np.float64)[:3, 3]
        R = np.asarray(T_w_c, dtype=np.float64)[:3, :3]
        f32 = np.float32
        tf, ff = t.reshape(-1), face.reshape(-1)
        rx, ry = self.rx.reshape(-1), self.ry.reshape(-1)
        p = [f32(o[i]) + tf * (f32(R[i, 0]) * rx + f32(R[i, 1]) * ry + f32(R[i, 2])) for i in range(3)]
        axis = (ff % 6) // 2
        u = np.where(axis == 0, p[1], p[0]) - self.face_u0[ff]
        v = np.where(axis == 2, p[1], p[2]) - self.face_v0[ff]
        return t, ff, p, self.scene.atlas.lookup(ff, u, v)

    def render(
        self,
        T_w_c: np.ndarray,
        rng: np.random.Generator | None = None,
        noise_sigma: float = 0.0,
        exposure: float = 1.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Render one frame.

        Args:
            T_w_c: (4, 4) camera pose in the world.
            rng: generator for the sensor noise (needed when ``noise_sigma > 0``).
            noise_sigma: standard deviation of additive Gaussian pixel noise [grey levels of 255].
            exposure: brightness factor.

        Returns:
            ``(image, depth)``: image (H, W) uint8 grey or (H, W, 3) uint8 RGB (following the scene's atlas);
            depth (H, W) float32 z-depth in the camera frame [m], all pixels valid (> 0).
        """
        t, ff, p, albedo = self._surface(T_w_c)
        H, W = self.shape
        f32 = np.float32
        val = albedo * (self.shade[ff] * f32(255.0 * exposure))[:, None]
        if noise_sigma > 0:
            if rng is None:
                raise ValueError("noise_sigma > 0 needs an rng")
            val += f32(noise_sigma) * rng.standard_normal(val.shape, dtype=np.float32)
        img = np.clip(val + f32(0.5), 0, 255).astype(np.uint8)
        img = img.reshape(H, W) if img.shape[1] == 1 else img.reshape(H, W, img.shape[1])
        return img, t

    def radiance(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear scene radiance (relative units, 1 = a white surface fully lit) and depth of one frame.

        Scenes with a ``point_light`` (:mod:`sim.rooms`) are shaded per pixel: ``shade * (ambient + diffuse * cos
        / (1 + (d / range)^2))`` with ``d`` the distance to the light; emissive faces get ``shade`` alone.
        Other scenes get their per-face ``shade``.

        Returns:
            ``(radiance, depth)``: (H, W) or (H, W, 3) float32 (following the atlas), (H, W) float32 z-depth [m].
        """
        t, ff, p, albedo = self._surface(T_w_c)
        H, W = self.shape
        f32 = np.float32
        sc = self.scene
        if sc.point_light is None:
            gain = self.shade[ff]
        else:
            if not hasattr(self, "_normals"):
                from sim.rooms import face_normals

                self._normals = face_normals(sc.n_boxes)
                self._emissive = (
                    np.zeros(6 * sc.n_boxes, bool) if sc.emissive is None else np.asarray(sc.emissive, bool)
                )
            n = self._normals[ff]  # (P, 3)
            lx = [f32(sc.point_light[i]) - p[i] for i in range(3)]
            d2 = lx[0] * lx[0] + lx[1] * lx[1] + lx[2] * lx[2]
            cos = (n[:, 0] * lx[0] + n[:, 1] * lx[1] + n[:, 2] * lx[2]) / np.sqrt(d2 + f32(1e-9))
            lit = f32(0.08) + f32(1.8) * np.maximum(cos, f32(0.0)) / (f32(1.0) + d2 / f32(sc.light_range**2))
            gain = self.shade[ff] * np.where(self._emissive[ff], f32(1.0), lit)
        val = albedo * gain[:, None]
        val = val.reshape(H, W) if val.shape[1] == 1 else val.reshape(H, W, val.shape[1])
        return val, t
