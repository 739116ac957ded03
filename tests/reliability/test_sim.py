"""dit-sim: an impossible scale is refused before any work with a memory estimate, an interrupted run of any job
(euroc, nyu, imu) removes its partial output and a rerun into the same folder equals an uninterrupted run, a
killed run's folder is marked partial and replaced by the next run (which says so), and PNGs and h5 frames are
written whole or not at all."""

import json
import os

import numpy as np
import pytest

from tests.reliability.fakes import fail_on_call

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
    monkeypatch.setattr(sim_euroc, "_render_frame", fail_on_call(render, 3, []))
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


def _digest(root):
    """Every file below ``root`` (links followed) and every link's target, by relative path."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_symlink():
            out[rel + " ->"] = os.readlink(p)
        if p.is_file():
            out[rel] = p.read_bytes()
    return out


NYU_KW = dict(n_train=2, n_val=1, seed=3, progress=False, frames_per_scene=2, compression=None)


def test_interrupted_nyu_removes_its_partial_output_and_a_rerun_equals_an_uninterrupted_run(tmp_path, monkeypatch):
    from sim import nyu

    ref = nyu.write_nyu_dataset(tmp_path / "ref", **NYU_KW)
    real, calls = nyu.atomic_write, []

    def interrupted(path, writer):  # Ctrl-C while the second frame's h5 file is being written
        calls.append(path)
        if len(calls) < 2:
            return real(path, writer)

        def half(tmp):
            writer(tmp)
            raise KeyboardInterrupt

        return real(path, half)

    monkeypatch.setattr(nyu, "atomic_write", interrupted)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        nyu.write_nyu_dataset(out, **NYU_KW)
    assert len(calls) == 2 and list(out.rglob("*")) == []  # no frame, no temporary file, no sim_info.json
    monkeypatch.undo()
    nyu.write_nyu_dataset(out, **NYU_KW)
    assert _digest(out) == _digest(ref) and len([k for k in _digest(ref) if k.endswith(".h5")]) == 3


def test_a_killed_nyu_run_is_marked_partial_refused_by_the_reader_and_replaced_by_a_rerun(
    tmp_path, monkeypatch, capsys
):
    from runtime.io.nyu import NyuFormatError, list_nyu_h5
    from sim import cli, nyu, output

    ref = nyu.write_nyu_dataset(tmp_path / "ref", **NYU_KW)
    render, calls = nyu._render_scene, []

    def killed(job):  # the process dies in the second scene: no cleanup runs (as after SIGKILL)
        calls.append(job)
        if len(calls) == 2:
            raise SystemExit("killed")
        return render(job)

    monkeypatch.setattr(nyu, "_render_scene", killed)
    monkeypatch.setattr(output, "remove_output", lambda out, parts: None)
    out = tmp_path / "out"
    with pytest.raises(SystemExit):
        nyu.write_nyu_dataset(out, **NYU_KW)
    info = json.loads((out / "sim_info.json").read_text())
    assert info["generator"] == "dit-sim" and info["job"] == "nyu" and info["complete"] is False
    assert len(list((out / "train").glob("*/*.h5"))) == 2  # the first scene's frames are there ...
    with pytest.raises(NyuFormatError, match=r"partial output of a dit-sim run that did not finish"):
        list_nyu_h5(out, "train")  # ... but never read as a whole data set
    monkeypatch.undo()
    cli.main(["nyu", f"out={out}", "n_train=2", "n_val=1", "seed=3", "frames_per_scene=2", "workers=1"])
    assert "replaced the partial output of an unfinished earlier run" in capsys.readouterr().out
    a, b = _digest(out), _digest(ref)  # the CLI writes gzip frames: same files, same sim_info.json
    assert a.keys() == b.keys() and a["sim_info.json"] == b["sim_info.json"]
    assert len(list_nyu_h5(out, "train")) == 2 and len(list_nyu_h5(out, "val")) == 1


def test_interrupted_imu_completion_removes_its_partial_output_and_a_rerun_equals_an_uninterrupted_run(
    tiny_seq, tmp_path, monkeypatch, capsys
):
    from sim.cli import main

    args = [f"source={tiny_seq}", "vibration=false", "seed=2"]
    main(["imu", f"out={tmp_path / 'ref'}", *args])
    monkeypatch.setattr(os, "symlink", fail_on_call(os.symlink, 6, []))  # Ctrl-C after 5 of the images were linked
    out = tmp_path / "out"
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["imu", f"out={out}", *args])
    err = capsys.readouterr().err
    assert e.value.code == 130 and "dit-sim imu: interrupted; the partial output was removed" in err
    assert list(out.rglob("*")) == []
    monkeypatch.undo()
    main(["imu", f"out={out}", *args])
    text = capsys.readouterr().out
    assert "dit-sim imu: wrote" in text and "replaced" not in text  # nothing was left to replace
    assert _digest(out) == _digest(tmp_path / "ref")


def test_a_killed_imu_completion_is_replaced_by_a_rerun_that_says_so(tiny_seq, tmp_path, monkeypatch, capsys):
    from sim import complete, output
    from sim.cli import main

    args = [f"source={tiny_seq}", "vibration=false", "seed=2"]
    main(["imu", f"out={tmp_path / 'ref'}", *args])

    def killed(*a):
        raise RuntimeError("killed")

    monkeypatch.setattr(complete, "_write_csv", killed)  # dies after the images were linked ...
    monkeypatch.setattr(output, "remove_output", lambda out, parts: None)  # ... with no cleanup (as after SIGKILL)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="killed"):
        complete.complete_imu(tiny_seq, out, errors=None, seed=2)
    assert json.loads((out / "sim_info.json").read_text())["complete"] is False
    monkeypatch.undo()
    capsys.readouterr()
    main(["imu", f"out={out}", *args])
    assert "replaced the partial output of an unfinished earlier run" in capsys.readouterr().out
    assert _digest(out) == _digest(tmp_path / "ref")
