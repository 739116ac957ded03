"""LightningModule: trains a depth network of :mod:`models` with the paper's losses (Eq. 6-8).

The network is injected (``net: {_target_: models.build_model, ...}`` in ``conf/model/*.yaml``), the optimizer
and the learning-rate schedule are ``_partial_`` configs, and ``_shared_step(batch, stage)`` serves train, val
and
test:

* train: the CVAE models decode the code sampled from the posterior of the ground truth and minimise
  ``L_rec + w(step) * L_KLD`` (Eq. 8; ``w`` = ``kl_weight``, optionally ramped up linearly over
  ``kl_warmup_steps``; the paper uses ``w = 1``, no warm-up); FastDepth minimises L1
  (``models.losses.total_loss`` falls back to L1 for models without uncertainty).
* val / test: the inference path of the SLAM system: the image alone, code = 0 (the prior mean). Logged:
  ``<stage>/loss`` (Eq. 6 or L1 at the prior code), the depth metrics of :mod:`train.metrics` over the whole
  set (all-reduced in DDP), ``<stage>/ms_per_frame`` (forward time / batch size), and the metrics of the
  per-image median ground-truth depth as a reference (``<stage>_median/rmse`` ...) and, for sparse modalities,
  those of the interpolated sparse input (``<stage>_interp/rmse`` ...).

Images of the first validation batch (input with the sparse samples, GT depth, predicted depth, uncertainty,
absolute error) are written after every validation to ``<run dir>/images/val_step<step>.png`` and sent to a
TensorBoard logger when there is one.

Every training step draws its random numbers (the CVAE's reparametrisation noise) from a torch generator
seeded by ``(seed, global_step, rank)``, so a resumed run repeats an uninterrupted one exactly (see
:mod:`train.datamodule` for the data side).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from functools import partial
from pathlib import Path

import cv2
import lightning as L
import numpy as np
import torch
from torch import nn

from models.losses import total_loss
from runtime.render import colour_map
from train.metrics import DepthMetrics

__all__ = ["DepthModule", "cosine_schedule", "constant_schedule", "net_spec"]

log = logging.getLogger(__name__)


def _cosine_factor(step: int, total_steps: int, warmup_steps: int, min_lr_ratio: float) -> float:
    if warmup_steps > 0 and step < warmup_steps:
        return (step + 1) / warmup_steps
    span = max(1, total_steps - warmup_steps)
    t = min(1.0, (step - warmup_steps) / span)
    return min_lr_ratio + (1.0 - min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * t))


def cosine_schedule(
    optimizer: torch.optim.Optimizer, total_steps: int, warmup_steps: int = 0, min_lr_ratio: float = 0.05
) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up then cosine decay to ``min_lr_ratio`` of the base rate at ``total_steps`` (per step)."""
    return torch.optim.lr_scheduler.LambdaLR(
        optimizer,
        partial(
            _cosine_factor,
            total_steps=int(total_steps),
            warmup_steps=int(warmup_steps),
            min_lr_ratio=float(min_lr_ratio),
        ),
    )


