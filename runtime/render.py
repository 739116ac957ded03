"""Point clouds as images: a z-buffered splat renderer from a virtual pinhole camera (notebook figures).

The maps ``dit-slam`` writes (``sparse_map.ply``, ``dense_map.ply``) are point clouds in the SLAM world
frame. To show them as pictures without a 3-D viewer:

* :func:`look_at` builds a virtual camera pose ``T_w_c`` (OpenCV optical frame: x right, y down, z forward)
  from an eye position and a target;
* :func:`render_points` projects the points with a pinhole :class:`runtime.geometry.Camera` and keeps, per
  pixel, the nearest point (z-buffer), each point covering a ``(2 r + 1) x (2 r + 1)`` pixel square
  (``radius`` r); it returns the depth image (0 = empty), the colour image and the index of the point seen;
* :func:`project_points` projects a polyline (e.g. a trajectory) into the same image, for overlays;
* :func:`map_views` is the picture `dit-slam` writes of the dense map (`dense_map.png`): a top and an oblique view
  with the trajectory;
* :func:`depth_panels` is the picture of a few keyframes' depth that `dit-slam` writes (`keyframe_depth.png`):
  each keyframe's image, its sparse network input interpolated, the network's depth and its uncertainty (and the
  true depth when the sequence has it), side by side;
* :func:`align_se3` is the SE(3) alignment (Umeyama, no scale) of an estimated trajectory to ground truth,
  as a transform, so that the maps can be drawn in the ground-truth frame (``runtime.eval`` aligns the
  same way inside ``evo`` but returns only the aligned positions).

Vectorised numpy (one ``np.minimum.at`` per splat offset); no per-point Python loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.geometry import Camera, inv_T, project_pinhole

__all__ = [
    *("RenderedPoints", "look_at", "project_points", "render_points", "align_se3", "map_views"),
    *("colour_map", "depth_panels"),
]


@dataclass
class RenderedPoints:
    """Result of :func:`render_points`.

    Attributes:
        depth: (H, W) float32 z-depth [m] of the nearest point per pixel, 0 where no point landed.
        rgb: (H, W, 3) uint8 colour of that point (``background`` where empty), or None without colours.
        index: (H, W) int64 index (into the input points) of the point seen, -1 where empty.
    """

    depth: np.ndarray
    rgb: np.ndarray | None
    index: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: pixels covered by a point."""
        return self.index >= 0


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Pose ``T_w_c`` (4, 4) of a camera at ``eye`` looking at ``target`` (world, metres).

    The camera's z axis points from ``eye`` to ``target``, its y axis (image down) is as close as possible
    to ``-up``, x = y cross z (image right).

    Raises:
        ValueError: ``eye == target`` or the viewing direction is parallel to ``up``.

    >>> T = look_at([0, 0, 0], [1, 0, 0])   # looking along world +x, z up: image right is world -y
    >>> np.round(T[:3, :3], 6).tolist()
    [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    z = target - eye
    if not np.linalg.norm(z) > 0:
        raise ValueError(f"eye {eye.tolist()} and target {target.tolist()} coincide")
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)  # right = down x forward
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"viewing direction {z.tolist()} is parallel to up {up.tolist()}: pass another up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def project_points(
    xyz_w: np.ndarray, T_w_c: np.ndarray, camera: Camera, near: float = 0.05
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (N, 3) -> pixels (N, 2) ``(u, v)``, depths z (N,) [m] and a mask (N,) of points in
    front of the camera (``z > near``) that land inside the image (pinhole, the camera's distortion is
    ignored)."""
    p = np.asarray(xyz_w, dtype=np.float64).reshape(-1, 3)
    T_c_w = inv_T(np.asarray(T_w_c, dtype=np.float64))
    pc = p @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    z = pc[:, 2]
    front = np.isfinite(pc).all(1) & (z > near)
    uv, _ = project_pinhole(camera.intrinsics, np.where(front[:, None], pc, [0.0, 0.0, 1.0]))
    inside = front & (uv[:, 0] > -0.5) & (uv[:, 1] > -0.5)
    inside &= (uv[:, 0] < camera.width - 0.5) & (uv[:, 1] < camera.height - 0.5)
    return uv, z, inside


#: Points projected at once by :func:`render_points` (its arrays scale with this, not with the map).
RENDER_CHUNK = 1 << 18


def render_points(
    xyz_w: np.ndarray,
    T_w_c: np.ndarray,
    camera: Camera,
    rgb: np.ndarray | None = None,
    radius: int = 0,
    near: float = 0.05,
    background: int = 255,
) -> RenderedPoints:
    """Z-buffered splat of a point cloud seen from a virtual camera.

    Args:
        xyz_w: (N, 3) points in the world [m].
        T_w_c: (4, 4) camera pose (camera to world, OpenCV optical frame), e.g. from :func:`look_at`.
        camera: pinhole intrinsics and image size of the virtual camera (distortion ignored).
        rgb: optional (N, 3) uint8 colours (or (N,) grey).
        radius: each point covers the pixels within ``radius`` (Chebyshev) of its projection.
        near: points closer than this [m] (or behind the camera) are dropped.
        background: grey level of empty pixels in ``rgb``.

    Returns:
        :class:`RenderedPoints`. Ties in depth keep the point with the lower index.

    >>> cam = Camera(10.0, 10.0, 2.0, 2.0, 5, 5)
    >>> r = render_points([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0]], np.eye(4), cam)
    >>> float(r.depth[2, 2]), int(r.index[2, 2]), int(r.mask.sum())   # the nearer point wins
    (1.0, 1, 1)
    """
    p = np.asarray(xyz_w, dtype=np.float64).reshape(-1, 3)
    if radius < 0:
        raise ValueError(f"radius={radius}: must be >= 0")
    if camera.width < 1 or camera.height < 1:
        raise ValueError(f"image size {camera.width}x{camera.height} is empty")
    col = None
    if rgb is not None:
        col = np.asarray(rgb)
        if col.ndim == 1:
            col = np.repeat(col[:, None], 3, 1)
        if col.shape != (p.shape[0], 3):
            raise ValueError(f"rgb has shape {np.asarray(rgb).shape}, expected ({p.shape[0]}, 3) or ({p.shape[0]},)")
        col = col.astype(np.uint8)
    W, H = int(camera.width), int(camera.height)
    offsets = [(du, dv) for dv in range(-radius, radius + 1) for du in range(-radius, radius + 1)]
    # The points in chunks, each projected in both passes: the arrays scale with a chunk, not with the map (a
    # 150 s run's dense map has 3 M points).
    chunks = [slice(a, min(a + RENDER_CHUNK, p.shape[0])) for a in range(0, p.shape[0], RENDER_CHUNK)]

    def projected(sl: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Nearest pixel ``(u0, v0)``, depth and index of each point of ``p[sl]`` that lands in the image."""
        uv, z, ok = project_points(p[sl], T_w_c, camera, near)
        u0 = np.floor(uv[ok, 0] + 0.5).astype(np.int64)  # pixel u covers [u - 0.5, u + 0.5)
        v0 = np.floor(uv[ok, 1] + 0.5).astype(np.int64)
        return u0, v0, z[ok], np.nonzero(ok)[0] + sl.start

    def covered(u0: np.ndarray, v0: np.ndarray, du: int, dv: int) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (flat) and positions (into ``u0``) of the points that cover a pixel at offset (du, dv)."""
        u, v = u0 + du, v0 + dv
        m = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        return v[m] * W + u[m], np.nonzero(m)[0]

    zbuf = np.full(H * W, np.inf)
    for sl in chunks:
        u0, v0, zi, _ = projected(sl)
        for du, dv in offsets:  # (2r + 1)^2 offsets, each vectorised over the chunk's points
            pix, k = covered(u0, v0, du, dv)
            np.minimum.at(zbuf, pix, zi[k])
    # Again, keeping only the points nearest at their pixel (no pass holds every offset's arrays at once).
    pix_win, pt_win = [], []
    for sl in chunks:
        u0, v0, zi, idx = projected(sl)
        for du, dv in offsets:
            pix, k = covered(u0, v0, du, dv)
            win = zi[k] == zbuf[pix]  # this point is the nearest at this pixel
            pix_win.append(pix[win])
            pt_win.append(idx[k[win]])
    index = np.full(H * W, -1, dtype=np.int64)
    pix = np.concatenate(pix_win) if pix_win else np.zeros(0, np.int64)
    if pix.size:  # some point lands in the image
        pts = np.concatenate(pt_win)
        order = np.lexsort((pts, pix))  # by pixel, then by point index
        pix, pts = pix[order], pts[order]
        first = np.r_[True, pix[1:] != pix[:-1]]  # per pixel, the lowest index among the nearest
        index[pix[first]] = pts[first]
    index = index.reshape(H, W)
    depth = np.where(index >= 0, zbuf.reshape(H, W), 0.0).astype(np.float32)
    img = None
    if col is not None:
        img = np.full((H, W, 3), background, dtype=np.uint8)
        img[index >= 0] = col[index[index >= 0]]
    return RenderedPoints(depth, img, index)


def align_se3(est_ts: np.ndarray, est_T: np.ndarray, gt_ts: np.ndarray, gt_T: np.ndarray) -> np.ndarray:
    """``T_gt_est`` (4, 4): the rigid transform (no scale) that best maps the estimated positions onto the
    ground truth interpolated at the estimate's timestamps (Umeyama, least squares over positions).

    Args:
        est_ts: (N,) int64 ns; est_T: (N, 4, 4) estimated ``T_w_b``.
        gt_ts: (K,) int64 ns; gt_T: (K, 4, 4) ground-truth ``T_w_b``.

    Returns:
        ``T_gt_est`` with ``p_gt = T_gt_est @ p_est`` (apply it to the estimated map and trajectory).

    Raises:
        ValueError: fewer than 3 estimated poses inside the ground truth's time range.
    """
    from runtime.eval import interpolate_poses

    est_T = np.asarray(est_T, dtype=np.float64)
    ref, inside = interpolate_poses(est_ts, gt_ts, gt_T)
    if inside.sum() < 3:
        raise ValueError(f"only {int(inside.sum())} estimated poses lie within the ground truth's time range")
    x = est_T[inside, :3, 3]  # (M, 3)
    y = ref[:, :3, 3]
    mx, my = x.mean(0), y.mean(0)
    S = (y - my).T @ (x - mx) / x.shape[0]  # (3, 3) cross-covariance
    U, _, Vt = np.linalg.svd(S)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = my - R @ mx
    return T


def map_views(
    xyz_w: np.ndarray,
    rgb: np.ndarray | None,
    trajectory_w: np.ndarray | None = None,
    size: tuple[int, int] = (640, 480),
    radius: int = 1,
) -> np.ndarray:
    """A picture of a map (``dense_map.png``): a top view and an oblique view side by side, each with the
    trajectory drawn in red, from virtual cameras placed to frame the central 96 % of the map and trajectory
    (z is up, as in the SLAM world frame).

    Args:
        xyz_w: (N, 3) map points; rgb: (N, 3) uint8 colours or None (grey).
        trajectory_w: (M, 3) positions drawn as a polyline, or None.
        size: (width, height) of each view.

    Returns:
        (height, 2 * width, 3) uint8 RGB image.
    """
    import cv2

    p = np.asarray(xyz_w, dtype=np.float64).reshape(-1, 3)
    traj = None if trajectory_w is None else np.asarray(trajectory_w, dtype=np.float64).reshape(-1, 3)
    W, H = int(size[0]), int(size[1])
    boxes = [np.percentile(x, [2, 98], axis=0) for x in (p, traj) if x is not None and x.shape[0]]
    boxes = boxes or [np.zeros((2, 3))]
    lo, hi = np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)
    centre = 0.5 * (lo + hi)
    r = max(0.5 * float(np.linalg.norm((hi - lo)[:2])), 0.25)  # horizontal radius framed [m]
    views = []
    for eye_offset, up in (((0.0, 0.0, 3.0), (0.0, 1.0, 0.0)), ((-1.6, -1.6, 1.4), (0.0, 0.0, 1.0))):
        eye = centre + r * np.asarray(eye_offset)
        T_w_c = look_at(eye, centre, up)
        dist = float(np.linalg.norm(eye - centre))
        f = 0.5 * min(W, H) * dist / (1.15 * r)
        cam = Camera(f, f, (W - 1) / 2.0, (H - 1) / 2.0, W, H)
        img = render_points(p, T_w_c, cam, rgb if rgb is not None else np.full(p.shape[0], 90), radius).rgb
        img = np.ascontiguousarray(img)
        if traj is not None and traj.shape[0] >= 2:
            uv, _, ok = project_points(traj, T_w_c, cam)
            line = np.round(uv[ok]).astype(np.int32).reshape(-1, 1, 2)
            if line.shape[0] >= 2:
                cv2.polylines(img, [line], False, (220, 30, 30), 2, cv2.LINE_AA)
        views.append(img)
    return np.concatenate(views, axis=1)


def colour_map(x: np.ndarray, lo: float, hi: float, cmap: int | None = None, invalid=None) -> np.ndarray:
    """Colours of ``x`` over ``[lo, hi]`` (..., 3) uint8 RGB through an OpenCV colour map (``cmap``, default
    turbo); pixels where ``invalid`` (a bool mask like ``x``) is set are black. The depth pictures of
    ``dit-slam`` (:func:`depth_panels`) and of training (``train.module.image_panel``) use it."""
    import cv2

    x = np.asarray(x)
    if invalid is not None:
        x = np.where(invalid, lo, x)
    u8 = np.clip((x - lo) / max(hi - lo, 1e-6) * 255.0, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(u8, cv2.COLORMAP_TURBO if cmap is None else cmap)[..., ::-1]
    return rgb if invalid is None else np.where(np.asarray(invalid)[..., None], 0, rgb).astype(np.uint8)


def _colour(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """:func:`colour_map` of a depth-like image: values ``<= 0`` or not finite are no value (black)."""
    x = np.asarray(x, np.float64)
    return colour_map(x, lo, hi, invalid=~(np.isfinite(x) & (x > 0)))


def depth_panels(rows: list[dict], min_width: int = 240) -> np.ndarray:
    """A picture of keyframes' depth (``keyframe_depth.png``): one row a keyframe, the panels side by side.

    Panels: the grey image with the sparse network input's samples as dots; those samples interpolated (the
    reference a network with sparse input has to beat); the network's depth; its uncertainty; the true depth
    where a row has it. The depth panels of a row share one colour scale (turbo, near = blue, from the 2nd to
    the 98th percentile of the row's depths), the uncertainty has its own; black is no value. Each row's title
    gives its scales.

    Args:
        rows: dicts with ``image`` (h, w) uint8 grey, ``sparse`` (h, w) metres (0 = no sample) or None,
            ``depth`` and ``uncertainty`` (h, w) metres, optional ``gt`` (h, w) metres (0 = invalid) and
            ``title`` (str); every row at one size.
        min_width: panels are enlarged (nearest neighbour, by an integer factor) to at least this width.

    Returns:
        (H, W, 3) uint8 RGB.

    Raises:
        ValueError: no rows, or arrays of different shapes.
    """
    import cv2

    from runtime.densify import interpolate_sparse

    if not rows:
        raise ValueError("depth_panels: no rows")
    h, w = np.asarray(rows[0]["depth"]).shape
    k = max(1, int(np.ceil(min_width / w)))
    with_gt = any(r.get("gt") is not None for r in rows)
    names = ["image, map points", "points interpolated", "network depth", "uncertainty"] + (
        ["true depth"] if with_gt else []
    )
    head = 18  # px of the title line above each row
    out = []
    for r in rows:
        arrays = [r["image"], r["depth"], r["uncertainty"]] + [r[n] for n in ("sparse", "gt") if r.get(n) is not None]
        if any(np.asarray(a).shape != (h, w) for a in arrays):
            raise ValueError(f"depth_panels: every array must be {(h, w)}, got {[np.asarray(a).shape for a in arrays]}")
        depth = np.asarray(r["depth"], np.float64)
        sparse = None if r.get("sparse") is None else np.asarray(r["sparse"], np.float64)
        gt = None if r.get("gt") is None else np.asarray(r["gt"], np.float64)
        vals = np.concatenate([x[np.isfinite(x) & (x > 0)] for x in (depth, gt) if x is not None])
        lo, hi = np.percentile(vals, [2, 98]) if vals.size else (0.0, 1.0)
        img = np.repeat(np.asarray(r["image"], np.uint8)[..., None], 3, axis=2).copy()
        fill = np.zeros((h, w)) if sparse is None or not (sparse > 0).any() else interpolate_sparse(sparse)
        unc = np.asarray(r["uncertainty"], np.float64)
        u_hi = float(np.percentile(unc[np.isfinite(unc)], 98)) if np.isfinite(unc).any() else 1.0
        panels = [img, _colour(fill, lo, hi), _colour(depth, lo, hi), _colour(unc, 0.0, u_hi)]
        if with_gt:
            panels.append(_colour(gt if gt is not None else np.zeros((h, w)), lo, hi))
        panels = [np.ascontiguousarray(np.kron(p, np.ones((k, k, 1), np.uint8))) for p in panels]
        if sparse is not None:
            for v, u in np.argwhere(sparse > 0):
                c = (int(u * k + k // 2), int(v * k + k // 2))
                cv2.circle(panels[0], c, max(1, k), (255, 40, 40), -1, cv2.LINE_AA)
        band = np.full((head, w * k * len(panels), 3), 255, np.uint8)
        title = f"{r.get('title', '')}  depth {lo:.2f}-{hi:.2f} m, uncertainty 0-{u_hi:.2f} m".strip()
        cv2.putText(band, title, (4, head - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        row = np.concatenate(panels, axis=1)
        for i, name in enumerate(names):
            cv2.putText(row, name, (i * w * k + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
        out += [band, row]
    return np.concatenate(out, axis=0)
