"""LightningModule pieces: KL warm-up, LR schedule, median reference, image panel, checkpoint spec."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models import build_model
from train.module import DepthModule, _median_prediction, cosine_schedule, image_panel, net_spec


def _module(**kw):
    net = build_model("dit", "grays", width_mult=0.25, height=64, width=64)
    return DepthModule(net, optimizer=lambda params: torch.optim.SGD(params, lr=1.0), **kw)


def test_kl_weight_warmup():
    assert _module().kl_weight_at(0) == 1.0  # paper: constant 1
    m = _module(kl_weight=0.5, kl_warmup_steps=10)
    assert [m.kl_weight_at(s) for s in (0, 5, 10, 20)] == [0.0, 0.25, 0.5, 0.5]


def test_cosine_schedule_values():
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched = cosine_schedule(opt, total_steps=12, warmup_steps=2, min_lr_ratio=0.1)
    lrs = []
    for _ in range(13):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[:3] == pytest.approx([0.5, 1.0, 1.0])
    assert lrs[7] == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert lrs[12] == pytest.approx(0.1)


def test_median_prediction_ignores_invalid():
    gt = torch.tensor([[[[1.0, 2.0], [0.0, 9.0]]], [[[0.0, 0.0], [0.0, 0.0]]]])
    med = _median_prediction(gt)
    assert med.shape == gt.shape
    assert med[0].unique().tolist() == [2.0] and med[1].unique().tolist() == [1.0]


def test_net_spec_and_checkpoint_fields():
    m = _module()
    assert net_spec(m.net) == {
        "name": "dit",
        "modality": "grays",
        "width_mult": 0.25,
        "height": 64,
        "width": 64,
        "code_dim": 8,
    }
    ck: dict = {}
    m.on_save_checkpoint(ck)
    assert build_model(**ck["net_config"]).code_dim == 8
    assert (
        net_spec(build_model("fastdepth", "rgb", width_mult=0.25, height=64, width=64))["name"] == "fastdepth"
    )
    for name in ("fastdepth", "codevio8"):  # a relative baseline is rebuilt relative
        spec = net_spec(build_model(name, "grays", width_mult=0.25, height=64, width=64, relative=True))
        assert spec["relative"] is True and build_model(**spec).relative


def test_image_panel_layout():
    rng = np.random.default_rng(0)
    img = rng.random((2, 2, 16, 16)).astype(np.float32)
    img[:, 1] = 0.0
    img[:, 1, 3, 4] = 2.0
    gt = np.full((2, 1, 16, 16), 2.0, np.float32)
    p = image_panel(img, gt, gt + 0.1, gt * 0 + 0.2, sparse=True)
    assert p.shape == (32, 5 * 16, 3) and p.dtype == np.uint8
    assert image_panel(img[:, :1], gt, gt, None, sparse=False).shape == (32, 4 * 16, 3)


def test_a_fill_made_by_the_loader_is_the_one_the_network_uses():
    from models.blocks import linear_fill

    net = build_model("dit", "grays", width_mult=0.25, height=64, width=64, relative=True)
    m = DepthModule(net, optimizer=lambda params: torch.optim.SGD(params, lr=1.0)).eval()
    g = torch.Generator().manual_seed(0)
    image = torch.rand(2, 2, 64, 64, generator=g)
    keep = torch.rand(2, 1, 64, 64, generator=g) < 0.02
    image[:, 1:] = torch.where(keep, 1.0 + 4.0 * image[:, 1:], torch.zeros_like(image[:, 1:]))
    with torch.no_grad():
        own = m(image)["depth"]
        given = m(image, fill=linear_fill(image[:, 1:]))["depth"]
        other = m(image, fill=2.0 * linear_fill(image[:, 1:]))["depth"]
    assert torch.equal(own, given)
    assert (other / own).mean() > 1.2  # the given fill is the one used (depth = fill * a bounded correction)
