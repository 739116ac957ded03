"""Depth metrics of the paper's Table 1 (Sec. 6.1), sparse-to-dense conventions.

Per image, over the valid pixels ``gt > 0`` (predictions are clamped to at least ``EPS`` metres):

* ``rmse``    sqrt(mean((p - g)^2))                       [m]
* ``irmse``   sqrt(mean((1/p - 1/g)^2))                   [1/m]  (inverse depth in 1/m, NOT 1/km)
* ``abs_rel`` mean(|p - g| / g)                            [-]
* ``mae``     mean(|p - g|)                                [m]
* ``delta_k`` mean(max(p/g, g/p) < 1.25^k), k = 1, 2, 3    [fraction]

These are averaged over images (each image with at least one valid pixel counts once), as sparse-to-dense's
``AverageMeter`` with validation batch 1. ``mape`` (mean absolute percentage error, as a fraction) is the same
ratio ``|p - g| / g`` pooled over all valid pixels of the whole set (a pixel-weighted mean, so it differs from
``abs_rel`` when images have different numbers of valid pixels; the paper reports both). Inference time per
frame is measured by :mod:`train.evaluate` and logged by the LightningModule, not here.
"""

from __future__ import annotations

import torch

__all__ = ["METRICS", "EPS", "image_metrics", "DepthMetrics", "format_table"]

#: Metric names in Table 1 order (``ms`` is added by the evaluation).
METRICS = ("rmse", "irmse", "abs_rel", "mae", "mape", "delta1", "delta2", "delta3")
_PER_IMAGE = ("rmse", "irmse", "abs_rel", "mae", "delta1", "delta2", "delta3")
#: Smallest predicted depth used in ratios and inverses [m].
EPS = 1e-3


def image_metrics(pred: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-image metrics.

    Args:
        pred: predicted depth (B, 1, H, W) or (B, H, W) [m].
        gt: ground-truth depth, same shape [m], 0 = invalid.

    Returns:
        dict of (B,) float64 tensors: the per-image metrics above, ``n`` (valid pixel count) and ``are_sum``
        (sum of |p - g| / g, for the pooled MAPE). Images without valid pixels have ``n = 0`` and metric 0.

    >>> p = torch.tensor([[[1.0, 2.0], [4.5, 9.0]]]); g = torch.tensor([[[1.0, 1.0], [5.0, 0.0]]])
    >>> m = image_metrics(p, g)  # 3 valid pixels, errors 0, 1, -0.5
    >>> round(float(m["rmse"]), 6), float(m["mae"]), round(float(m["delta1"]), 6)
    (0.645497, 0.5, 0.666667)
    """
    if pred.shape != gt.shape:
        raise ValueError(f"pred has shape {tuple(pred.shape)}, gt has {tuple(gt.shape)}")
    b = pred.shape[0]
    p = pred.detach().reshape(b, -1).double().clamp(min=EPS)
    g = gt.detach().reshape(b, -1).double()
    valid = g > 0
    n = valid.sum(1).double()
    nn = n.clamp(min=1)
    gs = torch.where(valid, g, torch.ones_like(g))
    err = torch.where(valid, p - g, torch.zeros_like(g))
    ierr = torch.where(valid, 1.0 / p - 1.0 / gs, torch.zeros_like(g))
    are = err.abs() / gs
    ratio = torch.maximum(p / gs, gs / p)
    out = {
        "rmse": (err.square().sum(1) / nn).sqrt(),
        "irmse": (ierr.square().sum(1) / nn).sqrt(),
        "abs_rel": are.sum(1) / nn,
        "mae": err.abs().sum(1) / nn,
    }
    for k in (1, 2, 3):
        out[f"delta{k}"] = ((ratio < 1.25**k) & valid).sum(1).double() / nn
    out["n"] = n
    out["are_sum"] = are.sum(1)
    return out


class DepthMetrics:
    """Accumulates :func:`image_metrics` over a data set; one flat float64 state, so DDP can all-reduce it.

    >>> acc = DepthMetrics()
    >>> _ = acc.update(torch.full((2, 1, 4, 4), 2.0), torch.full((2, 1, 4, 4), 2.0))
    >>> acc.compute()["rmse"], acc.compute()["delta1"], acc.count
    (0.0, 1.0, 2)
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        # [images, sum of per-image metrics..., valid pixels, sum of abs rel errors]
        self.state = torch.zeros(len(_PER_IMAGE) + 3, dtype=torch.float64)

    @property
    def count(self) -> int:
        return int(self.state[0])

    def update(self, pred: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
        """Add a batch; returns its per-image metrics."""
        m = image_metrics(pred, gt)
        has = (m["n"] > 0).double()
        vec = torch.stack(
            [has.sum()] + [(m[k] * has).sum() for k in _PER_IMAGE] + [m["n"].sum(), m["are_sum"].sum()]
        )
        self.state = self.state + vec.cpu()
        return m

    def compute(self, state: torch.Tensor | None = None) -> dict[str, float]:
        """Mean metrics (``state`` e.g. the all-reduced state of several processes); NaN when empty."""
        s = self.state if state is None else state.detach().cpu().double()
        k = float(s[0])
        out = {name: (float(s[1 + i]) / k if k > 0 else float("nan")) for i, name in enumerate(_PER_IMAGE)}
        npx = float(s[-2])
        out["mape"] = float(s[-1]) / npx if npx > 0 else float("nan")
        return {name: out[name] for name in METRICS}


def format_table(rows: dict[str, dict[str, float]], first: str = "method") -> str:
    """Markdown table in Table 1's layout: one row per entry, RMSE ... delta3 [and ``ms`` when present].

    Deltas are printed in percent, the rest with 3 decimals (units: m, 1/m, -, m, -, %).
    """
    has_ms = any("ms" in r for r in rows.values())
    head = [first, "RMSE [m]", "iRMSE [1/m]", "AbsRel", "MAE [m]", "MAPE", "d1", "d2", "d3"]
    if has_ms:
        head.append("ms/frame")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in rows.items():
        cells = [name] + [f"{r[k]:.3f}" for k in METRICS[:5]] + [f"{100 * r[k]:.1f}%" for k in METRICS[5:]]
        if has_ms:
            cells.append(f"{r['ms']:.2f}" if "ms" in r else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
