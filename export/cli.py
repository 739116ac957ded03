"""``dit-export ckpt=PATH out=DIR``: a training checkpoint -> prior.onnx + decoder.onnx + manifest.json."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

log = logging.getLogger("dit-export")


def run(cfg: DictConfig) -> dict:
    import torch

    from export.checkpoint import load_checkpoint
    from export.onnx import export_network

    for noisy in ("onnx_ir", "onnxscript", "torch.onnx"):  # per-pass INFO lines drown the result
        logging.getLogger(noisy).setLevel(logging.WARNING)
    ckpt = Path(str(cfg.ckpt)).expanduser()
    loaded = load_checkpoint(ckpt)
    parity_inputs = None
    if cfg.get("val_root"):
        from export.checkpoint import validation_inputs

        parity_inputs = validation_inputs(loaded, cfg.val_root, int(cfg.n_val_frames))
    torch.manual_seed(0)
    manifest = export_network(
        loaded.net,
        cfg.out,
        modality=loaded.modality,
        height=loaded.height,
        width=loaded.width,
        opset=int(cfg.opset),
        delta=float(cfg.delta),
        n_parity=int(cfg.n_parity),
        parity_inputs=parity_inputs,
        train_config=loaded.train_config,
        source=str(ckpt),
    )
    p = manifest["parity"]
    print(
        f"wrote {Path(cfg.out) / 'prior.onnx'}, {Path(cfg.out) / 'decoder.onnx'}, {Path(cfg.out) / 'manifest.json'}"
    )
    print(
        f"model {manifest['model']} / {manifest['modality']} {manifest['height']}x{manifest['width']}, "
        f"code {manifest['code_dim']}; parity on {p['inputs']} inputs at batch 1 and 8: "
        f"max |depth onnx - torch| = {p['max_abs_depth_m']:.2e} m (tolerance {p['tolerance_m']:g} m)"
    )
    return manifest


@hydra.main(version_base="1.3", config_path="../conf", config_name="export")
def _main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        sys.exit(f"dit-export: {e}")


def main() -> None:
    _main()
