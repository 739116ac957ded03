"""Smoke test of benchmarks/bench_network.py at 64x64 on a stand-in net, and of its exact Jacobian graph."""

import json

import numpy as np
import pytest
import torch

from benchmarks import bench_network as bench
from tests.benchmarks.conftest import standin_args


def test_session_configs_cover_the_sweep():
    cfgs = bench.session_configs(2)
    assert len(cfgs) == 24 and len(set(cfgs)) == 24
    assert {c.threads for c in cfgs} == {1, 2} and {c.optimization for c in cfgs} == {
        "all",
        "basic",
        "disable",
    }
    assert all(c.threads == 1 for c in bench.session_configs(1))  # never more threads than cores


def test_fresh_codes_never_repeat():
    codes = bench.FreshCodes(8, seed=0)
    a, b = codes(), codes()
    assert a.dtype == np.float32 and a.shape == (8,) and a.tobytes() != b.tobytes()


def test_bench_network_tiny(tiny, tmp_path, capsys):
    model_dir, data, _ = tiny
    out = tmp_path / "res"
    argv = standin_args(model_dir, data) + [
        "--runs",
        "2",
        "--torch-runs",
        "1",
        "--sweep-runs",
        "1",
        "--rounds",
        "1",
        "--warmup",
        "0",
        "--rev-chunk",
        "16",
        "--no-exact",
        "--out",
        str(out),
    ]
    bench.main(argv)
    res = json.loads((out / "network.json").read_text())
    stats = res["comparison"]["stats"]
    want = {
        "ort_fd",
        "ort_fd_separate",
        "ort_fd_loop",
        "torch_fd",
        "torch_autograd",
        "torch_jacfwd",
        "torch_reverse",
        "ort_prior",
        "torch_prior",
        "ort_decode",
        "torch_decode",
    }
    assert want <= set(stats)
    for k in want:
        assert 0 < stats[k]["median_ms"] < 600_000, k
    assert res["ratios_to_ort_fd"]["ort_fd"] == 1.0
    assert stats["torch_reverse"]["extrapolated"] is True
    # the timed methods compute the same Jacobian
    acc = res["comparison"]["accuracy"]
    assert acc["torch_jacfwd"] < 1e-4 and acc["torch_reverse_chunk_max_abs"] < 1e-4
    assert acc["ort_fd"] < 0.15 * acc["mean_abs_J"]
    assert res["comparison"]["exact_graph"]["status"].startswith("skipped")
    sweep = res["session_sweep"]
    assert len(sweep) == 12 and all(r["threads"] == 1 and r["median_ms"] > 0 for r in sweep)
    assert {r["optimization"] for r in sweep} == {"all", "basic", "disable"}
    assert res["session_fastest"]["median_ms"] == min(r["median_ms"] for r in sweep)
    assert res["machine"]["cpu"] and res["machine"]["ort_threads"] == 1
    printed = capsys.readouterr().out
    assert "x ORT FD" in printed and "4.5 ms" in printed and "STAND-IN" in printed


@pytest.mark.slow
def test_exact_jacobian_graph_matches_autograd(tiny, tmp_path):
    """Item 6: the forward-mode Jacobian exported to ONNX equals torch autograd to float32 round-off."""
    import onnxruntime as ort

    _, _, common = tiny
    net = common.standin_net("grays", 64, 64, 0.25, seed=0)
    for q in net.parameters():
        q.requires_grad_(False)
    with torch.no_grad():
        _, feats = net.prior(torch.rand(1, 2, 64, 64, generator=torch.Generator().manual_seed(1)))
    path = bench.export_exact_jacobian(net, list(feats), tmp_path / "jacobian_exact.onnx")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    code = np.linspace(-1, 1, 8).astype(np.float32)
    depth, J = sess.run(None, {"code": code[None], **{f"feat{i}": f.numpy() for i, f in enumerate(feats)}})
    J_ref = torch.autograd.functional.jacobian(
        lambda c: net.decoder(c[None], *feats)[0, 0],
        torch.from_numpy(code),
        vectorize=True,
        strategy="forward-mode",
    ).numpy()
    assert J.shape == (64, 64, 8) and depth.shape == (1, 1, 64, 64)
    assert np.abs(J_ref).mean() > 1e-2
    np.testing.assert_allclose(J, J_ref, atol=1e-4)
    with torch.no_grad():
        np.testing.assert_allclose(
            depth, net.decoder(torch.from_numpy(code)[None], *feats).numpy(), atol=1e-5
        )


def test_a_missing_model_exits_with_one_line_naming_the_benchmark(tiny, tmp_path):
    import argparse

    *_, common = tiny
    args = argparse.Namespace(
        model=str(tmp_path / "no_model"),
        ckpt=None,
        modality="grays",
        height=64,
        width=64,
        width_mult=0.25,
        seed=0,
        standin_dir=None,
        data=None,
    )
    with pytest.raises(SystemExit, match=r"^bench_x: .*no_model"):
        common.model_and_val_data(args, 1, "bench_x")


def test_parity_check_sees_a_prior_built_without_the_graphs_contrast_matching(tmp_path):
    """The benchmarks pair ONNX graphs with torch weights; the same weights without the exported graph's contrast
    matching must fail the parity check, with it pass."""
    from benchmarks.common import decoder_parity, standin_net
    from export.onnx import export_network
    from models import build_model

    plain = standin_net("grays", 64, 64)
    matched = build_model("dit", "grays", width_mult=0.25, height=64, width=64, image_contrast=0.2).eval()
    matched.load_state_dict(plain.state_dict())
    export_network(matched, tmp_path, modality="grays", height=64, width=64)
    assert decoder_parity(matched, tmp_path) < 1e-4
    assert decoder_parity(plain, tmp_path) > 1e-3
