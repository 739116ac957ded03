"""NYU-layout h5 frames from sim/: layout, dtypes, disjoint train/val rooms, determinism."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from sim.nyu import KINECT_RGB, scene_seeds, write_nyu_dataset


@pytest.fixture(scope="module")
def nyu_root(tmp_path_factory):
    out = tmp_path_factory.mktemp("nyu")
    return write_nyu_dataset(out, n_train=3, n_val=2, seed=0, progress=False, frames_per_scene=2)


def test_layout_shapes_dtypes(nyu_root):
    train = sorted(p.relative_to(nyu_root).as_posix() for p in (nyu_root / "train").glob("*/*.h5"))
    val = sorted(p.relative_to(nyu_root).as_posix() for p in (nyu_root / "val").glob("*/*.h5"))
    assert train == [
        "train/sim_train_0000/00000.h5",
        "train/sim_train_0000/00001.h5",
        "train/sim_train_0001/00000.h5",
    ]
    assert val == ["val/sim_val_0000/00000.h5", "val/sim_val_0000/00001.h5"]
    for rel in train + val:
        with h5py.File(nyu_root / rel, "r") as f:
            assert set(f.keys()) == {"rgb", "depth"}
            rgb, depth = f["rgb"][()], f["depth"][()]
        assert rgb.dtype == np.uint8 and rgb.shape == (3, 480, 640)
        assert depth.dtype == np.float32 and depth.shape == (480, 640)
        assert np.isfinite(depth).all() and 0.3 < depth.min() and depth.max() < 10.0
        assert rgb.std() > 10 and np.abs(rgb[0].astype(int) - rgb[2]).mean() > 1  # textured, in colour
    info = json.loads((nyu_root / "sim_info.json").read_text())
    assert info["camera"]["fx"] == 518.86 and info["camera"]["cy"] == 253.74
    assert (KINECT_RGB.width, KINECT_RGB.height, KINECT_RGB.has_distortion) == (640, 480, False)


def test_read_back_with_runtime_io(nyu_root):
    from runtime.io.nyu import list_nyu_h5, read_nyu_h5

    files = list_nyu_h5(nyu_root, "val")
    assert len(files) == 2
    rgb, depth = read_nyu_h5(files[0])
    with h5py.File(files[0], "r") as f:
        np.testing.assert_array_equal(rgb, f["rgb"][()].transpose(1, 2, 0))
        np.testing.assert_array_equal(depth, f["depth"][()])


def test_train_and_val_rooms_are_disjoint(nyu_root):
    info = json.loads((nyu_root / "sim_info.json").read_text())
    assert not set(info["scenes"]["train"]) & set(info["scenes"]["val"])
    assert not set(scene_seeds(0, "train", 500)) & set(scene_seeds(0, "val", 500))
    assert scene_seeds(0, "train", 3) == scene_seeds(0, "train", 5)[:3]  # adding frames keeps the rooms
    with (
        h5py.File(nyu_root / "train/sim_train_0000/00000.h5") as a,
        h5py.File(nyu_root / "val/sim_val_0000/00000.h5") as b,
    ):
        assert not np.array_equal(a["depth"][()], b["depth"][()])


def test_deterministic_by_seed(nyu_root, tmp_path):
    again = write_nyu_dataset(tmp_path / "a", n_train=1, n_val=0, seed=0, progress=False, frames_per_scene=2)
    other = write_nyu_dataset(tmp_path / "b", n_train=1, n_val=0, seed=1, progress=False, frames_per_scene=2)
    rel = "train/sim_train_0000/00000.h5"
    with h5py.File(nyu_root / rel) as f0, h5py.File(again / rel) as f1, h5py.File(other / rel) as f2:
        np.testing.assert_array_equal(f0["rgb"][()], f1["rgb"][()])
        np.testing.assert_array_equal(f0["depth"][()], f1["depth"][()])
        assert not np.array_equal(f0["depth"][()], f2["depth"][()])


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="n_train"):
        write_nyu_dataset(tmp_path, n_train=-1, n_val=1, progress=False)
    with pytest.raises(ValueError, match="frames_per_scene"):
        write_nyu_dataset(tmp_path, n_train=1, n_val=1, progress=False, frames_per_scene=0)
