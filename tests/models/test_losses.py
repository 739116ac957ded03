"""Eq. 6-8 on hand-made tensors (models/losses.py)."""

import math

import pytest
import torch

from models.losses import kld_loss, l1_loss, rec_loss, total_loss

torch.set_num_threads(1)

D = torch.tensor([[1.0, 2.0], [3.0, 4.0]]).view(1, 1, 2, 2)
B = torch.tensor([[1.0, 2.0], [0.5, 1.0]]).view(1, 1, 2, 2)
GT = torch.tensor([[2.0, 0.0], [2.0, 5.0]]).view(1, 1, 2, 2)  # pixel (0, 1) invalid
# valid pixels: |1-2|/1 + log 1 = 1;  |3-2|/0.5 + log 0.5;  |4-5|/1 + log 1 = 1
PX = [1.0, 2.0 + math.log(0.5), 1.0]


def test_rec_loss_known_values():
    assert rec_loss(D, B, GT).item() == pytest.approx(sum(PX) / 3)
    valid = torch.tensor([[True, True], [True, False]]).view(1, 1, 2, 2)
    assert rec_loss(D, B, GT, valid).item() == pytest.approx((PX[0] + PX[1]) / 2)
    # mean over all valid pixels of the batch (|Omega|), not a mean of per-image means
    d2 = torch.cat([D, torch.full_like(D, 2.0)])
    b2 = torch.cat([B, torch.ones_like(B)])
    g2 = torch.cat([GT, torch.tensor([[2.0, 0.0], [0.0, 0.0]]).view(1, 1, 2, 2)])
    assert rec_loss(d2, b2, g2).item() == pytest.approx((sum(PX) + 0.0) / 4)


def test_rec_loss_optimal_uncertainty_is_the_error():
    # d/dB (e / B + log B) = 0 at B = e (Laplace maximum likelihood)
    b = torch.tensor([0.5, 2.0, 0.25]).view(1, 1, 1, 3).requires_grad_(True)
    d = torch.tensor([1.5, 1.0, 3.0]).view(1, 1, 1, 3)
    g = torch.tensor([1.0, 3.0, 3.25]).view(1, 1, 1, 3)
    rec_loss(d, b, g).backward()
    torch.testing.assert_close(b.grad, torch.zeros_like(b), atol=1e-6, rtol=0)


def test_l1_and_empty_masks():
    assert l1_loss(D, GT).item() == pytest.approx((1 + 1 + 1) / 3)
    d = D.clone().requires_grad_(True)
    zero = rec_loss(d, B, torch.zeros_like(GT))
    assert zero.item() == 0.0
    zero.backward()  # still part of the graph
    assert torch.equal(d.grad, torch.zeros_like(D))
    assert l1_loss(D, torch.zeros_like(GT)).item() == 0.0
    with pytest.raises(ValueError, match="uncertainty has shape"):
        rec_loss(D, B[..., :1], GT)


def test_kld_known_values():
    assert kld_loss(torch.zeros(3, 8), torch.zeros(3, 8)).item() == 0.0
    mu = torch.tensor([[1.0, 0.0], [0.0, 0.0]])
    logvar = torch.tensor([[0.0, math.log(2.0)], [0.0, 0.0]])
    # row 0: 0.5 * [(1 + 1 - 0 - 1) + (0 + 2 - log 2 - 1)]; row 1: 0; mean over the batch
    expected = 0.5 * (1.0 + 1.0 - math.log(2.0)) / 2
    assert kld_loss(mu, logvar).item() == pytest.approx(expected)
    assert kld_loss(mu, logvar).item() > 0
    with pytest.raises(ValueError, match="mu and logvar"):
        kld_loss(mu, logvar[:, :1])


def test_total_loss_parts():
    mu = torch.tensor([[1.0, 0.0]])
    logvar = torch.zeros(1, 2)
    out = {"depth": D, "uncertainty": B, "mu": mu, "logvar": logvar}
    total, parts = total_loss(out, GT, kl_weight=0.1)
    assert parts["rec"].item() == pytest.approx(sum(PX) / 3)
    assert parts["kld"].item() == pytest.approx(0.5)
    assert total.item() == pytest.approx(sum(PX) / 3 + 0.05)
    assert parts["total"].item() == pytest.approx(total.item())
    # FastDepth: no uncertainty, no code -> L1 and zero KL
    total, parts = total_loss({"depth": D, "uncertainty": None, "mu": None, "logvar": None}, GT)
    assert total.item() == pytest.approx(1.0) and parts["kld"].item() == 0.0
