"""Models: a folder mixing two exports, or whose manifest records no file hashes, is refused at load; an
interrupted export leaves the old model; a model the runtime cannot feed is refused before any frame."""

import json
import shutil

import numpy as np
import pytest

from runtime.network import DepthNetwork, ModelError, default_model_dir
from tests.reliability.fakes import write_model


def test_folder_mixing_two_exports_is_refused(tmp_path):
    a = write_model(tmp_path / "a", bias=0.1)
    b = write_model(tmp_path / "b", bias=0.7)
    shutil.copy(b / "prior.onnx", a / "prior.onnx")  # the new prior beside the old decoder and manifest
    with pytest.raises(ModelError, match=r"prior\.onnx: SHA-256 does not match manifest\.json \(export fake-0\.1\)"):
        DepthNetwork(a)
    DepthNetwork(b)  # an untouched export loads


def test_model_whose_manifest_has_no_file_hashes_is_refused(tmp_path):
    old = write_model(tmp_path / "old", hashes=False)  # as dit-export wrote it before the hashes were added
    with pytest.raises(ModelError) as e:
        DepthNetwork(old)
    msg = str(e.value)
    assert (
        msg.startswith(f"{old}: manifest.json records no file hashes") and "re-export the model with dit-export" in msg
    )
    DepthNetwork(write_model(tmp_path / "new"))  # the same model with its hashes loads


def test_dit_slam_refuses_a_model_without_file_hashes_in_one_line(tiny_seq, tmp_path, capsys):
    from apps.slam import main as slam_main

    model = write_model(tmp_path / "old", hashes=False)
    with pytest.raises(SystemExit) as e:
        slam_main([f"sequence={tiny_seq}", f"out={tmp_path / 'o'}", "dense=true", f"model={model}", "progress=false"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert f"{model}: manifest.json records no file hashes" in err and "dit-export" in err
    assert not (tmp_path / "o" / "trajectory.txt").exists()


def test_shipped_manifest_records_the_hashes_of_its_files():
    from runtime.network import file_sha256

    m = json.loads((default_model_dir() / "manifest.json").read_text())
    assert m["run_id"] and set(m["files"]) == {"prior.onnx", "decoder.onnx"}
    for name, rec in m["files"].items():
        assert rec["sha256"] == file_sha256(default_model_dir() / name)


def test_interrupted_export_leaves_the_earlier_model_whole(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    import export.onnx as ex
    from benchmarks.common import standin_net

    out = write_model(tmp_path / "model")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    calls = []

    def fake_export(module, args, path, *rest):
        calls.append(path)
        if len(calls) == 2:  # Ctrl-C after prior.onnx was written, before decoder.onnx
            raise KeyboardInterrupt
        path.write_bytes(b"new prior")

    monkeypatch.setattr(ex, "_export", fake_export)
    with pytest.raises(KeyboardInterrupt):
        ex.export_network(standin_net("grays", 64, 96), out, modality="grays", height=64, width=96)
    assert calls[0].parent != out  # written into a temporary folder, not into the model
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]  # the temporary folder was removed
    DepthNetwork(out)


def test_export_refuses_a_folder_it_did_not_write(tmp_path):
    pytest.importorskip("torch")
    import export.onnx as ex
    from benchmarks.common import standin_net

    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="dit-export did not write"):
        ex.export_network(standin_net("grays", 64, 96), tmp_path, modality="grays", height=64, width=96)
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_rgb_model_is_refused_at_load_not_at_the_first_keyframe(tmp_path):
    net = DepthNetwork(write_model(tmp_path / "rgb", modality="rgb"))
    with pytest.raises(ModelError, match="modality is 'rgb'; dit-slam feeds grey images"):
        net.check_runtime()
    assert DepthNetwork(write_model(tmp_path / "g", modality="gray")).check_runtime().modality == "gray"


def test_dit_slam_refuses_an_rgb_model_before_processing_frames(tiny_seq, tmp_path, capsys):
    from apps.slam import main as slam_main

    model = write_model(tmp_path / "rgb", modality="rgb")
    with pytest.raises(SystemExit) as e:
        slam_main([f"sequence={tiny_seq}", f"out={tmp_path / 'o'}", "dense=true", f"model={model}", "progress=false"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "modality is 'rgb'" in err and "Traceback" not in err
    assert not (tmp_path / "o" / "trajectory.txt").exists()


def test_model_whose_graph_size_differs_from_its_manifest_is_refused(tmp_path):
    out = write_model(tmp_path / "m")
    m = json.loads((out / "manifest.json").read_text())
    m["height"], m["width"] = 96, 128  # the manifest of another size beside these graphs
    (out / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelError, match=r"input shape \[1, 2, 64, 96\] does not match"):
        DepthNetwork(out)
    assert np.isfinite(DepthNetwork(write_model(tmp_path / "ok")).height)


def test_run_sequence_checks_the_model_before_the_intrinsics_pass(tiny_seq, tmp_path, monkeypatch):
    import runtime.run
    from runtime.dense import DenseConfig
    from runtime.io.euroc import read_euroc

    def first_pass(*a, **k):
        raise AssertionError("the intrinsics' first pass ran before the model was checked")

    monkeypatch.setattr(runtime.run, "_refine_intrinsics", first_pass)
    model = write_model(tmp_path / "rgb", modality="rgb")
    with pytest.raises(ModelError, match="modality is 'rgb'"):
        runtime.run.run_sequence(read_euroc(tiny_seq), tmp_path / "o", dense=DenseConfig(), model_dir=model)
