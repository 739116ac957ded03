"""ONNX export: checker, torch/ORT parity at batch 1 and 8, manifest, and the runtime wrapper (runtime/network.py)."""

import json
import shutil

import numpy as np
import pytest
import torch

from benchmarks.common import standin_net
from export.onnx import PARITY_TOLERANCE_M, export_network
from models import build_model
from runtime.network import DepthNetwork, ModelError, SessionConfig

H, W = 64, 96


def make_net(modality="grays", seed=0):
    """A small DiT whose output depends visibly on the code (an untrained one is nearly constant in it):
    :func:`benchmarks.common.standin_net` (depth head redrawn, decoder BatchNorm statistics re-estimated)."""
    return standin_net(modality, height=H, width=W, width_mult=0.25, seed=seed)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.set_num_threads(1)
    net = make_net()
    out = tmp_path_factory.mktemp("model")
    manifest = export_network(net, out, modality="grays", height=H, width=W)
    return net, out, manifest


def inputs(seed=0):
    rng = np.random.default_rng(seed)
    img = rng.random((H, W)).astype(np.float32)
    sparse = np.zeros((H, W), np.float32)
    idx = rng.choice(H * W, 40, replace=False)
    sparse.flat[idx] = rng.uniform(0.5, 5.0, 40)
    return img, sparse


def test_manifest_records_sizes_io_and_parity(exported):
    _, out, manifest = exported
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk == json.loads(json.dumps(manifest))
    assert (on_disk["modality"], on_disk["in_channels"], on_disk["height"], on_disk["width"]) == (
        "grays",
        2,
        H,
        W,
    )
    assert on_disk["code_dim"] == 8 and on_disk["jacobian"]["delta"] == 0.01
    assert on_disk["prior"]["inputs"][0]["name"] == "image" and on_disk["prior"]["inputs"][0]["shape"] == [
        1,
        2,
        H,
        W,
    ]
    names = [x["name"] for x in on_disk["decoder"]["inputs"]]
    assert names[0] == "code" and names[1:] == [x["name"] for x in on_disk["prior"]["outputs"][1:]]
    assert isinstance(on_disk["decoder"]["inputs"][0]["shape"][0], str)  # symbolic batch
    assert on_disk["prior"]["opset"] >= 18
    assert on_disk["parity"]["max_abs_depth_m"] <= PARITY_TOLERANCE_M
    assert on_disk["parity"]["decoder_batches"] == [1, 8]


def test_onnx_matches_torch_on_new_inputs(exported):
    net, out, _ = exported
    dn = DepthNetwork(out)
    img, sparse = inputs(seed=3)
    kf = dn.prior(img, sparse)
    x = torch.from_numpy(dn.make_input(img, sparse))
    codes = np.random.default_rng(4).normal(size=(8, 8)).astype(np.float32)
    with torch.no_grad():
        unc, feats = net.prior(x)
        depth_t = net.decoder(torch.from_numpy(codes), *feats)[:, 0].numpy()
    np.testing.assert_allclose(kf.uncertainty, unc[0, 0].numpy(), atol=1e-5)
    depth_o = dn.decode(codes, kf.features)
    assert np.abs(depth_o - depth_t).max() < PARITY_TOLERANCE_M
    # batch 8 equals 8 calls of batch 1
    singles = np.stack([dn.decode(c[None], kf.features)[0] for c in codes])
    np.testing.assert_allclose(depth_o, singles, atol=1e-5)
    assert np.ptp(depth_o, axis=0).max() > 1e-3  # the code changes the depth


