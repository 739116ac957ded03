"""``dit-export ckpt=PATH out=DIR``: a training checkpoint -> prior.onnx + decoder.onnx + manifest.json.

The model is written into a temporary folder and renamed into place (:func:`export.onnx.export_network`).
Expected failures print one line and exit with status 2; ``--debug`` or ``HYDRA_FULL_ERROR=1`` adds the
traceback.
"""

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
    loaded = load_checkpoint(ckpt, cfg.get("image_contrast"))
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
    print(f"wrote {Path(cfg.out) / 'prior.onnx'}, {Path(cfg.out) / 'decoder.onnx'}, {Path(cfg.out) / 'manifest.json'}")
    print(
        f"model {manifest['model']} / {manifest['modality']} {manifest['height']}x{manifest['width']}, "
        f"code {manifest['code_dim']}; parity on {p['inputs']} inputs at batch 1 and 8: "
        f"max |depth onnx - torch| = {p['max_abs_depth_m']:.2e} m (tolerance {p['tolerance_m']:g} m)"
    )
    return manifest


_DEBUG = {"on": False}


@hydra.main(version_base="1.3", config_path="../conf", config_name="export")
def _main(cfg: DictConfig) -> None:
    from runtime.errors import EXPECTED, report

    try:
        run(cfg)
    except (*EXPECTED, RuntimeError) as e:  # RuntimeError: onnx.checker or the parity check refused the graphs
        sys.exit(report("dit-export", e, _DEBUG["on"]))
    except KeyboardInterrupt:
        print(f"dit-export: interrupted; {cfg.out} was left as it was", file=sys.stderr)
        sys.exit(130)


def _sigterm(signum, frame) -> None:
    raise KeyboardInterrupt("SIGTERM")


def main() -> None:
    import signal

    from runtime.errors import split_debug

    signal.signal(signal.SIGTERM, _sigterm)  # clean up the temporary folder as on Ctrl-C
    signal.signal(signal.SIGINT, signal.default_int_handler)  # also when started with SIGINT ignored (a background job)

    saved = sys.argv
    args, _DEBUG["on"] = split_debug(saved[1:])
    sys.argv = [saved[0], *args]
    try:
        _main()
    finally:
        sys.argv = saved
