"""``dit-export`` end to end on a checkpoint written by ``python train/fit.py`` (tiny run)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from runtime.network import DepthNetwork
from tests.train.conftest import REPO, write_fake_nyu


def _env():
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _export(*overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", "from export.cli import main; main()", *overrides]
    return subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_fit_then_export_then_runtime(tmp_path):
    data = write_fake_nyu(tmp_path / "nyu")
    run = tmp_path / "run"
    fit = [
        sys.executable,
        "train/fit.py",
        "data=nyu_h5",
        f"data.root={data}",
        "data.height=64",
        "data.width=96",
        "data.batch_size=2",
        "model.net.width_mult=0.25",
        "trainer.max_steps=2",
        "trainer.limit_val_batches=1",
        "trainer.val_check_interval=2",
        "trainer.enable_progress_bar=false",
        "logger.tensorboard=null",
        "num_threads=1",
        f"hydra.run.dir={run}",
    ]
    p = subprocess.run(fit, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    ckpt = run / "checkpoints" / "last.ckpt"
    out = tmp_path / "model"
    p = _export(f"ckpt={ckpt}", f"out={out}")
    assert p.returncode == 0, p.stderr[-3000:]
    assert "max |depth onnx - torch|" in p.stdout
    assert "the checkpoint was trained with" not in p.stderr  # its run config and its own net_config agree
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["input_normalization"]["image_contrast"] is None
    assert (manifest["modality"], manifest["height"], manifest["width"]) == ("grays", 64, 96)
    assert manifest["source"] == str(ckpt) and manifest["train_config"]["model"]["net"]["name"] == "dit"
    net = DepthNetwork(out)
    kf = net.prior(np.zeros((64, 96), np.uint8), np.zeros((64, 96), np.float32))
    assert kf.depth(np.zeros(8)).shape == (64, 96)
    # the same weights with contrast matching in prior.onnx: doubling the image's contrast changes nothing
    out2 = tmp_path / "model_contrast"
    p = _export(f"ckpt={ckpt}", f"out={out2}", "image_contrast=0.2")
    assert p.returncode == 0, p.stderr[-3000:]
    assert json.loads((out2 / "manifest.json").read_text())["input_normalization"]["image_contrast"] == 0.2
    rng = np.random.default_rng(0)
    grey = (0.5 + 0.08 * rng.standard_normal((64, 96))).clip(0.3, 0.7).astype(np.float32)
    sparse = np.where(rng.random((64, 96)) < 0.05, rng.uniform(0.5, 3.0, (64, 96)), 0).astype(np.float32)
    low, high = DepthNetwork(out2).prior(grey, sparse), DepthNetwork(out2).prior(0.5 + 2 * (grey - 0.5), sparse)
    np.testing.assert_allclose(low.depth(np.zeros(8)), high.depth(np.zeros(8)), rtol=1e-4)


def test_export_cli_names_a_missing_checkpoint(tmp_path):
    p = _export(f"ckpt={tmp_path / 'none.ckpt'}", f"out={tmp_path / 'm'}", timeout=120)
    assert p.returncode != 0 and "none.ckpt" in p.stderr and "not found" in p.stderr
