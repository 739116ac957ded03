"""DiTNet: the two-stream attention CVAE depth network (paper Sec. 3.2 and 4, Fig. 3).

UNet stream (``prior``): raw image [+ sparse depth] -> MobileNet encoder -> decoder with skip connections ->
uncertainty map ``B > 0`` at full resolution, plus the conditioning features of its decoder at strides
32, 16, 8, 4, 2, 1. CVAE stream: at training time a recognition encoder maps the ground-truth depth (and the
UNet bottleneck) to ``mu, logvar`` of a code ``c`` in R^C; the decoder (:class:`DepthDecoder`, the ONNX unit)
maps a code to a dense depth map, fusing the UNet feature at every scale (SK fusion + CBAM, or additive skips
without CBAM when ``attention=False``).

Conventions (also reported by :meth:`DiTNet.describe` for the export manifest):

* Input ``image`` float32 ``(B, Cin, H, W)``: image channels in [0, 1] (grey or RGB), then for ``*s``
  modalities one sparse-depth channel in metres (0 = no sample). Normalisation lives inside (buffers): image
  ``(x - mean) / std``; sparse depth -> log depth scaled to [-1, 1] over [depth_min, depth_max] + sample mask.
  With ``image_contrast`` the image is first rescaled about its own mean to that standard deviation
  (:func:`~models.blocks.match_contrast`), so the network does not see the camera's absolute contrast.
* Depth: ``depth = depth_min * (depth_max / depth_min) ** sigmoid(x)`` metres, default range (0.1, 20) m,
  smooth in the code (no clipping). Uncertainty: ``B = uncertainty_min + softplus(x)`` metres (the scale of
  the Laplace likelihood in Eq. 6), ``uncertainty_min = 0.01`` m.
* Relative depth (``relative=True``, sparse modalities): the fill is the linear interpolation of the sparse
  channel (:func:`~models.blocks.linear_fill`, the tables' interpolation reference), an input of the prior next to
  the image (``prior(image, fill)``; computed from the sparse channel when not given; ``prior.onnx`` takes it as
  ``fill``). Depths are divided by the samples' scale (their geometric mean); the encoder sees the image,
  ``log(sparse / scale)``, the sample mask and ``log(fill / scale)``. The decoder predicts a bounded log
  correction of the fill:
  ``depth = fill * exp(K tanh(x / K))``, ``K = REL_LOG_RANGE``; the uncertainty is ``scale * (u_rel + softplus)``.
  The fill travels to the decoder as the last channel of the stride-1 feature (``log fill``, metres), so the
  exported graphs keep their interface. Multiplying every input depth by ``a`` multiplies depth and
  uncertainty by ``a``: the network cannot ignore the scale of its sparse input.
* H and W are multiples of 32, fixed at construction (the code's fully connected layer maps to the
  stride-32 grid); feeding another size raises ``ValueError``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from models.blocks import (
    CBAM,
    AddFusion,
    BoundedLogDepth,
    ConvBNReLU,
    InputNorm,
    LogDepthNorm,
    MobileNetEncoder,
    RelativeSparseNorm,
    SKFusion,
    UpBlock,
    check_size,
    init_weights,
    linear_fill,
    modality_of,
    scaled_channels,
)

#: Decoder channels at strides 32, 16, 8, 4, 2, 1 (before the width multiplier), shared by both streams.
DECODER_CHANNELS = (256, 128, 64, 32, 16, 16)
#: Strides of the conditioning features, in the order ``prior`` returns them and ``decoder`` takes them.
FEATURE_STRIDES = (32, 16, 8, 4, 2, 1)

DEPTH_MIN = 0.1  # m
DEPTH_MAX = 20.0  # m
UNCERTAINTY_MIN = 0.01  # m
DEPTH_INIT = 2.0  # m, depth predicted at initialisation (head bias)
REL_LOG_RANGE = 2.0  # relative mode: |log(depth / fill)| < 2
REL_UNCERTAINTY_MIN = 0.005  # relative mode: smallest uncertainty as a fraction of the samples' scale
REL_UNCERTAINTY_INIT = 0.05  # relative mode: uncertainty at initialisation, fraction of the samples' scale
REL_GT_RANGE = (math.exp(-2.0), math.exp(2.0))  # relative mode: range of gt / fill seen by the CVAE encoder


def _check_input(x: torch.Tensor, name: str, channels: int, height: int, width: int) -> None:
    if x.dim() != 4 or x.shape[1] != channels or x.shape[2] != height or x.shape[3] != width:
        raise ValueError(
            f"{name} must have shape (B, {channels}, {height}, {width}), got {tuple(x.shape)}"
            + (
                f"; the network was built for {height}x{width}, rebuild it for another size (any multiple of 32)"
                if x.dim() == 4 and x.shape[1] == channels
                else ""
            )
        )


class UNetStream(nn.Module):
    """Image [+ sparse depth] -> (uncertainty (B,1,H,W) [m], features at strides 32..1).

    The decoder starts from a 1x1 projection of the stride-32 encoder output; at strides 16..2 the upsampled
    path is fused with a 1x1 projection of the encoder skip (SK fusion or addition), then refined by CBAM
    (when ``attention``). Each scale's result is one conditioning feature for the CVAE decoder.
    """

    def __init__(
        self,
        modality: str,
        width_mult: float,
        attention: bool,
        depth_min: float,
        depth_max: float,
        decoder_channels: tuple[int, ...] = DECODER_CHANNELS,
        relative: bool = False,
        image_contrast: float | None = None,
    ):
        super().__init__()
        if len(decoder_channels) != len(FEATURE_STRIDES):
            raise ValueError(f"decoder_channels={decoder_channels!r} needs {len(FEATURE_STRIDES)} entries")
        self.relative = bool(relative)
        self.norm = (
            RelativeSparseNorm(modality, image_contrast=image_contrast)
            if relative
            else InputNorm(modality, depth_min, depth_max, image_contrast)
        )
        self.encoder = MobileNetEncoder(self.norm.out_channels, width_mult)
        dec = [scaled_channels(c, width_mult) for c in decoder_channels]
        self.channels = tuple(dec)
        enc = self.encoder.channels  # strides 2, 4, 8, 16, 32
        # 1x1 projections: stride 32 (the start), then skips at strides 16, 8, 4, 2.
        self.proj = nn.ModuleList([ConvBNReLU(enc[4], dec[0])] + [ConvBNReLU(enc[3 - i], dec[1 + i]) for i in range(4)])
        self.ups = nn.ModuleList([UpBlock(dec[i], dec[i + 1]) for i in range(5)])
        self.fuse = nn.ModuleList([(SKFusion(c) if attention else AddFusion()) for c in dec[1:5]])
        self.cbam = nn.ModuleList([(CBAM(c) if attention else nn.Identity()) for c in dec])
        self.head = nn.Conv2d(dec[5], 1, 1)

    def forward(
        self, image: torch.Tensor, fill: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        if self.relative:
            x, scale = self.norm(image, fill)
        else:
            x, scale = self.norm(image), None
        e = self.encoder(x)  # strides 2, 4, 8, 16, 32
        x = self.cbam[0](self.proj[0](e[4]))  # (B, dec0, H/32, W/32)
        feats = [x]
        for i in range(5):
            x = self.ups[i](x)
            if i < 4:
                x = self.fuse[i](x, self.proj[1 + i](e[3 - i]))
            x = self.cbam[1 + i](x)
            feats.append(x)
        if self.relative:
            uncertainty = scale * (REL_UNCERTAINTY_MIN + nn.functional.softplus(self.head(x)))
            feats[-1] = torch.cat([x, torch.log(fill.clamp(min=1e-6))], dim=1)  # + log fill [log m]
        else:
            uncertainty = UNCERTAINTY_MIN + nn.functional.softplus(self.head(x))
        return uncertainty, tuple(feats)


def relative_depth(log_fill: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Relative mode's output: ``fill * exp(K tanh(x / K))`` [m] from ``log fill`` and a head's logit ``x``,
    ``K = REL_LOG_RANGE`` (a bounded log correction of the fill; ``x = 0`` gives the fill)."""
    k = REL_LOG_RANGE
    return torch.exp(log_fill + k * torch.tanh(x / k))


