"""Datasets, per-sample determinism, the resumable sampler, synthetic-data generation on first use."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from tests.train.conftest import write_fake_nyu
from train.augment import FrameTransform
from train.data import NyuH5Dataset, NyuMatDataset, default_sim_root, ensure_synthetic_nyu, sample_key
from train.datamodule import EpochSampler, NyuDataModule, ShardSampler


def test_h5_dataset_items_and_determinism(fake_nyu):
    ds = NyuH5Dataset(fake_nyu, "train", FrameTransform(32, 32, "grays", True), seed=3)
    assert len(ds) == 8 and all(p.suffix == ".h5" for p in ds.files)
    a, b = ds[(2, 5, 1)], ds[(2, 5, 1)]
    for k in ("image", "depth", "params"):
        np.testing.assert_array_equal(a[k], b[k])
    assert (int(a["epoch"]), int(a["pos"]), int(a["index"])) == (2, 5, 1)
    c = ds[(3, 0, 1)]  # same frame, next epoch: other augmentation
    assert not np.array_equal(a["params"], c["params"])
    assert a["image"].shape == (2, 32, 32) and a["depth"].shape == (1, 32, 32)
    assert sample_key(4) == (0, 4, 4)
    with pytest.raises(IndexError):
        ds[99]


def test_epoch_sampler_orders_shards_and_resumes():
    s = EpochSampler(10, seed=1)
    e0, e1 = list(s), list(s)  # each iterator is the next epoch
    assert [k[0] for k in e0] == [0] * 10 and [k[0] for k in e1] == [1] * 10
    assert sorted(k[2] for k in e0) == list(range(10)) and [k[2] for k in e0] != [k[2] for k in e1]
    assert [k[1] for k in e0] == list(range(10))
    # resume in epoch 1 at position 4 = the tail of an uninterrupted epoch 1
    r = EpochSampler(10, seed=1, epoch=1, start=4)
    assert list(r) == e1[4:] and list(r) == list(EpochSampler(10, seed=1, epoch=2))
    # two ranks: disjoint, equal-sized shards of the same order (tail dropped)
    r0, r1 = list(EpochSampler(9, 1, rank=0, world_size=2)), list(EpochSampler(9, 1, rank=1, world_size=2))
    assert len(r0) == len(r1) == 4 and not {k[2] for k in r0} & {k[2] for k in r1}
    order = np.random.default_rng([1, 0]).permutation(9)
    assert [k[2] for k in r0] == order[:8:2].tolist()
    assert list(ShardSampler(5, 1, 2)) == [1, 3]


def test_datamodule_loaders(fake_nyu):
    dm = NyuDataModule(kind="h5", root=str(fake_nyu), modality="rgbs", height=32, width=32, batch_size=3)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (3, 4, 32, 32) and batch["depth"].shape == (3, 1, 32, 32)
    assert len(dm.train_dataloader()) == 8 // 3
    vb = next(iter(dm.val_dataloader()))
    assert vb["image"].shape[0] == 3 and (vb["image"][:, 3] > 0).sum(dim=(1, 2)).tolist() == [125, 125, 125]
    # resume state round trip: (epoch 0, next pos 6) with batch 3 of 8 -> epoch 1 starts next
    dm.load_state_dict({"epoch": 0, "next_pos": 6, "seed": 0, "batch_size": 3})
    assert next(iter(dm.train_dataloader().sampler))[0] == 1
    dm.load_state_dict({"epoch": 2, "next_pos": 3, "seed": 0, "batch_size": 3})
    assert next(iter(dm.train_dataloader().sampler))[:2] == (2, 3)
    with pytest.raises(ValueError, match="data.root is required"):
        NyuDataModule(kind="h5")
    with pytest.raises(ValueError, match="kind"):
        NyuDataModule(kind="kitti")


def test_mat_dataset_with_official_split(tmp_path):
    h5py = pytest.importorskip("h5py")
    rng = np.random.default_rng(0)
    n, h, w = 5, 24, 32
    with h5py.File(tmp_path / "labeled.mat", "w") as f:  # MATLAB v7.3 axis order as h5py sees it
        f["images"] = (rng.random((n, 3, w, h)) * 255).astype(np.uint8)
        f["depths"] = (1 + rng.random((n, w, h))).astype(np.float32)
    (tmp_path / "split.txt").write_text("train 0\ntrain 2\ntrain 3\ntest 1\ntest 4\n")
    tf = FrameTransform(16, 16, "rgb", False)
    tr = NyuMatDataset(tmp_path / "labeled.mat", tmp_path / "split.txt", "train", tf)
    te = NyuMatDataset(tmp_path / "labeled.mat", tmp_path / "split.txt", "test", tf)
    assert len(tr) == 3 and len(te) == 2
    assert te[1]["depth"].shape == (1, 16, 16)
    with pytest.raises(ValueError, match="split"):
        NyuMatDataset(tmp_path / "labeled.mat", tmp_path / "split.txt", "dev", tf)


def test_synthetic_data_generated_once_atomically(tmp_path, monkeypatch):
    calls = []

    def fake_writer(out, n_train=1, n_val=1, seed=0, progress=True, compression="gzip"):
        calls.append((Path(out), n_train, n_val, seed, compression))
        write_fake_nyu(Path(out), n_train, n_val, seed=seed)
        (Path(out) / "sim_info.json").write_text(json.dumps({"seed": seed}))
        return Path(out)

    monkeypatch.setitem(sys.modules, "sim.nyu", types.SimpleNamespace(write_nyu_dataset=fake_writer))
    monkeypatch.setenv("DIT_SLAM_CACHE", str(tmp_path / "cache"))
    root = default_sim_root(4, 2, 7)
    assert root == tmp_path / "cache" / "nyu-sim-7-4-2"
    assert ensure_synthetic_nyu(None, 4, 2, seed=7, progress=False) == root
    assert len(calls) == 1 and calls[0][0].name.startswith("nyu-sim-7-4-2.tmp-") and calls[0][4] is None
    assert not calls[0][0].exists()  # renamed into place
    assert len(list((root / "train").glob("*/*.h5"))) == 4
    ensure_synthetic_nyu(None, 4, 2, seed=7)  # present: not rendered again
    assert len(calls) == 1
    dm = NyuDataModule(
        kind="sim",
        modality="gray",
        height=32,
        width=32,
        batch_size=2,
        sim={"n_train": 4, "n_val": 2, "seed": 7},
    )
    dm.prepare_data()
    dm.setup("fit")
    assert len(dm.data_train) == 4 and len(calls) == 1
    other = tmp_path / "busy"
    (other / "x").mkdir(parents=True)
    with pytest.raises(FileExistsError, match="no train/ and val/"):
        ensure_synthetic_nyu(other, 4, 2)


def test_a_failed_or_killed_render_leaves_no_temporary_folder(tmp_path, monkeypatch):
    def failing_writer(out, n_train=1, n_val=1, seed=0, progress=True):
        (Path(out) / "train").mkdir(parents=True)  # half-written, then the renderer fails
        raise RuntimeError("renderer crashed")

    monkeypatch.setitem(sys.modules, "sim.nyu", types.SimpleNamespace(write_nyu_dataset=failing_writer))
    root = tmp_path / "cache" / "nyu-sim-3-2-1"
    with pytest.raises(RuntimeError, match="renderer crashed"):
        ensure_synthetic_nyu(root, 2, 1, seed=3)
    assert sorted(p.name for p in root.parent.iterdir()) == []
    # a folder left by a process killed outright is removed by the next call; a live process's is kept
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (root.parent / f"{root.name}.tmp-{dead.pid}" / "train").mkdir(parents=True)
    live = root.parent / f"{root.name}.tmp-{os.getppid()}"
    live.mkdir()
    with pytest.raises(RuntimeError, match="renderer crashed"):
        ensure_synthetic_nyu(root, 2, 1, seed=3)
    assert sorted(p.name for p in root.parent.iterdir()) == [live.name]
