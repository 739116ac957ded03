"""Ablation baselines of the paper's Table 1.

* ``codevio8`` / ``codevio32``: the same two-stream CVAE as :class:`~models.ditnet.DiTNet` without attention
  (additive skips, no CBAM), code dimension 8 / 32.
* ``fastdepth``: FastDepth (Wofk et al. 2019): MobileNet encoder + NNConv5 decoder (5 x [depthwise-separable
  5x5 conv, nearest x2] with FastDepth's channels 1024 -> 512 -> 256 -> 128 -> 64 -> 32 times the width
  multiplier), additive skips from the encoder at strides 8, 4, 2, a 1x1 head; it regresses depth directly (no
  code, no uncertainty) and is trained with L1. Its output uses the same bounded log-depth as DiTNet, so depth
  is positive and in range.

Every baseline also takes DiTNet's relative formulation (``relative=True``, sparse modalities): the input in units
of the samples' scale and a bounded log correction of the interpolated sparse input (see :mod:`models.ditnet`),
so that a Table 1 can compare the architectures under one formulation.
"""

from __future__ import annotations

import torch
from torch import nn

from models.blocks import (
    BoundedLogDepth,
    DWSepConv,
    InputNorm,
    MobileNetEncoder,
    RelativeSparseNorm,
    check_size,
    init_weights,
    linear_fill,
    modality_of,
    scaled_channels,
)
from models.ditnet import DEPTH_INIT, DEPTH_MAX, DEPTH_MIN, DiTNet, relative_depth


def codevio(
    in_channels: int,
    code_dim: int,
    width_mult: float = 1.0,
    height: int = 224,
    width: int = 224,
    relative: bool = False,
) -> DiTNet:
    """CodeVIO-style network: :class:`DiTNet` with ``attention=False`` (additive skips, no CBAM)."""
    return DiTNet(
        in_channels,
        code_dim=code_dim,
        attention=False,
        width_mult=width_mult,
        height=height,
        width=width,
        relative=relative,
    )


def codevio8(in_channels: int, width_mult: float = 1.0, height: int = 224, width: int = 224) -> DiTNet:
    """CodeVIO (8D) of Table 1: no attention, C = 8."""
    return codevio(in_channels, 8, width_mult, height, width)


def codevio32(in_channels: int, width_mult: float = 1.0, height: int = 224, width: int = 224) -> DiTNet:
    """CodeVIO (32D) of Table 1: no attention, C = 32."""
    return codevio(in_channels, 32, width_mult, height, width)


