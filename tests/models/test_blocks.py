"""models/blocks.py: known answers for CBAM (Eq. 3), SK fusion (Eq. 4-5), normalisation, MobileNet."""

import math

import pytest
import torch
from torch import nn

from models import MODALITY_CHANNELS, build_model
from models.blocks import (
    CBAM,
    BoundedLogDepth,
    DWSepConv,
    InputNorm,
    MobileNetEncoder,
    SKFusion,
    UpBlock,
    check_size,
    modality_of,
    scaled_channels,
)

torch.set_num_threads(1)


def _force(linear_or_conv: nn.Module, bias: float) -> None:
    """Make a layer output the constant ``bias`` (so that the following sigmoid is ~0 or ~1)."""
    with torch.no_grad():
        linear_or_conv.weight.zero_()
        linear_or_conv.bias.fill_(bias)


def test_scaled_channels_and_modalities():
    assert [scaled_channels(c, 0.25) for c in (32, 64, 1024)] == [8, 16, 256]
    assert scaled_channels(64, 1.0) == 64 and scaled_channels(100, 0.5) == 48
    with pytest.raises(ValueError, match="width_mult"):
        scaled_channels(32, 0.0)
    assert {modality_of(c) for c in MODALITY_CHANNELS.values()} == set(MODALITY_CHANNELS)
    with pytest.raises(ValueError, match="in_channels=5"):
        modality_of(5)
    check_size(64, 96)
    for h, w in ((100, 64), (64, 0), (64, 33)):
        with pytest.raises(ValueError, match="multiple of 32"):
            check_size(h, w)


def test_dwsep_conv_structure_and_shape():
    m = DWSepConv(4, 12, kernel=5, stride=2)
    dw, pw = m[0][0], m[1][0]
    assert (dw.groups, dw.kernel_size, dw.stride, dw.in_channels) == (4, (5, 5), (2, 2), 4)
    assert (pw.groups, pw.kernel_size, pw.out_channels) == (1, (1, 1), 12)
    assert isinstance(m[0][1], nn.BatchNorm2d) and isinstance(m[1][2], nn.ReLU)
    y = m(torch.randn(2, 4, 16, 24))
    assert y.shape == (2, 12, 8, 12) and (y >= 0).all()
    up = UpBlock(8, 4)
    assert up(torch.randn(1, 8, 3, 5)).shape == (1, 4, 6, 10)
    assert up[1][0][0].kernel_size == (5, 5) and up[0].mode == "nearest"


def test_mobilenet_multiscale_features():
    enc = MobileNetEncoder(2, width_mult=0.25)
    assert enc.channels == (16, 32, 64, 128, 256)
    feats = enc(torch.randn(1, 2, 64, 96))
    assert [tuple(f.shape) for f in feats] == [
        (1, 16, 32, 48),
        (1, 32, 16, 24),
        (1, 64, 8, 12),
        (1, 128, 4, 6),
        (1, 256, 2, 3),
    ]
    # stem: depthwise with a channel multiplier (groups == in_channels), then pointwise
    stem_dw = enc.layers[0][0][0]
    assert (stem_dw.groups, stem_dw.in_channels, stem_dw.out_channels, stem_dw.stride) == (2, 2, 16, (2, 2))
    # full width: MobileNet v1 has about 3.2 M parameters without its classifier
    n = sum(p.numel() for p in MobileNetEncoder(3, 1.0).parameters())
    assert 3.0e6 < n < 3.4e6


@pytest.mark.parametrize("name", ["dit", "codevio8", "codevio32", "fastdepth"])
def test_every_conv_is_depthwise_or_pointwise(name):
    net = build_model(name, "grays", width_mult=0.25, height=64, width=64)
    convs = [m for m in net.modules() if isinstance(m, nn.Conv2d)]
    assert len(convs) > 20
    for m in convs:
        assert m.groups == m.in_channels or m.kernel_size == (1, 1), m
    n_dw5 = sum(m.kernel_size == (5, 5) and m.groups == m.in_channels for m in convs)
    assert n_dw5 >= 5  # the upsampling convs


