"""One error style across the commands: an expected failure is one line naming the problem and exit status 2."""

import os
import subprocess
import sys
import time

import pytest

from tests.train.conftest import REPO


def _run(code: str, *args: str, env_extra: dict | None = None):
    env = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE", **(env_extra or {}))
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.perf_counter()
    p = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=300
    )
    return p, time.perf_counter() - t0


def test_dit_export_of_a_truncated_checkpoint(tmp_path):
    pytest.importorskip("torch")
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(
        "model:\n  net:\n    _target_: models.build_model\n    name: dit\n    modality: grays\n"
    )
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "last.ckpt").write_bytes(b"PK\x03\x04 truncated")
    p, _ = _run(
        "from export.cli import main; main()", f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"out={tmp_path / 'm'}"
    )
    assert p.returncode == 2, p.stderr[-2000:]
    assert p.stderr.strip().startswith("dit-export: ") and len(p.stderr.strip().splitlines()) == 1
    assert "last.ckpt: not a readable checkpoint (truncated" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "m").exists() or not any((tmp_path / "m").glob("*.onnx"))


def test_dit_sim_scale_20_is_refused_at_once(tmp_path):
    p, took = _run("from sim.cli import main; main()", "euroc", f"out={tmp_path / 's'}", "scale=20", "workers=1")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "dit-sim euroc: scale=20 renders 15040x9600 frames: about 14.4 GB" in p.stderr
    assert took < 30 and not (tmp_path / "s" / "mav0").exists()
