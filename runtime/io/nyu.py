"""NYU Depth v2 readers: the sparse-to-dense h5 frames and the official labeled ``.mat``.

* h5 frame (sparse-to-dense layout, also written by ``sim/``):
  ``root/{train,val}/<scene>/<name>.h5`` with ``rgb`` uint8 (3, 480, 640) stored channels-first and
  ``depth`` float32 (480, 640) metres, registered to RGB.
* ``nyu_depth_v2_labeled.mat`` (MATLAB v7.3 = HDF5, read with h5py): ``images`` with h5py shape
  (1449, 3, 640, 480) uint8 and ``depths`` (1449, 640, 480) float metres. MATLAB stores column-major, so h5py
  sees the axes reversed: image ``i`` is ``images[i].transpose(2, 1, 0)`` -> (480, 640, 3), depth
  ``depths[i].T``.
* ``splits.mat`` (MATLAB v5, scipy.io.loadmat): ``trainNdxs`` (795, 1) and ``testNdxs`` (654, 1), 1-based.

All readers return RGB as HWC uint8 and depth as float32 metres with 0 = invalid.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = [
    "NyuFormatError",
    "NYU_HW",
    "read_nyu_h5",
    "list_nyu_h5",
    "NyuLabeledMat",
    "read_nyu_split",
]

#: (height, width) of NYU Depth v2 frames.
NYU_HW = (480, 640)


class NyuFormatError(ValueError):
    """A NYU-layout file is missing or malformed; the message names the file and the problem."""


def _h5py():
    """h5py, imported on first use: the readers of the other formats (and the peers' benchmark child, which reads
    only ``sensor.yaml`` files) do not need it."""
    import h5py

    return h5py


def _dataset(f, key: str, path: Path):
    if key not in f or not isinstance(f[key], _h5py().Dataset):
        raise NyuFormatError(f"{path}: missing dataset '{key}' (has {sorted(f.keys())})")
    return f[key]


def _check_depth(depth: np.ndarray, path: Path, what: str) -> np.ndarray:
    if depth.dtype.kind not in "fiu":
        raise NyuFormatError(f"{path}: {what} has non-numeric dtype {depth.dtype}")
    depth = depth.astype(np.float32, copy=False)
    bad = ~np.isfinite(depth) | (depth < 0)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise NyuFormatError(
            f"{path}: {what} has {int(bad.sum())} NaN/inf/negative values "
            f"(first {depth[r, c]} at row {r}, col {c})"
        )
    return depth


def read_nyu_h5(
    path: str | Path, expected_hw: tuple[int, int] | None = NYU_HW
) -> tuple[np.ndarray, np.ndarray]:
    """Read one sparse-to-dense h5 frame.

    Args:
        path: ``.h5`` file with datasets ``rgb`` uint8 (3, H, W) and ``depth`` float (H, W) [m].
        expected_hw: required (H, W); ``None`` accepts any size (rgb and depth must still agree).

    Returns:
        rgb (H, W, 3) uint8 HWC (C-contiguous), depth (H, W) float32 [m], 0 = invalid.

    Raises:
        NyuFormatError: missing file or dataset, wrong shape/dtype, NaN/inf/negative depth; names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise NyuFormatError(f"{path}: missing file")
    try:
        f = _h5py().File(path, "r")
    except OSError as e:
        raise NyuFormatError(f"{path}: not a readable HDF5 file ({e})") from e
    with f:
        rgb_ds, depth_ds = _dataset(f, "rgb", path), _dataset(f, "depth", path)
        if rgb_ds.ndim != 3 or rgb_ds.shape[0] != 3:
            raise NyuFormatError(
                f"{path}: 'rgb' must have shape (3, H, W) (channels first), got {rgb_ds.shape}"
            )
        if rgb_ds.dtype != np.uint8:
            raise NyuFormatError(f"{path}: 'rgb' must be uint8, got {rgb_ds.dtype}")
        hw = tuple(rgb_ds.shape[1:])
        if expected_hw is not None and hw != tuple(expected_hw):
            raise NyuFormatError(
                f"{path}: 'rgb' has shape {rgb_ds.shape}, expected (3, {expected_hw[0]}, {expected_hw[1]})"
            )
        if depth_ds.shape != hw:
            raise NyuFormatError(f"{path}: 'depth' has shape {depth_ds.shape}, expected {hw} like 'rgb'")
        rgb = np.ascontiguousarray(rgb_ds[()].transpose(1, 2, 0))  # (3,H,W) -> (H,W,3)
        depth = _check_depth(depth_ds[()], path, "'depth'")
    return rgb, depth


