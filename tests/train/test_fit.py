"""End-to-end training at 64x64, width 0.25: overfitting one batch, exact resume, CLI, evaluation, DDP."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.train.conftest import REPO, compose_fit, tiny_overrides
from train.fit import check_accelerator, main, resolve_ckpt_path, train


def _train_losses(run_dir: Path) -> list[float]:
    (path,) = (run_dir / "csv").glob("version_*/metrics.csv")
    rows = list(csv.DictReader(open(path)))
    return [float(r["train/loss"]) for r in rows if r.get("train/loss")]


def test_overfit_one_batch_loss_falls(fake_nyu, tmp_path):
    cfg = compose_fit(
        tiny_overrides(fake_nyu, tmp_path)
        + [
            "trainer.overfit_batches=1",
            "trainer.max_steps=30",
            "trainer.val_check_interval=30",
            "model.scheduler=null",
            "model.optimizer.lr=3e-3",
            "validate=false",
        ]
    )
    train(cfg)
    loss = _train_losses(tmp_path)
    assert len(loss) == 30
    first, last = sum(loss[:3]) / 3, sum(loss[-3:]) / 3
    assert last < 0.6 * first, (first, last)


def _weights(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def test_resume_is_exact(fake_nyu, tmp_path):
    # 8 train frames, batch 2: 4 steps per epoch. Stop at 5 (inside epoch 1), resume to 10 (into epoch 2).
    base = ["trainer.val_check_interval=3", "validate=false", "model.kl_warmup_steps=4"]
    full, part = tmp_path / "full", tmp_path / "part"
    train(compose_fit(tiny_overrides(fake_nyu, full) + base + ["trainer.max_steps=10"]))
    train(compose_fit(tiny_overrides(fake_nyu, part) + base + ["trainer.max_steps=5"]))
    assert _weights(part / "checkpoints" / "last.ckpt")["global_step"] == 5
    train(compose_fit(tiny_overrides(fake_nyu, part) + base + ["trainer.max_steps=10", "ckpt_path=last"]))
    a, b = _weights(full / "checkpoints" / "last.ckpt"), _weights(part / "checkpoints" / "last.ckpt")
    assert a["global_step"] == b["global_step"] == 10
    assert a["NyuDataModule"] == b["NyuDataModule"] == {"epoch": 2, "next_pos": 4, "seed": 0, "batch_size": 2}
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for k in a["state_dict"]:
        assert torch.equal(a["state_dict"][k], b["state_dict"][k]), k
    sa, sb = a["optimizer_states"][0]["state"], b["optimizer_states"][0]["state"]
    assert all(torch.equal(sa[i]["exp_avg_sq"], sb[i]["exp_avg_sq"]) for i in sa)
    # a different run (other seed) does differ: the comparison is not vacuous
    other = tmp_path / "other"
    train(compose_fit(tiny_overrides(fake_nyu, other) + base + ["trainer.max_steps=10", "seed=1"]))
    c = _weights(other / "checkpoints" / "last.ckpt")
    assert not all(torch.equal(a["state_dict"][k], c["state_dict"][k]) for k in a["state_dict"])


def test_gpu_trainer_without_a_gpu_is_one_line_and_status_2(fake_nyu, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    check_accelerator({"accelerator": "cpu"})  # no error
    with pytest.raises(ValueError, match="sees no CUDA GPU: use trainer=cpu"):
        check_accelerator({"accelerator": "gpu"})
    with pytest.raises(SystemExit) as e:
        main(tiny_overrides(fake_nyu, tmp_path) + ["trainer=gpu"])
    assert e.value.code == 2
    assert "fit: trainer.accelerator=gpu, but torch" in capsys.readouterr().err
    assert not (tmp_path / "checkpoints").exists()  # stopped before any training


def test_resolve_ckpt_path(tmp_path):
    assert resolve_ckpt_path(None, tmp_path) is None
    assert resolve_ckpt_path("last", tmp_path / "new", tmp_path) is None  # nothing yet: from scratch
    old = tmp_path / "runs" / "a" / "checkpoints"
    old.mkdir(parents=True)
    (old / "last.ckpt").write_bytes(b"x")
    assert resolve_ckpt_path("last", tmp_path / "runs" / "b", tmp_path / "runs") == str(old / "last.ckpt")
    with pytest.raises(FileNotFoundError):
        resolve_ckpt_path(str(tmp_path / "nope.ckpt"), tmp_path)


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["OMP_NUM_THREADS"] = "1"
    return env


def test_cli_user_example_then_evaluate(fake_nyu, tmp_path):
    """The issue's example command line (at test size), then ``dit-eval depth`` on its checkpoint."""
    run = tmp_path / "x"
    cmd = [
        sys.executable,
        "train/fit.py",
        "modality=rgbs",
        "model=codevio8",
        "trainer.max_steps=3",
        "trainer.limit_val_batches=2",
        "data.batch_size=4",
        f"data.root={fake_nyu}",
        f"hydra.run.dir={run}",
        "data=nyu_h5",
        "data.height=64",
        "data.width=64",
        "model.net.width_mult=0.25",
        "logger.tensorboard=null",
        "trainer.enable_progress_bar=false",
        "trainer.val_check_interval=3",
        "num_threads=1",
    ]
    p = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "| codevio8/rgbs |" in p.stdout and "median GT (reference)" in p.stdout
    assert (run / "checkpoints" / "last.ckpt").is_file() and list(
        (run / "checkpoints").glob("best-step*.ckpt")
    )
    assert list((run / "images").glob("val_step*.png"))
    m = json.loads((run / "metrics.json").read_text())
    assert m["global_step"] == 3 and m["val/rmse"] > 0

    from train.evaluate import main as eval_main

    out = tmp_path / "eval.json"
    res = eval_main(
        [
            "depth",
            f"ckpt={run / 'checkpoints' / 'last.ckpt'}",
            "modality=rgbs",
            f"out={out}",
            "timing_frames=2",
            "timing_warmup=1",
            "num_threads=1",
        ]
    )
    saved = json.loads(out.read_text())
    assert saved["model"] == "codevio8" and saved["modality"] == "rgbs" and saved["frames"] == 4
    assert saved["metrics"]["rmse"] == pytest.approx(res["metrics"]["rmse"]) and saved["ms"] > 0
    # the same frames through another data group gives the same numbers
    res2 = eval_main(
        [
            "depth",
            f"ckpt={run / 'checkpoints' / 'last.ckpt'}",
            "data=nyu_h5",
            f"data.root={fake_nyu}",
            f"out={tmp_path / 'eval2.json'}",
            "timing_frames=1",
            "timing_warmup=0",
        ]
    )
    assert res2["metrics"]["rmse"] == pytest.approx(res["metrics"]["rmse"])
    with pytest.raises(SystemExit, match="modality=gray but the checkpoint"):
        eval_main(
            [
                f"ckpt={run / 'checkpoints' / 'last.ckpt'}",
                "modality=gray",
                f"out={tmp_path / 'e3.json'}",
                "timing_frames=1",
                "timing_warmup=0",
            ]
        )


