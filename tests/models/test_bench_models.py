"""Smoke test of benchmarks/bench_models.py at a tiny size: it runs, counts, and writes its JSON."""

import importlib.util
import json
from pathlib import Path

import torch

torch.set_num_threads(1)

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_models.py"


def test_bench_models_tiny(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("bench_models", SCRIPT)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "models.json"
    argv = ["--models", "codevio8", "fastdepth", "--modalities", "gray", "--height", "64", "--width", "64"]
    argv += ["--width-mult", "0.25", "--runs", "1", "--warmup", "0", "--threads", "1", "--out", str(out)]
    bench.main(argv)
    data = json.loads(out.read_text())
    rows = {r["model"]: r for r in data["rows"]}
    assert set(rows) == {"codevio8", "fastdepth"}
    assert rows["fastdepth"]["ratio_vs_fastdepth"] == 1.0
    for r in rows.values():
        assert r["params"] > 1e5 and r["gflops"] > 0 and r["forward_ms"] > 0
    # the inference graph excludes the training-only depth encoder
    assert rows["codevio8"]["infer_params"] < rows["codevio8"]["params"]
    assert rows["codevio8"]["decoder_b8_ms"] > 0
    assert "| codevio8 | gray |" in capsys.readouterr().out
