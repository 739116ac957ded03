"""Depth evaluation of a checkpoint: ``dit-eval depth ckpt=PATH [data=...] [modality=...] [key=value ...]``.

Prints a Table-1-style markdown table (RMSE, iRMSE, AbsRel, MAE, MAPE, d1, d2, d3, ms/frame) and writes JSON.
The network is rebuilt from the checkpoint (``net_config``: the ``models.build_model`` arguments stored by
``train/fit.py``); data settings default to the checkpoint's training run (``run_config``) and can be replaced
with a data group (``data=nyu_h5 data.root=...``, ``data=nyu_mat data.mat_path=... data.split_path=...``) or
single keys (``data.root=...``). Evaluation uses the validation transform (resize + centre crop) and, for
``*s`` modalities, exactly 125 noise-free FAST samples; the code is the prior mean (0), as in the SLAM system.

Every table has the reference rows next to the network: the **interpolation** of the network's own sparse input
(:func:`train.sparse.interpolate_sparse`: linear over the samples' triangulation, nearest outside their hull;
``*s`` modalities) and the per-image **median** of the ground truth. A sparse-input network that does not beat
the interpolation adds nothing to the points it was given.

The paper's G-S protocol on other frames (:func:`evaluate_protocol`): ``model_dir=DIR`` (an exported model, ONNX
Runtime, exactly what the SLAM system runs) or ``ckpt=PATH`` (torch, which also scores the posterior-mean code),
on ``real=DIR`` (a folder of RGB-D frame folders in the ``rgbd_real`` layout, or one such folder;
:mod:`runtime.io.rgbd_frames`) and on fresh synthetic validation rooms (``sim.seed``, ``sim.n_val``): 125 FAST
corners with their true depth, no noise, network resolution, code c = 0. ``protocol=slam`` gives SLAM-like sparse
input instead (30 points, 0.1 m noise, 5 % outliers). Per set: network, interpolation and median rows, and the
largest per-frame AbsRel of each.

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
import numpy as np
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from train.metrics import DepthMetrics, format_table

__all__ = [
    "PROTOCOLS",
    "evaluate_checkpoint",
    "evaluate_protocol",
    "interpolation_prediction",
    "load_network",
    "main",
    "protocol_sets",
]

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


def _data_config(cfg: DictConfig, net_cfg: dict, run_cfg: dict, data_keys: list[str] | None = None) -> DictConfig:
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
            raise ValueError("the checkpoint has no run_config: pass a data group (data=nyu_sim|nyu_h5|nyu_mat)")
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


def interpolation_prediction(image: torch.Tensor) -> torch.Tensor:
    """The interpolation reference: :func:`train.sparse.interpolate_sparse` of the last input channel.

    Args:
        image: (B, Cin, H, W) network input whose last channel is the sparse depth [m] (0 = no sample).

    Returns:
        (B, 1, H, W) float32 [m].
    """
    from train.sparse import interpolate_sparse

    sp = image[:, -1].detach().cpu().numpy()
    out = np.stack([interpolate_sparse(x) for x in sp])[:, None]
    return torch.from_numpy(out).to(image.device)


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

    acc, med, interp = DepthMetrics(), DepthMetrics(), DepthMetrics()
    sparse_input = str(net_cfg.get("modality", "")).endswith("s")
    from train.module import _median_prediction

    timing_inputs = []
    for batch in loader:
        image = batch["image"].to(device)
        gt = batch["depth"].to(device)
        out = net(image)
        acc.update(out["depth"], gt)
        if median_baseline:
            med.update(_median_prediction(gt), gt)
            if sparse_input:
                interp.update(interpolation_prediction(image), gt)
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
        if sparse_input:
            result["interpolation"] = interp.compute()
    return result


#: Sparse input of the protocols: (points, noise std [m], outlier fraction). ``gs``: the paper's G-S protocol.
PROTOCOLS: dict[str, tuple[int, float, float]] = {"gs": (125, 0.0, 0.0), "slam": (30, 0.1, 0.05)}


class _OnnxPredictor:
    """An exported model directory under ONNX Runtime: ``(B, Cin, H, W)`` input -> depth (B, 1, H, W) at c = 0."""

    def __init__(self, model_dir: str | Path, threads: int = 1):
        from runtime.network import DepthNetwork, SessionConfig

        self.net = DepthNetwork(model_dir, SessionConfig(threads=threads))
        self.modality, self.height, self.width = self.net.modality, self.net.height, self.net.width
        self.code = np.zeros(self.net.code_dim, np.float32)

    def __call__(self, image: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
        x = image.numpy()
        out = []
        n_img = 3 if self.modality.startswith("rgb") else 1
        for xi in x:
            img = xi[:n_img].transpose(1, 2, 0) if n_img == 3 else xi[0]
            sparse = xi[-1] if self.net.uses_sparse else None
            out.append(self.net.prior(img, sparse).depth(self.code))
        return {"network": torch.from_numpy(np.stack(out)[:, None])}


class _TorchPredictor:
    """A checkpoint under torch: depth at c = 0 and with the posterior mean of the ground truth (oracle)."""

    def __init__(self, ckpt: str | Path, device: str = "cpu"):
        self.net, cfg, _ = load_network(ckpt, device)
        self.modality, self.height, self.width = cfg["modality"], int(cfg["height"]), int(cfg["width"])
        self.device = device

    def __call__(self, image: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
        x, g = image.to(self.device), gt.to(self.device)
        out = {"network": self.net(x)["depth"].cpu()}
        if hasattr(self.net, "recognition"):
            out["network, posterior-mean code (oracle)"] = self.net(x, gt_depth=g)["depth"].cpu()
        return out


@torch.inference_mode()
def evaluate_protocol(
    predict,
    sets: dict[str, object],
    batch_size: int = 8,
) -> dict[str, dict]:
    """Score a predictor and the reference rows on frame sets (each a dataset of the validation transform).

    Args:
        predict: ``(image (B, Cin, H, W), gt (B, 1, H, W)) -> {row name: depth (B, 1, H, W) [m]}``.
        sets: name -> dataset yielding ``image`` and ``depth`` (:class:`train.data.NyuFrames`).
        batch_size: frames per call.

    Returns:
        name -> ``{"frames", "rows": {row: metrics + "max_frame_abs_rel"}}``; rows: the predictor's, then
        ``interpolation`` (sparse modalities) and ``median GT``.
    """
    from torch.utils.data import DataLoader

    from train.module import _median_prediction

    results = {}
    for name, ds in sets.items():
        accs: dict[str, DepthMetrics] = {}
        worst: dict[str, float] = {}
        frames = 0
        for batch in DataLoader(ds, batch_size=batch_size, shuffle=False):
            image, gt = batch["image"], batch["depth"]
            rows = dict(predict(image, gt))
            if image.shape[1] in (2, 4):
                rows["interpolation"] = interpolation_prediction(image)
            rows["median GT"] = _median_prediction(gt)
            for row, pred in rows.items():
                m = accs.setdefault(row, DepthMetrics()).update(pred.float(), gt)
                worst[row] = max(worst.get(row, 0.0), float(m["abs_rel"][m["n"] > 0].max()))
            frames += image.shape[0]
        results[name] = {
            "frames": frames,
            "rows": {row: {**acc.compute(), "max_frame_abs_rel": worst[row]} for row, acc in accs.items()},
        }
    return results


def protocol_sets(cfg: DictConfig, modality: str, height: int, width: int) -> dict[str, object]:
    """The frame sets of a protocol evaluation: ``cfg.real`` folders and ``cfg.sim`` rooms, name -> dataset."""
    from runtime.io.rgbd_frames import RgbdFolder
    from train.augment import FrameTransform
    from train.data import NyuFrames, NyuH5Dataset, ensure_synthetic_nyu
    from train.sparse import SparseConfig

    if str(cfg.protocol) not in PROTOCOLS:
        raise ValueError(f"protocol={cfg.protocol} not in {sorted(PROTOCOLS)}")
    num, noise, outliers = PROTOCOLS[str(cfg.protocol)]
    sparse = SparseConfig(num_eval=num, eval_noise_std=noise, eval_outlier_frac=outliers)
    tf = FrameTransform(height, width, modality, False, None, sparse)
    seed = int(cfg.seed)
    sets = {}
    sim = cfg.get("sim") or {}
    if int(sim.get("n_val") or 0) > 0:
        realism = bool(sim.get("realism", False))
        root = ensure_synthetic_nyu(sim.get("root"), 1, int(sim.n_val), int(sim.seed), realism=realism)
        kind = "realistic " if realism else ""
        sets[f"synthetic {kind}val (dit-sim nyu seed {int(sim.seed)})"] = NyuH5Dataset(
            root, "val", tf, seed, cfg.get("limit")
        )
    if cfg.get("real"):
        real = Path(str(cfg.real)).expanduser()
        if not real.is_dir():
            raise FileNotFoundError(f"real={real}: no such folder")
        if any(real.glob("frame-*.color.*")):
            folders = [real]
        else:
            folders = sorted(p for p in real.iterdir() if p.is_dir() and any(p.glob("frame-*.color.*")))
        for f in folders:
            sets[f"real {f.name}"] = NyuFrames(RgbdFolder(f, cfg.get("limit")), tf, seed)
    if not sets:
        raise ValueError("nothing to evaluate: give real=DIR and/or sim.n_val=N")
    return sets


def run_protocol(cfg: DictConfig) -> dict:
    """``dit-eval depth [model_dir=DIR | ckpt=PATH] real=DIR sim.n_val=N protocol=gs|slam``: print and write JSON."""
    if cfg.get("model_dir"):
        predict = _OnnxPredictor(cfg.model_dir, threads=int(cfg.get("num_threads") or 1))
        source = str(cfg.model_dir)
    elif cfg.get("ckpt"):
        predict = _TorchPredictor(cfg.ckpt, str(cfg.device))
        source = str(cfg.ckpt)
    else:
        raise ValueError("model_dir=DIR (exported) or ckpt=PATH is required")
    sets = protocol_sets(cfg, predict.modality, predict.height, predict.width)
    num, noise, outliers = PROTOCOLS[str(cfg.protocol)]
    res = {
        "source": source,
        "protocol": {
            "name": str(cfg.protocol),
            "points": num,
            "noise_std_m": noise,
            "outlier_frac": outliers,
            "code": "c = 0 (network row)",
            "resolution": [predict.height, predict.width],
            "seed": int(cfg.seed),
        },
        "sets": evaluate_protocol(predict, sets, int(cfg.batch_size)),
    }
    print(
        f"\nDepth of {source} ({predict.modality}, {predict.height}x{predict.width}), protocol {cfg.protocol}: "
        f"{num} FAST points, noise {noise} m, outliers {outliers:.0%}, code c = 0\n"
    )
    for name, r in res["sets"].items():
        print(f"{name}: {r['frames']} frames")
        rows = {row: m for row, m in r["rows"].items()}
        print(format_table(rows, first="method"))
        print(
            "max per-frame AbsRel: "
            + ", ".join(f"{row} {m['max_frame_abs_rel']:.3f}" for row, m in rows.items())
            + "\n"
        )
    if cfg.get("out"):
        out = Path(cfg.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=2))
        print(f"wrote {out}")
    return res


def table_rows(results: list[dict]) -> dict[str, dict]:
    """Rows for :func:`train.metrics.format_table` from :func:`evaluate_checkpoint` results."""
    rows = {}
    for r in results:
        rows[f"{r['modality']} / {r['model']}"] = {**r["metrics"], "ms": r["ms"]}
    return rows


def run(cfg: DictConfig, data_keys: list[str] | None = None) -> dict:
    if cfg.get("num_threads"):
        torch.set_num_threads(int(cfg.num_threads))
    if cfg.get("model_dir") or cfg.get("real") or int((cfg.get("sim") or {}).get("n_val") or 0) > 0:
        return run_protocol(cfg)
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
    if "interpolation" in res:
        rows["interpolation of the sparse input (reference)"] = res["interpolation"]
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
