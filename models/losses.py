"""Training losses (paper Sec. 4.3, Eq. 6-8) and FastDepth's L1.

All depths are metres, shapes ``(B, 1, H, W)``; a ground-truth pixel is valid where ``gt > 0`` (or where an
explicit ``valid`` mask is True). Means are taken over all valid pixels of the batch (Eq. 6's ``|Omega|``).
"""

from __future__ import annotations

import torch


def _valid_mask(gt: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    if valid is None:
        return gt > 0
    if valid.shape != gt.shape:
        raise ValueError(f"valid has shape {tuple(valid.shape)}, gt has {tuple(gt.shape)}")
    return valid.bool() & (gt > 0)


def _check_same(name: str, x: torch.Tensor, gt: torch.Tensor) -> None:
    if x.shape != gt.shape:
        raise ValueError(f"{name} has shape {tuple(x.shape)}, gt has {tuple(gt.shape)}")


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    # No valid pixel: 0, still connected to the graph so that backward() works.
    n = mask.sum()
    return torch.where(n > 0, (x * mask).sum() / n.clamp(min=1), x.sum() * 0.0)


def rec_loss(
    depth: torch.Tensor, uncertainty: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Eq. 6, uncertainty-aware L1 (Laplace negative log-likelihood up to a constant).

    ``L_rec = mean over valid x of |D(x) - gt(x)| / B(x) + log B(x)``.

    Args:
        depth: predicted depth D (B, 1, H, W) [m].
        uncertainty: predicted scale B > 0 (B, 1, H, W) [m].
        gt: ground-truth depth (B, 1, H, W) [m], 0 = invalid.
        valid: optional bool mask (B, 1, H, W), and-ed with ``gt > 0``.

    Returns:
        Scalar tensor; 0 when no pixel is valid.

    >>> d, b = torch.tensor([[[[1.0, 2.0]]]]), torch.tensor([[[[1.0, 0.5]]]])
    >>> g = torch.tensor([[[[2.0, 0.0]]]])
    >>> float(rec_loss(d, b, g))  # only the first pixel is valid: |1 - 2| / 1 + log 1
    1.0
    """
    _check_same("depth", depth, gt)
    _check_same("uncertainty", uncertainty, gt)
    mask = _valid_mask(gt, valid)
    per_px = (depth - gt).abs() / uncertainty + torch.log(uncertainty)
    return _masked_mean(torch.where(mask, per_px, torch.zeros_like(per_px)), mask)


def l1_loss(depth: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error [m] over valid pixels (FastDepth's training loss); 0 when no pixel is valid."""
    _check_same("depth", depth, gt)
    mask = _valid_mask(gt, valid)
    err = (depth - gt).abs()
    return _masked_mean(torch.where(mask, err, torch.zeros_like(err)), mask)


def kld_loss(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """Eq. 7: ``0.5 * sum_i (mu_i^2 + sigma_i^2 - log sigma_i^2 - 1)``, summed over the code, mean over batch.

    Args:
        mu, logvar: (B, C) mean and log-variance ``log sigma^2`` of the code posterior.

    >>> float(kld_loss(torch.zeros(2, 8), torch.zeros(2, 8)))
    0.0
    """
    if mu.shape != logvar.shape or mu.dim() != 2:
        raise ValueError(
            f"mu and logvar must both be (B, C), got {tuple(mu.shape)} and {tuple(logvar.shape)}"
        )
    return 0.5 * (mu.pow(2) + logvar.exp() - logvar - 1.0).sum(dim=1).mean()


def total_loss(
    out: dict, gt: torch.Tensor, kl_weight: float = 1.0, valid: torch.Tensor | None = None
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 8: ``L_total = L_rec + kl_weight * L_KLD`` (paper: ``kl_weight = 1``).

    Args:
        out: a model's output dict (``depth``, ``uncertainty``, ``mu``, ``logvar``). Without uncertainty
            (FastDepth) the reconstruction term is :func:`l1_loss`; without ``mu`` the KL term is 0.
        gt: ground-truth depth (B, 1, H, W) [m], 0 = invalid.
        kl_weight: weight of the KL term (e.g. a warm-up schedule).
        valid: optional extra validity mask.

    Returns:
        ``(total, parts)``: the scalar to back-propagate and detached ``{"rec", "kld", "total"}`` for logging.
    """
    if out.get("uncertainty") is None:
        rec = l1_loss(out["depth"], gt, valid)
    else:
        rec = rec_loss(out["depth"], out["uncertainty"], gt, valid)
    if out.get("mu") is not None:
        kld = kld_loss(out["mu"], out["logvar"])
    else:
        kld = rec.new_zeros(())
    total = rec + kl_weight * kld
    return total, {"rec": rec.detach(), "kld": kld.detach(), "total": total.detach()}
