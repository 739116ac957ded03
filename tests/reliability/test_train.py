"""Training run directories and checkpoints: resuming another network is refused naming both, a new run in an
old run directory sets the old checkpoints aside, and dit-export reads truncated or mismatched checkpoints
with one clear error or the checkpoint's own network settings."""

import logging

import pytest
import yaml

torch = pytest.importorskip("torch")

import models  # noqa: E402
from export.checkpoint import load_checkpoint  # noqa: E402

NET = {"name": "dit", "modality": "grays", "height": 64, "width": 96, "width_mult": 0.25}


def _run_dir(tmp_path, net_cfg):
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / "checkpoints").mkdir()
    (run / ".hydra" / "config.yaml").write_text(
        yaml.safe_dump({"model": {"net": {"_target_": "models.build_model", **net_cfg}}})
    )
    return run


def _save(path, net_cfg):
    net = models.build_model(**net_cfg)
    sd = {f"net.{k}": v for k, v in net.state_dict().items()}
    torch.save({"state_dict": sd, "net_config": dict(net_cfg)}, path)
    return path


def test_truncated_checkpoint_is_one_clear_error(tmp_path):
    run = _run_dir(tmp_path, NET)
    ckpt = _save(run / "checkpoints" / "last.ckpt", NET)
    ckpt.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"last\.ckpt: not a readable checkpoint \(truncated"):
        load_checkpoint(ckpt)


def test_rgb_checkpoint_in_a_grays_run_directory_uses_its_own_settings(tmp_path, caplog):
    run = _run_dir(tmp_path, NET)
    rgb = {**NET, "modality": "rgb"}
    ckpt = _save(run / "checkpoints" / "best.ckpt", rgb)
    with caplog.at_level(logging.WARNING, logger="export.checkpoint"):
        loaded = load_checkpoint(ckpt)
    assert loaded.modality == "rgb" and loaded.net.in_channels == 3
    assert "'modality': 'rgb'" in caplog.text and "'modality': 'grays'" in caplog.text


def test_resuming_a_checkpoint_of_another_network_is_refused(tmp_path):
    from train.fit import check_resume_compatible

    ckpt = _save(tmp_path / "last.ckpt", {**NET, "modality": "rgb"})
    with pytest.raises(
        ValueError, match=r"holds another network \(modality='rgb'\) than this run \(modality='grays'\)"
    ):
        check_resume_compatible(ckpt, {"_target_": "models.build_model", **NET})
    check_resume_compatible(ckpt, {**NET, "modality": "rgb"})


def test_a_new_run_in_an_old_run_directory_sets_the_old_checkpoints_aside(tmp_path):
    from train.fit import set_aside_earlier_run

    run = _run_dir(tmp_path, NET)
    (run / "checkpoints" / "best-step10.ckpt").write_bytes(b"old best")
    (run / "metrics.json").write_text("{}")
    dest = set_aside_earlier_run(run)
    assert dest.parent == run and dest.name.startswith("previous-")
    assert (dest / "checkpoints" / "best-step10.ckpt").read_bytes() == b"old best"
    assert (dest / "metrics.json").is_file() and not (run / "checkpoints").exists()
    assert set_aside_earlier_run(run) is None


@pytest.mark.parametrize("debug", ["", "--debug", "HYDRA_FULL_ERROR=1"])
def test_fit_expected_failure_is_one_line_and_exit_2_with_the_traceback_on_request(tmp_path, debug):
    import os
    import subprocess
    import sys

    from tests.train.conftest import REPO

    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("HYDRA_FULL_ERROR", None)
    if debug.startswith("HYDRA"):
        env["HYDRA_FULL_ERROR"] = "1"
    missing = tmp_path / "no" / "last.ckpt"
    cmd = [sys.executable, "train/fit.py", f"ckpt_path={missing}", f"hydra.run.dir={tmp_path / 'run'}"]
    p = subprocess.run(
        cmd + ([debug] if debug == "--debug" else []), cwd=REPO, env=env, capture_output=True, text=True, timeout=300
    )
    err = p.stderr.strip()
    assert p.returncode == 2, err[-2000:]
    assert err.splitlines()[-1] == f"fit: ckpt_path={missing} does not exist"
    if debug:
        assert "Traceback (most recent call last)" in err and "FileNotFoundError" in err
    else:
        assert len(err.splitlines()) == 1 and "Traceback" not in err  # nothing else: checked before any work
    assert not (tmp_path / "run" / "checkpoints").exists()
