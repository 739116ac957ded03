"""RGB-D frame folders (3DMatch / tsdf-fusion layout): a written folder reads back; the real ones when present."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from runtime.io.rgbd_frames import RgbdFolder, RgbdFormatError

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "rgbd_real"


def _write(root: Path, n=3, k_name="camera-intrinsics.txt"):
    root.mkdir(parents=True, exist_ok=True)
    for i in (4, 2, 10)[:n]:
        rgb = np.zeros((6, 8, 3), np.uint8)
        rgb[..., 0] = 200  # red
        cv2.imwrite(str(root / f"frame-{i:06d}.color.png"), rgb[..., ::-1])
        depth = np.full((6, 8), 1000 + i, np.uint16)
        depth[0, 0] = 0
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), depth)
        pose = np.eye(4)
        pose[0, 3] = i
        np.savetxt(root / f"frame-{i:06d}.pose.txt", pose)
    np.savetxt(root / k_name, np.array([[500.0, 0, 4], [0, 500, 3], [0, 0, 1]]))
    return root


def test_folder_round_trip(tmp_path):
    f = RgbdFolder(_write(tmp_path / "a"))
    assert len(f) == 3 and [p.name[:12] for p in f.frames] == ["frame-000002", "frame-000004", "frame-000010"]
    rgb, depth = f[1]
    assert rgb.shape == (6, 8, 3) and rgb.dtype == np.uint8 and rgb[0, 0].tolist() == [200, 0, 0]
    assert depth.dtype == np.float32 and depth[0, 0] == 0 and depth[1, 1] == pytest.approx(1.004)
    assert f.pose(2)[0, 3] == 10 and f.K[0, 0] == 500
    assert len(RgbdFolder(_write(tmp_path / "b", k_name="intrinsics.K.txt"), limit=2)) == 2


def test_bad_folders(tmp_path):
    with pytest.raises(RgbdFormatError, match="no such folder"):
        RgbdFolder(tmp_path / "nope")
    root = _write(tmp_path / "c")
    (root / "camera-intrinsics.txt").unlink()
    with pytest.raises(RgbdFormatError, match="intrinsics"):
        RgbdFolder(root)
    root = _write(tmp_path / "d")
    cv2.imwrite(str(root / "frame-000002.depth.png"), np.zeros((6, 8), np.uint8))
    with pytest.raises(RgbdFormatError, match="uint16"):
        RgbdFolder(root)[0]


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real RGB-D frames not present at {REAL}")
def test_real_folders():
    for name, k00, lo, hi in [("sun3d_fragment1", 570.342, 0.3, 10.0), ("realsense_box", 615.195, 0.1, 2.0)]:
        f = RgbdFolder(REAL / name)
        assert len(f) == 50 and f.K[0, 0] == pytest.approx(k00, abs=1e-3)
        rgb, depth = f[0]
        assert rgb.shape == (480, 640, 3)
        valid = depth[depth > 0]
        assert lo < np.median(valid) < hi
        assert f.pose(0).shape == (4, 4)
