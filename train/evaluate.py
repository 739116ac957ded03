"""Depth evaluation of a checkpoint: ``dit-eval depth ckpt=PATH [data=...] [modality=...] [key=value ...]``.

Prints a Table-1-style markdown table (RMSE, iRMSE, AbsRel, MAE, MAPE, d1, d2, d3, ms/frame) and writes JSON.
The network is rebuilt from the checkpoint (``net_config``: the ``models.build_model`` arguments stored by
``train/fit.py``); data settings default to the checkpoint's training run (``run_config``) and can be replaced
with a data group (``data=nyu_h5 data.root=...``, ``data=nyu_mat data.mat_path=... data.split_path=...``) or
single keys (``data.root=...``). Evaluation uses the validation transform (resize + centre crop) and, for
``*s`` modalities, exactly 125 noise-free FAST samples; the code is the prior mean (0), as in the SLAM system.

``ms/frame`` is the median wall time of a batch-1 forward pass on this machine (``timing_frames`` frames after
``timing_warmup``; torch, ``num_threads`` threads; ``device=cuda`` for a GPU).

Also the Table 1 ablation: :func:`evaluate_checkpoint` is called by :mod:`train.ablation`.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported; see train/fit.py

import json
import logging
import statistics
import sys
import time
from pathlib import Path

import hydra
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from train.metrics import DepthMetrics, format_table

__all__ = ["main", "evaluate_checkpoint", "load_network"]

log = logging.getLogger("train.evaluate")

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def load_network(ckpt: str | Path, device: str = "cpu") -> tuple[torch.nn.Module, dict, dict]:
    """Rebuild the network of a ``train/fit.py`` checkpoint.

    Returns:
        ``(net in eval mode, net_config (build_model kwargs), run_config (resolved training config or {}))``.

    Raises:
        FileNotFoundError: no such checkpoint. ValueError: not a checkpoint of ``train/fit.py``.
    """
    from models import build_model

    ckpt = Path(ckpt).expanduser()
    if not ckpt.is_file():
        raise FileNotFoundError(f"checkpoint {ckpt} does not exist")
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    if "net_config" not in state or "state_dict" not in state:
        raise ValueError(f"{ckpt} has no 'net_config'/'state_dict': not a checkpoint written by train/fit.py")
    net_cfg = dict(state["net_config"])
    net = build_model(**net_cfg)
    sd = {k[len("net.") :]: v for k, v in state["state_dict"].items() if k.startswith("net.")}
    net.load_state_dict(sd)
    return net.eval().to(device), net_cfg, dict(state.get("run_config") or {})


def _data_config(
    cfg: DictConfig, net_cfg: dict, run_cfg: dict, data_keys: list[str] | None = None
) -> DictConfig:
    """The data config to evaluate on, at the network's modality and size.

    A data group chosen on the command line (``data=nyu_h5 data.root=...``) is used as composed; otherwise the
    training run's data config, with ``data.<key>=<value>`` overrides (``data_keys``) applied on top.
    """
    if cfg.get("data") is not None:
        OmegaConf.set_struct(cfg, False)
        cfg.data.modality = net_cfg["modality"]
        data = OmegaConf.create(OmegaConf.to_container(cfg.data, resolve=True))
    else:
        if not run_cfg.get("data"):
            raise ValueError(
                "the checkpoint has no run_config: pass a data group (data=nyu_sim|nyu_h5|nyu_mat)"
            )
        data = OmegaConf.create(run_cfg["data"])
        if data_keys:
            data = OmegaConf.merge(data, OmegaConf.from_dotlist([k[len("data.") :] for k in data_keys]))
    data.modality = net_cfg["modality"]
    data.height, data.width = int(net_cfg["height"]), int(net_cfg["width"])
    if cfg.get("batch_size"):
        data.val_batch_size = int(cfg.batch_size)
    data.num_workers = int(cfg.get("num_workers") or 0)
    if cfg.get("limit") is not None:
        data.limit_val = int(cfg.limit)
    return data


@torch.inference_mode()
def evaluate_checkpoint(
    ckpt: str | Path,
    data: DictConfig | dict | None = None,
    split: str = "val",
    device: str = "cpu",
    timing_frames: int = 30,
    timing_warmup: int = 5,
    median_baseline: bool = True,
    cfg: DictConfig | None = None,
    data_keys: list[str] | None = None,
) -> dict:
    """Evaluate a checkpoint on a split; returns ``{"model", "modality", "metrics", "median", "ms", ...}``.

    Args:
        ckpt: checkpoint of ``train/fit.py``.
        data: data module config (``_target_`` + keys) or None = the training run's.
        split: ``val`` or ``test`` (the datamodule's ``val_split`` / ``test_split``).
        device: torch device.
        timing_frames, timing_warmup: batch-1 forward passes timed / discarded first.
        median_baseline: also score the per-image median ground-truth depth.
        cfg: the CLI config (``data``, ``batch_size``, ``limit``, ``num_workers``), used when ``data`` is
        None. data_keys: ``data.<key>=<value>`` overrides of the training run's data config (when ``cfg.data``
        is None).
    """
    net, net_cfg, run_cfg = load_network(ckpt, device)
    if data is not None:
        data_cfg = OmegaConf.create(dict(data) if not isinstance(data, DictConfig) else data)
        data_cfg.modality = net_cfg["modality"]
        data_cfg.height, data_cfg.width = int(net_cfg["height"]), int(net_cfg["width"])
    else:
        data_cfg = _data_config(cfg if cfg is not None else OmegaConf.create({}), net_cfg, run_cfg, data_keys)
    dm = hydra.utils.instantiate(data_cfg)
    dm.setup("test" if split == "test" else "validate")
    loader = dm.test_dataloader() if split == "test" else dm.val_dataloader()

    acc, med = DepthMetrics(), DepthMetrics()
    from train.module import _median_prediction

    timing_inputs = []
    for batch in loader:
        image = batch["image"].to(device)
        gt = batch["depth"].to(device)
        out = net(image)
        acc.update(out["depth"], gt)
        if median_baseline:
            med.update(_median_prediction(gt), gt)
        if len(timing_inputs) < timing_warmup + timing_frames:
            timing_inputs.extend(image[i : i + 1] for i in range(image.shape[0]))
    times = []
    for i, x in enumerate(timing_inputs[: timing_warmup + timing_frames]):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        net(x)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        if i >= timing_warmup:
            times.append(1000.0 * (time.perf_counter() - t0))
    metrics = acc.compute()
    result = {
        "checkpoint": str(ckpt),
        "model": net_cfg.get("name"),
        "modality": net_cfg.get("modality"),
        "net_config": net_cfg,
        "data": {
            "kind": str(data_cfg.get("kind")),
            "root": str(dm.data_root or data_cfg.get("mat_path")),
            "split": split,
        },
        "frames": acc.count,
        "metrics": metrics,
        "ms": statistics.median(times) if times else float("nan"),
        "timing": {"device": device, "threads": torch.get_num_threads(), "batch": 1, "frames": len(times)},
        "units": {
            "rmse": "m",
            "irmse": "1/m",
            "abs_rel": "-",
            "mae": "m",
            "mape": "fraction",
            "delta": "fraction",
            "ms": "ms/frame",
        },
    }
    if median_baseline:
        result["median"] = med.compute()
    return result


def table_rows(results: list[dict]) -> dict[str, dict]:
    """Rows for :func:`train.metrics.format_table` from :func:`evaluate_checkpoint` results."""
    rows = {}
    for r in results:
        rows[f"{r['modality']} / {r['model']}"] = {**r["metrics"], "ms": r["ms"]}
    return rows


def run(cfg: DictConfig, data_keys: list[str] | None = None) -> dict:
    if cfg.get("num_threads"):
        torch.set_num_threads(int(cfg.num_threads))
    if not cfg.get("ckpt"):
        raise ValueError("ckpt=PATH is required (a checkpoint written by train/fit.py)")
    res = evaluate_checkpoint(
        cfg.ckpt,
        None,
        split=str(cfg.split),
        device=str(cfg.device),
        timing_frames=int(cfg.timing_frames),
        timing_warmup=int(cfg.timing_warmup),
        median_baseline=bool(cfg.median_baseline),
        cfg=cfg,
        data_keys=data_keys,
    )
    if cfg.get("modality") is not None and cfg.modality.name != res["modality"]:
        raise ValueError(f"modality={cfg.modality.name} but the checkpoint was trained on {res['modality']}")
    rows = table_rows([res])
    if "median" in res:
        rows["median GT (reference)"] = res["median"]
    print(
        f"\nDepth evaluation of {res['checkpoint']} on {res['frames']} frames "
        f"({res['data']['kind']} {res['data']['split']}: {res['data']['root']}); ms/frame: batch 1, "
        f"{res['timing']['threads']} threads, {res['timing']['device']}\n"
    )
    print(format_table(rows, first="modality / method"))
    out = Path(cfg.out) if cfg.get("out") else Path(cfg.ckpt).expanduser().parent.parent / "eval_depth.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    print(f"\nwrote {out}")
    return res


def main(argv: list[str] | None = None) -> dict | None:
    """``dit-eval depth``: Hydra overrides ``argv`` (default ``sys.argv[1:]``) on ``conf/eval_depth.yaml``."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    overrides = list(sys.argv[1:] if argv is None else argv)
    if overrides and overrides[0] == "depth":
        overrides = overrides[1:]
    # Without a data group, data.<key> overrides apply to the training run's data config (read from the
    # checkpoint).
    group = any(o.startswith("data=") for o in overrides)
    data_keys = [] if group else [o for o in overrides if o.startswith("data.")]
    overrides = [o for o in overrides if o not in data_keys]
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name="eval_depth"):
            cfg = compose(config_name="eval_depth", overrides=overrides)
        return run(cfg, data_keys)
    except (FileNotFoundError, ValueError) as e:
        sys.exit(f"dit-eval depth: {e}")


if __name__ == "__main__":
    main()
