"""The G-S protocol evaluation (``dit-eval depth ... real=DIR``): reference rows and the real-frame reader."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from models import build_model
from train.evaluate import PROTOCOLS, interpolation_prediction, main

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "rgbd_real"


def _folder(root: Path, n: int = 3) -> Path:
    """Frames of a slanted plane (depth 1-3 m) with a random texture, in the rgbd_real layout."""
    rng = np.random.default_rng(0)
    root.mkdir(parents=True)
    h, w = 120, 160
    depth = np.linspace(1.0, 3.0, w, dtype=np.float32)[None].repeat(h, 0)
    for i in range(n):
        tex = cv2.resize(
            rng.integers(0, 255, (h // 4, w // 4), dtype=np.uint8), (w, h), interpolation=cv2.INTER_NEAREST
        )
        cv2.imwrite(str(root / f"frame-{i:06d}.color.png"), np.stack([tex] * 3, -1))
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), (depth * 1000).astype(np.uint16))
    np.savetxt(root / "camera-intrinsics.txt", np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 1]]))
    return root


def _ckpt(path: Path) -> Path:
    torch.manual_seed(0)
    cfg = {
        "name": "dit",
        "modality": "grays",
        "width_mult": 0.25,
        "height": 64,
        "width": 64,
        "code_dim": 8,
        "relative": True,
    }
    net = build_model(**cfg)
    torch.save({"net_config": cfg, "state_dict": {f"net.{k}": v for k, v in net.state_dict().items()}}, path)
    return path


def test_interpolation_prediction_of_a_plane():
    x = torch.zeros(1, 2, 16, 16)
    gv, gu = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    plane = 1.0 + 0.1 * gu + 0.05 * gv
    keep = torch.zeros(16, 16, dtype=torch.bool)
    keep[::5, ::5] = True
    keep[15, 15] = keep[0, 15] = keep[15, 0] = True
    x[0, 1] = plane * keep
    torch.testing.assert_close(interpolation_prediction(x)[0, 0], plane, rtol=1e-5, atol=1e-5)


def test_protocol_on_a_frame_folder(tmp_path, capsys):
    folder = _folder(tmp_path / "frames")
    out = tmp_path / "eval.json"
    res = main(["depth", f"ckpt={_ckpt(tmp_path / 'net.ckpt')}", f"real={folder}", f"out={out}", "batch_size=2"])
    rows = res["sets"]["real frames"]["rows"]
    assert res["sets"]["real frames"]["frames"] == 3
    assert list(rows) == ["network", "network, posterior-mean code (oracle)", "interpolation", "median GT"]
    # an untrained relative network starts at its densified input; on a plane the interpolation is exact
    assert rows["interpolation"]["rmse"] < 0.05 < rows["median GT"]["rmse"]
    assert rows["network"]["rmse"] < rows["median GT"]["rmse"]
    assert res["protocol"]["points"] == PROTOCOLS["gs"][0] and res["protocol"]["noise_std_m"] == 0.0
    assert json.loads(out.read_text())["sets"]["real frames"]["frames"] == 3
    assert "max per-frame AbsRel" in capsys.readouterr().out
    slam = main(["depth", f"ckpt={tmp_path / 'net.ckpt'}", f"real={folder}", "protocol=slam", "limit=1"])
    assert slam["protocol"]["points"] == 30 and slam["sets"]["real frames"]["frames"] == 1


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real RGB-D frames not present at {REAL}")
def test_protocol_finds_the_real_folders(tmp_path):
    res = main(["depth", f"ckpt={_ckpt(tmp_path / 'net.ckpt')}", f"real={REAL}", "limit=2", "batch_size=2"])
    assert {"real sun3d_fragment1", "real sun3d_fragment2", "real realsense_box"} <= set(res["sets"])
