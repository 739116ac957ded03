"""Depth training data: NYU h5 frames, the official labeled ``.mat``, and the synthetic default set.

Every dataset yields the dict of :class:`train.augment.FrameTransform` plus the sample's identity. Items are
addressed by a key ``(epoch, pos, index)`` (or a plain ``index``, read as ``(0, index, index)``): the random
generator of a sample is ``numpy.random.default_rng([seed, epoch, index])``, so augmentation and sparse
sampling depend only on the seed, the epoch and the frame, never on worker scheduling, process rank or how a
run was interrupted (see :class:`train.datamodule.EpochSampler`).

Synthetic default data: when ``kind="sim"`` and the folder is missing, :func:`ensure_synthetic_nyu` renders it
once with ``sim.nyu.write_nyu_dataset`` into ``~/.cache/dit-slam/nyu-sim-<seed>-<n_train>-<n_val>`` (or the
given root) with a progress bar. Importing ``sim`` from ``train`` breaks the usual ``train -> models,
runtime.io`` flow on purpose and only here: it is what makes ``python train/fit.py`` work with no downloaded
data.
"""

from __future__ import annotations

import inspect
import logging
import os
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from runtime.io.nyu import NyuLabeledMat, list_nyu_h5, read_nyu_h5, read_nyu_split

__all__ = [
    "NyuFrames",
    "NyuH5Dataset",
    "NyuMatDataset",
    "cache_dir",
    "default_sim_root",
    "ensure_synthetic_nyu",
    "sample_key",
]

log = logging.getLogger(__name__)

Transform = Callable[[np.ndarray, np.ndarray, np.random.Generator], dict]


def sample_key(key: int | tuple[int, int, int] | Sequence[int]) -> tuple[int, int, int]:
    """Normalise a dataset key to ``(epoch, pos, index)``."""
    if isinstance(key, (int, np.integer)):
        return 0, int(key), int(key)
    if len(key) != 3:
        raise KeyError(f"dataset key must be an index or (epoch, pos, index), got {key!r}")
    e, p, i = (int(k) for k in key)
    return e, p, i


class NyuFrames(Dataset):
    """Frames from a reader, transformed for the network.

    Args:
        reader: ``len(reader)`` and ``reader[i] -> (rgb (H, W, 3) uint8, depth (H, W) float32 [m])``.
        transform: :class:`train.augment.FrameTransform` (or any callable ``(rgb, depth, rng) -> dict``).
        seed: base seed of the per-sample random generators.

    ``ds[key]`` returns the transform's dict plus ``index``, ``epoch``, ``pos`` (int64 scalars).
    """

    def __init__(self, reader, transform: Transform, seed: int = 0):
        self.reader = reader
        self.transform = transform
        self.seed = int(seed)

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, key) -> dict:
        epoch, pos, index = sample_key(key)
        n = len(self)
        if not 0 <= index < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        rgb, depth = self.reader[index]
        rng = np.random.default_rng([self.seed, epoch, index])
        out = self.transform(rgb, depth, rng)
        out["index"] = np.int64(index)
        out["epoch"] = np.int64(epoch)
        out["pos"] = np.int64(pos)
        return out


class _H5Reader:
    def __init__(self, files: list[Path]):
        self.files = files

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return read_nyu_h5(self.files[i], expected_hw=None)


class NyuH5Dataset(NyuFrames):
    """``root/<split>/<scene>/<name>.h5`` frames (sparse-to-dense layout; also the synthetic set).

    Args:
        root: dataset root (holds ``train/`` and ``val/``).
        split: sub-folder, e.g. ``train`` or ``val``.
        transform, seed: see :class:`NyuFrames`.
        limit: keep only the first ``limit`` frames (sorted order); None = all.
    """

    def __init__(self, root: str | Path, split: str, transform: Transform, seed: int = 0, limit: int | None = None):
        files = list_nyu_h5(root, split)
        if limit is not None:
            files = files[: int(limit)]
        self.root, self.split = Path(root), split
        super().__init__(_H5Reader(files), transform, seed)

    @property
    def files(self) -> list[Path]:
        return self.reader.files


class NyuMatDataset(NyuFrames):
    """Frames of the official ``nyu_depth_v2_labeled.mat`` selected by the official split file.

    Args:
        path: ``nyu_depth_v2_labeled.mat``.
        split_path: ``splits.mat`` (1-based ``trainNdxs``/``testNdxs``) or a text split, see
            :func:`runtime.io.nyu.read_nyu_split`.
        split: ``train`` (795 frames) or ``test`` / ``val`` (654 frames).
        transform, seed, limit: see :class:`NyuH5Dataset`.
    """

    def __init__(
        self,
        path: str | Path,
        split_path: str | Path,
        split: str,
        transform: Transform,
        seed: int = 0,
        limit: int | None = None,
    ):
        train_idx, test_idx = read_nyu_split(split_path)
        if split == "train":
            idx = train_idx
        elif split in ("test", "val"):
            idx = test_idx
        else:
            raise ValueError(f"split={split!r} must be 'train', 'val' or 'test' for the labeled .mat")
        if limit is not None:
            idx = idx[: int(limit)]
        super().__init__(NyuLabeledMat(path, idx), transform, seed)


