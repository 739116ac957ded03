"""benchmarks/code_oracle.py: the best code for a frame's true depth, on the shipped model."""

import json

import numpy as np
import pytest

from benchmarks.code_oracle import best_code, main
from runtime.network import DepthNetwork, default_model_dir
from tests.train.test_evaluate_protocol import _folder


@pytest.fixture(scope="module")
def prior():
    net = DepthNetwork(default_model_dir())
    rng = np.random.default_rng(3)
    image = rng.integers(0, 255, (net.height, net.width)).astype(np.uint8)
    sparse = np.zeros((net.height, net.width), np.float32)
    iy, ix = rng.integers(0, net.height, 120), rng.integers(0, net.width, 120)
    sparse[iy, ix] = rng.uniform(0.5, 4.0, 120)
    return net.prior(image, sparse)


def test_the_best_code_recovers_a_depth_the_decoder_made(prior):
    c_true = np.array([0.9, -0.6, 0.4, 0.0, -0.3, 0.7, 0.2, -0.5], np.float32)[: prior.net.code_dim]
    target = prior.depth(c_true).copy()
    code, sse = best_code(prior, target, iters=15)
    assert sse[0] > 0 and sse[-1] < 1e-3 * sse[0]  # from c = 0's error to nearly none
    assert all(b <= a for a, b in zip(sse, sse[1:], strict=False))  # never worse
    assert np.sqrt(np.mean((prior.depth(code) - target) ** 2)) < 0.01


def test_the_best_code_stays_inside_its_radius_and_ignores_pixels_without_depth(prior):
    c_true = np.full(prior.net.code_dim, 1.5, np.float32)  # |c| = 4.2 for C = 8
    target = prior.depth(c_true).copy()
    target[:, : target.shape[1] // 2] = 0.0  # no ground truth on the left half
    code, sse = best_code(prior, target, radius=1.0)
    assert np.linalg.norm(code) <= 1.0 + 1e-5
    assert sse[-1] < sse[0]  # closer than c = 0 even when bounded
    free, sse_free = best_code(prior, target)
    assert sse_free[-1] <= sse[-1]  # the bound only costs
    with pytest.raises(ValueError, match="no valid pixel"):
        best_code(prior, np.zeros_like(target))


def test_main_on_a_frame_folder(tmp_path, capsys):
    folder = _folder(tmp_path / "frames", n=2)
    out = tmp_path / "o.json"
    doc = main(["--real", str(folder), "--radius", "0", "2", "--iters", "3", "--out", str(out)])
    r = doc["sets"]["real frames"]
    rm = r["rmse_m"]
    assert r["frames"] == 2 and set(rm) == {"c=0", "interpolation", "best code, unbounded", "best code, |c| <= 2"}
    assert rm["best code, unbounded"] <= rm["best code, |c| <= 2"] + 1e-6 <= rm["c=0"] + 1e-6
    assert float(r["code_norm_median"]["2"]) <= 2.0 + 1e-5
    assert json.loads(out.read_text())["sets"]["real frames"]["rmse_m"] == rm
    assert "best code, unbounded" in capsys.readouterr().out
