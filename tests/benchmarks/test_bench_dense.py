"""benchmarks/bench_dense.py end to end at a tiny size: the table, the JSON, and runtime overrides (--slam-set)."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_dense


def _argv(tmp_path, *extra: str) -> list[str]:
    return [
        "--presets", "textured", "--seeds", "0", "--duration", "8", "--scale", "0.25", "--modes", "sparse",
        "--data", str(tmp_path / "data"), "--out", str(tmp_path / "out"), *extra,
    ]  # fmt: skip


def test_slam_set_reaches_the_runs_and_the_json(tmp_path, capsys):
    assert bench_dense.main(_argv(tmp_path, "--slam-set", "backend.window_size=6", "reloc.enabled=false")) == 0
    run = json.loads((tmp_path / "out" / "textured_s0_sparse" / "metrics.json").read_text())
    assert run["config"]["backend"]["window_size"] == 6 and run["config"]["reloc"]["enabled"] is False
    assert run["config"]["backend"]["marginal_visual_fix"] is True  # untouched keys keep the defaults
    res = json.loads((tmp_path / "out" / "bench_dense.json").read_text())
    assert res["args"]["slam_set"] == ["backend.window_size=6", "reloc.enabled=false"]
    assert res["machine"]["cpu"]  # runs differ between CPUs: the result names its CPU
    (row,) = res["rows"]
    assert row["mode"] == "sparse" and row["ate"] == pytest.approx(run["ate_se3_rmse_m"])
    assert row["peak_rss_mb"] == run["peak_rss_mb"] > 0 and row["later_jobs_at_last_frame"] is None  # no network
    assert "textured   sparse" in capsys.readouterr().out


def test_an_unknown_runtime_key_is_refused_before_anything_is_rendered(tmp_path):
    with pytest.raises(ValueError, match="unknown setting runtime.backend.no_such_key"):
        bench_dense.main(_argv(tmp_path, "--slam-set", "backend.no_such_key=1"))
    assert not (tmp_path / "data").exists() and not (tmp_path / "out").exists()


def test_dense_overrides_leave_the_mode_its_residuals_and_parse_numbers():
    sets = ["factors.sigma_per_b=3", "use_depth_residual=true", "factors.edge_rel=5e-2"]
    cfg = bench_dense.dense_config("dense_gt_eq14", sets)
    assert cfg.factors.sigma_per_b == 3.0 and cfg.factors.edge_rel == pytest.approx(0.05)  # "5e-2": a number
    assert cfg.use_depth_residual is False and cfg.use_consistency and "dense_gt_eq14" in bench_dense.GROUND_TRUTH_MODES
    assert bench_dense.dense_config("dense_gt_eq14", []).factors.sigma_per_b == pytest.approx(2**0.5)  # the mode's
    assert bench_dense.dense_config("sparse", ["factors.edge_rel=0.05"]) is None
    net = bench_dense.dense_config("dense_eq13", ["start_after_s=5"])
    assert not net.use_consistency and net.start_after_s == 5.0 and "dense_eq13" not in bench_dense.GROUND_TRUTH_MODES


def test_an_interrupted_invocation_keeps_its_runs_and_resume_runs_only_the_missing_ones(tmp_path, interrupt_second_run):
    argv = _argv(tmp_path, "--seeds", "0", "1")
    calls = interrupt_second_run(bench_dense)  # the second run is stopped by the user
    with pytest.raises(KeyboardInterrupt):
        bench_dense.main(argv)
    path = tmp_path / "out" / "bench_dense.json"
    part = json.loads(path.read_text())
    assert part["complete"] is False and [(r["seed"], r["mode"]) for r in part["rows"]] == [(0, "sparse")]
    with pytest.raises(ValueError, match="other arguments"):  # a resume must not mix settings
        bench_dense.main([*argv, "--resume", "--slam-set", "backend.window_size=6"])
    calls.clear()
    assert bench_dense.main([*argv, "--resume"]) == 0
    assert calls == ["textured_s1_sparse"]  # seed 0 was kept, only seed 1 ran
    res = json.loads(path.read_text())
    assert res["complete"] is True and [r["seed"] for r in res["rows"]] == [0, 1]
    assert res["rows"][0] == part["rows"][0] and "resume" not in res["args"]
    assert not path.with_name(path.name + ".tmp").exists()
    part["machine"]["cpu"] = "another CPU"
    path.write_text(json.dumps(part))
    with pytest.raises(ValueError, match="another CPU"):
        bench_dense.main([*argv, "--resume"])


def test_a_missing_model_is_refused_before_anything_is_rendered(tmp_path):
    from runtime.network import ModelError

    with pytest.raises(ModelError):
        bench_dense.main(_argv(tmp_path, "--model", str(tmp_path / "no_model")))
    assert not (tmp_path / "data").exists() and not (tmp_path / "out").exists()


def test_model_reaches_the_runs_and_the_json_names_it(tmp_path, monkeypatch):
    import hashlib
    import shutil

    from runtime.network import default_model_dir

    model = tmp_path / "model"
    shutil.copytree(default_model_dir(), model)
    real, seen = bench_dense.run_sequence, []

    def recording(seq, out, *a, **kw):
        seen.append(kw["model_dir"])
        return real(seq, out, *a, **kw)

    monkeypatch.setattr(bench_dense, "run_sequence", recording)
    assert bench_dense.main(_argv(tmp_path, "--model", str(model))) == 0
    assert seen == [str(model)]
    res = json.loads((tmp_path / "out" / "bench_dense.json").read_text())
    assert res["model"]["dir"] == str(model) and res["model"]["shipped"] is False
    assert res["model"]["sha256"]["decoder.onnx"] == hashlib.sha256((model / "decoder.onnx").read_bytes()).hexdigest()
    shipped = bench_dense.model_identity(None)
    assert shipped["shipped"] is True and shipped["sha256"] == res["model"]["sha256"]  # a copy: the same files


def test_paired_difference_of_dense_against_sparse_over_common_seeds():
    rows = [
        {"preset": "p", "mode": "sparse", "seed": 0, "ate": 0.10, "fps": 40.0},
        {"preset": "p", "mode": "dense_eq13_14", "seed": 0, "ate": 0.08, "fps": 20.0},
        {"preset": "p", "mode": "sparse", "seed": 1, "ate": 0.20, "fps": 30.0},
        {"preset": "p", "mode": "dense_eq13_14", "seed": 1, "ate": 0.21, "fps": 30.0},
        {"preset": "p", "mode": "dense_eq13_14", "seed": 2, "ate": 9.0, "fps": 1.0},  # no sparse run: not paired
        {"preset": "q", "mode": "sparse", "seed": 0, "ate": 5.0, "fps": 1.0},
    ]
    d = bench_dense.paired(rows, "p", "dense_eq13_14", "sparse")
    assert d["n_seeds"] == 2
    assert d["ate_diff_mean"] == pytest.approx(-0.005)  # -0.02 and +0.01
    assert d["ate_diff_se"] == pytest.approx(0.015)  # std (ddof 1) 0.0212 / sqrt(2)
    assert d["fps_ratio_mean"] == pytest.approx(0.75) and d["met"]


def test_given_sequences_take_their_seed_from_the_folder_name(tmp_path):
    for name in ("euroc_flight_30s_s2", "mh05"):
        (tmp_path / name / "mav0" / "cam0").mkdir(parents=True)
        (tmp_path / name / "mav0" / "cam0" / "data.csv").write_text("#\n")
    assert bench_dense.named_sequence(str(tmp_path / "euroc_flight_30s_s2"))[:2] == ("euroc_flight_30s", 2)
    assert bench_dense.named_sequence(str(tmp_path / "mh05"))[:2] == ("mh05", 0)
    with pytest.raises(SystemExit, match="not an EuRoC-layout sequence"):
        bench_dense.named_sequence(str(tmp_path / "nothing"))