def cache_dir() -> Path:
    """``$DIT_SLAM_CACHE`` or ``$XDG_CACHE_HOME/dit-slam`` or ``~/.cache/dit-slam``."""
    if os.environ.get("DIT_SLAM_CACHE"):
        return Path(os.environ["DIT_SLAM_CACHE"]).expanduser()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "dit-slam"


def default_sim_root(n_train: int, n_val: int, seed: int, realism: bool = False) -> Path:
    """Where the default synthetic NYU-layout set lives: ``<cache>/nyu-sim-<seed>-<n_train>-<n_val>[-real]``."""
    return cache_dir() / f"nyu-sim-{int(seed)}-{int(n_train)}-{int(n_val)}{'-real' if realism else ''}"


def _complete(root: Path) -> bool:
    try:
        return bool(list_nyu_h5(root, "train")) and bool(list_nyu_h5(root, "val"))
    except ValueError:
        return False


def ensure_synthetic_nyu(
    root: str | Path | None,
    n_train: int,
    n_val: int,
    seed: int = 0,
    progress: bool = True,
    realism: bool = False,
) -> Path:
    """Return a synthetic NYU-layout root, rendering it first when it does not exist yet.

    The set is written to a temporary sibling folder ``<root>.tmp-<pid>`` and renamed when complete, so an
    interrupted generation never leaves a half-written set behind, and concurrent callers (one per node in DDP)
    cannot see one. The temporary folder is removed when the rendering fails or is interrupted; those of processes
    that no longer exist (killed outright) are removed by the next call.

    Args:
        root: target folder; None = :func:`default_sim_root`.
        n_train, n_val: frames per split.
        seed: scene seed of the generator.
        progress: show a progress bar.
        realism: realistic rooms (hand-held and tabletop) through the camera physics (``sim.nyu``).
    """
    root = Path(root).expanduser() if root is not None else default_sim_root(n_train, n_val, seed, realism)
    _remove_dead_tmp(root)
    if _complete(root):
        return root
    if root.exists() and any(root.iterdir()):
        raise FileExistsError(f"{root} exists but holds no train/ and val/ h5 frames; remove it or pick another root")
    try:
        from sim.nyu import write_nyu_dataset  # the one train -> sim import, see the module docstring
    except ImportError as e:  # pragma: no cover - depends on the installed tree
        raise RuntimeError(f"synthetic data requested but sim.nyu is not importable ({e})") from e
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = root.with_name(f"{root.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        return _render_into(root, tmp, write_nyu_dataset, n_train, n_val, seed, progress, realism)
    except BaseException:  # a failure or Ctrl-C: leave no temporary folder behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _remove_dead_tmp(root: Path) -> None:
    """Remove ``<root>.tmp-<pid>`` folders whose process no longer exists (a render killed outright)."""
    for old in root.parent.glob(f"{root.name}.tmp-*"):
        pid = old.name.rsplit("-", 1)[-1]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(old, ignore_errors=True)
            log.info("removed %s, left by a render that did not finish", old)
        except OSError:  # alive, someone else's: leave it
            pass


def _render_into(root: Path, tmp: Path, write_nyu_dataset, n_train, n_val, seed, progress, realism) -> Path:
    """Render the set into ``tmp`` and rename it to ``root`` (:func:`ensure_synthetic_nyu`)."""
    log.info(
        "rendering the synthetic NYU-layout set (%d train + %d val frames, seed %d%s) into %s",
        n_train,
        n_val,
        seed,
        ", realistic" if realism else "",
        root,
    )
    # Optional knobs of the sim writer: uncompressed h5 reads ~10x faster than gzip (3 vs 30 ms per frame, for
    # 1.4x the disk), which keeps data loading well below the network's time; render with all cores.
    params = inspect.signature(write_nyu_dataset).parameters
    extra = {}
    if "compression" in params:
        extra["compression"] = None
    if "workers" in params:
        extra["workers"] = max(1, min(4, os.cpu_count() or 1))
    if realism:
        extra["realism"] = True
    out = Path(
        write_nyu_dataset(tmp, n_train=int(n_train), n_val=int(n_val), seed=int(seed), progress=progress, **extra)
    )
    if not _complete(out):
        raise RuntimeError(f"sim.nyu.write_nyu_dataset wrote no train/ and val/ h5 frames under {out}")
    if root.exists():  # empty folder created by someone else, or another process won the race
        if _complete(root):
            shutil.rmtree(tmp, ignore_errors=True)
            return root
        root.rmdir()
    os.replace(out, root)
    if out != tmp:
        shutil.rmtree(tmp, ignore_errors=True)
    return root