def constant_schedule(
    optimizer: torch.optim.Optimizer, total_steps: int = 0
) -> torch.optim.lr_scheduler.LambdaLR:
    """Constant learning rate (``total_steps`` is accepted for a uniform interface)."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)


def net_spec(net: nn.Module) -> dict:
    """``models.build_model`` keyword arguments that rebuild ``net`` (from its attributes)."""
    name = net.describe()["model"] if hasattr(net, "describe") else None
    spec = {
        "name": name,
        "modality": getattr(net, "modality", None),
        "width_mult": getattr(net, "width_mult", 1.0),
        "height": getattr(net, "height", None),
        "width": getattr(net, "width", None),
    }
    if getattr(net, "relative", False):
        spec["relative"] = True
    if name == "dit":
        spec["code_dim"] = getattr(net, "code_dim", None)
        if getattr(net, "image_contrast", None) is not None:
            spec["image_contrast"] = net.image_contrast
    return spec


def _seed_of(*ints: int) -> int:
    return int(np.random.SeedSequence([int(i) for i in ints]).generate_state(1, np.uint64)[0] >> 1)


class DepthModule(L.LightningModule):
    """Training wrapper of a depth network.

    Args:
        net: a :mod:`models` network (``forward(image, gt_depth=None, code=None) -> dict``).
        optimizer: partial optimizer (``optimizer(params=...)``).
        scheduler: partial schedule ``scheduler(optimizer=..., total_steps=...)`` stepped every step, or None.
        kl_weight: weight of the KL term (Eq. 8: 1).
        kl_warmup_steps: linear ramp of the KL weight from 0 over this many steps (0 = none, the paper).
        seed: seed of the per-step random generator.
        log_images: write the validation image panel.
        num_log_images: images in the panel.
        median_baseline: also log the per-image median-depth reference metrics.
    """

    def __init__(
        self,
        net: nn.Module,
        optimizer=None,
        scheduler=None,
        kl_weight: float = 1.0,
        kl_warmup_steps: int = 0,
        seed: int = 0,
        log_images: bool = True,
        num_log_images: int = 4,
        median_baseline: bool = True,
    ):
        super().__init__()
        # Plain values only, so checkpoints load with torch.load(weights_only=True); the partials stay
        # attributes.
        self.save_hyperparameters(logger=False, ignore=["net", "optimizer", "scheduler"])
        self.net = net
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.metrics = {"val": DepthMetrics(), "test": DepthMetrics()}
        self.median = {"val": DepthMetrics(), "test": DepthMetrics()}
        self.interp = {"val": DepthMetrics(), "test": DepthMetrics()}
        self._time = {"val": [0.0, 0], "test": [0.0, 0]}
        #: build_model kwargs and the resolved run config, stored in checkpoints (set by train/fit.py).
        self.net_config: dict | None = None
        self.run_config: dict | None = None

    # ----------------------------------------------------------------- core
    def forward(self, image: torch.Tensor, code: torch.Tensor | None = None, fill: torch.Tensor | None = None) -> dict:
        """Inference: ``image`` (B, Cin, H, W) -> the network's dict (code = ``code`` or 0).

        ``fill``: a relative network's interpolated sparse input, when the data loader made it (else the network
        computes it).
        """
        kw = self._fill_kw(fill)
        return self.net(image, code=code, **kw) if code is not None else self.net(image, **kw)

    def _fill_kw(self, fill: torch.Tensor | None) -> dict:
        """``{"fill": fill}`` for a relative network when the data loader made the fill, else ``{}`` (the network
        then computes it, and the other networks take none)."""
        return {"fill": fill} if fill is not None and getattr(self.net, "relative", False) else {}

    def kl_weight_at(self, step: int) -> float:
        w, n = float(self.hparams.kl_weight), int(self.hparams.kl_warmup_steps)
        return w if n <= 0 else w * min(1.0, step / n)

    @contextlib.contextmanager
    def _step_rng(self):
        """Fork the global torch generator and seed it from (seed, global_step, rank)."""
        cuda = self.device.type == "cuda"
        with torch.random.fork_rng(devices=[self.device] if cuda else [], device_type="cuda"):
            torch.manual_seed(_seed_of(self.hparams.seed, self.global_step, self.global_rank))
            yield

    def _shared_step(self, batch: dict, stage: str) -> tuple[torch.Tensor, dict]:
        """One batch of ``stage`` (train / val / test): returns (loss, network output)."""
        image, gt = batch["image"], batch["depth"]
        fill = batch.get("fill")
        b = image.shape[0]
        if stage == "train":
            with self._step_rng():
                out = self.net(image, gt_depth=gt, **self._fill_kw(fill))
            w = self.kl_weight_at(self.global_step)
            loss, parts = total_loss(out, gt, kl_weight=w)
            self.log_dict(
                {"train/loss": parts["total"], "train/rec": parts["rec"], "train/kld": parts["kld"]},
                prog_bar=True,
                batch_size=b,
            )
            self.log("train/kl_weight", w, batch_size=b)
            return loss, out
        t0 = time.perf_counter()
        out = self.forward(image, fill=fill)
        self._time[stage][0] += time.perf_counter() - t0
        self._time[stage][1] += b
        loss, _ = total_loss({"depth": out["depth"], "uncertainty": out.get("uncertainty")}, gt)
        self.log(f"{stage}/loss", loss, batch_size=b, sync_dist=True)
        self.metrics[stage].update(out["depth"], gt)
        if self.hparams.median_baseline:
            self.median[stage].update(_median_prediction(gt), gt)
            if getattr(self.net, "modality", "").endswith("s"):
                from train.evaluate import interpolation_prediction

                self.interp[stage].update(interpolation_prediction(image), gt)
        return loss, out

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        return self._shared_step(batch, "train")[0]

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        _, out = self._shared_step(batch, "val")
        if batch_idx == 0 and self.hparams.log_images and not self.trainer.sanity_checking:
            self._log_images(batch, out)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        self._shared_step(batch, "test")

    # ------------------------------------------------------------- epochs
    def _eval_start(self, stage: str) -> None:
        self.metrics[stage].reset()
        self.median[stage].reset()
        self.interp[stage].reset()
        self._time[stage] = [0.0, 0]

    def _eval_end(self, stage: str) -> None:
        def reduced(acc: DepthMetrics) -> dict[str, float]:
            state = acc.state.to(self.device)
            if self.trainer.world_size > 1:
                state = self.trainer.strategy.reduce(state, reduce_op="sum")
            return acc.compute(state)

        m = reduced(self.metrics[stage])
        self.log_dict({f"{stage}/{k}": v for k, v in m.items()}, sync_dist=True)
        if self.hparams.median_baseline:
            med = reduced(self.median[stage])
            self.log_dict({f"{stage}_median/{k}": v for k, v in med.items()}, sync_dist=True)
            if self.interp[stage].count:
                itp = reduced(self.interp[stage])
                self.log_dict({f"{stage}_interp/{k}": v for k, v in itp.items()}, sync_dist=True)
        t, n = self._time[stage]
        if n:
            self.log(f"{stage}/ms_per_frame", 1000.0 * t / n, sync_dist=True)

    def on_validation_epoch_start(self) -> None:
        self._eval_start("val")

    def on_validation_epoch_end(self) -> None:
        self._eval_end("val")

    def on_test_epoch_start(self) -> None:
        self._eval_start("test")

    def on_test_epoch_end(self) -> None:
        self._eval_end("test")

    # --------------------------------------------------------- optimisers
    def configure_optimizers(self):
        if self.optimizer_factory is None:
            raise ValueError("DepthModule needs an optimizer (model.optimizer in the config)")
        opt = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return opt
        total = int(self.trainer.estimated_stepping_batches)
        sched = self.scheduler_factory(optimizer=opt, total_steps=total)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}

    # --------------------------------------------------------- checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["net_config"] = dict(self.net_config) if self.net_config else net_spec(self.net)
        if self.run_config is not None:
            checkpoint["run_config"] = self.run_config

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.net_config = checkpoint.get("net_config", self.net_config)
        self.run_config = checkpoint.get("run_config", self.run_config)

    # -------------------------------------------------------------- images
    def _log_images(self, batch: dict, out: dict) -> None:
        if self.global_rank != 0:
            return
        n = min(int(self.hparams.num_log_images), batch["image"].shape[0])
        panel = image_panel(
            batch["image"][:n].detach().cpu().numpy(),
            batch["depth"][:n].detach().cpu().numpy(),
            out["depth"][:n].detach().float().cpu().numpy(),
            None if out.get("uncertainty") is None else out["uncertainty"][:n].detach().float().cpu().numpy(),
            sparse=getattr(self.net, "modality", "").endswith("s"),
        )
        root = Path(self.trainer.default_root_dir)
        path = root / "images" / f"val_step{self.global_step:06d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), panel[..., ::-1])
        for lg in self.loggers:
            exp = getattr(lg, "experiment", None)
            if hasattr(exp, "add_image"):
                exp.add_image("val/panel", panel, self.global_step, dataformats="HWC")


def _median_prediction(gt: torch.Tensor) -> torch.Tensor:
    """Per-image constant prediction: the median of the valid ground truth (B, 1, H, W) [m]."""
    b = gt.shape[0]
    flat = gt.reshape(b, -1)
    med = torch.stack(
        [(row[row > 0].median() if bool((row > 0).any()) else row.new_tensor(1.0)) for row in flat]
    )
    return med.reshape(b, 1, 1, 1).expand_as(gt)


def image_panel(
    image: np.ndarray, gt: np.ndarray, depth: np.ndarray, uncertainty: np.ndarray | None, sparse: bool
) -> np.ndarray:
    """Rows of (input + sparse samples, GT depth, prediction, uncertainty, |error|) as one RGB uint8 image.

    Args:
        image: (N, Cin, H, W) network input; gt, depth, uncertainty: (N, 1, H, W) [m].
        sparse: the last input channel is sparse depth (drawn as dots on the input).
    """
    rows = []
    for i in range(image.shape[0]):
        x = image[i]
        chans = x[:-1] if sparse else x
        img = chans.transpose(1, 2, 0)
        img = np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img
        img = (np.clip(img, 0, 1) * 255).astype(np.uint8).copy()
        g, d = gt[i, 0], depth[i, 0]
        valid = g > 0
        hi = float(g[valid].max()) if valid.any() else float(d.max())
        lo = float(g[valid].min()) if valid.any() else float(d.min())
        if sparse:
            v, u = np.nonzero(x[-1] > 0)
            img[v, u] = colour_map(x[-1][v, u][None], lo, hi)[0]
        cols = [img, colour_map(g, lo, hi, invalid=~valid), colour_map(d, lo, hi)]
        if uncertainty is not None:
            un = uncertainty[i, 0]
            cols.append(colour_map(un, 0.0, float(np.percentile(un, 99)) + 1e-6, cv2.COLORMAP_INFERNO))
        err = np.abs(d - g)
        cols.append(
            colour_map(
                err,
                0.0,
                max(0.5, float(np.percentile(err[valid], 95)) if valid.any() else 1.0),
                cv2.COLORMAP_INFERNO,
                invalid=~valid,
            )
        )
        rows.append(np.concatenate(cols, axis=1))
    return np.concatenate(rows, axis=0)