def test_fd_jacobian_matches_autograd(exported):
    """Eq. 17 at delta = 1e-2 against torch autograd on the same weights.

    Forward differences err by ~delta/2 * |d2F/dc2| (truncation, and kinks of ReLU/max layers crossed by the step)
    plus ~eps32 * |F| / delta (float32 round-off). On this network the sweep gives a mean error of 10% of mean |J|
    at delta = 1e-5, 0.2% at 1e-3, 1.5% at 1e-2, 10% at 1e-1 and 40% at 1 (benchmarks/bench_jacobian.py draws the
    same curve for the shipped model); a few pixels near a kink stay off at any step, so the bound is on the mean.
    """
    net, out, _ = exported
    dn = DepthNetwork(out)
    img, sparse = inputs(seed=5)
    kf = dn.prior(img, sparse)
    code = np.random.default_rng(6).normal(size=8).astype(np.float32) * 0.5
    depth, J = kf.jacobian(code)
    assert depth.shape == (H, W) and J.shape == (H, W, 8)
    x = torch.from_numpy(dn.make_input(img, sparse))
    with torch.no_grad():
        _, feats = net.prior(x)
    # forward mode: exact like reverse mode, but 8 passes (one per code dimension) instead of one per pixel
    J_ad = torch.autograd.functional.jacobian(
        lambda c: net.decoder(c[None], *feats)[0, 0],
        torch.from_numpy(code),
        vectorize=True,
        strategy="forward-mode",
    )
    J_ad = J_ad.detach().numpy()
    scale = np.abs(J_ad).mean()
    assert scale > 1e-2
    err = np.abs(J - J_ad).mean()
    assert err < 0.05 * scale, (err, scale)
    # a deliberately bad step is visibly worse (the test can fail)
    _, J_big = kf.jacobian(code, delta=1.0)
    assert np.abs(J_big - J_ad).mean() > 0.2 * scale


def test_decoder_runs_once_per_code(exported):
    _, out, _ = exported
    dn = DepthNetwork(out, SessionConfig(threads=1, nominal_in_batch=True))
    kf = dn.prior(*inputs(seed=7))
    code = np.zeros(8, np.float32)
    d0, J0 = kf.jacobian(code)
    assert dn.decoder_calls == 1  # nominal + 8 perturbed codes in one batch of 9
    d1, J1 = kf.jacobian(code.copy())
    np.testing.assert_array_equal(kf.depth(code), d0)
    assert dn.decoder_calls == 1 and J1 is J0
    kf.jacobian(code + 0.1)
    assert dn.decoder_calls == 2
    # without the nominal in the batch: a depth() first, then only the 8 perturbed codes
    dn2 = DepthNetwork(out, SessionConfig(threads=1, nominal_in_batch=False))
    kf2 = dn2.prior(*inputs(seed=7))
    d2 = kf2.depth(code)
    _, J2 = kf2.jacobian(code)
    assert dn2.decoder_calls == 2
    np.testing.assert_allclose(d2, d0, atol=1e-6)
    np.testing.assert_allclose(J2, J0, atol=1e-3)


def test_wrong_inputs_and_mismatched_models_are_clear_errors(exported, tmp_path):
    _, out, _ = exported
    dn = DepthNetwork(out)
    img, sparse = inputs()
    with pytest.raises(ModelError, match="needs a sparse depth"):
        dn.prior(img)
    with pytest.raises(ModelError, match="96x64"):
        dn.prior(np.zeros((480, 752), np.uint8), sparse)
    with pytest.raises(ModelError, match="'rgbs'"):
        dn.check_compatible(modality="rgbs")
    with pytest.raises(ModelError, match="224x224"):
        dn.check_compatible(size=(224, 224))
    kf = dn.prior(img, sparse)
    with pytest.raises(ModelError, match="code has shape"):
        kf.depth(np.zeros(32))
    # a manifest that does not match its graphs
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["prior"]["inputs"][0]["shape"] = [1, 4, H, W]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelError, match="do not match the manifest"):
        DepthNetwork(bad)
    with pytest.raises(ModelError, match="no manifest"):
        DepthNetwork(tmp_path / "nowhere")


def test_fastdepth_has_no_code_to_export(tmp_path):
    net = build_model("fastdepth", "grays", width_mult=0.25, height=H, width=W)
    with pytest.raises(ValueError, match="no depth code"):
        export_network(net, tmp_path, modality="grays", height=H, width=W)


def test_runtime_network_does_not_import_torch():
    import subprocess
    import sys

    code = "import sys, runtime.network; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
