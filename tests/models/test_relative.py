"""Relative-depth DiT: the densification it corrects and the normalisation (known answers), scale equivariance,
and torch vs ONNX Runtime agreement of both (the runtime computes the fill the same way)."""

import numpy as np
import pytest
import torch

from models import build_model
from models.blocks import RelativeSparseNorm, linear_fill, match_contrast, sample_scale
from runtime.densify import DEFAULT_FILL_M

torch.set_num_threads(1)

H, W = 64, 96


def _sparse(b=2, seed=0, p=0.03, lo=0.5, hi=5.0, h=H, w=W):
    g = torch.Generator().manual_seed(seed)
    keep = torch.rand(b, 1, h, w, generator=g) < p
    return keep * (lo + (hi - lo) * torch.rand(b, 1, h, w, generator=g))


def test_fill_constant_single_samples_kept_and_linear():
    sp = _sparse()
    const = (sp > 0) * 3.0
    assert torch.allclose(linear_fill(const), torch.full_like(sp, 3.0), atol=1e-6)
    one = torch.zeros(1, 1, H, W)
    one[0, 0, 10, 20] = 1.7
    assert torch.allclose(linear_fill(one), torch.full_like(one, 1.7))
    fill = linear_fill(sp)
    hit = sp > 0
    assert torch.allclose(fill[hit], sp[hit], atol=1e-6)  # the samples themselves are kept
    assert float(fill.min()) >= float(sp[hit].min()) - 1e-6 and float(fill.max()) <= float(sp.max()) + 1e-6
    assert torch.allclose(linear_fill(2.5 * sp), 2.5 * fill, rtol=1e-6)  # linear in the depths
    # a plane sampled at scattered pixels (corners included) is reproduced exactly
    gv, gu = torch.meshgrid(torch.arange(float(H)), torch.arange(float(W)), indexing="ij")
    plane = 1.0 + 0.02 * gu + 0.01 * gv
    keep = _sparse(1, seed=5) > 0
    keep[..., 0, 0] = keep[..., 0, -1] = keep[..., -1, 0] = keep[..., -1, -1] = True
    torch.testing.assert_close(linear_fill(plane * keep)[0, 0], plane, rtol=1e-5, atol=1e-5)


def test_fill_no_samples_and_geometric_scale():
    fill = linear_fill(torch.zeros(1, 1, 32, 32))
    assert torch.allclose(fill, torch.full_like(fill, DEFAULT_FILL_M))
    mask, scale = sample_scale(torch.zeros(1, 1, 32, 32))
    assert float(mask.sum()) == 0 and float(scale) == pytest.approx(DEFAULT_FILL_M)
    sp = torch.zeros(1, 1, 32, 32)
    sp[0, 0, 1, 1], sp[0, 0, 30, 30], sp[0, 0, 5, 25] = 1.0, 4.0, 2.0
    assert float(sample_scale(sp)[1]) == pytest.approx(2.0, rel=1e-6)  # (1 * 4 * 2) ** (1/3)
    with pytest.raises(ValueError, match="B, 1, H, W"):
        linear_fill(torch.zeros(1, 2, 8, 8))


def test_relative_norm_is_scale_free():
    norm = RelativeSparseNorm("grays")
    x = torch.cat([torch.rand(2, 1, H, W), _sparse()], 1)
    y, scale = norm(x, linear_fill(x[:, -1:]))
    x2 = x.clone()
    x2[:, -1] *= 2.0
    y2, scale2 = norm(x2, linear_fill(x2[:, -1:]))
    assert y.shape == (2, 4, H, W)
    assert torch.allclose(y, y2, atol=1e-5)
    assert torch.allclose(scale2, 2 * scale, rtol=1e-5)
    with pytest.raises(ValueError, match="sparse modality"):
        RelativeSparseNorm("gray")


def _relative_net(seed=0, image_contrast=None):
    torch.manual_seed(seed)
    net = build_model("dit", "grays", width_mult=0.25, height=H, width=W, relative=True, image_contrast=image_contrast)
    with torch.no_grad():  # a decoder that visibly depends on the input and the code
        net.decoder.head.weight.normal_(0.0, 0.05)
        for m in net.decoder.modules():  # as benchmarks.common.standin_net: the decoder's statistics only
            if isinstance(m, torch.nn.BatchNorm2d):
                m.momentum = None
        net.decoder.train()
        for _ in range(3):
            x = torch.cat([torch.rand(4, 1, H, W), _sparse(4)], 1)
            net(x, code=torch.randn(4, 8))
    return net.eval()


