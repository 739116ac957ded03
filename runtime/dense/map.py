"""Local dense map (Sec. 5.3, Fig. 1 and 12) and depth evaluation (Table 2).

* :func:`uncertainty_mask`, :func:`backproject`, :func:`voxel_downsample`: the pixel filter, the pinhole
  back-projection and the plain voxel means that :class:`runtime.dense.fusion.VoxelMap` (the fused map of a run,
  ``dit-slam``'s ``dense_map.ply``, written by :func:`runtime.dense.fusion.write_fused_map`) builds on.
* :func:`save_keyframe_maps`: per-keyframe depth and uncertainty maps (``.npz`` float32 and 16-bit PNGs in
  the depth0 convention, value = metres * 5000); :func:`write_keyframe_maps` writes the ``keyframe_depth/``
  folder of them. Both outputs are written atomically (temporary name, then rename).
* :func:`depth_metrics`: RMSE, iRMSE, AbsRel, MAE, delta_k of a prediction against ground truth at network
  resolution (:func:`gt_depth_to_network` maps ``mav0/depth0`` there), numpy only (``train.metrics`` is the
  torch version used in training; the formulas are the same).

Uncertainty filter: :class:`runtime.dense.config.DenseMapConfig`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from runtime.dense.config import DenseMapConfig
from runtime.geometry import Camera, NetworkMapping
from runtime.outputs import atomic_folder

__all__ = [
    "uncertainty_mask",
    "backproject",
    "voxel_downsample",
    "write_keyframe_maps",
    "save_keyframe_maps",
    "gt_depth_to_network",
    "sparse_depth_image",
    "depth_metrics",
    "mean_metrics",
    "DEPTH_PNG_SCALE",
]

#: 16-bit PNG depth scale of the project (TUM / depth0): value = metres * 5000.
DEPTH_PNG_SCALE = 5000.0
#: Smallest predicted depth used in ratios and inverses [m] (as ``train.metrics.EPS``).
EPS = 1e-3


def uncertainty_mask(depth: np.ndarray, uncertainty: np.ndarray | None, cfg: DenseMapConfig) -> np.ndarray:
    """Pixels (H, W) bool kept by the depth range and the uncertainty filter (:class:`DenseMapConfig`)."""
    d = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(d) & (d >= cfg.min_depth) & (d <= cfg.max_depth)
    if uncertainty is not None:
        b = np.asarray(uncertainty, dtype=np.float64)
        if b.shape != d.shape:
            raise ValueError(f"uncertainty has shape {b.shape}, depth has {d.shape}")
        ok &= np.isfinite(b)
        if cfg.max_uncertainty is not None:
            ok &= b <= cfg.max_uncertainty
        if cfg.max_rel_uncertainty is not None:
            ok &= b <= cfg.max_rel_uncertainty * np.where(ok, d, 0.0)
    return ok


def backproject(
    depth: np.ndarray, camera: Camera, mask: np.ndarray | None = None, stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points of a depth map (pinhole camera, z-depth).

    Args:
        depth: (H, W) [m]; camera: pinhole camera of the map (its size must be W x H, no distortion).
        mask: (H, W) bool of pixels to use (default: depth > 0).
        stride: take every ``stride``-th row and column.

    Returns:
        p_c (N, 3) [m] and the pixels (N, 2) ``(u, v)`` they come from.

    >>> cam = Camera(2.0, 2.0, 1.0, 1.0, 3, 3)
    >>> backproject(np.full((3, 3), 2.0), cam)[0][0].tolist()   # pixel (0, 0) at depth 2
    [-1.0, -1.0, 2.0]
    """
    d = np.asarray(depth, dtype=np.float64)
    H, W = d.shape
    if (camera.width, camera.height) != (W, H):
        raise ValueError(f"camera is {camera.width}x{camera.height}, depth map is {W}x{H}")
    if camera.has_distortion:
        raise ValueError("backproject expects the pinhole camera of the network image (no distortion)")
    m = (np.isfinite(d) & (d > 0)) if mask is None else (np.asarray(mask, bool) & np.isfinite(d) & (d > 0))
    if stride > 1:
        sub = np.zeros_like(m)
        sub[::stride, ::stride] = True
        m &= sub
    v, u = np.nonzero(m)
    z = d[v, u]
    p = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)
    return p, np.stack([u, v], -1).astype(np.float64)


