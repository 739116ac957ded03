"""Train a depth network: ``python train/fit.py [experiment=...] [group=option] [key=value ...]``.

Hydra entry point (config ``conf/fit.yaml``; groups ``model/``, ``modality/``, ``data/``, ``trainer/``,
``experiment/``), laid out like lightning-hydra-template's ``src/train.py``. With no arguments it renders the
synthetic NYU-layout set on first use, trains ``dit`` on ``grays`` on the short default schedule and prints
the
validation table. Examples::

    python train/fit.py modality=rgbs model=codevio8 trainer.max_steps=100 trainer.limit_val_batches=2 \\
        data.batch_size=4 data.root=/path hydra.run.dir=runs/x
    python train/fit.py ckpt_path=last hydra.run.dir=runs/x        # resume runs/x exactly
    python train/fit.py experiment=codevio32_rgb trainer=gpu
    python train/fit.py trainer=gpu data.num_workers=12    # a GPU waits on the CPU's data work otherwise
    python train/fit.py trainer=ddp trainer.devices=2              # DDP (gloo on CPU, NCCL on GPUs)

Outputs in the run directory: ``checkpoints/last.ckpt`` (always), ``checkpoints/best-step*.ckpt`` (lowest
``val/rmse``), ``csv/`` logs (and ``tensorboard/`` when installed), ``images/`` validation panels,
``metrics.json`` and ``.hydra/`` (the composed config).

An expected failure (a missing checkpoint, bad settings) prints one line ``fit: <problem>`` and exits with
status 2, before any data or model is built where it can; ``--debug`` or ``HYDRA_FULL_ERROR=1`` adds the
traceback (:mod:`runtime.errors`).

``ckpt_path=last`` resumes from ``<run dir>/checkpoints/last.ckpt``; when the run directory is new (no
``hydra.run.dir`` given), the newest ``last.ckpt`` under ``paths.log_dir/<task_name>/`` is used instead. A
checkpoint to resume from must hold the same network (``model.net``) as this run, else the run stops with a
one-line error naming both. A new run (no ``ckpt_path``) in a run directory that holds checkpoints of an earlier
run moves them to ``previous-<time>/checkpoints`` first and says so: nothing is lost, nothing is mixed.
"""

from __future__ import annotations

import os

# Idle OpenMP threads sleep instead of spinning. On a shared or oversubscribed CPU, spinning threads made a
# training step 5-10x slower (measured: 2 threads, batch 16 at 128x128: 6-25 s/step spinning, 1.3 s passive).
# Must be set before torch is imported; an explicit OMP_WAIT_POLICY in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import hydra  # noqa: E402
import lightning as L  # noqa: E402
import torch  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from train.metrics import METRICS, format_table  # noqa: E402

log = logging.getLogger("train.fit")

# train.datamodule restores the sampler position itself (its state_dict), which Lightning does not see.
warnings.filterwarnings("ignore", message=r"You're resuming from a checkpoint that ended before the epoch ended")

__all__ = [
    "main",
    "train",
    "resolve_ckpt_path",
    "check_resume_compatible",
    "check_accelerator",
    "set_aside_earlier_run",
    "instantiate_callbacks",
    "instantiate_loggers",
]


def instantiate_callbacks(cfg: DictConfig | None) -> list[L.Callback]:
    """Instantiate every ``_target_`` entry of ``cfg.callbacks`` (null entries are skipped)."""
    out: list[L.Callback] = []
    for name, c in (cfg or {}).items():
        if isinstance(c, DictConfig) and "_target_" in c:
            log.debug("callback %s <%s>", name, c._target_)
            out.append(hydra.utils.instantiate(c))
    return out


def instantiate_loggers(cfg: DictConfig | None) -> list:
    """Instantiate ``cfg.logger`` entries; TensorBoard is skipped when tensorboard is not installed."""
    out = []
    for name, c in (cfg or {}).items():
        if not (isinstance(c, DictConfig) and "_target_" in c):
            continue
        if "TensorBoard" in str(c._target_):
            try:
                import tensorboard  # noqa: F401
            except ImportError:
                try:
                    import tensorboardX  # noqa: F401
                except ImportError:
                    log.info("logger %s skipped: tensorboard is not installed", name)
                    continue
        out.append(hydra.utils.instantiate(c))
    return out


