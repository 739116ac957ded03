"""Smoke test of benchmarks/bench_jacobian.py (Fig. 6) at 64x64 on a stand-in net, plus its FD helper."""

import json

import numpy as np
import pytest
import torch

from benchmarks import bench_jacobian as bench
from tests.benchmarks.conftest import standin_args


def test_delta_grid_holds_exact_decades():
    g = bench.delta_grid(1e-5, 1.0, 2)
    assert len(g) == 11 and g[0] == pytest.approx(1e-5) and g[-1] == pytest.approx(1.0)
    assert np.any(np.isclose(g, 1e-2, rtol=1e-12))
    with pytest.raises(ValueError, match="0 < lo < hi"):
        bench.delta_grid(1.0, 1e-5, 2)


def test_fd_helper_matches_the_runtime_jacobian(tiny):
    """fd_jacobian with one delta for all dimensions is the runtime's KeyframeDepth.jacobian, bit for bit."""
    from runtime.network import DepthNetwork, SessionConfig

    model_dir, _, _ = tiny
    dn = DepthNetwork(model_dir, SessionConfig(threads=1))
    rng = np.random.default_rng(0)
    kf = dn.prior(rng.random((64, 64)).astype(np.float32), np.zeros((64, 64), np.float32))
    code = (0.5 * rng.standard_normal(8)).astype(np.float32)
    d_rt, J_rt = kf.jacobian(code, delta=3e-3)
    d, J = bench.fd_jacobian(dn, kf.features, code, np.full(8, 3e-3))
    np.testing.assert_array_equal(J, J_rt)
    np.testing.assert_array_equal(d, d_rt)
    # nominal in a separate call: equal up to batch-dependent float32 kernels (~1e-7 m / 3e-3)
    _, J_sep = bench.fd_jacobian(dn, kf.features, code, np.full(8, 3e-3), nominal_in_batch=False)
    np.testing.assert_allclose(J_sep, J_rt, atol=1e-2)
    # one dimension at its own step: that column changes, the others stay bit for bit
    steps = np.full(8, 3e-3)
    steps[2] = 1e-1
    _, J_mixed = bench.fd_jacobian(dn, kf.features, code, steps)
    np.testing.assert_array_equal(np.delete(J_mixed, 2, axis=2), np.delete(J_rt, 2, axis=2))
    assert np.abs(J_mixed[:, :, 2] - J_rt[:, :, 2]).max() > 1e-4
    with pytest.raises(ValueError, match="positive steps"):
        bench.fd_jacobian(dn, kf.features, code, np.zeros(8))


def test_bench_jacobian_tiny(tiny, tmp_path, capsys):
    model_dir, data, _ = tiny
    out = tmp_path / "res"
    argv = standin_args(model_dir, data) + [
        "--frames",
        "1",
        "--random-codes",
        "1",
        "--delta-min",
        "1e-4",
        "--delta-max",
        "1",
        "--per-decade",
        "1",
        "--out",
        str(out),
    ]
    bench.main(argv)
    res = json.loads((out / "jacobian.json").read_text())
    assert (out / "jacobian_delta.png").stat().st_size > 10_000
    deltas = np.array(res["deltas"])
    np.testing.assert_allclose(deltas, [1e-4, 1e-3, 1e-2, 1e-1, 1.0])
    assert res["model"]["source"] == "stand-in" and res["data"]["synthetic"] is True
    assert len(res["pairs"]) == 2 and res["machine"]["cores"] >= 1 and res["machine"]["cpu"]
    a = res["sweep_all_dims"]
    mean_abs, rel = np.array(a["mean_abs"]), np.array(a["rel_mean"])
    assert mean_abs.shape == (5,) and np.isfinite(mean_abs).all() and (mean_abs > 0).all()
    assert (np.array(a["max_abs"]) >= mean_abs).all()
    assert res["mean_abs_J"] > 1e-2  # the stand-in's code visibly matters
    k = {d: i for i, d in enumerate([1e-4, 1e-3, 1e-2, 1e-1, 1.0])}
    # Fig. 6 (a): a small step beats a step of 1 by far; at 1e-2 the error is a few % of |J|
    assert mean_abs[k[1e-2]] < 0.5 * mean_abs[k[1.0]]
    assert rel[k[1e-2]] < 0.15 and rel[k[1.0]] > rel[k[1e-2]]
    # (b): 8 curves over the same deltas, and a batch's rows do not interact
    b = res["sweep_per_dim"]
    col = np.array(b["mean_abs"])
    assert col.shape == (8, 5) and (col[:, k[1e-2]] < col[:, k[1.0]]).all()
    assert b["rows_independent_max_abs"] == 0.0
    best = res["best"]
    assert best["all_dims"]["delta"] in res["deltas"] and len(best["per_dim"]) == 8
    assert (
        best["at_fixed_delta"]["delta"] == pytest.approx(1e-2) and best["at_fixed_delta"]["over_best"] >= 1.0
    )
    printed = capsys.readouterr().out
    assert "STAND-IN" in printed and "smallest mean error at delta" in printed and "| delta |" in printed


def test_autograd_reference_is_exact(tiny):
    """The reference (forward mode) equals reverse-mode autograd on a few pixels."""
    model_dir, _, common = tiny
    net = common.standin_net("grays", 64, 64, 0.25, seed=0)
    with torch.no_grad():
        _, feats = net.prior(torch.rand(1, 2, 64, 64, generator=torch.Generator().manual_seed(0)))
    code = np.linspace(-0.5, 0.5, 8).astype(np.float32)
    J = bench.autograd_jacobian(net, feats, code)
    c = torch.from_numpy(code).requires_grad_()
    depth = net.decoder(c[None], *feats)[0, 0]
    for v, u in [(0, 0), (31, 17), (63, 63)]:
        (g,) = torch.autograd.grad(depth[v, u], c, retain_graph=True)
        np.testing.assert_allclose(J[v, u], g.numpy(), atol=1e-5)