@pytest.mark.slow
def test_ddp_two_cpu_processes(fake_nyu, tmp_path):
    run = tmp_path / "ddp"
    cmd = [
        sys.executable,
        "train/fit.py",
        "trainer=ddp",
        "trainer.accelerator=cpu",
        "trainer.devices=2",
        *[o for o in tiny_overrides(fake_nyu, run) if not o.startswith("paths.")],
    ]
    p = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "distributed_backend=gloo" in p.stdout + p.stderr
    assert "Starting with 2 processes" in p.stdout + p.stderr
    ck = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ck["global_step"] == 4
    # 8 frames over 2 ranks = 4 per rank, batch 2: 2 steps per epoch -> after 4 steps at the end of epoch 1
    assert ck["NyuDataModule"] == {"epoch": 1, "next_pos": 4, "seed": 0, "batch_size": 2}
    assert json.loads((run / "metrics.json").read_text())["val/rmse"] > 0


@pytest.mark.slow
def test_ablation_two_cells(fake_nyu, tmp_path):
    from train.ablation import run_ablation

    over = [o for o in tiny_overrides(fake_nyu, tmp_path) if not o.startswith(("paths.", "hydra."))]
    s = run_ablation(
        tmp_path / "abl", over + ["trainer.max_steps=2"], ["dit", "fastdepth"], ["grays"], timing_frames=2
    )
    lines = s["table"].splitlines()
    assert [ln.split(" | ")[0] for ln in lines[2:]] == [
        "| G-S / FastDepth",
        "| G-S / Ours (DiT)",
        "| G-S / interpolation of the sparse input (reference)",
        "| G-S / median GT (reference)",
    ]
    assert set(s["cells"]) == {"dit_grays", "fastdepth_grays"}
    assert (tmp_path / "abl" / "ablation.md").read_text().count("G-S /") == 4
    again = run_ablation(
        tmp_path / "abl", over + ["trainer.max_steps=2"], ["dit"], ["grays"], timing_frames=2
    )
    assert again["cells"]["dit_grays"]["metrics"] == s["cells"]["dit_grays"]["metrics"]  # reused, not re-run


