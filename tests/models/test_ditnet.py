"""DiTNet and baselines: shapes per modality/variant, ranges, the decoder (ONNX unit), the code matters."""

import json

import pytest
import torch

from models import MODALITY_CHANNELS, DiTNet, build_model
from models.losses import total_loss

torch.set_num_threads(1)

H, W = 64, 96
WM = 0.25  # tiny width for speed


def _input(modality: str, b: int = 2, seed: int = 0, h: int = H, w: int = W) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(b, MODALITY_CHANNELS[modality], h, w, generator=g)
    if modality.endswith("s"):  # sparse depth: ~3% of pixels with 0.5..5 m, 0 elsewhere
        keep = torch.rand(b, h, w, generator=g) < 0.03
        x[:, -1] = keep * (0.5 + 4.5 * torch.rand(b, h, w, generator=g))
    return x


def _gt(b: int = 2, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    gt = 0.5 + 4.5 * torch.rand(b, 1, H, W, generator=g)
    gt[:, :, :4] = 0.0  # some invalid pixels
    return gt


def _calibrate_bn(net: torch.nn.Module, modality: str) -> torch.nn.Module:
    """Give BatchNorm real running statistics (as after training), then switch to eval mode.

    Freshly initialised running stats (mean 0, var 1) with Kaiming-initialised depthwise convs make eval-mode
    activations vanish with depth, which would hide the code's effect in a float32 test.
    """
    for m in net.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.reset_running_stats()
            m.momentum = None  # cumulative average
    net.train()
    with torch.no_grad():
        for s in range(3):
            code = torch.randn(4, net.code_dim, generator=torch.Generator().manual_seed(10 + s))
            net(_input(modality, b=4, seed=10 + s), code=code)
    return net.eval()


@pytest.fixture(scope="module")
def dit():
    torch.manual_seed(0)
    return build_model("dit", "grays", width_mult=WM, height=H, width=W).eval()


@pytest.mark.parametrize("modality", sorted(MODALITY_CHANNELS))
@pytest.mark.parametrize("name", ["dit", "codevio8", "codevio32", "fastdepth"])
def test_shapes_and_ranges(name, modality):
    torch.manual_seed(0)
    net = build_model(name, modality, width_mult=WM, height=H, width=W)
    assert (net.in_channels, net.modality) == (MODALITY_CHANNELS[modality], modality)
    c = {"dit": 8, "codevio8": 8, "codevio32": 32, "fastdepth": None}[name]
    assert net.code_dim == c
    x = _input(modality)
    with torch.no_grad():
        out = net.train()(x, _gt()) if c else net.train()(x)
        out_eval = net.eval()(x)
    assert out.keys() == {"depth", "uncertainty", "mu", "logvar", "code"}
    for o in (out, out_eval):
        assert o["depth"].shape == (2, 1, H, W)
        assert torch.isfinite(o["depth"]).all()
        assert (o["depth"] >= 0.1).all() and (o["depth"] <= 20.0).all()
    if c is None:
        assert all(out[k] is None for k in ("uncertainty", "mu", "logvar", "code"))
        return
    assert out["uncertainty"].shape == (2, 1, H, W) and (out["uncertainty"] > 0).all()
    assert out["mu"].shape == out["logvar"].shape == out["code"].shape == (2, c)
    assert out_eval["mu"] is None and out_eval["logvar"] is None
    torch.testing.assert_close(out_eval["code"], torch.zeros(2, c))  # prior mean
    assert hasattr(net, "decoder") and hasattr(net, "prior")
    assert net.attention == (name == "dit")
    assert len([m for m in net.modules() if type(m).__name__ == "CBAM"]) == (12 if name == "dit" else 0)


def test_sizes_multiple_of_32_only():
    torch.manual_seed(0)
    net = DiTNet(1, width_mult=WM, height=32, width=128).eval()
    with torch.no_grad():
        assert net(torch.rand(1, 1, 32, 128))["depth"].shape == (1, 1, 32, 128)
    for h, w in ((100, 96), (64, 90)):
        with pytest.raises(ValueError, match=r"(height|width)=(100|90) must be a positive multiple of 32"):
            DiTNet(1, width_mult=WM, height=h, width=w)
    with pytest.raises(ValueError, match=r"built for 32x128"):
        net(torch.rand(1, 1, 64, 128))
    with pytest.raises(ValueError, match=r"image must have shape \(B, 1, 32, 128\), got \(1, 3, 32, 128\)"):
        net(torch.rand(1, 3, 32, 128))
    fd = build_model("fastdepth", "rgb", width_mult=WM, height=H, width=W).eval()
    with torch.no_grad():  # fully convolutional: any multiple of 32 at run time
        assert fd(torch.rand(1, 3, 96, 32))["depth"].shape == (1, 1, 96, 32)
    with pytest.raises(ValueError, match="height=65"):
        fd(torch.rand(1, 3, 65, 32))
    with pytest.raises(ValueError, match=r"image must have shape \(B, 3, H, W\), got \(1, 4, 64, 64\)"):
        fd(torch.rand(1, 4, 64, 64))


def test_build_model_errors():
    with pytest.raises(ValueError, match="name='ditt'"):
        build_model("ditt", "rgb")
    with pytest.raises(ValueError, match="modality='rgbd'"):
        build_model("dit", "rgbd")
    with pytest.raises(ValueError, match="code_dim=16"):
        build_model("codevio8", "rgb", code_dim=16)
    with pytest.raises(ValueError, match="code_dim=8"):
        build_model("fastdepth", "rgb", code_dim=8)
    assert build_model("dit", "gray", code_dim=4, width_mult=WM, height=H, width=W).code_dim == 4
    with pytest.raises(ValueError, match="code_dim=0"):
        build_model("dit", "gray", code_dim=0)


def test_prior_plus_decoder_equals_forward(dit):
    x = _input("grays", b=3)
    code = torch.randn(3, 8, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        out = dit(x, code=code)
        unc, feats = dit.prior(x)
        depth = dit.decoder(code, *feats)
    assert len(feats) == 6
    assert [tuple(f.shape[1:]) for f in feats] == [tuple(s) for s in dit.feature_shapes]
    assert [f.shape[-1] for f in feats] == [W // s for s in (32, 16, 8, 4, 2, 1)]
    torch.testing.assert_close(out["depth"], depth)
    torch.testing.assert_close(out["uncertainty"], unc)
    torch.testing.assert_close(out["code"], code)


def test_decoder_batch_of_codes_with_batch1_features(dit):
    x = _input("grays", b=1)
    codes = torch.randn(8, 8, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        _, feats = dit.prior(x)
        batch = dit.decoder(codes, *feats)
        single = torch.cat([dit.decoder(codes[i : i + 1], *feats) for i in range(8)])
    assert batch.shape == (8, 1, H, W)
    torch.testing.assert_close(batch, single, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match=r"code must have shape \(B, 8\)"):
        dit.decoder(codes[:, :4], *feats)
    with pytest.raises(ValueError, match="feature 0 .stride 32"):
        dit.decoder(codes, feats[0].expand(3, -1, -1, -1), *feats[1:])
    with pytest.raises(ValueError, match="takes 6 features"):
        dit.decoder(codes, *feats[:5])


@pytest.mark.parametrize("name", ["dit", "codevio8"])
def test_decoder_uses_every_code_dimension(name):
    torch.manual_seed(0)
    net = _calibrate_bn(build_model(name, "rgbs", width_mult=WM, height=H, width=W), "rgbs")
    with torch.no_grad():
        _, feats = net.prior(_input("rgbs", b=1))
        c0 = torch.zeros(1, 8)
        delta = 1e-2  # Eq. 17: one batch of 8 perturbed codes
        d0 = net.decoder(c0, *feats)
        d = net.decoder(c0 + delta * torch.eye(8), *feats)
    jac = ((d - d0) / delta).flatten(1).T  # (H*W, 8)
    assert (jac.abs().amax(0) > 1e-2).all()  # every code dimension changes the depth [m per unit code]
    assert torch.linalg.matrix_rank(jac.double(), rtol=1e-3) == 8  # and in independent ways


def test_train_mode_samples_eval_mode_uses_mu(dit):
    x, gt = _input("grays"), _gt()
    torch.manual_seed(4)
    with torch.no_grad():
        out = dit.train()(x, gt)
    dit.eval()
    assert not torch.allclose(out["code"], out["mu"])
    with torch.no_grad():
        out = dit(x, gt)
        torch.testing.assert_close(out["code"], out["mu"])
        torch.testing.assert_close(out["depth"], dit(x, code=out["mu"])["depth"])
    with pytest.raises(ValueError, match="not both"):
        dit(x, gt, code=torch.zeros(2, 8))
    with pytest.raises(ValueError, match=r"gt_depth must have shape"):
        dit(x, gt[..., :32])


@pytest.mark.parametrize("name", ["dit", "codevio32", "fastdepth"])
def test_every_parameter_gets_a_gradient(name):
    torch.manual_seed(0)
    net = build_model(name, "grays", width_mult=WM, height=H, width=W).train()
    out = net(_input("grays"), _gt())
    total, parts = total_loss(out, _gt())
    assert torch.isfinite(total) and not parts["total"].requires_grad
    total.backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert missing == []


def test_describe_is_json_and_matches(dit):
    info = json.loads(json.dumps(dit.describe()))
    assert info["modality"] == "grays" and info["code_dim"] == 8 and info["model"] == "dit"
    assert info["depth"]["depth_min"] == 0.1 and info["depth"]["depth_max"] == 20.0
    assert info["feature_shapes"][-1] == [dit.feature_shapes[-1][0], H, W]
    fd = build_model("fastdepth", "rgb", width_mult=WM, height=H, width=W)
    assert json.loads(json.dumps(fd.describe()))["input"]["image_mean"] == pytest.approx(
        [0.485, 0.456, 0.406]
    )