class DepthRecognition(nn.Module):
    """Training-time CVAE encoder: GT depth (B,1,H,W) [m] + UNet stride-32 feature -> (mu, logvar) (B, C).

    A narrow MobileNet reads (normalised log depth, validity mask); its stride-32 output is concatenated with
    the UNet stride-32 feature (the condition), reduced by a 1x1 conv and flattened into a linear layer.
    """

    def __init__(
        self,
        code_dim: int,
        cond_channels: int,
        height: int,
        width: int,
        width_mult: float,
        depth_min: float,
        depth_max: float,
        flat_channels: int = 32,
    ):
        super().__init__()
        self.norm = LogDepthNorm(depth_min, depth_max)
        self.encoder = MobileNetEncoder(2, width_mult)
        self.reduce = ConvBNReLU(self.encoder.channels[4] + cond_channels, flat_channels)
        self.fc = nn.Linear(flat_channels * (height // 32) * (width // 32), 2 * code_dim)
        self.code_dim = code_dim

    def forward(self, depth: torch.Tensor, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.encoder(torch.cat(self.norm(depth), dim=1))[4]
        x = self.reduce(torch.cat([x, cond], dim=1)).flatten(1)
        mu, logvar = self.fc(x).split(self.code_dim, dim=1)
        return mu, logvar


class DepthDecoder(nn.Module):
    """CVAE decoder, the ONNX unit: ``decoder(code (B, C), *features) -> depth (B, 1, H, W)`` [m].

    ``features`` are the six UNet features of :meth:`DiTNet.prior` (strides 32..1, shapes ``feature_shapes``),
    with batch 1 (broadcast to the code batch with ``expand``) or batch B. The code goes through a linear
    layer onto the stride-32 grid; at every scale the path is fused with the feature (SK or addition),
    refined by CBAM (when ``attention``) and upsampled (nearest x2 + depthwise-separable 5x5); a 1x1 head
    and :class:`~models.blocks.BoundedLogDepth` give metres.

    With ``code_injection`` (default) the code is also added after every upsampling as a per-channel bias
    (one linear map per scale), so that it reaches the output directly. Without it the code's effect is
    diluted by the six fusions with image features: at initialisation a unit code moved the depth by ~7 mm,
    and in a 300-step toy run (grey, 64x64, width 0.25, KL weight 1e-3) the posterior collapsed (KL 0.2
    nats; depth error 0.345 m with mu, 0.346 m with code 0), while with injection the code carried the
    ground truth's information (KL 11.2 nats; 0.296 m with mu, 0.449 m with code 0).
    """

    def __init__(
        self,
        code_dim: int,
        channels: tuple[int, ...],
        height: int,
        width: int,
        attention: bool,
        depth_min: float,
        depth_max: float,
        code_injection: bool = True,
        relative: bool = False,
    ):
        super().__init__()
        self.code_dim = code_dim
        self.channels = tuple(channels)
        self.relative = bool(relative)
        self.grid = (height // 32, width // 32)
        extra = [0] * (len(channels) - 1) + [1 if relative else 0]  # relative: log fill at stride 1
        self.feature_shapes = tuple(
            (c + e, height // s, width // s) for c, e, s in zip(channels, extra, FEATURE_STRIDES, strict=True)
        )
        self.fc = nn.Linear(code_dim, channels[0] * self.grid[0] * self.grid[1])
        # code -> per-channel bias at strides 16..1 (see the class docstring)
        self.inject = nn.ModuleList([nn.Linear(code_dim, c) for c in channels[1:]]) if code_injection else None
        self.fuse = nn.ModuleList([(SKFusion(c) if attention else AddFusion()) for c in channels])
        self.cbam = nn.ModuleList([(CBAM(c) if attention else nn.Identity()) for c in channels])
        self.ups = nn.ModuleList([UpBlock(channels[i], channels[i + 1]) for i in range(len(channels) - 1)])
        self.head = nn.Conv2d(channels[-1], 1, 1)
        self.to_depth = BoundedLogDepth(depth_min, depth_max)

    def forward(self, code: torch.Tensor, *features: torch.Tensor) -> torch.Tensor:
        if code.dim() != 2 or code.shape[1] != self.code_dim:
            raise ValueError(f"code must have shape (B, {self.code_dim}), got {tuple(code.shape)}")
        if len(features) != len(self.feature_shapes):
            raise ValueError(f"decoder takes {len(self.feature_shapes)} features, got {len(features)}")
        b = code.shape[0]
        for i, (f, shape) in enumerate(zip(features, self.feature_shapes, strict=True)):
            if f.dim() != 4 or tuple(f.shape[1:]) != shape or not (f.shape[0] == 1 or f.shape[0] == b):
                raise ValueError(
                    f"feature {i} (stride {FEATURE_STRIDES[i]}) must have shape (1 or {b}, {shape[0]}, "
                    f"{shape[1]}, {shape[2]}), got {tuple(f.shape)}"
                )
        log_fill = None
        if self.relative:
            *features, last = features
            features.append(last[:, :-1])
            log_fill = last[:, -1:]  # (1 or B, 1, H, W)
        x = self.fc(code).reshape(-1, self.channels[0], self.grid[0], self.grid[1])  # (B, c0, H/32, W/32)
        for i, f in enumerate(features):
            x = self.cbam[i](self.fuse[i](x, f.expand(b, -1, -1, -1)))
            if i < len(self.ups):
                x = self.ups[i](x)
                if self.inject is not None:
                    x = x + self.inject[i](code)[:, :, None, None]
        if self.relative:
            return relative_depth(log_fill, self.head(x))
        return self.to_depth(self.head(x))


class DiTNet(nn.Module):
    """Two-stream CVAE depth network with CBAM + SK attention (``attention=True``) or additive skips.

    Args:
        in_channels: network input channels: 1 ``gray``, 2 ``grays``, 3 ``rgb``, 4 ``rgbs``.
        code_dim: dimension C of the depth code (paper: 8).
        attention: CBAM + SK fusion (DiT-SLAM) or additive skips without CBAM (CodeVIO-style).
        width_mult: channel multiplier of the UNet encoder and of both decoders.
        height, width: network input size [px], multiples of 32.
        depth_encoder_width: width multiplier of the training-time depth encoder, relative to ``width_mult``.
        depth_min, depth_max: output depth range [m].
        decoder_channels: channels of both decoders at strides 32, 16, 8, 4, 2, 1 (before ``width_mult``).
        code_injection: also add the code to every decoder scale (see :class:`DepthDecoder`).
        relative: predict relative to the densified sparse input (see the module docstring); sparse modalities.

    Attributes: ``in_channels``, ``modality``, ``code_dim``, ``attention``, ``height``, ``width``,
    ``prior_net`` (UNet stream), ``recognition`` (CVAE encoder), ``decoder`` (:class:`DepthDecoder`).

    Example:
        >>> net = DiTNet(2, width_mult=0.25, height=64, width=64).eval()
        >>> out = net(torch.rand(1, 2, 64, 64))
        >>> out["depth"].shape, out["uncertainty"].shape, out["code"].shape
        (torch.Size([1, 1, 64, 64]), torch.Size([1, 1, 64, 64]), torch.Size([1, 8]))
    """

    def __init__(
        self,
        in_channels: int,
        code_dim: int = 8,
        attention: bool = True,
        width_mult: float = 1.0,
        height: int = 224,
        width: int = 224,
        depth_encoder_width: float = 0.25,
        depth_min: float = DEPTH_MIN,
        depth_max: float = DEPTH_MAX,
        decoder_channels: tuple[int, ...] = DECODER_CHANNELS,
        code_injection: bool = True,
        relative: bool = False,
        image_contrast: float | None = None,
    ):
        super().__init__()
        check_size(height, width)
        if not (isinstance(code_dim, int) and code_dim >= 1):
            raise ValueError(f"code_dim={code_dim!r} must be a positive int")
        self.modality = modality_of(in_channels)
        self.in_channels = in_channels
        self.code_dim = code_dim
        self.attention = bool(attention)
        self.width_mult = float(width_mult)
        self.height, self.width = height, width
        self.depth_min, self.depth_max = float(depth_min), float(depth_max)
        self.relative = bool(relative)

        self.prior_net = UNetStream(
            self.modality, width_mult, attention, depth_min, depth_max, decoder_channels, relative, image_contrast
        )
        self.image_contrast = self.prior_net.norm.image_contrast
        ch = self.prior_net.channels
        gt_range = REL_GT_RANGE if relative else (depth_min, depth_max)
        self.recognition = DepthRecognition(code_dim, ch[0], height, width, width_mult * depth_encoder_width, *gt_range)
        self.decoder = DepthDecoder(
            code_dim, ch, height, width, attention, depth_min, depth_max, code_injection, relative
        )

        self.apply(init_weights)
        # code ~ N(0, I): unit-variance activations after the code's linear layers.
        nn.init.normal_(self.decoder.fc.weight, 0.0, 1.0 / math.sqrt(code_dim))
        for layer in self.decoder.inject or ():
            nn.init.normal_(layer.weight, 0.0, 1.0 / math.sqrt(code_dim))
        # Heads start near constant outputs: depth DEPTH_INIT, uncertainty UNCERTAINTY_MIN + softplus(0).
        for head in (self.decoder.head, self.prior_net.head):
            nn.init.normal_(head.weight, 0.0, 0.01)
        if relative:
            nn.init.zeros_(self.decoder.head.bias)  # depth = fill at initialisation
            # uncertainty starts at REL_UNCERTAINTY_INIT of the scale, not at softplus(0) = 69 % of it: Eq. 6 weighs
            # the depth error by 1 / B, and with B that large the correction learned several times slower (one
            # batch overfitted 150 steps: mean |error| 0.085 -> 0.068 m against 0.085 -> 0.039 m with this start).
            b0 = REL_UNCERTAINTY_INIT - REL_UNCERTAINTY_MIN
            nn.init.constant_(self.prior_net.head.bias, math.log(math.expm1(b0)))
        else:
            nn.init.constant_(self.decoder.head.bias, self.decoder.to_depth.inverse_logit(DEPTH_INIT))

    @property
    def feature_shapes(self) -> tuple[tuple[int, int, int], ...]:
        """(C, H, W) of each conditioning feature, strides 32, 16, 8, 4, 2, 1."""
        return self.decoder.feature_shapes

    def prior(
        self, image: torch.Tensor, fill: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """UNet stream: raw input (B,Cin,H,W) -> (uncertainty (B,1,H,W) [m], 6 features (B,C_s,H/s,W/s)).

        ``fill`` (B, 1, H, W) [m], relative mode only: the interpolated sparse channel; default
        :func:`~models.blocks.linear_fill` of it.
        """
        _check_input(image, "image", self.in_channels, self.height, self.width)
        if not self.relative:
            if fill is not None:
                raise ValueError("only a relative DiTNet takes a fill")
            return self.prior_net(image)
        if fill is None:
            fill = linear_fill(image[:, -1:])
        _check_input(fill, "fill", 1, self.height, self.width)
        return self.prior_net(image, fill)

    def encode(
        self, gt_depth: torch.Tensor, cond: torch.Tensor, features: tuple[torch.Tensor, ...] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """CVAE encoder: GT depth (B, 1, H, W) [m, 0 = invalid] + stride-32 feature -> (mu, logvar) (B, C).

        In relative mode the encoder reads ``gt / fill`` (the fill from ``features``, the prior's output).
        """
        _check_input(gt_depth, "gt_depth", 1, self.height, self.width)
        if self.relative:
            if features is None:
                raise ValueError("a relative DiTNet encodes gt / fill: pass the prior's features")
            fill = torch.exp(features[-1][:, -1:])
            gt_depth = torch.where(gt_depth > 0, gt_depth / fill, torch.zeros_like(gt_depth))
        return self.recognition(gt_depth, cond)

    def forward(
        self,
        image: torch.Tensor,
        gt_depth: torch.Tensor | None = None,
        code: torch.Tensor | None = None,
        fill: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor | None]:
        """Run both streams.

        Args:
            image: (B, Cin, H, W) raw input (image in [0, 1], sparse depth [m], 0 = no sample).
            gt_depth: (B, 1, H, W) ground-truth depth [m] (0 = invalid), training only. When given the code is
                sampled ``mu + sigma * eps`` in train mode and is ``mu`` in eval mode.
            code: (B, C) code to decode when ``gt_depth`` is None; default zeros (the prior mean).
            fill: relative mode: the interpolated sparse channel (see :meth:`prior`).

        Returns:
            dict with ``depth`` (B, 1, H, W) [m], ``uncertainty`` (B, 1, H, W) [m], ``mu`` and ``logvar``
            (B, C) or None without ``gt_depth``, ``code`` (B, C) the code that was decoded.
        """
        uncertainty, feats = self.prior(image, fill)
        b = image.shape[0]
        mu = logvar = None
        if gt_depth is not None:
            if code is not None:
                raise ValueError("give gt_depth (code from the CVAE encoder) or code, not both")
            if gt_depth.shape[0] != b:
                raise ValueError(f"gt_depth batch {gt_depth.shape[0]} != image batch {b}")
            mu, logvar = self.encode(gt_depth, feats[0], feats)
            code = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if self.training else mu
        elif code is None:
            code = image.new_zeros(b, self.code_dim)
        elif code.shape != (b, self.code_dim):
            raise ValueError(f"code must have shape ({b}, {self.code_dim}), got {tuple(code.shape)}")
        depth = self.decoder(code, *feats)
        return {"depth": depth, "uncertainty": uncertainty, "mu": mu, "logvar": logvar, "code": code}

    def describe(self) -> dict:
        """Everything an exporter / runtime needs to feed and read the network (JSON-serialisable)."""
        norm = self.prior_net.norm
        return {
            "model": "dit" if self.attention else f"codevio{self.code_dim}",
            "modality": self.modality,
            "in_channels": self.in_channels,
            "code_dim": self.code_dim,
            "attention": self.attention,
            "code_injection": self.decoder.inject is not None,
            "relative": self.relative,
            "width_mult": self.width_mult,
            "height": self.height,
            "width": self.width,
            "input": {
                "image_range": [0.0, 1.0],
                "image_mean": norm.mean.flatten().tolist(),
                "image_std": norm.std.flatten().tolist(),
                "image_contrast": self.image_contrast,
                "sparse_depth": "metres, 0 = no sample" if norm.sparse else None,
                "fill": "linear" if self.relative else None,
                "sparse_normalisation": (
                    "linear interpolation of the samples (runtime.densify.interpolate_sparse), prior.onnx input "
                    "'fill'; depths divided by the samples' geometric mean inside prior.onnx"
                    if self.relative
                    else None
                ),
            },
            "depth": {
                "parametrisation": (
                    f"depth = fill * exp({REL_LOG_RANGE} * tanh(x / {REL_LOG_RANGE})), fill = the densified "
                    "sparse input (log fill is the last channel of the stride-1 feature)"
                    if self.relative
                    else "depth = depth_min * (depth_max / depth_min) ** sigmoid(x)"
                ),
                "unit": "m",
                "depth_min": self.depth_min,
                "depth_max": self.depth_max,
            },
            "uncertainty": {
                "parametrisation": "uncertainty_min + softplus(x)",
                "uncertainty_min": UNCERTAINTY_MIN,
            },
            "feature_strides": list(FEATURE_STRIDES),
            "feature_shapes": [list(s) for s in self.feature_shapes],
        }
