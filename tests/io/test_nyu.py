"""NYU Depth v2 readers: sparse-to-dense h5 frames, the labeled .mat layout (v7.3 / HDF5), splits."""

from __future__ import annotations

import pickle
import re

import h5py
import numpy as np
import pytest

from runtime.io import NyuFormatError, NyuLabeledMat, list_nyu_h5, read_nyu_h5, read_nyu_split

H, W = 480, 640


def _frame(seed=0):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)  # HWC, what readers return
    depth = rng.uniform(0.5, 10.0, (H, W)).astype(np.float32)
    depth[0, :5] = 0.0  # invalid pixels stay 0
    return rgb, depth


def _write_h5(path, rgb_chw, depth):
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        if rgb_chw is not None:
            f.create_dataset("rgb", data=rgb_chw)
        if depth is not None:
            f.create_dataset("depth", data=depth)
    return path


def test_h5_round_trip_channels_first_to_hwc(tmp_path):
    rgb, depth = _frame()
    p = _write_h5(tmp_path / "00001.h5", rgb.transpose(2, 0, 1), depth)  # stored (3, 480, 640)
    got_rgb, got_depth = read_nyu_h5(p)
    assert got_rgb.shape == (480, 640, 3) and got_rgb.dtype == np.uint8 and got_rgb.flags.c_contiguous
    assert got_depth.shape == (480, 640) and got_depth.dtype == np.float32
    np.testing.assert_array_equal(got_rgb, rgb)
    np.testing.assert_array_equal(got_depth, depth)


def test_h5_float64_depth_is_cast(tmp_path):
    rgb, depth = _frame()
    p = _write_h5(tmp_path / "a.h5", rgb.transpose(2, 0, 1), depth.astype(np.float64))
    assert read_nyu_h5(p)[1].dtype == np.float32


def test_h5_other_size_only_when_allowed(tmp_path):
    rgb = np.zeros((3, 24, 32), np.uint8)
    p = _write_h5(tmp_path / "s.h5", rgb, np.ones((24, 32), np.float32))
    with pytest.raises(
        NyuFormatError, match=re.escape(str(p)) + r".*\(3, 24, 32\).*expected \(3, 480, 640\)"
    ):
        read_nyu_h5(p)
    assert read_nyu_h5(p, expected_hw=None)[0].shape == (24, 32, 3)


@pytest.mark.parametrize(
    "rgb,depth,fragment",
    [
        (np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32), "'rgb' must have shape (3, H, W)"),
        (np.zeros((3, H, W), np.float32), np.zeros((H, W), np.float32), "'rgb' must be uint8"),
        (np.zeros((3, H, W), np.uint8), np.zeros((W, H), np.float32), "'depth' has shape (640, 480)"),
        (np.zeros((3, H, W), np.uint8), None, "missing dataset 'depth'"),
        (None, np.zeros((H, W), np.float32), "missing dataset 'rgb'"),
        (np.zeros((3, H, W), np.uint8), np.full((H, W), np.nan, np.float32), "NaN/inf/negative"),
    ],
)
def test_h5_bad_frames_name_the_file(tmp_path, rgb, depth, fragment):
    p = _write_h5(tmp_path / "bad.h5", rgb, depth)
    with pytest.raises(NyuFormatError, match=re.escape(str(p)) + ".*" + re.escape(fragment)):
        read_nyu_h5(p)


def test_h5_not_hdf5_or_missing(tmp_path):
    p = tmp_path / "x.h5"
    p.write_text("nope")
    with pytest.raises(NyuFormatError, match=re.escape(str(p)) + ".*not a readable HDF5"):
        read_nyu_h5(p)
    with pytest.raises(NyuFormatError, match="missing file"):
        read_nyu_h5(tmp_path / "y.h5")


def test_list_nyu_h5(tmp_path):
    for rel in (
        "train/sceneB/00002.h5",
        "train/sceneA/00010.h5",
        "train/sceneA/00001.h5",
        "val/sceneC/00001.h5",
    ):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    (tmp_path / "train/sceneA/notes.txt").write_text("x")
    got = list_nyu_h5(tmp_path, "train")
    assert [str(p.relative_to(tmp_path)) for p in got] == [
        "train/sceneA/00001.h5",
        "train/sceneA/00010.h5",
        "train/sceneB/00002.h5",
    ]
    assert len(list_nyu_h5(tmp_path, "val")) == 1
    with pytest.raises(NyuFormatError, match=re.escape(str(tmp_path / "test")) + ": missing folder"):
        list_nyu_h5(tmp_path, "test")
    (tmp_path / "empty").mkdir()
    with pytest.raises(NyuFormatError, match="no h5 frames"):
        list_nyu_h5(tmp_path, "empty")