def list_nyu_h5(root: str | Path, split: str) -> list[Path]:
    """Sorted h5 frames ``root/<split>/<scene>/<name>.h5`` (hidden files, such as a writer's temporary ones, skipped).

    Raises:
        NyuFormatError: the split folder is missing or holds no frames, or ``root`` is the partial output of a
            ``dit-sim nyu`` run that did not finish (its ``sim_info.json`` says ``"complete": false``).
    """
    info = Path(root) / "sim_info.json"
    if info.is_file():
        try:
            partial = json.loads(info.read_text()).get("complete", True) is False
        except (OSError, ValueError, AttributeError):
            partial = False
        if partial:
            raise NyuFormatError(
                f"{root}: partial output of a dit-sim run that did not finish ({info} says complete=false); "
                "run dit-sim nyu again into this folder"
            )
    d = Path(root) / split
    if not d.is_dir():
        raise NyuFormatError(f"{d}: missing folder (expected {Path(root)}/<split>/<scene>/<name>.h5)")
    files = sorted(p for p in d.glob("*/*.h5") if not p.name.startswith("."))
    if not files:
        raise NyuFormatError(f"{d}: no h5 frames found (expected {d}/<scene>/<name>.h5)")
    return files


class NyuLabeledMat:
    """Frames of the official ``nyu_depth_v2_labeled.mat`` (MATLAB v7.3), read lazily with h5py.

    Args:
        path: the ``.mat`` file.
        indices: 0-based frame indices to expose (e.g. from :func:`read_nyu_split`); default all frames.

    ``len(ds)`` is the number of exposed frames and
    ``ds[i] -> (rgb (480, 640, 3) uint8, depth (480, 640) float32 [m])``. The file handle is reopened after a
    fork or unpickling, so an instance can be handed to DataLoader workers.

    Example:
        >>> ds = NyuLabeledMat("nyu_depth_v2_labeled.mat", read_nyu_split("splits.mat")[1])  # doctest: +SKIP
        >>> rgb, depth = ds[0]  # doctest: +SKIP
    """

    def __init__(self, path: str | Path, indices: np.ndarray | list[int] | None = None):
        self.path = Path(path)
        self._file = None  # h5py.File, opened on first use
        self._pid: int | None = None
        f = self._open()
        images, depths = _dataset(f, "images", self.path), _dataset(f, "depths", self.path)
        if images.ndim != 4 or images.shape[1] != 3:
            raise NyuFormatError(
                f"{self.path}: 'images' must have h5py shape (N, 3, W, H) (MATLAB H x W x 3 x N), "
                f"got {images.shape}"
            )
        if images.dtype != np.uint8:
            raise NyuFormatError(f"{self.path}: 'images' must be uint8, got {images.dtype}")
        n = images.shape[0]
        if depths.ndim != 3 or depths.shape != (n,) + images.shape[2:]:
            raise NyuFormatError(
                f"{self.path}: 'depths' has h5py shape {depths.shape}, "
                f"expected {(n,) + images.shape[2:]} to match "
                f"'images' {images.shape}"
            )
        self.num_total = int(n)
        self.hw = (int(images.shape[3]), int(images.shape[2]))  # MATLAB (H, W)
        if indices is None:
            idx = np.arange(n, dtype=np.int64)
        else:
            idx = np.asarray(indices)
            if idx.ndim != 1 or (idx.size and idx.dtype.kind not in "iu"):
                raise ValueError(
                    f"indices must be a 1-D integer array, got shape {idx.shape} dtype {idx.dtype}"
                )
            idx = idx.astype(np.int64)
            bad = (idx < 0) | (idx >= n)
            if bad.any():
                raise ValueError(
                    f"index {int(idx[bad][0])} out of range for {n} frames in {self.path} (0-based)"
                )
        self.indices = idx

    def _open(self):
        if self._file is None or self._pid != os.getpid():
            if not self.path.is_file():
                raise NyuFormatError(f"{self.path}: missing file")
            try:
                self._file = _h5py().File(self.path, "r")
            except OSError as e:
                raise NyuFormatError(f"{self.path}: not a MATLAB v7.3 / HDF5 file ({e})") from e
            self._pid = os.getpid()
        return self._file

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames")
        j = int(self.indices[i])
        f = self._open()
        rgb = np.ascontiguousarray(f["images"][j].transpose(2, 1, 0))  # (3, W, H) -> (H, W, 3)
        depth = _check_depth(np.ascontiguousarray(f["depths"][j].T), self.path, f"'depths'[{j}]")
        return rgb, depth

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> NyuLabeledMat:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_file"] = None
        state["_pid"] = None
        return state

    def __repr__(self) -> str:
        return f"NyuLabeledMat({str(self.path)!r}, {len(self)} of {self.num_total} frames)"