def test_scale_every_input_depth_by_two():
    """A network that ignores the scale of its sparse input fails this."""
    net = _relative_net()
    x = torch.cat([torch.rand(2, 1, H, W), _sparse()], 1)
    x2 = x.clone()
    x2[:, -1] *= 2.0
    code = torch.randn(2, 8)
    with torch.no_grad():
        a, b = net(x, code=code), net(x2, code=code)
    assert torch.allclose(b["depth"], 2 * a["depth"], rtol=2e-3)  # float32 round-off through the net
    assert torch.allclose(b["uncertainty"], 2 * a["uncertainty"], rtol=1e-4)
    # ... and the code still moves the depth
    with torch.no_grad():
        c = net(x, code=code + 1.0)["depth"]
    assert float((c - a["depth"]).abs().mean()) > 1e-3
    # an absolute-depth network does not have the property (the test has teeth)
    torch.manual_seed(0)
    absn = build_model("dit", "grays", width_mult=0.25, height=H, width=W).eval()
    with torch.no_grad():
        da, db = absn(x)["depth"], absn(x2)["depth"]
    assert not torch.allclose(db, 2 * da, rtol=1e-2)


def test_relative_training_step_and_describe():
    net = _relative_net().train()
    x = torch.cat([torch.rand(2, 1, H, W), _sparse()], 1)
    gt = 0.5 + 4.5 * torch.rand(2, 1, H, W)
    out = net(x, gt_depth=gt)
    assert out["mu"].shape == (2, 8)
    loss = (out["depth"] - gt).abs().mean() + out["mu"].square().mean()
    loss.backward()
    assert net.recognition.fc.weight.grad is not None
    d = net.describe()
    assert d["relative"] is True and "fill" in d["depth"]["parametrisation"]
    assert d["feature_shapes"][-1][0] == net.prior_net.channels[-1] + 1
    assert not build_model("dit", "gray", width_mult=0.25, height=H, width=W, relative=True).relative


@pytest.mark.parametrize("name", ["fastdepth", "codevio8", "codevio32"])
def test_relative_baselines_start_at_the_fill_and_carry_the_scale(name):
    """The baselines under DiT's relative formulation (the GPU Table 1): at initialisation (head ~0) the depth is
    the interpolation of the samples; scaling every input depth scales the output; the fill reaches the output
    (a different fill, same image and samples, gives a different depth); and the absolute variant is unchanged."""
    torch.manual_seed(0)
    net = build_model(name, "grays", width_mult=0.25, height=H, width=W, relative=True).eval()
    assert net.relative
    x = torch.cat([torch.rand(2, 1, H, W), _sparse()], 1)
    fill = linear_fill(x[:, 1:])
    with torch.no_grad():
        d = net(x)["depth"]
        d2 = net(x * torch.tensor([1.0, 3.0])[None, :, None, None])["depth"]
        d_fill = net(x, fill=1.5 * fill)["depth"]
    assert torch.allclose(d2, 3.0 * d, rtol=1e-4)
    assert float((d / fill - 1).abs().max()) < 0.2  # near the fill at initialisation
    assert float((d_fill / d).mean()) > 1.2  # the fill is the base of the prediction
    if name == "fastdepth":
        assert net.describe()["relative"] is True
        with pytest.raises(ValueError, match="relative FastDepth"):
            build_model(name, "grays", width_mult=0.25, height=H, width=W)(x, fill=fill)
    absolute = build_model(name, "grays", width_mult=0.25, height=H, width=W)
    assert not absolute.relative


