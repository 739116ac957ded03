"""dit-sim: an impossible scale is refused before any work with a memory estimate, an interrupted run removes
its partial output (a rerun into the same folder works), and PNGs are written whole or not at all."""

import json
import os

import numpy as np
import pytest

sim_euroc = pytest.importorskip("sim.euroc")


def test_scale_20_is_refused_up_front_with_a_memory_estimate(tmp_path, monkeypatch):
    def never(*a, **k):
        raise AssertionError("simulated before refusing the scale")

    monkeypatch.setattr(sim_euroc, "simulate_sequence", never)
    with pytest.raises(ValueError, match=r"scale=20 renders 15040x9600 frames: about 14\.4 GB .*scale must be <= 4"):
        sim_euroc.write_euroc_sequence(tmp_path / "s", scale=20, workers=1, progress=False)
    assert not (tmp_path / "s").exists()


def test_interrupted_rendering_removes_its_partial_output_and_a_rerun_works(tmp_path, monkeypatch):
    render = sim_euroc._render_frame
    calls = []

    def interrupted(job):
        calls.append(job)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return render(job)

    monkeypatch.setattr(sim_euroc, "_render_frame", interrupted)
    out = tmp_path / "s"
    with pytest.raises(KeyboardInterrupt):
        sim_euroc.write_euroc_sequence(out, duration=3.0, scale=0.25, progress=False)
    assert sorted(p.name for p in out.iterdir()) == []
    monkeypatch.setattr(sim_euroc, "_render_frame", render)
    sim_euroc.write_euroc_sequence(out, duration=3.0, scale=0.25, progress=False)
    info = json.loads((out / "sim_info.json").read_text())
    assert "complete" not in info and len(list((out / "mav0" / "cam0" / "data").iterdir())) == info["frames"]


def test_a_killed_runs_output_is_replaced_by_the_next_run(tmp_path):
    out = tmp_path / "s"
    (out / "mav0" / "cam0" / "data").mkdir(parents=True)  # what a SIGKILL during rendering leaves
    (out / "sim_info.json").write_text(json.dumps({"generator": "dit-sim", "job": "euroc", "complete": False}))
    sim_euroc.write_euroc_sequence(out, duration=3.0, scale=0.25, progress=False)
    assert json.loads((out / "sim_info.json").read_text()).get("complete", True) is True


def test_png_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    img = np.full((8, 8), 7, np.uint8)

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        sim_euroc.write_png(tmp_path / "1.png", img)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    sim_euroc.write_png(tmp_path / "1.png", img)
    import cv2

    assert (cv2.imread(str(tmp_path / "1.png"), cv2.IMREAD_UNCHANGED) == img).all()


def test_the_cache_does_not_take_a_partial_sequence(tmp_path, monkeypatch):
    from sim import cache

    seq = tmp_path / "euroc_textured_3s_s0"
    (seq / "mav0" / "cam0").mkdir(parents=True)
    (seq / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
    meta = {"generator": "dit-sim", "preset": "textured", "duration_s": 3.0, "seed": 0, "imu_noise": True}
    (seq / "sim_info.json").write_text(json.dumps({**meta, "complete": False}))
    rendered = []
    monkeypatch.setattr(cache, "write_euroc_sequence", lambda out, **k: rendered.append(out) or out)
    cache.cached_sequence("textured", 3.0, 0, True, tmp_path, progress=False)
    assert rendered == [seq]
