"""The shipped default model (runtime/assets/default_model): loads, matches its manifest, reproduces its metrics."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from runtime.network import DepthNetwork, default_model_dir

ROOT = Path(__file__).resolve().parents[1]
MODEL = default_model_dir()


def test_shipped_files_exist_and_are_small():
    names = {p.name for p in MODEL.iterdir()}
    assert {"prior.onnx", "decoder.onnx", "manifest.json", "val_metrics.json", "README.md"} <= names
    assert sum(p.stat().st_size for p in MODEL.iterdir()) < 20e6


def test_shipped_model_loads_and_matches_its_manifest():
    net = DepthNetwork(MODEL)  # checks every graph input/output against the manifest
    m = net.manifest
    assert (net.modality, net.code_dim) == ("grays", 8)
    assert (net.height, net.width) == (m["height"], m["width"]) and net.height % 32 == 0
    assert m["parity"]["max_abs_depth_m"] <= 1e-4
    assert m["jacobian"]["delta"] == 0.01
    # the code matters: decoding two codes gives different depth
    rng = np.random.default_rng(0)
    kf = net.prior(
        rng.random((net.height, net.width)).astype(np.float32),
        np.where(rng.random((net.height, net.width)) < 0.01, 3.0, 0.0).astype(np.float32),
    )
    assert np.all(kf.uncertainty > 0)
    d0, J = kf.jacobian(np.zeros(8, np.float32))
    assert np.all((d0 > 0.05) & (d0 < 25.0))
    assert np.abs(J).mean() > 1e-3


def _eval_script():
    spec = importlib.util.spec_from_file_location(
        "_eval_onnx_depth", ROOT / "benchmarks" / "eval_onnx_depth.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_shipped_model_reproduces_recorded_validation_metrics():
    """Regenerate the validation frames (same generator, seed and count) and recompute the recorded metrics."""
    recorded = json.loads((MODEL / "val_metrics.json").read_text())
    got = _eval_script().onnx_depth_metrics(
        MODEL, n_val=recorded["frames"], seed=0, realism=bool(recorded.get("realism", False))
    )
    assert got["frames"] == recorded["frames"]
    for k in ("rmse", "irmse", "abs_rel", "mae", "delta1", "delta2", "delta3"):
        assert got[k] == pytest.approx(recorded[k], rel=1e-3, abs=1e-4), k
