"""Depth metrics against values computed by hand."""

from __future__ import annotations

import math

import pytest
import torch

from train.metrics import METRICS, DepthMetrics, format_table, image_metrics


def test_image_metrics_hand_values():
    # one image, 2x2; one invalid pixel (gt 0). valid pairs (p, g): (2, 2), (3, 2), (1, 2)
    p = torch.tensor([[[[2.0, 3.0], [1.0, 7.0]]]])
    g = torch.tensor([[[[2.0, 2.0], [2.0, 0.0]]]])
    m = image_metrics(p, g)
    # errors 0, 1, -1
    assert m["rmse"].item() == pytest.approx(math.sqrt(2 / 3))
    assert m["mae"].item() == pytest.approx(2 / 3)
    assert m["abs_rel"].item() == pytest.approx((0 + 0.5 + 0.5) / 3)
    # inverse errors 0, 1/3 - 1/2, 1 - 1/2  [1/m]
    assert m["irmse"].item() == pytest.approx(math.sqrt(((1 / 3 - 1 / 2) ** 2 + 0.5**2) / 3))
    # ratios max(p/g, g/p): 1, 1.5, 2 -> delta1 (<1.25): 1/3, delta2 (<1.5625): 2/3, delta3 (<1.953): 2/3
    assert m["delta1"].item() == pytest.approx(1 / 3)
    assert m["delta2"].item() == pytest.approx(2 / 3)
    assert m["delta3"].item() == pytest.approx(2 / 3)
    assert m["n"].item() == 3


def test_accumulator_averages_images_and_pools_mape():
    # image A: 1 valid pixel, p=2 g=1 (rel err 1); image B: 3 valid pixels, exact (rel err 0)
    p = torch.tensor([[[[2.0, 5.0], [5.0, 5.0]]], [[[4.0, 4.0], [4.0, 4.0]]]])
    g = torch.tensor([[[[1.0, 0.0], [0.0, 0.0]]], [[[4.0, 4.0], [4.0, 0.0]]]])
    acc = DepthMetrics()
    acc.update(p[:1], g[:1])
    acc.update(p[1:], g[1:])
    r = acc.compute()
    assert list(r) == list(METRICS)
    assert r["abs_rel"] == pytest.approx(0.5)  # mean over images of (1, 0)
    assert r["mape"] == pytest.approx(0.25)  # pooled over 4 pixels: (1 + 0 + 0 + 0) / 4
    assert r["rmse"] == pytest.approx(0.5)  # per-image RMSE (1, 0) averaged
    assert r["delta1"] == pytest.approx(0.5)
    assert acc.count == 2
    # an image without valid pixels does not count
    acc.update(torch.ones(1, 1, 2, 2), torch.zeros(1, 1, 2, 2))
    assert acc.count == 2 and acc.compute()["rmse"] == pytest.approx(0.5)
    # all-reduce contract: summing two states averages over all images
    both = acc.compute(acc.state * 2)
    assert both["rmse"] == pytest.approx(0.5)


def test_empty_and_shape_errors():
    assert math.isnan(DepthMetrics().compute()["rmse"])
    with pytest.raises(ValueError, match="pred has shape"):
        image_metrics(torch.ones(1, 1, 2, 2), torch.ones(1, 1, 2, 3))


def test_format_table_layout():
    row = dict(zip(METRICS, (0.5, 0.075, 0.119, 0.328, 0.121, 0.868, 0.966, 0.987), strict=True))
    t = format_table({"RGB / Ours": {**row, "ms": 3.764}})
    lines = t.splitlines()
    assert lines[0].startswith("| method | RMSE [m] | iRMSE [1/m]")
    assert lines[2] == "| RGB / Ours | 0.500 | 0.075 | 0.119 | 0.328 | 0.121 | 86.8% | 96.6% | 98.7% | 3.76 |"
