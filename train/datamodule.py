"""LightningDataModule for NYU-layout depth data (synthetic by default), with exactly resumable sampling.

Exact resume. The train sampler (:class:`EpochSampler`) draws epoch ``e``'s order from ``(seed, e)`` alone and
counts epochs itself (each new iterator is the next epoch), so the sequence of batches does not depend on
Lightning's epoch bookkeeping. The data module remembers which training batch was consumed last
(``on_before_batch_transfer``: the batch carries its ``epoch`` and ``pos``) and stores ``(epoch, next
position)`` in every checkpoint (``state_dict``); on resume the sampler continues from there. Together with
per-sample random generators seeded by ``(seed, epoch, index)`` (:mod:`train.data`) and the per-step torch
generator of :class:`train.module.DepthModule`, a resumed run sees exactly the batches an uninterrupted run
would. This assumes ``accumulate_grad_batches=1``.

DDP. The sampler shards each epoch's order over ranks itself (``rank::world_size`` after dropping the tail),
so trainers must run with ``use_distributed_sampler=False`` (set in ``conf/trainer/*.yaml``); this is checked.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler

from train.augment import AugmentConfig, FrameTransform
from train.data import NyuFrames, NyuH5Dataset, NyuMatDataset, default_sim_root, ensure_synthetic_nyu
from train.sparse import SparseConfig

__all__ = ["EpochSampler", "ShardSampler", "NyuDataModule"]

log = logging.getLogger(__name__)

KINDS = ("sim", "h5", "mat")


class EpochSampler(Sampler):
    """Deterministic, self-counting, resumable and rank-sharded sampler of ``(epoch, pos, index)`` keys.

    Each ``iter()`` is the next epoch. Epoch ``e`` uses ``default_rng([seed, e]).permutation(n)`` (or the
    identity when ``shuffle=False``), drops the tail so all ranks get ``n // world_size`` items and takes
    ``order[rank::world_size]``; ``pos`` is the position within this rank's shard.

    Args:
        n: dataset size.
        seed: order seed.
        shuffle: random order per epoch.
        rank, world_size: DDP shard.
        epoch, start: the first iterator yields epoch ``epoch`` from position ``start`` on (resume).

    >>> s = EpochSampler(5, seed=0, shuffle=False, rank=1, world_size=2)
    >>> list(s), list(s)[0]
    ([(0, 0, 1), (0, 1, 3)], (1, 0, 1))
    """

    def __init__(
        self,
        n: int,
        seed: int = 0,
        shuffle: bool = True,
        rank: int = 0,
        world_size: int = 1,
        epoch: int = 0,
        start: int = 0,
    ):
        if n <= 0 or world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"bad sampler n={n}, rank={rank}, world_size={world_size}")
        if n < world_size:
            raise ValueError(f"{n} samples cannot be split over {world_size} processes")
        self.n, self.seed, self.shuffle = int(n), int(seed), bool(shuffle)
        self.rank, self.world_size = int(rank), int(world_size)
        self.epoch, self.start = int(epoch), int(start)

    def __len__(self) -> int:
        return self.n // self.world_size

    def order(self, epoch: int) -> np.ndarray:
        """This rank's frame indices of ``epoch``."""
        perm = np.random.default_rng([self.seed, epoch]).permutation(self.n) if self.shuffle else np.arange(self.n)
        return perm[: len(self) * self.world_size][self.rank :: self.world_size]

    def __iter__(self):
        epoch, start = self.epoch, self.start
        self.epoch, self.start = epoch + 1, 0
        order = self.order(epoch)
        for pos in range(start, len(order)):
            yield (epoch, pos, int(order[pos]))


class ShardSampler(Sampler):
    """Evaluation sampler: frames ``rank::world_size`` in order (uneven shards allowed, nothing repeated)."""

    def __init__(self, n: int, rank: int = 0, world_size: int = 1):
        self.indices = list(range(rank, n, world_size))

    def __len__(self) -> int:
        return len(self.indices)

    def __iter__(self):
        return iter(self.indices)


def _worker_init(_: int) -> None:
    cv2.setNumThreads(1)
    torch.set_num_threads(1)