class FastDepth(nn.Module):
    """FastDepth-style direct depth regression.

    Args:
        in_channels: 1 ``gray``, 2 ``grays``, 3 ``rgb``, 4 ``rgbs`` (same raw input as DiTNet).
        width_mult: MobileNet and decoder channel multiplier.
        height, width: nominal input size [px] (multiples of 32); the network is fully convolutional
            and accepts any multiple of 32 at run time.
        relative: sparse modalities: DiTNet's relative formulation, ``depth = fill * exp(K tanh(x / K))`` with
            the encoder reading the input in units of the samples' scale (:class:`~models.blocks.RelativeSparseNorm`).

    ``forward(image, gt_depth=None, code=None, fill=None)`` returns the DiTNet dict with ``depth`` (B, 1, H, W)
    [m] and ``uncertainty``, ``mu``, ``logvar``, ``code`` all None (``gt_depth`` and ``code`` are accepted and
    ignored, so that training code can treat every model alike). ``fill``: relative mode, the interpolated sparse
    channel (:func:`~models.blocks.linear_fill`, computed when not given).

    >>> import torch
    >>> m = FastDepth(2, width_mult=0.25, height=64, width=64, relative=True).eval()
    >>> x = torch.rand(1, 2, 64, 64); x[:, 1] = 0.0; x[0, 1, 10, 10], x[0, 1, 40, 50] = 1.0, 3.0
    >>> d1, d2 = m(x)["depth"], m(x * torch.tensor([1.0, 2.0])[None, :, None, None])["depth"]
    >>> bool(torch.allclose(d2, 2 * d1, rtol=1e-4))  # the scale of the sparse input carries through
    True
    """

    code_dim = None

    def __init__(
        self,
        in_channels: int,
        width_mult: float = 1.0,
        height: int = 224,
        width: int = 224,
        depth_min: float = DEPTH_MIN,
        depth_max: float = DEPTH_MAX,
        relative: bool = False,
    ):
        super().__init__()
        check_size(height, width)
        self.modality = modality_of(in_channels)
        self.in_channels = in_channels
        self.width_mult = float(width_mult)
        self.height, self.width = height, width
        self.depth_min, self.depth_max = float(depth_min), float(depth_max)
        self.relative = bool(relative)
        self.norm = RelativeSparseNorm(self.modality) if relative else InputNorm(self.modality, depth_min, depth_max)
        self.encoder = MobileNetEncoder(self.norm.out_channels, width_mult)
        ch = [scaled_channels(c, width_mult) for c in (1024, 512, 256, 128, 64, 32)]
        self.decode = nn.ModuleList([DWSepConv(ch[i], ch[i + 1], 5) for i in range(5)])
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.head = nn.Conv2d(ch[5], 1, 1)
        self.to_depth = BoundedLogDepth(depth_min, depth_max)
        self.apply(init_weights)
        nn.init.normal_(self.head.weight, 0.0, 0.01)
        if relative:
            nn.init.zeros_(self.head.bias)  # depth = fill at initialisation
        else:
            nn.init.constant_(self.head.bias, self.to_depth.inverse_logit(DEPTH_INIT))

    def forward(
        self,
        image: torch.Tensor,
        gt_depth: torch.Tensor | None = None,
        code: torch.Tensor | None = None,
        fill: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor | None]:
        if image.dim() != 4 or image.shape[1] != self.in_channels:
            raise ValueError(f"image must have shape (B, {self.in_channels}, H, W), got {tuple(image.shape)}")
        check_size(int(image.shape[2]), int(image.shape[3]))
        if self.relative:
            fill = linear_fill(image[:, -1:]) if fill is None else fill
            x, _ = self.norm(image, fill)
        elif fill is not None:
            raise ValueError("only a relative FastDepth takes a fill")
        else:
            x = self.norm(image)
        e = self.encoder(x)  # strides 2, 4, 8, 16, 32
        x = e[4]
        skips = {1: e[2], 2: e[1], 3: e[0]}  # after decode i: stride 8, 4, 2 (FastDepth's x3, x2, x1)
        for i, layer in enumerate(self.decode):
            x = self.up(layer(x))
            if i in skips:
                x = x + skips[i]
        if self.relative:
            depth = relative_depth(torch.log(fill.clamp(min=1e-6)), self.head(x))
        else:
            depth = self.to_depth(self.head(x))
        return {"depth": depth, "uncertainty": None, "mu": None, "logvar": None, "code": None}

    def describe(self) -> dict:
        """Input/output conventions (JSON-serialisable), as :meth:`DiTNet.describe`."""
        return {
            "model": "fastdepth",
            "modality": self.modality,
            "in_channels": self.in_channels,
            "code_dim": None,
            "width_mult": self.width_mult,
            "height": self.height,
            "width": self.width,
            "relative": self.relative,
            "input": {
                "image_range": [0.0, 1.0],
                "image_mean": self.norm.mean.flatten().tolist(),
                "image_std": self.norm.std.flatten().tolist(),
                "sparse_depth": "metres, 0 = no sample" if self.norm.sparse else None,
            },
            "depth": {
                "parametrisation": "depth = depth_min * (depth_max / depth_min) ** sigmoid(x)",
                "unit": "m",
                "depth_min": self.depth_min,
                "depth_max": self.depth_max,
            },
        }


def fastdepth(
    in_channels: int, width_mult: float = 1.0, height: int = 224, width: int = 224, relative: bool = False
) -> FastDepth:
    """FastDepth of Table 1 (direct regression, L1)."""
    return FastDepth(in_channels, width_mult, height, width, relative=relative)
