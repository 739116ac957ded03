"""Depth networks (plain torch): DiTNet, the Table 1 baselines, their blocks and losses.

``build_model(name, modality, ...)`` is the one entry point used by training and export.
"""

from __future__ import annotations

from torch import nn

from models.baselines import FastDepth, codevio, fastdepth
from models.blocks import MODALITY_CHANNELS
from models.ditnet import DepthDecoder, DiTNet

#: Model names of the paper's Table 1 and their default code dimension (None: no code).
MODEL_NAMES: dict[str, int | None] = {"dit": 8, "codevio8": 8, "codevio32": 32, "fastdepth": None}


def build_model(
    name: str,
    modality: str,
    code_dim: int | None = None,
    width_mult: float = 1.0,
    height: int = 224,
    width: int = 224,
    relative: bool = False,
    image_contrast: float | None = None,
) -> nn.Module:
    """Build one of ``dit | codevio8 | codevio32 | fastdepth`` for a modality ``rgb | rgbs | gray | grays``.

    Args:
        name: model name (see :data:`MODEL_NAMES`).
        modality: input modality (see :data:`MODALITY_CHANNELS`).
        code_dim: code dimension; None = the model's default. ``dit`` accepts any C >= 1; the CodeVIO variants
            only their own (8 / 32); ``fastdepth`` has no code and accepts only None.
        width_mult: channel multiplier of encoders and decoders.
        height, width: network input size [px], multiples of 32.
        relative: predict relative to the densified sparse input (:class:`~models.ditnet.DiTNet`; the baselines
            take the same formulation, :mod:`models.baselines`); it has no effect on the modalities without
            sparse depth.
        image_contrast: ``dit`` only: each input image's contrast is matched to this standard deviation inside
            the network (:func:`~models.blocks.match_contrast`); None = the image as it comes.

    >>> m = build_model("codevio32", "rgbs", width_mult=0.25, height=64, width=96)
    >>> (m.code_dim, m.in_channels, m.modality, m.attention)
    (32, 4, 'rgbs', False)
    """
    if name not in MODEL_NAMES:
        raise ValueError(f"model name={name!r} not in {sorted(MODEL_NAMES)}")
    if modality not in MODALITY_CHANNELS:
        raise ValueError(f"modality={modality!r} not in {sorted(MODALITY_CHANNELS)}")
    cin = MODALITY_CHANNELS[modality]
    default = MODEL_NAMES[name]
    if image_contrast is not None and name != "dit":
        raise ValueError(f"image_contrast needs model dit, got {name}")
    relative = bool(relative) and modality.endswith("s")  # without sparse input there is nothing to be relative to
    if name == "fastdepth":
        if code_dim is not None:
            raise ValueError(f"fastdepth has no depth code, got code_dim={code_dim!r}")
        return fastdepth(cin, width_mult, height, width, relative=relative)
    if name == "dit":
        code = default if code_dim is None else code_dim
        return DiTNet(
            cin, code, True, width_mult, height, width, relative=bool(relative), image_contrast=image_contrast
        )
    if code_dim is not None and code_dim != default:
        raise ValueError(f"{name} has code_dim {default}, got code_dim={code_dim!r} (use dit or codevio())")
    return codevio(cin, default, width_mult, height, width, relative=relative)


__all__ = ["MODALITY_CHANNELS", "MODEL_NAMES", "DepthDecoder", "DiTNet", "FastDepth", "build_model"]
