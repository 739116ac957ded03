"""The map's codes refined at fixed poses (:mod:`runtime.dense.refine`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from runtime.dense.config import SIGMA_PER_LAPLACE_B, DepthFactorConfig, MapCodeConfig
from runtime.dense.linearized import LinearizedDepth
from runtime.dense.refine import refine_codes
from runtime.dense.sampling import sample_consistency_pixels
from tests.dense.fakes import T_B_C, ExpDepth, LinearDepth, body_pose, dct_bases, network_K, plane_depth

H, W, CD = 48, 64, 8
K = network_K(H, W)
CFG = DepthFactorConfig(sigma_per_b=SIGMA_PER_LAPLACE_B, min_sigma=0.01, edge_rel=None)


class _Net:
    code_dim = CD


def _wall(n: int, seed: int, kind=LinearDepth, spread: float = 0.7):
    """``n`` keyframes with fixed poses facing a wall; each provider decodes the true depth at its code c*.

    Keyframe 0's prior is right (c* = 0). Eq. 14 alone cannot tell one consistent scene from another (the wall a
    little further away agrees with itself as well), so keyframe 0's code prior is what fixes where the wall is."""
    rng = np.random.default_rng(seed)
    Ts = [body_pose((0.05 * k - 0.05, 0.02 * k, 0.0), (0.1 * k, 0.25 * k - 0.25, 0.05 * k)) for k in range(n)]
    bases = dct_bases(CD, H, W, amplitude=0.1)
    truth = [plane_depth(T, K, (H, W), 3.0) for T in Ts]
    c_true = [np.zeros(CD)] + [rng.normal(0, spread, CD) for _ in range(n - 1)]
    B = np.full((H, W), 0.02)
    offsets = [np.tensordot(c, bases, 1) for c in c_true]
    if kind is LinearDepth:
        provs = [LinearDepth(d - o, bases, B) for d, o in zip(truth, offsets, strict=True)]
    else:
        provs = [ExpDepth(d * np.exp(-o), bases, B) for d, o in zip(truth, offsets, strict=True)]
    lin = []
    for p in provs:
        p.net = _Net()
        L = LinearizedDepth(p)
        L.relinearize(np.zeros(CD))
        lin.append(L)
    samples = [sample_consistency_pixels(np.zeros((0, 2)), W, H, 200, rng=k, margin=2).uv for k in range(n)]
    return lin, Ts, truth, c_true, samples


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


def test_consistency_alone_brings_the_maps_to_the_wall():
    """From c = 0, Eq. 14 at the true poses brings the other keyframes' maps most of the way to keyframe 0's wall.
    (Not all of it: a slightly shifted wall is as consistent, and it spreads the code prior's cost over the four.)"""
    lin, Ts, truth, c_true, samples = _wall(4, seed=1)
    codes, info = refine_codes(lin, [np.zeros(CD)] * 4, Ts, samples, T_B_C, K, CFG, code_prior_sigma=1.0, iterations=8)
    before = [_rmse(p.depth(np.zeros(CD)), d) for p, d in zip(lin, truth, strict=True)]
    after = [_rmse(p.depth(c), d) for p, c, d in zip(lin, codes, truth, strict=True)]
    assert before[0] < 1e-9 and min(before[1:]) > 0.04
    assert after[0] < 0.02
    assert all(a < 0.35 * b for a, b in zip(after[1:], before[1:], strict=True)), (before, after)
    assert info["cost"][1] < 0.01 * info["cost"][0]
    assert info["rows"] > 0 and info["iterations"] >= 1


def _disagreement(lin, codes, Ts, samples) -> float:
    """RMS [m] of Eq. 14 over every ordered pair, with the exact decoder at ``codes``."""
    from runtime.dense.factors import consistency_residuals
    from runtime.dense.lookup import Bilinear

    fx, fy, cx, cy = K
    r = []
    for a in range(len(lin)):
        for b in range(len(lin)):
            if a != b:
                uv = samples[b]
                rays = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))], -1)
                res = consistency_residuals(
                    Ts[a], Ts[b], T_B_C, K, Bilinear(uv, (H, W)), rays, lin[a].exact(codes[a]), lin[b].exact(codes[b])
                )
                r.append(res.r[res.valid])
    return float(np.sqrt(np.mean(np.concatenate(r) ** 2)))


def test_a_nonlinear_decoder_is_made_consistent_and_the_robust_cost_never_rises():
    """The decoder is exponential in the code; the fit sees its expansion at c = 0 only. The exact maps still
    come to agree with each other, and the robust cost falls."""
    lin, Ts, truth, _, samples = _wall(3, seed=2, kind=ExpDepth, spread=0.5)
    cfg = dataclasses.replace(CFG, consis_huber_k=1.5)
    zero = [np.zeros(CD)] * 3
    codes, info = refine_codes(lin, zero, Ts, samples, T_B_C, K, cfg, code_prior_sigma=1.0, iterations=4)
    assert info["cost"][1] <= info["cost"][0]
    before, after = _disagreement(lin, zero, Ts, samples), _disagreement(lin, codes, Ts, samples)
    assert after < 0.2 * before, (before, after)


def test_the_code_prior_holds_codes_the_views_do_not_ask_to_move():
    """Maps that already agree at c = 0 stay there; a tight prior keeps a disagreement from moving codes."""
    lin, Ts, truth, c_true, samples = _wall(3, seed=3, spread=0.0)  # c* = 0 everywhere: the prior is right
    codes, _ = refine_codes(lin, [np.zeros(CD)] * 3, Ts, samples, T_B_C, K, CFG, code_prior_sigma=1.0, iterations=4)
    assert max(np.abs(c).max() for c in codes) < 1e-3
    lin, Ts, truth, c_true, samples = _wall(3, seed=4)
    loose, _ = refine_codes(lin, [np.zeros(CD)] * 3, Ts, samples, T_B_C, K, CFG, code_prior_sigma=10.0, iterations=4)
    tight, _ = refine_codes(lin, [np.zeros(CD)] * 3, Ts, samples, T_B_C, K, CFG, code_prior_sigma=1e-4, iterations=4)
    assert np.linalg.norm(tight[1]) < 0.05 * np.linalg.norm(loose[1])


def test_bad_input_is_refused():
    lin, Ts, _, _, samples = _wall(2, seed=5)
    with pytest.raises(ValueError, match="2 or more"):
        refine_codes(lin[:1], [np.zeros(CD)], Ts[:1], samples[:1], T_B_C, K, CFG)
    with pytest.raises(ValueError, match="code_prior_sigma"):
        refine_codes(lin, [np.zeros(CD)] * 2, Ts, samples, T_B_C, K, CFG, code_prior_sigma=0.0)
    with pytest.raises(ValueError, match="neighbours"):
        MapCodeConfig(neighbours=-1)
    with pytest.raises(ValueError, match="sigma_per_b"):
        MapCodeConfig(sigma_per_b=0.0)
