"""Network building blocks (paper Sec. 4): depthwise-separable convs, MobileNet, CBAM, SK fusion.

Every spatial convolution here is depthwise (``groups == in_channels``); the only dense convolutions are
1x1 (pointwise) ones. CBAM's 7x7 spatial convolution over the two pooled maps is written as a depthwise 7x7
followed by a 1x1 that sums the two maps, which spans exactly the same functions as a dense
``Conv2d(2, 1, 7)``.

Shapes follow torch: images and features are ``(B, C, H, W)``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from runtime.densify import DEFAULT_FILL_M, network_fill

#: Network input channels per modality: image channels in [0, 1], then (``*s``) one sparse-depth channel [m].
MODALITY_CHANNELS: dict[str, int] = {"rgb": 3, "rgbs": 4, "gray": 1, "grays": 2}

#: Input normalisation of the image channels (ImageNet statistics; grey uses their channel mean).
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)
GRAY_MEAN = (0.449,)
GRAY_STD = (0.226,)

#: MobileNet v1 body after the stem: (output channels, stride) of each depthwise-separable layer.
_MOBILENET_V1 = (
    (64, 1),  # 1: stride 2 (skip "s2")
    (128, 2),
    (128, 1),  # 3: stride 4 (skip "s4")
    (256, 2),
    (256, 1),  # 5: stride 8 (skip "s8")
    (512, 2),
    (512, 1),
    (512, 1),
    (512, 1),
    (512, 1),
    (512, 1),  # 11: stride 16 (skip "s16")
    (1024, 2),
    (1024, 1),  # 13: stride 32
)
#: Indices (1-based, stem = 0) of the layers whose outputs MobileNet returns, strides 2, 4, 8, 16, 32.
_MOBILENET_TAPS = (1, 3, 5, 11, 13)


def modality_of(in_channels: int) -> str:
    """Modality name for a number of network input channels (1, 2, 3 or 4).

    >>> modality_of(2)
    'grays'
    """
    for name, ch in MODALITY_CHANNELS.items():
        if ch == in_channels:
            return name
    raise ValueError(f"in_channels={in_channels!r} matches no modality {MODALITY_CHANNELS}")


def scaled_channels(channels: int, width_mult: float, divisor: int = 8) -> int:
    """Channels times the width multiplier, rounded to a multiple of ``divisor`` (at least ``divisor``).

    Same rounding as MobileNet v2's ``_make_divisible``: never more than 10% below ``channels * width_mult``.

    >>> scaled_channels(1024, 0.25), scaled_channels(32, 0.5), scaled_channels(64, 1.0)
    (256, 16, 64)
    """
    if not width_mult > 0:
        raise ValueError(f"width_mult must be > 0, got {width_mult!r}")
    v = channels * width_mult
    out = max(divisor, int(v + divisor / 2) // divisor * divisor)
    if out < 0.9 * v:
        out += divisor
    return out


def check_size(height: int, width: int, multiple: int = 32) -> None:
    """Raise ``ValueError`` unless ``height`` and ``width`` are positive multiples of ``multiple`` [px]."""
    for name, v in (("height", height), ("width", width)):
        if not isinstance(v, int) or v <= 0 or v % multiple:
            raise ValueError(f"{name}={v!r} must be a positive multiple of {multiple} (the encoder's stride)")


class ConvBNReLU(nn.Sequential):
    """One convolution + BatchNorm + ReLU; only depthwise (``groups=in_ch``) or pointwise (``kernel=1``)."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int = 1, stride: int = 1, groups: int = 1):
        if not (groups == in_ch or kernel == 1):
            raise ValueError(f"dense {kernel}x{kernel} conv ({in_ch}->{out_ch}): only depthwise or 1x1 allowed")
        super().__init__(
            nn.Conv2d(in_ch, out_ch, kernel, stride, padding=kernel // 2, groups=groups, bias=False),
            nn.BatchNorm2d(out_ch),
            nn.ReLU(inplace=True),
        )


class DWSepConv(nn.Sequential):
    """Depthwise-separable convolution: depthwise kxk + BN + ReLU, then pointwise 1x1 + BN + ReLU.

    Args:
        in_ch: input channels.
        out_ch: output channels.
        kernel: depthwise kernel size (odd), 'same' padding.
        stride: depthwise stride.
        depth_mult: depthwise channel multiplier (``in_ch * depth_mult`` depthwise outputs, still
            ``groups == in_ch``); MobileNet's stem uses it so that a 1-channel grey input gets several
            filters.

    Shapes: ``(B, in_ch, H, W) -> (B, out_ch, H / stride, W / stride)``.
    """

    def __init__(self, in_ch: int, out_ch: int, kernel: int = 3, stride: int = 1, depth_mult: int = 1):
        mid = in_ch * depth_mult
        super().__init__(
            ConvBNReLU(in_ch, mid, kernel, stride, groups=in_ch),
            ConvBNReLU(mid, out_ch, 1),
        )


class MobileNetEncoder(nn.Module):
    """MobileNet v1 with every layer depthwise-separable (the stem too), returning multi-scale features.

    Args:
        in_channels: input channels (already normalised).
        width_mult: channel multiplier of every layer (MobileNet's alpha).
        stem_depth_mult: depthwise multiplier of the stem's 3x3 stride-2 depthwise conv.

    Forward: ``(B, in_channels, H, W)`` with H, W multiples of 32 -> tuple of 5 features at strides
    2, 4, 8, 16, 32 with ``self.channels`` channels (64, 128, 256, 512, 1024 times ``width_mult``).
    """

    def __init__(self, in_channels: int, width_mult: float = 1.0, stem_depth_mult: int = 8):
        super().__init__()
        if in_channels < 1:
            raise ValueError(f"in_channels={in_channels!r} must be >= 1")
        c = scaled_channels(32, width_mult)
        layers = [DWSepConv(in_channels, c, 3, 2, depth_mult=stem_depth_mult)]
        for out, stride in _MOBILENET_V1:
            o = scaled_channels(out, width_mult)
            layers.append(DWSepConv(c, o, 3, stride))
            c = o
        self.layers = nn.ModuleList(layers)
        self.channels = tuple(scaled_channels(_MOBILENET_V1[i - 1][0], width_mult) for i in _MOBILENET_TAPS)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        feats = []
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i in _MOBILENET_TAPS:
                feats.append(x)
        return tuple(feats)


class UpBlock(nn.Sequential):
    """Upsampling: nearest x2, then depthwise-separable 5x5 conv. ``(B,in,H,W) -> (B,out,2H,2W)``."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__(nn.Upsample(scale_factor=2, mode="nearest"), DWSepConv(in_ch, out_ch, 5))


class ChannelAttention(nn.Module):
    """CBAM channel attention ``M_c``: shared MLP on average- and max-pooled features, sigmoid.

    ``(B, C, H, W) -> (B, C, 1, 1)`` in (0, 1).
    """

    def __init__(self, channels: int, reduction: int = 8, min_hidden: int = 4):
        super().__init__()
        hidden = max(channels // reduction, min_hidden)
        self.mlp = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        avg = self.mlp(x.mean(dim=(2, 3)))  # (B, C)
        mx = self.mlp(x.amax(dim=(2, 3)))  # (B, C)
        return torch.sigmoid(avg + mx)[:, :, None, None]


class SpatialAttention(nn.Module):
    """CBAM spatial attention ``M_s``: 7x7 conv over the [channel mean, channel max] maps, sigmoid.

    The 7x7 conv is depthwise (2 maps) + a 1x1 summing them: the same function class as ``Conv2d(2, 1, 7)``.
    ``(B, C, H, W) -> (B, 1, H, W)`` in (0, 1).
    """

    def __init__(self, kernel: int = 7):
        super().__init__()
        self.dw = nn.Conv2d(2, 2, kernel, padding=kernel // 2, groups=2, bias=False)
        self.pw = nn.Conv2d(2, 1, 1, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)  # (B, 2, H, W)
        return torch.sigmoid(self.pw(self.dw(pooled)))


class CBAM(nn.Module):
    """Convolutional block attention with the paper's residual (Eq. 3).

    ``F_c = M_c(F) * F``, ``F_s = M_s(F_c) * F_c``, ``F_refined = F_s + F``. Shape-preserving.
    """

    def __init__(self, channels: int, reduction: int = 8, kernel: int = 7):
        super().__init__()
        self.channel = ChannelAttention(channels, reduction)
        self.spatial = SpatialAttention(kernel)

    def maps(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The two attention maps ``(M_c(F) (B,C,1,1), M_s(F_c) (B,1,H,W))`` for input ``F = x``."""
        mc = self.channel(x)
        return mc, self.spatial(mc * x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        fc = self.channel(x) * x
        return self.spatial(fc) * fc + x


class SKFusion(nn.Module):
    """SK-like fusion of two same-shape branches (Eq. 4-5), replacing ``F1 + F2``.

    ``S = AVG(F1 + F2)`` (B, C); ``Z = ReLU(FC(S))`` (B, d); ``[A1, A2] = softmax([FC1(Z), FC2(Z)])``
    across the two branches, per channel; output ``A1 * F1 + A2 * F2``. ``d = max(C // reduction, min_dim)``.
    Either input may have batch 1 while the other has batch B (broadcast).
    """

    def __init__(self, channels: int, reduction: int = 8, min_dim: int = 16):
        super().__init__()
        d = max(channels // reduction, min_dim)
        self.fc = nn.Sequential(nn.Linear(channels, d), nn.ReLU(inplace=True))
        self.fc1 = nn.Linear(d, channels)
        self.fc2 = nn.Linear(d, channels)

    def weights(self, f1: torch.Tensor, f2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Attention ``(A1, A2)``, each (B, C, 1, 1) in (0, 1), ``A1 + A2 = 1``."""
        s = (f1 + f2).mean(dim=(2, 3))  # (B, C)
        z = self.fc(s)  # (B, d)
        a = torch.softmax(torch.stack([self.fc1(z), self.fc2(z)], dim=0), dim=0)  # (2, B, C)
        return a[0, :, :, None, None], a[1, :, :, None, None]

    def forward(self, f1: torch.Tensor, f2: torch.Tensor) -> torch.Tensor:
        a1, a2 = self.weights(f1, f2)
        return a1 * f1 + a2 * f2


class AddFusion(nn.Module):
    """Plain additive skip (the no-attention baselines): ``F1 + F2``."""

    def forward(self, f1: torch.Tensor, f2: torch.Tensor) -> torch.Tensor:
        return f1 + f2


def match_contrast(img: torch.Tensor, target_std: float, min_std: float = 0.01) -> torch.Tensor:
    """Each image's channels rescaled about their own mean to standard deviation ``target_std``, clipped to [0, 1].

    Keeps each image's brightness and removes its absolute contrast, which differs between cameras and scenes far
    more than the network's training renders show. ``min_std`` bounds the gain on a flat image.

    >>> x = torch.tensor([0.2, 0.4, 0.6, 0.8]).view(1, 1, 2, 2)
    >>> y = match_contrast(x, 0.05)
    >>> round(float(y.mean()), 4), round(float(y.std(unbiased=False)), 4)
    (0.5, 0.05)
    """
    mean = img.mean(dim=(2, 3), keepdim=True)
    std = img.std(dim=(2, 3), keepdim=True, unbiased=False).clamp(min=min_std)
    return (mean + (img - mean) * (target_std / std)).clamp(0.0, 1.0)


class _ImageInput(nn.Module):
    """The image part of the raw input, shared by the input normalisations: ``modality``, ``image_channels``, the
    fixed ``mean`` / ``std`` buffers and the optional contrast matching, applied by :meth:`image`."""

    def __init__(self, modality: str, image_contrast: float | None = None):
        super().__init__()
        if modality not in MODALITY_CHANNELS:
            raise ValueError(f"modality={modality!r} not in {sorted(MODALITY_CHANNELS)}")
        if image_contrast is not None and not 0.0 < float(image_contrast) <= 0.5:
            raise ValueError(f"image_contrast={image_contrast!r} must be None or a standard deviation in (0, 0.5]")
        self.modality = modality
        rgb = modality.startswith("rgb")
        self.image_channels = 3 if rgb else 1
        self.register_buffer("mean", torch.tensor(RGB_MEAN if rgb else GRAY_MEAN).view(1, -1, 1, 1))
        self.register_buffer("std", torch.tensor(RGB_STD if rgb else GRAY_STD).view(1, -1, 1, 1))
        self.image_contrast = None if image_contrast is None else float(image_contrast)

    def image(self, x: torch.Tensor) -> torch.Tensor:
        """The image channels of the raw input, normalised."""
        img = x[:, : self.image_channels]
        if self.image_contrast is not None:
            img = match_contrast(img, self.image_contrast)
        return (img - self.mean) / self.std


class InputNorm(_ImageInput):
    """Raw network input -> normalised encoder input; the constants are buffers, so ONNX takes raw inputs.

    Input ``(B, Cin, H, W)``: image channels in [0, 1] (1 grey or 3 RGB), then for ``*s`` modalities one
    sparse-depth channel in metres (0 = no sample). Output: ``(image - mean) / std``, and for ``*s`` two more
    channels: the log depth mapped to [-1, 1] over [``depth_min``, ``depth_max``] (0 where no sample) and the
    sample mask (1 where a sample exists). With ``image_contrast`` the image first goes through
    :func:`match_contrast`.
    """

    def __init__(self, modality: str, depth_min: float, depth_max: float, image_contrast: float | None = None):
        super().__init__(modality, image_contrast)
        self.sparse = modality.endswith("s")
        self.depth_log = LogDepthNorm(depth_min, depth_max)
        self.out_channels = self.image_channels + (2 if self.sparse else 0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        img = self.image(x)
        if not self.sparse:
            return img
        return torch.cat([img, *self.depth_log(x[:, self.image_channels :])], dim=1)


def sample_scale(sparse: torch.Tensor, default_depth: float = DEFAULT_FILL_M) -> tuple[torch.Tensor, torch.Tensor]:
    """Sparse depth (B, 1, H, W) [m, 0 = none] -> (sample mask, scale (B, 1, 1, 1) [m]).

    The scale is the geometric mean of the samples ``exp(mean log d)``, ``default_depth`` without samples (the
    constant :func:`linear_fill` gives then, so that the relative input is 0).

    >>> sp = torch.zeros(1, 1, 4, 4); sp[0, 0, 0, 0] = 2.0; sp[0, 0, 3, 3] = 8.0
    >>> mask, scale = sample_scale(sp)
    >>> int(mask.sum()), float(scale)
    (2, 4.0)
    """
    mask = (sparse > 0).to(sparse.dtype)
    n = mask.sum(dim=(2, 3), keepdim=True)
    logsum = (torch.log(sparse.clamp(min=1e-6)) * mask).sum(dim=(2, 3), keepdim=True)
    scale = torch.where(n > 0, torch.exp(logsum / n.clamp(min=1.0)), torch.full_like(n, float(default_depth)))
    return mask, scale


def linear_fill(sparse: torch.Tensor) -> torch.Tensor:
    """Sparse depth (B, 1, H, W) [m] -> its interpolation (B, 1, H, W) [m], no gradient.

    :func:`runtime.densify.network_fill` per image (linear over the samples' triangulation, nearest outside
    their hull; a constant without samples). Computed with scipy on the CPU: it is an input of the relative
    network (``prior.onnx`` takes it as ``fill``), not part of the graph.
    """
    if sparse.dim() != 4 or sparse.shape[1] != 1:
        raise ValueError(f"sparse must have shape (B, 1, H, W), got {tuple(sparse.shape)}")
    out = np.stack([network_fill(x) for x in sparse.detach().float().cpu().numpy()[:, 0]])
    return torch.from_numpy(out)[:, None].to(sparse.device, sparse.dtype)


class RelativeSparseNorm(_ImageInput):
    """Raw ``*s`` input + its fill -> encoder input in units of the samples' scale, plus the scale.

    Output channels: ``(image - mean) / std``, then ``log(sparse / scale)`` at samples (0 elsewhere, clamped to
    +-``log_range``), the sample mask, and ``log(fill / scale)``, the fill being :func:`linear_fill` of the sparse
    channel. None of them changes when every depth is multiplied by the same factor: the network sees relative
    depth only.

    ``forward(x, fill)`` returns ``(x, scale (B, 1, 1, 1) [m])``. ``image_contrast``: as in :class:`InputNorm`.
    """

    def __init__(self, modality: str, log_range: float = 3.0, image_contrast: float | None = None):
        if modality not in MODALITY_CHANNELS or not modality.endswith("s"):
            raise ValueError(f"relative depth needs a sparse modality (grays, rgbs), got {modality!r}")
        super().__init__(modality, image_contrast)
        self.sparse = True
        self.log_range = float(log_range)
        self.out_channels = self.image_channels + 3

    def forward(self, x: torch.Tensor, fill: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        img = self.image(x)
        sparse = x[:, self.image_channels : self.image_channels + 1]
        mask, scale = sample_scale(sparse)
        r = self.log_range
        rel = torch.log(sparse.clamp(min=1e-6) / scale).clamp(-r, r) * mask
        rel_fill = torch.log(fill.clamp(min=1e-6) / scale).clamp(-r, r)
        return torch.cat([img, rel, mask, rel_fill], dim=1), scale


class LogDepthNorm(nn.Module):
    """Metric depth (0 = invalid) -> (log depth scaled to [-1, 1] and 0 where invalid, validity mask)."""

    def __init__(self, depth_min: float, depth_max: float):
        super().__init__()
        self.depth_min, self.depth_max = float(depth_min), float(depth_max)
        self.center = 0.5 * (math.log(depth_min) + math.log(depth_max))
        self.half_range = 0.5 * (math.log(depth_max) - math.log(depth_min))

    def forward(self, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mask = (depth > 0).to(depth.dtype)
        logd = (torch.log(depth.clamp(self.depth_min, self.depth_max)) - self.center) / self.half_range
        return logd * mask, mask


class BoundedLogDepth(nn.Module):
    """Output parametrisation: ``depth = d_min * (d_max / d_min) ** sigmoid(x)`` [m], in (d_min, d_max).

    Smooth everywhere (no clamp), so finite-difference Jacobians w.r.t. the code never see a flat region
    caused by clipping; ``x = 0`` gives the geometric mean ``sqrt(d_min * d_max)``.
    """

    def __init__(self, depth_min: float, depth_max: float):
        super().__init__()
        if not 0 < depth_min < depth_max:
            raise ValueError(f"need 0 < depth_min < depth_max, got {depth_min!r}, {depth_max!r}")
        self.log_min = math.log(depth_min)
        self.log_span = math.log(depth_max) - math.log(depth_min)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.exp(self.log_min + self.log_span * torch.sigmoid(x))

    def inverse_logit(self, depth: float) -> float:
        """The pre-activation ``x`` giving ``depth`` [m] (used to initialise the head's bias)."""
        s = (math.log(depth) - self.log_min) / self.log_span
        return math.log(s / (1.0 - s))


def init_weights(module: nn.Module) -> None:
    """Kaiming-normal convs (fan-out), unit BN, small-normal linears; applied with ``module.apply``."""
    if isinstance(module, nn.Conv2d):
        nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
        if module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, nn.BatchNorm2d):
        nn.init.ones_(module.weight)
        nn.init.zeros_(module.bias)
    elif isinstance(module, nn.Linear):
        nn.init.normal_(module.weight, 0.0, 0.01)
        nn.init.zeros_(module.bias)


__all__ = [
    "MODALITY_CHANNELS",
    "AddFusion",
    "BoundedLogDepth",
    "CBAM",
    "ChannelAttention",
    "ConvBNReLU",
    "DWSepConv",
    "InputNorm",
    "LogDepthNorm",
    "MobileNetEncoder",
    "RelativeSparseNorm",
    "SKFusion",
    "SpatialAttention",
    "UpBlock",
    "check_size",
    "init_weights",
    "linear_fill",
    "modality_of",
    "sample_scale",
    "scaled_channels",
]