def voxel_downsample(
    xyz: np.ndarray, voxel: float, rgb: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Average the points (and colours) falling into each cubic voxel of edge ``voxel`` [m].

    Returns points (M, 3) sorted by voxel index, colours (M, 3) uint8 or None.

    >>> p, _ = voxel_downsample(np.array([[0.01, 0, 0], [0.03, 0, 0], [0.5, 0, 0]]), 0.1)
    >>> p[:, 0].round(3).tolist()
    [0.02, 0.5]
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if voxel <= 0 or xyz.shape[0] == 0:
        return xyz, rgb
    idx = np.floor(xyz / voxel).astype(np.int64)
    _, inv, cnt = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    out = np.stack([np.bincount(inv, weights=xyz[:, i]) for i in range(3)], -1) / cnt[:, None]
    col = None
    if rgb is not None:
        rgb = np.asarray(rgb).reshape(-1, 3)
        col = np.stack([np.bincount(inv, weights=rgb[:, i].astype(np.float64)) for i in range(3)], -1) / cnt[:, None]
        col = np.clip(np.rint(col), 0, 255).astype(np.uint8)
    return out, col


def write_keyframe_maps(
    out_dir: str | Path, maps: Sequence[tuple[str, np.ndarray, np.ndarray | None]], png: bool = True
) -> Path:
    """Write the folder ``out_dir`` (``keyframe_depth/`` by convention) with each keyframe's maps.

    Args:
        out_dir: the folder (replaced as a whole).
        maps: ``(name, depth, uncertainty or None)`` per keyframe, as :func:`save_keyframe_maps` takes them.
        png: also the 16-bit PNGs.

    The folder is filled under a temporary name and renamed into place (:func:`runtime.outputs.atomic_folder`):
    an earlier folder stays whole until the new one is complete, and a failed or interrupted write leaves no
    folder under the final name.

    Returns:
        ``out_dir`` as a Path.
    """

    def fill(tmp: Path) -> None:
        for name, depth, uncertainty in maps:
            save_keyframe_maps(tmp, name, depth, uncertainty, png)

    return atomic_folder(out_dir, fill)


def save_keyframe_maps(
    out_dir: str | Path, name: str, depth: np.ndarray, uncertainty: np.ndarray | None = None, png: bool = True
) -> list[Path]:
    """Save one keyframe's maps: ``<name>.npz`` (``depth``, ``uncertainty`` float32 [m]) and, with ``png``,
    ``<name>_depth.png`` / ``<name>_uncertainty.png`` (uint16, metres * 5000, 0 = invalid, clipped at 13.1 m).

    Returns the paths written.
    """
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    d = np.asarray(depth, dtype=np.float32)
    arrays = {"depth": d}
    if uncertainty is not None:
        u = np.asarray(uncertainty, dtype=np.float32)
        if u.shape != d.shape:
            raise ValueError(f"uncertainty has shape {u.shape}, depth has {d.shape}")
        arrays["uncertainty"] = u
    paths = [out / f"{name}.npz"]
    np.savez_compressed(paths[0], **arrays)
    if png:
        for key, arr in arrays.items():
            a = np.where(np.isfinite(arr) & (arr > 0), arr, 0.0)
            q = np.clip(np.rint(a * DEPTH_PNG_SCALE), 0, 65535).astype(np.uint16)
            p = out / f"{name}_{key}.png"
            if not cv2.imwrite(str(p), q):
                raise OSError(f"{p}: cv2.imwrite failed")
            paths.append(p)
    return paths


# --------------------------------------------------------------------------- evaluation
def gt_depth_to_network(gt: np.ndarray, camera: Camera, mapping: NetworkMapping) -> np.ndarray:
    """Ground-truth depth on the (distorted) camera grid (H, W) [m] -> network resolution, nearest neighbour.

    The depth0 images share cam0's distorted pixel grid; they are undistorted to the pinhole image (as the
    grey images fed to the network) and mapped with the same resize + crop, without mixing depths across
    edges. 0 stays invalid.
    """
    import cv2

    g = np.asarray(gt, dtype=np.float32)
    if g.shape != (camera.height, camera.width):
        raise ValueError(f"gt depth is {g.shape[1]}x{g.shape[0]}, camera is {camera.width}x{camera.height}")
    g = np.where(np.isfinite(g), g, 0.0).astype(np.float32)
    und = camera.undistort_image(g, interpolation=cv2.INTER_NEAREST)
    return mapping.image_to_network(und, nearest=True).astype(np.float32)


def sparse_depth_image(uv: np.ndarray, z: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Sparse depth map (H, W) float32 [m] of points at pixels ``uv`` (N, 2) with depth ``z`` (N,).

    Each point goes to its nearest pixel; where several land on one pixel the closest wins; points outside,
    or with non-positive or non-finite depth, are skipped; 0 = no point.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if z.shape[0] != uv.shape[0]:
        raise ValueError(f"{uv.shape[0]} pixels but {z.shape[0]} depths")
    H, W = shape
    out = np.full(H * W, np.inf)
    with np.errstate(invalid="ignore"):
        u = np.floor(uv[:, 0] + 0.5)
        v = np.floor(uv[:, 1] + 0.5)
        ok = np.isfinite(u) & np.isfinite(v) & np.isfinite(z) & (z > 0) & (u >= 0) & (v >= 0) & (u < W) & (v < H)
    idx = (v[ok] * W + u[ok]).astype(np.int64)
    np.minimum.at(out, idx, z[ok])
    out[~np.isfinite(out)] = 0.0
    return out.reshape(H, W).astype(np.float32)


def depth_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Depth metrics of one image at pixels with ``gt > 0`` and a prediction ``pred > 0`` (and ``mask``).

    Args:
        pred: (H, W) predicted depth [m]; 0 or non-finite = no prediction (a sparse map).
        gt: (H, W) ground truth [m], 0 = invalid, same grid.
        mask: optional (H, W) bool restricting the evaluation.

    Returns:
        ``rmse`` [m], ``irmse`` [1/m], ``abs_rel`` [-], ``mae`` [m], ``delta1..3`` [fraction], ``n`` (pixels
        evaluated) and ``coverage`` (``n`` / valid ground-truth pixels). Metrics are NaN when ``n == 0``.

    >>> m = depth_metrics(np.array([[1.0, 2.0], [4.5, 9.0]]), np.array([[1.0, 1.0], [5.0, 0.0]]))
    >>> round(m["rmse"], 6), m["mae"], round(m["delta1"], 6), m["n"]
    (0.645497, 0.5, 0.666667, 3)
    """
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    if p.shape != g.shape:
        raise ValueError(f"pred has shape {p.shape}, gt has {g.shape}")
    gt_ok = np.isfinite(g) & (g > 0)
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != g.shape:
            raise ValueError(f"mask has shape {mask.shape}, gt has {g.shape}")
        gt_ok &= mask
    valid = gt_ok & np.isfinite(p) & (p > 0)
    n = int(valid.sum())
    n_gt = int(gt_ok.sum())
    out = {"n": n, "coverage": (n / n_gt) if n_gt else float("nan")}
    names = ("rmse", "irmse", "abs_rel", "mae", "delta1", "delta2", "delta3")
    if n == 0:
        out.update({k: float("nan") for k in names})
        return out
    pv = np.maximum(p[valid], EPS)
    gv = g[valid]
    err = pv - gv
    ratio = np.maximum(pv / gv, gv / pv)
    out.update(
        rmse=float(np.sqrt(np.mean(err**2))),
        irmse=float(np.sqrt(np.mean((1.0 / pv - 1.0 / gv) ** 2))),
        abs_rel=float(np.mean(np.abs(err) / gv)),
        mae=float(np.mean(np.abs(err))),
        delta1=float(np.mean(ratio < 1.25)),
        delta2=float(np.mean(ratio < 1.25**2)),
        delta3=float(np.mean(ratio < 1.25**3)),
    )
    return out


def mean_metrics(per_image: Sequence[dict[str, float]]) -> dict[str, float]:
    """Average per-image metrics over the images with ``n > 0`` (each counts once, as ``train.metrics``);
    ``n`` is summed and ``images`` counts the images averaged."""
    used = [m for m in per_image if m.get("n", 0) > 0]
    keys = ("rmse", "irmse", "abs_rel", "mae", "delta1", "delta2", "delta3", "coverage")
    out = {k: (float(np.mean([m[k] for m in used])) if used else float("nan")) for k in keys}
    out["n"] = int(sum(m["n"] for m in used))
    out["images"] = len(used)
    return out
