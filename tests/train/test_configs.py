"""Every config group composes and instantiates (hydra compose API)."""

from __future__ import annotations

from pathlib import Path

import hydra
import pytest
import torch
from omegaconf import OmegaConf

from tests.train.conftest import CONF, compose_fit, tiny_overrides

MODELS = ["dit", "codevio8", "codevio32", "fastdepth"]
MODALITIES = {"rgb": 3, "rgbs": 4, "gray": 1, "grays": 2}


def _names(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_groups_are_complete():
    assert _names("model") == sorted(MODELS)
    assert _names("modality") == sorted(MODALITIES)
    assert _names("data") == ["nyu_h5", "nyu_mat", "nyu_sim"]
    assert {"cpu", "gpu", "ddp"} <= set(_names("trainer"))
    assert _names("experiment") == sorted(f"{m}_{x}" for m in MODELS for x in MODALITIES)


def test_default_config(tmp_path):
    cfg = compose_fit([f"paths.output_dir={tmp_path}"])
    assert cfg.model.net.name == "dit" and cfg.modality.name == "grays" and cfg.data.kind == "sim"
    assert cfg.model.net.code_dim == 8 and cfg.model.kl_weight == 1.0e-4  # see conf/model/dit.yaml
    assert cfg.model.optimizer._partial_ and list(cfg.model.keys())[0] == "_target_"
    assert cfg.trainer.use_distributed_sampler is False
    assert cfg.callbacks.model_checkpoint.monitor == "val/rmse"
    assert cfg.callbacks.model_checkpoint.dirpath == f"{tmp_path}/checkpoints"


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("modality", list(MODALITIES))
def test_model_x_modality_instantiates(model, modality, tmp_path, fake_nyu):
    cfg = compose_fit(tiny_overrides(fake_nyu, tmp_path) + [f"model={model}", f"modality={modality}"])
    module = hydra.utils.instantiate(cfg.model)
    net = module.net
    assert net.in_channels == MODALITIES[modality] and net.modality == modality
    assert (net.height, net.width) == (64, 64)
    dm = hydra.utils.instantiate(cfg.data)
    assert dm.modality == modality
    assert dm.transform(True).with_fill == bool(getattr(net, "relative", False))  # a relative net's fill: in the loader
    out = module(torch.rand(1, MODALITIES[modality], 64, 64))
    assert out["depth"].shape == (1, 1, 64, 64) and bool((out["depth"] > 0).all())
    assert (out["uncertainty"] is None) == (model == "fastdepth")
    opt = module.optimizer_factory(params=module.parameters())
    sched = module.scheduler_factory(optimizer=opt, total_steps=10)
    assert isinstance(opt, torch.optim.AdamW) and sched.get_last_lr()[0] > 0


@pytest.mark.parametrize("experiment", _names("experiment"))
def test_experiments_compose(experiment, tmp_path):
    cfg = compose_fit([f"experiment={experiment}", f"paths.output_dir={tmp_path}"])
    model, modality = experiment.rsplit("_", 1)
    assert cfg.model.net.name == model and cfg.modality.name == modality
    assert cfg.data.modality == modality and cfg.task_name == "table1"


@pytest.mark.parametrize("data", ["nyu_sim", "nyu_h5", "nyu_mat"])
def test_data_groups_instantiate(data, tmp_path):
    extra = {"nyu_h5": ["data.root=/some/nyu"], "nyu_mat": ["data.mat_path=/x.mat", "data.split_path=/s.mat"]}
    cfg = compose_fit([f"data={data}", f"paths.output_dir={tmp_path}"] + extra.get(data, []))
    dm = hydra.utils.instantiate(cfg.data)
    assert dm.kind == {"nyu_sim": "sim", "nyu_h5": "h5", "nyu_mat": "mat"}[data]
    assert dm.sparse.num_eval == 125 and dm.sparse.noise_std == 0.1 and dm.augment.scale == (1.0, 1.5)
    if data == "nyu_mat":
        assert dm.val_split == "test"


@pytest.mark.parametrize("trainer", ["cpu", "gpu", "ddp"])
def test_trainer_groups(trainer, tmp_path):
    cfg = compose_fit([f"trainer={trainer}", f"paths.output_dir={tmp_path}", "logger.tensorboard=null"])
    assert cfg.trainer.use_distributed_sampler is False and cfg.trainer.max_steps > 0
    if trainer == "gpu" and not torch.cuda.is_available():
        assert cfg.trainer.accelerator == "gpu"
        return
    t = hydra.utils.instantiate(cfg.trainer, logger=False)
    if trainer == "ddp":
        assert type(t.strategy).__name__ == "DDPStrategy" and t.num_devices == 2
    else:
        assert t.num_devices == 1


def test_user_example_overrides_compose(tmp_path):
    cfg = compose_fit(
        "modality=rgbs model=codevio8 trainer.max_steps=100 trainer.limit_val_batches=2 data.batch_size=4 "
        f"data.root=/path paths.output_dir={tmp_path}".split()
    )
    c = OmegaConf.to_container(cfg, resolve=True)
    assert c["model"]["net"]["name"] == "codevio8" and c["model"]["net"]["modality"] == "rgbs"
    assert c["trainer"]["max_steps"] == 100 and c["trainer"]["limit_val_batches"] == 2
    assert c["data"]["batch_size"] == 4 and c["data"]["root"] == "/path"
    assert Path(c["trainer"]["default_root_dir"]) == tmp_path