class NyuDataModule(L.LightningDataModule):
    """NYU-layout depth data for one modality and network size.

    Args:
        kind: ``sim`` (synthetic, generated on first use), ``h5`` (``root/{train,val}/<scene>/*.h5``, real NYU
        in
            the sparse-to-dense layout) or ``mat`` (official labeled ``.mat`` + split file).
        root: data folder for ``sim``/``h5``; for ``sim`` None = the cache
        (:func:`train.data.default_sim_root`). mat_path, split_path: ``nyu_depth_v2_labeled.mat`` and
        ``splits.mat`` (``kind="mat"``). train_split, val_split, test_split: split names (``h5``: sub-folders;
        ``mat``: ``train``/``test``). modality: ``rgb | rgbs | gray | grays``.
        height, width: network input size [px].
        batch_size, val_batch_size: per process.
        num_workers, pin_memory: DataLoader settings.
        seed: seed of sample order, augmentation and sparse sampling.
        augment, sparse: :class:`~train.augment.AugmentConfig` / :class:`~train.sparse.SparseConfig` fields.
        sim: ``n_train``, ``n_val``, ``seed`` of the synthetic set.
        limit_train, limit_val: use only the first frames of a split (None = all).
        fill_in_loader: add each sample's interpolated sparse input (``fill``, the relative network's second input) in
            the data loader's workers; the training step computes it on the main process otherwise, which held
            a GPU run at 5.4 steps/s (``benchmarks/results/depth_ablations/gpu_more_rooms.json``).
    """

    def __init__(
        self,
        kind: str = "sim",
        root: str | None = None,
        mat_path: str | None = None,
        split_path: str | None = None,
        train_split: str = "train",
        val_split: str = "val",
        test_split: str | None = None,
        modality: str = "grays",
        height: int = 224,
        width: int = 224,
        batch_size: int = 8,
        val_batch_size: int | None = None,
        num_workers: int = 0,
        pin_memory: bool = False,
        seed: int = 0,
        augment: dict | None = None,
        sparse: dict | None = None,
        sim: dict | None = None,
        limit_train: int | None = None,
        limit_val: int | None = None,
        fill_in_loader: bool = False,
    ):
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"data kind={kind!r} not in {KINDS}")
        if kind == "h5" and not root:
            raise ValueError("data.root is required for kind='h5' (folder with train/ and val/)")
        if kind == "mat" and not (mat_path and split_path):
            raise ValueError("data.mat_path and data.split_path are required for kind='mat'")
        if batch_size < 1:
            raise ValueError(f"batch_size={batch_size} must be >= 1")
        self.kind, self.root = kind, root
        self.mat_path, self.split_path = mat_path, split_path
        self.train_split, self.val_split = train_split, val_split
        self.test_split = test_split or val_split
        self.modality, self.height, self.width = modality, int(height), int(width)
        self.batch_size = int(batch_size)
        self.val_batch_size = int(val_batch_size or batch_size)
        self.num_workers, self.pin_memory = int(num_workers), bool(pin_memory)
        self.seed = int(seed)
        aug = dict(augment or {})
        if "scale" in aug:
            aug["scale"] = tuple(aug["scale"])
        self.augment = AugmentConfig(**aug)
        sp = dict(sparse or {})
        if "train_num" in sp:
            sp["train_num"] = tuple(sp["train_num"])
        self.sparse = SparseConfig(**sp)
        self.sim = {"n_train": 1000, "n_val": 100, "seed": 0, **dict(sim or {})}
        self.limit_train, self.limit_val = limit_train, limit_val
        self.fill_in_loader = bool(fill_in_loader)
        self.data_train: NyuFrames | None = None
        self.data_val: NyuFrames | None = None
        self.data_test: NyuFrames | None = None
        self._resume: tuple[int, int] | None = None  # (epoch, next pos) to start the train sampler from
        self._pos: list[tuple[int, int, int]] = []  # last consumed train batches: (global step, epoch, next pos)

    # ------------------------------------------------------------------ data
    @property
    def _realism(self) -> bool:
        return bool(self.sim.get("realism", False))

    @property
    def data_root(self) -> Path | None:
        if self.kind == "sim" and not self.root:
            return default_sim_root(self.sim["n_train"], self.sim["n_val"], self.sim["seed"], self._realism)
        return Path(self.root).expanduser() if self.root else None

    def prepare_data(self) -> None:
        """Render the synthetic set when missing (once per node)."""
        if self.kind == "sim":
            ensure_synthetic_nyu(
                self.data_root, self.sim["n_train"], self.sim["n_val"], self.sim["seed"], realism=self._realism
            )

    def transform(self, train: bool) -> FrameTransform:
        return FrameTransform(
            self.height, self.width, self.modality, train, self.augment, self.sparse, self.fill_in_loader
        )

    def make_dataset(self, split: str, train: bool, limit: int | None = None) -> NyuFrames:
        """The dataset of one split with the train or evaluation transform."""
        tf = self.transform(train)
        if self.kind == "mat":
            return NyuMatDataset(self.mat_path, self.split_path, split, tf, self.seed, limit)
        if self.kind == "sim":
            ensure_synthetic_nyu(
                self.data_root, self.sim["n_train"], self.sim["n_val"], self.sim["seed"], realism=self._realism
            )
        return NyuH5Dataset(self.data_root, split, tf, self.seed, limit)

    def setup(self, stage: str | None = None) -> None:
        trainer = self.trainer
        if trainer is not None and trainer.world_size > 1:
            conn = getattr(trainer, "_accelerator_connector", None)
            if getattr(conn, "use_distributed_sampler", False):
                raise ValueError(
                    "NyuDataModule shards data itself: run the Trainer with use_distributed_sampler=False "
                    "(as conf/trainer/*.yaml do)"
                )
        if stage in (None, "fit") and self.data_train is None:
            self.data_train = self.make_dataset(self.train_split, True, self.limit_train)
        if stage in (None, "fit", "validate") and self.data_val is None:
            self.data_val = self.make_dataset(self.val_split, False, self.limit_val)
        if stage in (None, "test") and self.data_test is None:
            self.data_test = self.make_dataset(self.test_split, False, self.limit_val)

    def _rank_world(self) -> tuple[int, int]:
        t = self.trainer
        return (int(t.global_rank), int(t.world_size)) if t is not None else (0, 1)

    def _loader(self, ds, sampler, batch_size: int, drop_last: bool) -> DataLoader:
        return DataLoader(
            ds,
            batch_size=batch_size,
            sampler=sampler,
            drop_last=drop_last,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.num_workers > 0,
            worker_init_fn=_worker_init if self.num_workers > 0 else None,
        )

    def train_dataloader(self) -> DataLoader:
        if self.data_train is None:
            self.setup("fit")
        rank, world = self._rank_world()
        n = len(self.data_train)
        per_rank = n // world
        if per_rank < self.batch_size:
            raise ValueError(f"{n} training frames over {world} processes give fewer than batch_size={self.batch_size}")
        epoch, start = self._resume or (0, 0)
        if start + self.batch_size > per_rank:  # the saved epoch was finished
            epoch, start = epoch + 1, 0
        self._resume = None
        sampler = EpochSampler(n, self.seed, True, rank, world, epoch, start)
        return self._loader(self.data_train, sampler, self.batch_size, drop_last=True)

    def _eval_loader(self, ds) -> DataLoader:
        rank, world = self._rank_world()
        return self._loader(ds, ShardSampler(len(ds), rank, world), self.val_batch_size, drop_last=False)

    def val_dataloader(self) -> DataLoader:
        if self.data_val is None:
            self.setup("validate")
        return self._eval_loader(self.data_val)

    def test_dataloader(self) -> DataLoader:
        if self.data_test is None:
            self.setup("test")
        return self._eval_loader(self.data_test)

    # ---------------------------------------------------------- exact resume
    def on_before_batch_transfer(self, batch, dataloader_idx: int):
        t = self.trainer
        if t is not None and t.training and isinstance(batch, dict) and "pos" in batch:
            rec = (int(t.global_step), int(batch["epoch"][0]), int(batch["pos"][-1]) + 1)
            self._pos = (self._pos + [rec])[-2:]
        return batch

    def state_dict(self) -> dict:
        """The train sampler position after the last *completed* optimisation step."""
        if not self._pos:
            return {}
        step = int(self.trainer.global_step) if self.trainer is not None else None
        done = [r for r in self._pos if step is None or r[0] < step]  # its optimizer step has run
        if not done:
            return {}
        _, epoch, pos = done[-1]
        return {"epoch": epoch, "next_pos": pos, "seed": self.seed, "batch_size": self.batch_size}

    def load_state_dict(self, state_dict: dict) -> None:
        if not state_dict:
            return
        if (
            state_dict.get("seed", self.seed) != self.seed
            or state_dict.get("batch_size", self.batch_size) != self.batch_size
        ):
            log.warning(
                "resuming with data seed/batch size %s/%s, the checkpoint used %s/%s: the data order differs",
                self.seed,
                self.batch_size,
                state_dict.get("seed"),
                state_dict.get("batch_size"),
            )
        self._resume = (int(state_dict["epoch"]), int(state_dict["next_pos"]))
