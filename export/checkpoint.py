"""Rebuild the network of a ``python train/fit.py`` checkpoint (without importing ``train``).

A run directory looks like ``<run>/.hydra/config.yaml`` + ``<run>/checkpoints/*.ckpt``; the network is the
config's ``model.net`` node (``_target_: models.build_model``) and the weights are the checkpoint's
``state_dict`` entries under ``net.``. A checkpoint that stores its own ``net_config`` (``train/module.py`` does)
is built from that; when the run directory's config says otherwise (e.g. the run directory was reused for
another model) a warning names both.
"""

from __future__ import annotations

import logging
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from torch import nn

import models

log = logging.getLogger(__name__)


@dataclass
class LoadedCheckpoint:
    net: nn.Module
    modality: str
    height: int
    width: int
    net_config: dict
    train_config: dict | None
    path: Path


def find_run_config(ckpt: Path) -> Path:
    for parent in ckpt.resolve().parents[:3]:
        candidate = parent / ".hydra" / "config.yaml"
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"{ckpt}: no .hydra/config.yaml in the run directory above it (was it written by python train/fit.py?)"
    )


def load_checkpoint(ckpt: str | Path, image_contrast: float | None = None) -> LoadedCheckpoint:
    """Build the net from the run's config and load the checkpoint's weights (eval mode, CPU).

    ``image_contrast``: build the network with this contrast matching of its image input
    (:func:`models.blocks.match_contrast`), whatever it was trained with; None keeps the checkpoint's own.
    """
    ckpt = Path(ckpt)
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: checkpoint not found")
    cfg_path = find_run_config(ckpt)
    cfg = OmegaConf.load(cfg_path)
    try:
        net_cfg = OmegaConf.to_container(cfg.model.net, resolve=True)
    except Exception as e:  # omegaconf raises several types for missing/unresolvable keys
        raise ValueError(f"{cfg_path}: cannot read model.net: {e}") from e
    target = net_cfg.pop("_target_", None)
    if target != "models.build_model":
        raise ValueError(f"{cfg_path}: model.net._target_ is {target!r}, expected 'models.build_model'")
    state = _read_checkpoint(ckpt)
    own = state.get("net_config") if isinstance(state, dict) else None
    if isinstance(own, dict) and own:
        own = {k: v for k, v in own.items() if k != "_target_"}
        diff = sorted(k for k in set(own) | set(net_cfg) if own.get(k) != net_cfg.get(k))
        if diff:
            log.warning(
                "%s: the checkpoint was trained with %s, but %s says %s; using the checkpoint's own",
                ckpt,
                {k: own.get(k) for k in diff},
                cfg_path,
                {k: net_cfg.get(k) for k in diff},
            )
        net_cfg = own
    if image_contrast is not None:
        net_cfg = {**net_cfg, "image_contrast": float(image_contrast)}
    try:
        net = models.build_model(**net_cfg)
    except TypeError as e:
        raise ValueError(f"{ckpt}: cannot build the network from {net_cfg}: {e}") from e
    weights = {k[len("net.") :]: v for k, v in state.get("state_dict", {}).items() if k.startswith("net.")}
    if not weights:
        raise ValueError(f"{ckpt}: no 'net.*' weights in its state_dict")
    try:
        missing, unexpected = net.load_state_dict(weights, strict=False)
    except RuntimeError as e:  # shape mismatches ("size mismatch for ...")
        first = next((ln.strip() for ln in str(e).splitlines() if "size mismatch" in ln), str(e).splitlines()[0])
        raise ValueError(f"{ckpt}: weights do not fit the network of {net_cfg} ({first})") from e
    if missing or unexpected:
        raise ValueError(f"{ckpt}: weights do not match {net_cfg} (missing {missing[:5]}, unexpected {unexpected[:5]})")
    train_cfg = OmegaConf.to_container(cfg, resolve=False)
    return LoadedCheckpoint(
        net.eval(),
        net_cfg["modality"],
        int(net_cfg["height"]),
        int(net_cfg["width"]),
        net_cfg,
        train_cfg,
        ckpt,
    )


def _read_checkpoint(ckpt: Path) -> dict:
    """``torch.load`` of a checkpoint; a truncated or foreign file raises ValueError naming it."""
    try:
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
    except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError, OSError) as e:
        raise ValueError(f"{ckpt}: not a readable checkpoint (truncated or not written by torch?): {e}") from e
    if not isinstance(state, dict):
        raise ValueError(f"{ckpt}: not a training checkpoint (got {type(state).__name__})")
    return state


def validation_inputs(loaded: LoadedCheckpoint, root: str | Path, n: int, seed: int = 0) -> list[torch.Tensor]:
    """Up to ``n`` network inputs from NYU-layout validation frames (resize + centre crop; 125 sparse samples
    of the ground truth for the ``*s`` modalities), for the parity check on realistic data."""
    from runtime.geometry import NetworkMapping
    from runtime.io.nyu import list_nyu_h5, read_nyu_h5

    files = list_nyu_h5(root, "val")[:n]
    if not files:
        raise FileNotFoundError(f"{root}: no val/*/*.h5 frames")
    rng = np.random.default_rng(seed)
    out = []
    for f in files:
        rgb, depth = read_nyu_h5(f)
        m = NetworkMapping.fit(rgb.shape[1], rgb.shape[0], loaded.width, loaded.height)
        img = m.image_to_network(rgb).astype(np.float32) / 255.0
        d = m.image_to_network(depth, nearest=True)
        if loaded.modality.startswith("gray"):
            img = img @ np.array([0.299, 0.587, 0.114], np.float32)
        chans = [img.transpose(2, 0, 1)] if img.ndim == 3 else [img[None]]
        if loaded.modality.endswith("s"):
            sparse = np.zeros_like(d)
            valid = np.flatnonzero(d > 0)
            pick = rng.choice(valid, size=min(125, valid.size), replace=False)
            sparse.flat[pick] = d.flat[pick]
            chans.append(sparse[None])
        out.append(torch.from_numpy(np.concatenate(chans, 0)[None].astype(np.float32)))
    return out