def test_onnx_agrees_on_fill_scale_and_depth(tmp_path):
    pytest.importorskip("onnxruntime")
    from export.onnx import export_network
    from runtime.network import DepthNetwork

    net = _relative_net()
    export_network(net, tmp_path, modality="grays", height=H, width=W)
    dn = DepthNetwork(tmp_path)
    rng = np.random.default_rng(0)
    grey = rng.random((H, W)).astype(np.float32)
    sparse = np.where(rng.random((H, W)) < 0.03, rng.uniform(0.3, 1.4, (H, W)), 0).astype(np.float32)
    code = rng.normal(size=8).astype(np.float32)
    kf, kf2 = dn.prior(grey, sparse), dn.prior(grey, 2 * sparse)
    x = torch.from_numpy(np.stack([grey, sparse])[None])
    with torch.no_grad():
        unc_t, feats = net.prior(x)
        d_t = net.decoder(torch.from_numpy(code[None]), *feats)[0, 0].numpy()
        fill_t = linear_fill(x[:, 1:])[0, 0].numpy()
    log_fill_o = kf.features[dn.feature_names[-1]][0, -1]
    assert dn.takes_fill
    np.testing.assert_allclose(np.exp(log_fill_o), fill_t, rtol=1e-5)  # the runtime feeds the same fill
    np.testing.assert_allclose(kf.depth(code), d_t, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(kf.uncertainty, unc_t[0, 0].numpy(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(kf2.depth(code), 2 * kf.depth(code), rtol=1e-4)  # the scale test, in ONNX
    _, J = kf.jacobian(code)
    assert J.shape == (H, W, 8) and np.linalg.matrix_rank(J.reshape(-1, 8)) == 8


def test_match_contrast_known_answer_and_flat_image():
    x = torch.tensor([0.2, 0.4, 0.6, 0.8]).view(1, 1, 2, 2)
    y = match_contrast(x, 0.1)
    assert torch.allclose(y.mean(), torch.tensor(0.5)) and abs(float(y.std(unbiased=False)) - 0.1) < 1e-6
    assert torch.allclose(y, 0.5 + (x - 0.5) * (0.1 / float(x.std(unbiased=False))))
    flat = torch.full((1, 1, 4, 4), 0.3)
    flat[0, 0, 0, 0] = 0.301  # std 2.4e-4: the gain is bounded by min_std, not 700x
    z = match_contrast(flat, 0.1)
    assert float((z - flat).abs().max()) < 0.01
    assert float(match_contrast(torch.rand(1, 1, 8, 8) * 40 - 20, 0.4).min()) >= 0.0  # clipped to [0, 1]


def test_image_contrast_makes_the_prior_blind_to_image_contrast(tmp_path):
    """The same scene at twice the contrast gives the same prior, in torch and in prior.onnx; without the option
    it does not (the test has teeth)."""
    pytest.importorskip("onnxruntime")
    from export.onnx import export_network
    from runtime.network import DepthNetwork

    net = _relative_net(image_contrast=0.166)
    assert net.describe()["input"]["image_contrast"] == 0.166
    rng = np.random.default_rng(1)
    grey = (0.45 + 0.08 * rng.standard_normal((H, W))).clip(0, 1).astype(np.float32)
    grey2 = (0.45 + 2.0 * (grey - 0.45)).astype(np.float32)  # within [0, 1]: no clipping
    sparse = _sparse(b=1)[0, 0].numpy()
    code = rng.normal(size=8).astype(np.float32)
    export_network(net, tmp_path, modality="grays", height=H, width=W)
    dn = DepthNetwork(tmp_path)
    np.testing.assert_allclose(dn.prior(grey2, sparse).depth(code), dn.prior(grey, sparse).depth(code), rtol=1e-4)
    x = torch.from_numpy(np.stack([grey, sparse])[None])
    with torch.no_grad():
        d_t = net.decoder(torch.from_numpy(code[None]), *net.prior(x)[1])[0, 0].numpy()
    np.testing.assert_allclose(dn.prior(grey, sparse).depth(code), d_t, rtol=1e-4, atol=1e-5)
    plain = _relative_net()
    x2 = torch.from_numpy(np.stack([grey2, sparse])[None])
    c = torch.from_numpy(code[None])
    with torch.no_grad():
        d1, d2 = plain.decoder(c, *plain.prior(x)[1]), plain.decoder(c, *plain.prior(x2)[1])
    assert not torch.allclose(d1, d2, rtol=1e-3)
    with pytest.raises(ValueError, match="image_contrast"):
        build_model("fastdepth", "grays", width_mult=0.25, height=H, width=W, image_contrast=0.2)
    with pytest.raises(ValueError, match="image_contrast"):
        build_model("dit", "grays", width_mult=0.25, height=H, width=W, relative=True, image_contrast=0.0)