def _write_labeled_mat(path, n=3):
    """A tiny file with the h5py layout of nyu_depth_v2_labeled.mat: MATLAB H x W x 3 x N seen reversed."""
    frames = [_frame(seed) for seed in range(n)]
    rgb = np.stack([f[0] for f in frames])  # (N, H, W, 3)
    depth = np.stack([f[1] for f in frames])  # (N, H, W)
    with h5py.File(path, "w") as f:
        f.create_dataset("images", data=rgb.transpose(0, 3, 2, 1))  # (N, 3, W, H) = (N, 3, 640, 480)
        f.create_dataset("depths", data=depth.transpose(0, 2, 1))  # (N, W, H) = (N, 640, 480)
        f.create_dataset("labels", data=np.zeros((n, W, H), np.uint16))  # other variables are ignored
    return rgb, depth


def test_labeled_mat_layout(tmp_path):
    p = tmp_path / "nyu_depth_v2_labeled.mat"
    rgb, depth = _write_labeled_mat(p)
    with h5py.File(p, "r") as f:
        assert f["images"].shape == (3, 3, 640, 480) and f["depths"].shape == (3, 640, 480)
    ds = NyuLabeledMat(p)
    assert len(ds) == 3 and ds.hw == (480, 640)
    for i in range(3):
        r, d = ds[i]
        assert (
            r.shape == (480, 640, 3)
            and r.dtype == np.uint8
            and d.shape == (480, 640)
            and d.dtype == np.float32
        )
        np.testing.assert_array_equal(r, rgb[i])
        np.testing.assert_array_equal(d, depth[i])
    sub = NyuLabeledMat(p, indices=[2, 0])
    assert len(sub) == 2
    np.testing.assert_array_equal(sub[0][0], rgb[2])
    np.testing.assert_array_equal(sub[-1][1], depth[0])
    with pytest.raises(IndexError):
        sub[2]
    clone = pickle.loads(pickle.dumps(sub))  # DataLoader workers get a copy that reopens the file
    np.testing.assert_array_equal(clone[1][0], rgb[0])
    ds.close()
    sub.close()
    clone.close()


def test_labeled_mat_errors(tmp_path):
    p = tmp_path / "l.mat"
    _write_labeled_mat(p)
    with pytest.raises(ValueError, match="index 3 out of range for 3 frames"):
        NyuLabeledMat(p, indices=[0, 3])
    bad = tmp_path / "bad.mat"
    with h5py.File(bad, "w") as f:
        f.create_dataset("images", data=np.zeros((2, 480, 640, 3), np.uint8))
        f.create_dataset("depths", data=np.zeros((2, 640, 480), np.float32))
    with pytest.raises(
        NyuFormatError, match=re.escape(str(bad)) + r".*'images' must have h5py shape \(N, 3, W, H\)"
    ):
        NyuLabeledMat(bad)
    nodepth = tmp_path / "nodepth.mat"
    with h5py.File(nodepth, "w") as f:
        f.create_dataset("images", data=np.zeros((2, 3, 640, 480), np.uint8))
    with pytest.raises(NyuFormatError, match=re.escape(str(nodepth)) + ".*missing dataset 'depths'"):
        NyuLabeledMat(nodepth)


def test_split_mat_is_one_based(tmp_path):
    import scipy.io

    p = tmp_path / "splits.mat"
    scipy.io.savemat(
        p, {"trainNdxs": np.array([[1], [4], [3]], np.float64), "testNdxs": np.array([[2], [1449]])}
    )
    train, test = read_nyu_split(p)
    assert train.dtype == np.int64
    np.testing.assert_array_equal(train, [0, 2, 3])
    np.testing.assert_array_equal(test, [1, 1448])


def test_split_text_is_zero_based(tmp_path):
    p = tmp_path / "split.txt"
    p.write_text("# 0-based indices\ntrain 0\ntest 1\n\ntrain 5\ntest 1448\n")
    train, test = read_nyu_split(p)
    np.testing.assert_array_equal(train, [0, 5])
    np.testing.assert_array_equal(test, [1, 1448])


def test_split_errors(tmp_path):
    import scipy.io

    p = tmp_path / "s.txt"
    p.write_text("train 0\nvalid 3\n")
    with pytest.raises(NyuFormatError, match=re.escape(str(p)) + ": line 2"):
        read_nyu_split(p)
    p.write_text("train 0\ntest 0\n")
    with pytest.raises(NyuFormatError, match="in both train and test"):
        read_nyu_split(p)
    m = tmp_path / "m.mat"
    scipy.io.savemat(m, {"trainNdxs": np.array([[1]])})
    with pytest.raises(NyuFormatError, match=re.escape(str(m)) + ".*missing variable 'testNdxs'"):
        read_nyu_split(m)
    scipy.io.savemat(m, {"trainNdxs": np.array([[0]]), "testNdxs": np.array([[2]])})
    with pytest.raises(NyuFormatError, match="negative index"):
        read_nyu_split(m)