def read_nyu_split(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read the train/test split of the labeled set.

    Two formats:

    * ``.mat``: the official ``splits.mat`` with ``trainNdxs`` and ``testNdxs`` (MATLAB v5 via
      scipy.io.loadmat, v7.3 via h5py), **1-based** column vectors.
    * any other suffix: a text file with one ``train <idx>`` or ``test <idx>`` per line, **0-based** indices
      (the same numbers this function returns); ``#`` comments and blank lines are ignored.

    Returns:
        (train_idx, test_idx): sorted 0-based int64 arrays.

    Raises:
        NyuFormatError: missing file/key, non-integer or out-of-range index, or an index in both splits.
    """
    path = Path(path)
    if not path.is_file():
        raise NyuFormatError(f"{path}: missing file")
    if path.suffix.lower() == ".mat":
        train, test = _read_split_mat(path)
        train, test = train - 1, test - 1  # MATLAB 1-based -> 0-based
    else:
        train_l: list[int] = []
        test_l: list[int] = []
        for ln, line in enumerate(path.read_text().splitlines(), 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) != 2 or parts[0] not in ("train", "test") or not parts[1].isdigit():
                raise NyuFormatError(
                    f"{path}: line {ln}: expected 'train <idx>' or 'test <idx>' (0-based), got {s!r}"
                )
            (train_l if parts[0] == "train" else test_l).append(int(parts[1]))
        train, test = np.asarray(train_l, dtype=np.int64), np.asarray(test_l, dtype=np.int64)
    if (train < 0).any() or (test < 0).any():
        raise NyuFormatError(f"{path}: negative index after conversion to 0-based (was a .mat index 0?)")
    both = np.intersect1d(train, test)
    if both.size:
        raise NyuFormatError(
            f"{path}: {both.size} indices are in both train and test (first: {int(both[0])})"
        )
    return np.sort(train), np.sort(test)


def _read_split_mat(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import scipy.io

    try:
        m = scipy.io.loadmat(str(path))
    except NotImplementedError:  # MATLAB v7.3 is HDF5
        with _h5py().File(path, "r") as f:
            m = {k: f[k][()] for k in ("trainNdxs", "testNdxs") if k in f}
    except (ValueError, OSError) as e:
        raise NyuFormatError(f"{path}: not a readable MATLAB file ({e})") from e
    out = []
    for key in ("trainNdxs", "testNdxs"):
        if key not in m:
            raise NyuFormatError(f"{path}: missing variable '{key}'")
        a = np.asarray(m[key]).ravel()
        if a.dtype.kind == "f":
            if not np.all(np.isfinite(a)) or not np.all(a == np.round(a)):
                raise NyuFormatError(f"{path}: '{key}' holds non-integer indices")
        elif a.dtype.kind not in "iu":
            raise NyuFormatError(f"{path}: '{key}' has non-numeric dtype {a.dtype}")
        out.append(a.astype(np.int64))
    return out[0], out[1]