def test_cbam_residual_form_and_maps():
    torch.manual_seed(0)
    cbam = CBAM(16).eval()
    x = torch.randn(2, 16, 8, 12)
    mc, ms = cbam.maps(x)
    assert mc.shape == (2, 16, 1, 1) and ms.shape == (2, 1, 8, 12)
    assert ((mc > 0) & (mc < 1)).all() and ((ms > 0) & (ms < 1)).all()
    # Eq. 3: F_c = M_c(F) F, F_s = M_s(F_c) F_c, out = F_s + F
    fc = mc * x
    torch.testing.assert_close(cbam(x), ms * fc + x)
    # spatial attention is a 7x7 conv over [channel mean, channel max]
    pooled = torch.cat([fc.mean(1, keepdim=True), fc.amax(1, keepdim=True)], 1)
    w = cbam.spatial.dw.weight * cbam.spatial.pw.weight.view(2, 1, 1, 1)  # (2, 1, 7, 7) -> dense (1, 2, 7, 7)
    dense = nn.functional.conv2d(pooled, w.view(1, 2, 7, 7), cbam.spatial.pw.bias, padding=3)
    torch.testing.assert_close(ms, torch.sigmoid(dense))


def test_cbam_forced_attention_maps():
    x = torch.randn(1, 8, 5, 7)
    cbam = CBAM(8).eval()
    _force(cbam.channel.mlp[2], -1e4)  # M_c = 0 -> F_c = 0 -> output = F
    torch.testing.assert_close(cbam(x), x, rtol=0, atol=0)
    cbam = CBAM(8).eval()
    _force(cbam.spatial.pw, -1e4)  # M_s = 0 -> output = F
    torch.testing.assert_close(cbam(x), x, rtol=0, atol=0)
    _force(cbam.channel.mlp[2], 1e4)
    _force(cbam.spatial.pw, 1e4)  # both maps = 1 -> output = 2 F
    torch.testing.assert_close(cbam(x), 2 * x)


def test_sk_fusion_weights_and_output():
    torch.manual_seed(1)
    sk = SKFusion(24).eval()
    f1, f2 = torch.randn(3, 24, 6, 8), torch.randn(3, 24, 6, 8)
    a1, a2 = sk.weights(f1, f2)
    assert a1.shape == (3, 24, 1, 1)
    torch.testing.assert_close(a1 + a2, torch.ones_like(a1))
    assert ((a1 > 0) & (a1 < 1)).all() and not torch.allclose(a1, a2)
    torch.testing.assert_close(sk(f1, f2), a1 * f1 + a2 * f2)
    # attention is computed from the sum F1 + F2 (Eq. 4): swapping the inputs keeps the weights
    b1, _ = sk.weights(f2, f1)
    torch.testing.assert_close(a1, b1)
    # known answer: constant logits log 3 and 0 -> softmax 0.75 / 0.25 for every channel
    _force(sk.fc1, math.log(3.0))
    _force(sk.fc2, 0.0)
    torch.testing.assert_close(sk(f1, f2), 0.75 * f1 + 0.25 * f2)
    # batch-1 branch broadcasts against a batch-B branch
    torch.testing.assert_close(sk(f1, f2[:1]), sk(f1, f2[:1].expand(3, -1, -1, -1)))


def test_input_norm_known_values():
    norm = InputNorm("grays", 0.1, 20.0)
    x = torch.zeros(1, 2, 1, 5)
    x[0, 0] = 0.449
    x[0, 1, 0] = torch.tensor([0.0, 0.1, math.sqrt(2.0), 20.0, 50.0])
    y = norm(x)
    assert y.shape == (1, 3, 1, 5)
    torch.testing.assert_close(y[0, 0, 0], torch.zeros(5))
    torch.testing.assert_close(y[0, 1, 0], torch.tensor([0.0, -1.0, 0.0, 1.0, 1.0]))
    torch.testing.assert_close(y[0, 2, 0], torch.tensor([0.0, 1.0, 1.0, 1.0, 1.0]))
    rgb = InputNorm("rgb", 0.1, 20.0)
    img = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1) + torch.tensor([0.229, 0.224, 0.225]).view(
        1, 3, 1, 1
    )
    torch.testing.assert_close(rgb(img), torch.ones(1, 3, 1, 1))
    assert dict(rgb.named_buffers()).keys() == {"mean", "std"}


def test_bounded_log_depth():
    p = BoundedLogDepth(0.1, 20.0)
    d = p(torch.tensor([-100.0, 0.0, 100.0]))
    torch.testing.assert_close(d, torch.tensor([0.1, math.sqrt(2.0), 20.0]))
    for depth in (0.5, 2.0, 7.0):
        assert p(torch.tensor(p.inverse_logit(depth))).item() == pytest.approx(depth, rel=1e-5)
    with pytest.raises(ValueError, match="depth_min"):
        BoundedLogDepth(2.0, 1.0)