def test_variant_order_ranks_by_rmse():
    from train.ablation import variant_order

    cells = {f"{v}_grays": {"metrics": {"rmse": r}} for v, r in [("dit", 0.3), ("fastdepth", 0.2), ("codevio8", 0.4)]}
    cells["dit_gray"] = {"metrics": {"rmse": 0.1}}
    assert variant_order(cells, "grays") == ["fastdepth", "dit", "codevio8"]
    assert variant_order(cells, "gray") == ["dit"]
    assert variant_order(cells, "rgb") == []


@pytest.mark.slow
def test_ablation_over_two_seeds_in_parallel(fake_nyu, tmp_path):
    """Two training seeds, two cells each, four trainings at once: one table per seed, each seed's order, and
    whether they agree; the second seed's weights differ from the first's (the seed reaches the training)."""
    from train.ablation import run_seeds

    over = [o for o in tiny_overrides(fake_nyu, tmp_path) if not o.startswith(("paths.", "hydra."))]
    s = run_seeds(
        tmp_path / "abl", [0, 1], over + ["trainer.max_steps=2", "seed=7"], ["dit", "fastdepth"], ["grays"],
        timing_frames=2, jobs=4,
    )
    assert "seed=7" not in s["overrides"]
    for seed, run in zip([0, 1], s["runs"], strict=True):
        assert f"seed={seed}" in run["overrides"]
        assert (tmp_path / "abl" / f"seed{seed}" / "dit_grays" / "eval_depth.json").is_file()
        assert sorted(s["order"]["grays"][str(seed)]) == ["dit", "fastdepth"]
    orders = list(s["order"]["grays"].values())
    assert s["same_order"]["grays"] == (orders[0] == orders[1])
    r0, r1 = (run["cells"]["dit_grays"]["metrics"]["rmse"] for run in s["runs"])
    assert r0 != r1
    md = (tmp_path / "abl" / "ablation.md").read_text()
    assert md.count("### Training seed") == 2 and "| G-S |" in md


def test_ablation_command_line_takes_overrides_anywhere():
    """Hydra overrides after a list option (``--variants a b key=value``) are overrides, not list items; an
    option's own value may hold '='."""
    from train.ablation import parse_args

    a = parse_args(["--variants", "dit", "codevio8", "--modalities", "gray", "grays", "trainer=gpu", "--jobs", "2"])
    assert (a.variants, a.modalities, a.jobs) == (["dit", "codevio8"], ["gray", "grays"], 2)
    assert a.overrides == ["trainer=gpu"]
    a = parse_args(["seed=1", "--seeds", "0", "1", "data.root=/x", "--out", "o/a=b"])
    assert (a.seeds, a.overrides, a.out) == ([0, 1], ["seed=1", "data.root=/x"], "o/a=b")
