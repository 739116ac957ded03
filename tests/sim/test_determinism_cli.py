"""Same seed -> same bytes (in-process or in worker processes), other seed -> other data; the CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.cli import main
from sim.euroc import write_euroc_sequence

REPO = Path(__file__).resolve().parents[2]


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    kw = dict(preset="textured", duration=3.0, imu_noise=True, progress=False, scale=0.25, realism=False)
    a = _files(write_euroc_sequence(tmp_path / "a", seed=5, **kw))
    b = _files(write_euroc_sequence(tmp_path / "b", seed=5, workers=2, **kw))  # spawn pool: same bytes
    c = _files(write_euroc_sequence(tmp_path / "c", seed=6, **kw))
    assert len(a) == 60 + 60 + 4 + 3 + 1  # images, depth PNGs, 4 data.csv, 3 sensor.yaml, sim_info.json
    assert a == b
    assert a.keys() == c.keys()
    differ = [k for k in a if a[k] != c[k]]
    assert "mav0/imu0/data.csv" in differ and "mav0/state_groundtruth_estimate0/data.csv" in differ
    assert sum(k.startswith("mav0/cam0/data/") for k in differ) == 60


def test_rewrite_replaces_own_output_but_refuses_foreign(tmp_path):
    kw = dict(duration=3.0, seed=0, imu_noise=False, progress=False, scale=0.25, realism=False)
    root = write_euroc_sequence(tmp_path / "seq", **kw)
    stale = root / "mav0" / "cam0" / "data" / "stale.png"
    stale.write_bytes(b"x")
    write_euroc_sequence(root, **kw)  # our own earlier output: replaced
    assert not stale.exists()
    foreign = tmp_path / "foreign"
    (foreign / "mav0").mkdir(parents=True)
    with pytest.raises(FileExistsError, match="not written by dit-sim"):
        write_euroc_sequence(foreign, **kw)


def test_cli_euroc_subprocess(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = tmp_path / "cli_euroc"
    cmd = [
        sys.executable,
        "-m",
        "sim.cli",
        "euroc",
        f"out={out}",
        "duration=3",
        "seed=2",
        "imu_noise=false",
        "realism=false",
        "scale=0.25",
        "workers=1",
        "progress=false",
    ]
    res = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "60 frames 188x120" in res.stdout and "600 samples @ 200 Hz" in res.stdout
    info = json.loads((out / "sim_info.json").read_text())
    assert (info["job"], info["preset"], info["seed"], info["imu_noise"], info["frames"]) == (
        "euroc",
        "textured",
        2,
        False,
        60,
    )
    assert len(list((out / "mav0" / "cam0" / "data").glob("*.png"))) == 60
    assert not (tmp_path / "outputs").exists()  # hydra writes no run folders
    bad = subprocess.run(
        [sys.executable, "-m", "sim.cli", "euroc", f"out={tmp_path / 'x'}", "preset=whitewall", "duration=5"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "duration" in bad.stderr
    assert (
        subprocess.run(
            [sys.executable, "-m", "sim.cli", "render"], env=env, capture_output=True, timeout=120
        ).returncode
        != 0
    )


def test_cli_nyu_in_process(tmp_path, capsys):
    out = tmp_path / "cli_nyu"
    main(["nyu", f"out={out}", "n_train=1", "n_val=1", "seed=3", "workers=1", "progress=false"])
    assert "train: 1 frames in 1 scenes" in capsys.readouterr().out
    assert [p.name for p in (out / "train").glob("*/*.h5")] == ["00000.h5"]
    assert [p.parent.name for p in (out / "val").glob("*/*.h5")] == ["sim_val_0000"]
    np.testing.assert_equal(json.loads((out / "sim_info.json").read_text())["seed"], 3)