def resolve_ckpt_path(ckpt_path: str | None, output_dir: str | Path, runs_root: str | Path | None = None) -> str | None:
    """Resolve ``None``, a path or ``last`` (this run's last.ckpt, else the newest one under ``runs_root``).

    Raises:
        FileNotFoundError: an explicit path that does not exist.
    """
    if ckpt_path in (None, "", "null"):
        return None
    if str(ckpt_path) != "last":
        p = Path(str(ckpt_path)).expanduser()
        if not p.is_file():
            raise FileNotFoundError(f"ckpt_path={ckpt_path} does not exist")
        return str(p)
    own = Path(output_dir) / "checkpoints" / "last.ckpt"
    if own.is_file():
        return str(own)
    if runs_root is not None and Path(runs_root).is_dir():
        found = sorted(Path(runs_root).glob("**/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
        if found:
            log.info("ckpt_path=last: %s has no last.ckpt, resuming the newest run %s", output_dir, found[-1])
            return str(found[-1])
    log.warning("ckpt_path=last: no last.ckpt in %s or under %s; training from scratch", own.parent, runs_root)
    return None


def check_resume_compatible(ckpt: str | Path, net_cfg: dict) -> None:
    """Raise ValueError when checkpoint ``ckpt`` holds another network than ``net_cfg`` (``model.net``)."""
    try:
        state = torch.load(str(ckpt), map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - torch raises several types for truncated or foreign files
        raise ValueError(f"ckpt_path={ckpt}: not a readable checkpoint (truncated?): {e}") from e
    theirs = state.get("net_config") if isinstance(state, dict) else None
    if not isinstance(theirs, dict):
        return  # an older checkpoint without its network settings: Lightning checks the weights
    ours = {k: v for k, v in net_cfg.items() if k != "_target_"}
    theirs = {k: v for k, v in theirs.items() if k != "_target_"}
    diff = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))
    if diff:
        raise ValueError(
            f"ckpt_path={ckpt} holds another network ({', '.join(f'{k}={theirs.get(k)!r}' for k in diff)}) "
            f"than this run ({', '.join(f'{k}={ours.get(k)!r}' for k in diff)}); give a matching ckpt_path or "
            "the same model/modality"
        )


def set_aside_earlier_run(out_dir: Path) -> Path | None:
    """Move the checkpoints of an earlier run in ``out_dir`` to ``out_dir/previous-<UTC time>/``; returns it."""
    ckpts = out_dir / "checkpoints"
    if not ckpts.is_dir() or not any(ckpts.glob("*.ckpt")):
        return None
    import time

    dest = out_dir / f"previous-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
    dest.mkdir(parents=True, exist_ok=False)
    for name in ("checkpoints", "metrics.json"):
        if (out_dir / name).exists():
            os.replace(out_dir / name, dest / name)
    log.warning("%s held checkpoints of an earlier run: moved them to %s (resume with ckpt_path=last)", out_dir, dest)
    return dest


def _output_dir(cfg: DictConfig) -> Path:
    try:
        return Path(cfg.paths.output_dir)
    except Exception:  # no Hydra runtime (compose API): fall back to the trainer's root dir
        return Path(cfg.trainer.get("default_root_dir") or ".")


def check_accelerator(trainer_cfg: DictConfig | dict | None) -> None:
    """``trainer=gpu`` (accelerator gpu or cuda) where torch sees no CUDA device raises ValueError (one line, before
    any data is rendered or any model is built) instead of Lightning's error from inside the Trainer."""
    acc = str((trainer_cfg or {}).get("accelerator", "cpu")).lower()
    if acc in ("gpu", "cuda") and not torch.cuda.is_available():
        raise ValueError(
            f"trainer.accelerator={acc}, but torch {torch.__version__} sees no CUDA GPU: use trainer=cpu (the default)"
        )


def train(cfg: DictConfig) -> dict:
    """Fit, then validate the best (else the final) weights; returns the validation metrics.

    Returns:
        ``{"val/rmse": ..., ..., "val_median/rmse": ..., "best_model_path": ..., "last_model_path": ...}``.
    """
    out_dir = _output_dir(cfg)
    net_cfg = OmegaConf.to_container(cfg.model.net, resolve=True)
    net_cfg.pop("_target_", None)
    ckpt = None
    if cfg.get("train", True):  # a missing or foreign checkpoint fails here, before any data or model is built
        runs_root = Path(cfg.paths.log_dir) / str(cfg.task_name) if cfg.get("paths") else None
        ckpt = resolve_ckpt_path(cfg.get("ckpt_path"), out_dir, runs_root)
        if ckpt is not None:
            check_resume_compatible(ckpt, net_cfg)
    check_accelerator(cfg.get("trainer"))
    if cfg.get("num_threads"):
        torch.set_num_threads(int(cfg.num_threads))
    if cfg.get("seed") is not None:
        L.seed_everything(int(cfg.seed), workers=True)

    log.info("data <%s>, model <%s>", cfg.data._target_, cfg.model._target_)
    datamodule: L.LightningDataModule = hydra.utils.instantiate(cfg.data)
    model: L.LightningModule = hydra.utils.instantiate(cfg.model)
    model.net_config = net_cfg
    model.run_config = OmegaConf.to_container(cfg, resolve=True)

    callbacks = instantiate_callbacks(cfg.get("callbacks"))
    loggers = instantiate_loggers(cfg.get("logger"))
    trainer: L.Trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)

    if cfg.get("train", True):
        if ckpt is None and trainer.is_global_zero:
            set_aside_earlier_run(out_dir)
        trainer.fit(model=model, datamodule=datamodule, ckpt_path=ckpt)

    metrics: dict = {}
    best = getattr(trainer.checkpoint_callback, "best_model_path", "") if trainer.checkpoint_callback else ""
    if cfg.get("validate", True):
        which = best if best and Path(best).is_file() else None
        res = trainer.validate(model=model, datamodule=datamodule, ckpt_path=which, verbose=False)
        metrics = {k: float(v) for k, v in (res[0] if res else {}).items()}
        metrics["weights"] = which or "final"
    metrics["best_model_path"] = best
    last = [c for c in trainer.callbacks if hasattr(c, "last_path")]
    metrics["last_model_path"] = str(last[0].last_path) if last else ""
    metrics["global_step"] = int(trainer.global_step)

    if trainer.is_global_zero and metrics.get("val/rmse") is not None:
        name = f"{cfg.model.net.name}/{cfg.modality.name}"
        rows = {name: {k: metrics[f"val/{k}"] for k in METRICS}}
        if "val/ms_per_frame" in metrics:
            rows[name]["ms"] = metrics["val/ms_per_frame"]
        if "val_interp/rmse" in metrics:
            rows["interpolation of the sparse input (reference)"] = {k: metrics[f"val_interp/{k}"] for k in METRICS}
        if "val_median/rmse" in metrics:
            rows["median GT (reference)"] = {k: metrics[f"val_median/{k}"] for k in METRICS}
        src = "best checkpoint" if metrics["weights"] != "final" else "final weights"
        print(f"\nValidation after {trainer.global_step} steps ({src}; ms/frame = forward time / val batch):\n")
        print(format_table(rows, first="model/modality"))
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
        print(f"\nwrote {out_dir / 'metrics.json'}; checkpoints in {out_dir / 'checkpoints'}")
    return metrics


_DEBUG = {"on": False}


@hydra.main(version_base="1.3", config_path="../conf", config_name="fit")
def _run(cfg: DictConfig) -> float | None:
    """Hydra entry; returns ``val/rmse`` (for sweepers)."""
    from runtime.errors import EXPECTED, report

    try:
        metrics = train(cfg)
    except EXPECTED as e:  # bad settings, a missing or foreign checkpoint: one line, exit 2 (runtime.errors)
        sys.exit(report("fit", e, _DEBUG["on"]))
    return metrics.get("val/rmse")


def main(argv: list[str] | None = None) -> float | None:
    """Command line entry: Hydra overrides; ``--debug`` (or ``HYDRA_FULL_ERROR=1``) also prints the traceback of
    an expected failure, which is otherwise one line ``fit: <problem>`` and exit status 2."""
    from runtime.errors import split_debug

    saved = sys.argv
    args, _DEBUG["on"] = split_debug(list(saved[1:] if argv is None else argv))
    sys.argv = [saved[0] if saved else "fit.py", *args]
    try:
        return _run()
    finally:
        sys.argv = saved


if __name__ == "__main__":
    main()
