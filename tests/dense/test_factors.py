"""Depth factors (Eq. 13-14): known answers, Jacobians of every key against central differences, noise models,
code recovery by LM on a small window, and the cost of one linearisation."""

import dataclasses
import time

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import C, L, X

from runtime.backend.factors import analytic_jacobians, custom_factor, numerical_jacobians
from runtime.dense.config import SIGMA_PER_LAPLACE_B, DepthFactorConfig
from runtime.dense.factors import consistency_residuals, make_consistency_factor, make_geometric_depth_factors
from runtime.dense.linearized import LinearizedDepth
from runtime.dense.lookup import Bilinear, MapExpansion, depth_edge_ratio, inside_image
from runtime.dense.sampling import sample_consistency_pixels
from runtime.geometry import inv_T, to_pose3
from tests.dense.fakes import (
    T_B_C,
    ExpDepth,
    LinearDepth,
    body_pose,
    dct_bases,
    network_K,
    plane_depth,
    smooth_bases,
)

H, W, CD = 48, 64, 8
K = network_K(H, W)
#: the factors on their own: Laplace sigmas, no edge test, every Jacobian's shape checked (the dense system's
#: defaults are DepthFactorConfig's)
PLAIN = DepthFactorConfig(
    sigma_per_b=SIGMA_PER_LAPLACE_B, min_sigma=0.01, consis_huber_k=None, edge_rel=None, check_shapes=True
)


def fcfg(**kw) -> DepthFactorConfig:
    return dataclasses.replace(PLAIN, **kw)


NO_ROBUST = fcfg(geo_huber_k=None, consis_huber_k=None)


# --------------------------------------------------------------------------- helpers
def assert_jacobians_match(factor, values, rtol=1e-5, atol=1e-7):
    num = numerical_jacobians(factor, values)
    ana = analytic_jacobians(factor, values)
    assert len(num) == len(ana) == factor.size()
    for key, a, n in zip(factor.keys(), ana, num, strict=True):
        assert a.shape == n.shape, gtsam.DefaultKeyFormatter(key)
        scale = max(1.0, np.abs(n).max())
        np.testing.assert_allclose(a, n, rtol=rtol, atol=atol * scale, err_msg=gtsam.DefaultKeyFormatter(key))
    return num


def wall_points(T_w_b, uv, depth):
    """World points of network pixels (N, 2) at depths (N,) seen from body pose T_w_b."""
    fx, fy, cx, cy = K
    p_c = np.stack([(uv[:, 0] - cx) / fx * depth, (uv[:, 1] - cy) / fy * depth, depth], -1)
    T_w_c = T_w_b @ T_B_C
    return p_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]


def with_landmarks(values, X_w):
    """``values`` with the landmarks ``L(j)`` at ``X_w`` (N, 3); returns their keys."""
    for j, p in enumerate(X_w):
        values.insert(L(j), p)
    return [L(j) for j in range(len(X_w))]


# --------------------------------------------------------------------------- bilinear
def test_bilinear_is_exact_on_affine_maps_with_its_gradient():
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    img = 0.5 + 0.25 * u - 0.125 * v
    uv = np.array([[0.0, 0.0], [3.3, 7.8], [W - 1.0, H - 1.0], [W - 1.0, 2.5], [-0.5, 3.0], [10.0, H - 0.5]])
    lk = Bilinear(uv, img.shape)
    val, du, dv = lk.sample_grad(img)
    np.testing.assert_allclose(val[:4], 0.5 + 0.25 * uv[:4, 0] - 0.125 * uv[:4, 1], atol=1e-12)
    np.testing.assert_allclose(du, 0.25, atol=1e-12)
    np.testing.assert_allclose(dv, -0.125, atol=1e-12)
    assert lk.inside.tolist() == [True, True, True, True, False, False]
    assert inside_image(uv, img.shape).tolist() == lk.inside.tolist()
    # multi-channel maps interpolate per channel
    stack = np.stack([img, 2 * img], -1)
    np.testing.assert_allclose(lk.sample(stack)[:, 1], 2 * lk.sample(img), atol=1e-12)


def test_an_expansion_looks_up_what_the_formed_map_gives():
    """``MapExpansion(D0, J0, dc)`` at some pixels = the map ``D0 + J0 dc`` looked up there: values, gradient,
    code Jacobian and the depth-edge ratio, float32 maps as the network gives them included."""
    rng = np.random.default_rng(5)
    D0 = (2.0 + smooth_bases(1, H, W, seed=3, amplitude=0.5)[0]).astype(np.float32)
    J0 = smooth_bases(CD, H, W, seed=4).transpose(1, 2, 0).astype(np.float32)
    D0[10:14, 20:30] += 1.0  # a step, for the edge test
    dc = rng.normal(0, 0.3, CD)
    uv = np.c_[rng.uniform(-2, W + 1, 300), rng.uniform(-2, H + 1, 300)]
    lk = Bilinear(uv, (H, W))
    e = MapExpansion(D0, J0, dc)
    D = D0 + np.asarray(J0, np.float64) @ dc
    np.testing.assert_allclose(e.sample(lk), lk.sample(D), rtol=1e-12)
    for got, want in zip(e.sample_grad(lk), lk.sample_grad(D), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(e.sample_jacobian(lk), lk.sample(J0), rtol=1e-12)
    ratio = depth_edge_ratio(e, uv)
    np.testing.assert_allclose(ratio, depth_edge_ratio(D, uv), rtol=1e-12)
    assert (ratio > 0.2).sum() > 3  # the step is seen
    np.testing.assert_allclose(MapExpansion(D0, J0, np.zeros(CD)).sample(lk), lk.sample(D0), rtol=1e-12)  # dc = 0
    # the lookup keeps the last expansion point's values at its pixels: another point is looked up afresh
    D1, J1 = D0 + np.float32(1.0), 2 * J0
    np.testing.assert_allclose(
        MapExpansion(D1, J1, dc).sample(lk), lk.sample(D1 + np.asarray(J1, float) @ dc), rtol=1e-12
    )
    np.testing.assert_allclose(e.sample(lk), lk.sample(D), rtol=1e-12)
    with pytest.raises(ValueError, match="Jacobian"):
        MapExpansion(D0, None, dc)
    with pytest.raises(ValueError, match="shape"):
        e.sample(Bilinear(uv, (H + 1, W)))


class _Net:
    code_dim = CD


def linearized(prov: LinearDepth, c0: np.ndarray) -> LinearizedDepth:
    """``prov`` behind the decoder cache, linearised at ``c0`` (exact everywhere: the decoder is linear)."""
    prov.net = _Net()
    p = LinearizedDepth(prov)
    p.relinearize(np.asarray(c0, np.float32).astype(np.float64))  # a code the network can see (float32)
    return p


def test_factors_on_the_decoder_cache_match_the_decoded_maps():
    """With a linear decoder the cache's expansion is exact away from its point: the factors evaluated on
    :class:`LinearizedDepth` (looked up, no map formed) give the residuals and Jacobians of the decoded maps."""
    cfg = fcfg(geo_huber_k=None, consis_huber_k=None, edge_rel=0.05)
    T, uv, X_w, prov, code = geometric_setup(seed=2, provider_cls=LinearDepth)
    v = gtsam.Values()
    v.insert(X(0), to_pose3(T))
    v.insert(C(0), code)
    keys = with_landmarks(v, X_w)
    far = code + 0.3  # the point the cache was linearised at is not where the factor is evaluated
    cached = linearized(prov, far)
    (exact,) = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, keys, cfg, prov.depth(code))
    (fast,) = make_geometric_depth_factors(X(0), C(0), uv, cached, T_B_C, keys, cfg, cached.expansion(code))
    calls = prov.jacobian_calls
    np.testing.assert_allclose(fast.unwhitenedError(v), exact.unwhitenedError(v), atol=1e-12)
    for a, b in zip(analytic_jacobians(fast, v), analytic_jacobians(exact, v), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    Ts, provs, uv2, codes = pair_setup(seed=3, provider_cls=LinearDepth)
    caches = tuple(linearized(p, c - 0.2) for p, c in zip(provs, codes, strict=True))
    v = pair_values(Ts, codes)
    exact = make_consistency_factor((X(0), X(1)), (C(0), C(1)), provs, uv2, K, T_B_C, Ts, codes, cfg)
    fast = make_consistency_factor((X(0), X(1)), (C(0), C(1)), caches, uv2, K, T_B_C, Ts, codes, cfg)
    assert fast.dim() == exact.dim() > 40
    r = exact.unwhitenedError(v)
    assert 0 < np.count_nonzero(r) < r.size  # rows that left k1's image or sit on an edge are silent
    np.testing.assert_allclose(fast.unwhitenedError(v), r, atol=1e-12)
    np.testing.assert_allclose(fast.noiseModel().sigmas(), exact.noiseModel().sigmas(), rtol=1e-12)
    for a, b in zip(analytic_jacobians(fast, v), analytic_jacobians(exact, v), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert prov.jacobian_calls == calls + 1  # the exact factor decoded; the cached one only looked up


# --------------------------------------------------------------------------- Eq. 13
def geometric_setup(seed=0, n=12, provider_cls=ExpDepth):
    rng = np.random.default_rng(seed)
    T = body_pose((0.05, -0.03, 0.02), (0.1, -0.2, 0.05))
    uv = np.stack([rng.uniform(2, W - 3, n), rng.uniform(2, H - 3, n)], -1)
    X_w = wall_points(T, uv, rng.uniform(1.5, 3.0, n))
    D0 = 2.0 + smooth_bases(1, H, W, seed=seed + 7, amplitude=0.3)[0]
    prov = provider_cls(D0, smooth_bases(CD, H, W, seed=seed), uncertainty=rng.uniform(0.01, 0.1, (H, W)))
    code = rng.normal(0, 0.5, CD)
    return T, uv, X_w, prov, code


def test_geometric_residual_known_answer():
    T = body_pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    uv = np.array([[10.0, 10.0], [30.5, 20.25], [50.0, 40.0]])
    X_w = wall_points(T, uv, np.array([2.0, 2.1, 1.7]))
    prov = LinearDepth(np.full((H, W), 2.0), np.zeros((CD, H, W)))
    v = gtsam.Values()
    v.insert(X(0), to_pose3(T))
    v.insert(C(0), np.zeros(CD))
    (f,) = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, with_landmarks(v, X_w), cfg=NO_ROBUST)
    np.testing.assert_allclose(f.unwhitenedError(v), [0.0, 0.1, -0.3], atol=1e-12)


@pytest.mark.parametrize("mode", ["variables", "chunked"])
def test_geometric_jacobians_every_key(mode):
    T, uv, X_w, prov, code = geometric_setup()
    v = gtsam.Values()
    v.insert(X(0), to_pose3(T))
    v.insert(C(0), code)
    cfg = fcfg(geo_huber_k=None, chunk_size=5 if mode == "chunked" else 0)
    for j, p in enumerate(X_w):
        v.insert(L(j), p)
    keys = [L(j) for j in range(len(X_w))]
    facs = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, landmark_keys=keys, cfg=cfg)
    assert [f.size() for f in facs] == ([2 + 5, 2 + 5, 2 + 2] if mode == "chunked" else [2 + 12])
    for f in facs:
        num = assert_jacobians_match(f, v)
        assert np.abs(num[0]).max() > 0.1 and np.abs(num[1]).max() > 1e-3  # pose and code really matter
    # residual values agree with a direct evaluation
    r = np.concatenate([f.unwhitenedError(v) for f in facs])
    T_c_w = inv_T(T @ T_B_C)
    z = (X_w @ T_c_w[:3, :3].T + T_c_w[:3, 3])[:, 2]
    np.testing.assert_allclose(r, z - Bilinear(uv, (H, W)).sample(prov.depth(code)), atol=1e-12)


def test_geometric_sigmas_and_robust_loss():
    T, uv, X_w, prov, code = geometric_setup(seed=1, n=20)
    cfg = fcfg(geo_huber_k=1.0, min_sigma=0.03)
    v = gtsam.Values()
    v.insert(X(0), to_pose3(T))
    v.insert(C(0), code)
    (f,) = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, with_landmarks(v, X_w), cfg=cfg)
    B = Bilinear(uv, (H, W)).sample(prov.uncertainty)
    sig = np.maximum(np.sqrt(2.0) * B, 0.03)
    np.testing.assert_allclose(f.noiseModel().noise().sigmas(), sig, rtol=1e-12)
    e = np.abs(f.unwhitenedError(v)) / sig
    assert (e > 1).any() and (e < 1).any()
    huber = np.where(e <= 1.0, 0.5 * e**2, e - 0.5)  # k = 1: per row, not on the stacked norm
    assert f.error(v) == pytest.approx(huber.sum(), rel=1e-9)


def test_geometric_drops_pixels_outside_and_checks_inputs():
    T, uv, X_w, prov, code = geometric_setup(n=4)
    uv[1] = [W + 3.0, 5.0]
    (f,) = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, [L(j) for j in range(4)], cfg=NO_ROBUST)
    assert f.dim() == 3
    with pytest.raises(ValueError, match="landmark_keys"):
        make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, None)
    with pytest.raises(ValueError, match="duplicates"):
        make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, landmark_keys=[L(0), L(0), L(1), L(2)])


def test_a_wrong_jacobian_is_caught():
    """The checks above have teeth: translation-first pose columns, or a wrong shape, are detected."""
    T, uv, X_w, prov, code = geometric_setup(n=6)
    v = gtsam.Values()
    v.insert(X(0), to_pose3(T))
    v.insert(C(0), code)
    (good,) = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, with_landmarks(v, X_w), cfg=NO_ROBUST)
    ana = analytic_jacobians(good, v)

    def swapped(values, want):
        r = good.unwhitenedError(values)
        return r, ([np.concatenate([ana[0][:, 3:], ana[0][:, :3]], 1), ana[1]] if want else None)

    bad = custom_factor(gtsam.noiseModel.Unit.Create(6), [X(0), C(0)], swapped, [6, CD])
    with pytest.raises(AssertionError):
        assert_jacobians_match(bad, v)

    def wrong_shape(values, want):
        return good.unwhitenedError(values), ([ana[0][:, :3], ana[1]] if want else None)

    bad2 = custom_factor(gtsam.noiseModel.Unit.Create(6), [X(0), C(0)], wrong_shape, [6, CD])
    with pytest.raises(Exception, match="shape"):
        bad2.linearize(v)


# --------------------------------------------------------------------------- Eq. 14
def pair_setup(seed=0, n=60, provider_cls=ExpDepth):
    rng = np.random.default_rng(seed)
    T1 = body_pose((0.02, 0.01, -0.01), (0.0, 0.0, 0.0))
    T2 = body_pose((-0.04, 0.02, 0.03), (0.15, 0.2, -0.05))
    provs = []
    for k in range(2):
        D0 = 2.5 + smooth_bases(1, H, W, seed=seed + 10 + k, amplitude=0.4)[0]
        provs.append(provider_cls(D0, smooth_bases(CD, H, W, seed=seed + k), rng.uniform(0.01, 0.05, (H, W))))
    uv2 = np.stack([rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)], -1)
    codes = [rng.normal(0, 0.5, CD) for _ in range(2)]
    return (T1, T2), provs, uv2, codes


def pair_values(Ts, codes):
    v = gtsam.Values()
    for k in range(2):
        v.insert(X(k), to_pose3(Ts[k]))
        v.insert(C(k), np.asarray(codes[k], np.float64))
    return v


def test_consistency_known_answer_and_silent_rows():
    # fronto-parallel wall x_w = 3; k2 is 0.5 m closer and 0.3 m to the side: constant depths 3 and 2.5
    T1 = body_pose(t=(0.0, 0.0, 0.0))
    T2 = body_pose(t=(0.5, 0.3, 0.0))
    p1 = LinearDepth(np.full((H, W), 3.0), np.zeros((CD, H, W)))
    p2 = LinearDepth(np.full((H, W), 2.5), np.zeros((CD, H, W)))
    uv2 = np.array([[5.0, 5.0], [32.0, 24.0], [60.0, 40.0], [1.0, 47.0]])
    lk = Bilinear(uv2, (H, W))
    fx, fy, cx, cy = K
    rays = np.stack([(uv2[:, 0] - cx) / fx, (uv2[:, 1] - cy) / fy, np.ones(4)], -1)
    res = consistency_residuals(T1, T2, T_B_C, K, lk, rays, p1.D0, p2.D0, p1.J, p2.J)
    # k2 is closer and to the side: all four samples land inside k1's image
    assert res.valid.all()
    np.testing.assert_allclose(res.r, 0.0, atol=1e-12)
    np.testing.assert_allclose(res.z1, 3.0, atol=1e-12)
    # a 5 cm error in k1's map shows up as r = +0.05
    res = consistency_residuals(T1, T2, T_B_C, K, lk, rays, p1.D0 + 0.05, p2.D0, p1.J, p2.J)
    np.testing.assert_allclose(res.r, 0.05, atol=1e-12)
    # move k2 far to the side: every sample leaves k1's image -> zero rows, same row count
    T2far = body_pose(t=(0.5, -10.0, 0.0))
    res = consistency_residuals(T1, T2far, T_B_C, K, lk, rays, p1.D0, p2.D0, p1.J, p2.J)
    assert res.r.shape == (4,) and not res.valid.any()
    assert all(np.all(Jk == 0) for Jk in res.jacobians) and np.all(res.r == 0)
    # behind the camera (k2 looks the other way): silent as well
    T2back = body_pose((0.0, 0.0, np.pi), (0.5, 0.0, 0.0))
    res = consistency_residuals(T1, T2back, T_B_C, K, lk, rays, p1.D0, p2.D0, p1.J, p2.J)
    assert not res.valid.any() and np.all(res.r == 0)


@pytest.mark.parametrize("seed", [0, 1])
def test_consistency_jacobians_every_key(seed):
    Ts, provs, uv2, codes = pair_setup(seed)
    f = make_consistency_factor((X(0), X(1)), (C(0), C(1)), provs, uv2, K, T_B_C, Ts, codes, cfg=NO_ROBUST)
    v = pair_values(Ts, codes)
    r = f.unwhitenedError(v)
    assert r.shape == (60,) and 10 < np.count_nonzero(r) < 60  # some samples leave k1's view
    num = assert_jacobians_match(f, v)
    for Jk in num:
        assert np.abs(Jk).max() > 1e-3  # every key matters
        assert np.all(Jk[r == 0] == 0)  # silent rows have zero Jacobians
    with pytest.raises(ValueError, match="distinct"):
        make_consistency_factor((X(0), X(0)), (C(0), C(1)), provs, uv2, K, T_B_C, Ts, codes, cfg=NO_ROBUST)


def test_consistency_sigmas_propagate_both_maps():
    T1 = body_pose(t=(0.0, 0.0, 0.0))
    T2 = body_pose(t=(0.5, 0.3, 0.0))
    B = np.full((H, W), 0.02)
    p1 = LinearDepth(np.full((H, W), 3.0), np.zeros((CD, H, W)), B)
    p2 = LinearDepth(np.full((H, W), 2.5), np.zeros((CD, H, W)), B)
    uv2 = np.array([[32.0, 24.0], [20.0, 10.0]])
    zero = (np.zeros(CD), np.zeros(CD))
    for mode in ("full", "z"):
        cfg = fcfg(consis_covariance=mode, consis_huber_k=None, min_sigma=1e-4)
        f = make_consistency_factor((X(0), X(1)), (C(0), C(1)), (p1, p2), uv2, K, T_B_C, (T1, T2), zero, cfg)
        # pure translation: dz1/dd2 = 1, and d_k1 is flat: s = sqrt(s1^2 + s2^2) = sqrt(2) * sqrt(2) * 0.02
        np.testing.assert_allclose(f.noiseModel().sigmas(), 0.04, rtol=1e-9)
    # a depth gradient in k1 adds to the propagated variance in "full" mode only
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    p1g = LinearDepth(3.0 + 0.02 * (u - K[2]), np.zeros((CD, H, W)), B)
    sig = {}
    for mode in ("full", "z"):
        cfg = fcfg(consis_covariance=mode, consis_huber_k=None, min_sigma=1e-4)
        f = make_consistency_factor((X(0), X(1)), (C(0), C(1)), (p1g, p2), uv2, K, T_B_C, (T1, T2), zero, cfg)
        sig[mode] = np.asarray(f.noiseModel().sigmas())
    # "full" uses dr/dd2 (here below dz/dd2: k1's slope partly cancels), checked by moving d2
    fx, fy, cx, cy = K
    rays = np.stack([(uv2[:, 0] - cx) / fx, (uv2[:, 1] - cy) / fy, np.ones(2)], -1)
    lk = Bilinear(uv2, (H, W))
    res = consistency_residuals(T1, T2, T_B_C, K, lk, rays, p1g.D0, p2.D0)
    eps = 1e-6
    res_p = consistency_residuals(T1, T2, T_B_C, K, lk, rays, p1g.D0, p2.D0 + eps)
    res_m = consistency_residuals(T1, T2, T_B_C, K, lk, rays, p1g.D0, p2.D0 - eps)
    np.testing.assert_allclose(res.dr_dd2, (res_p.r - res_m.r) / (2 * eps), rtol=1e-6)
    s = np.sqrt(2.0) * 0.02
    np.testing.assert_allclose(sig["full"], np.sqrt(s**2 + (res.dr_dd2 * s) ** 2), rtol=1e-9)
    np.testing.assert_allclose(sig["z"], 0.04, rtol=1e-9)
    assert np.all(np.abs(sig["full"] - sig["z"]) > 1e-4)


# --------------------------------------------------------------------------- depth edges
def board_depth(T_w_b, shape=(H, W)):
    """Depth (H, W) of a wall ``x_w = 3`` with a board ``x_w = 2`` in front of it covering ``y_w > 0`` (the
    left of a camera looking along +x): one occlusion edge, fronto-parallel surfaces (bilinear-exact)."""
    wall = plane_depth(T_w_b, K, shape, 3.0)
    near = plane_depth(T_w_b, K, shape, 2.0)
    Hh, Ww = shape
    fx, fy, cx, cy = K
    v, u = np.mgrid[0:Hh, 0:Ww].astype(np.float64)
    T_w_c = T_w_b @ T_B_C
    rays_w = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1) @ T_w_c[:3, :3].T
    y_hit = T_w_c[1, 3] + near * rays_w[..., 1]  # where the ray meets the board's plane
    return np.where(y_hit > 0, near, wall)


def test_depth_edge_ratio_on_a_board():
    T = body_pose(t=(0.0, 0.0, 0.0))
    D = board_depth(T)
    edge_col = int(np.argmax(np.diff(D[H // 2]) != 0))  # last column on the board
    assert D[H // 2, 0] == pytest.approx(2.0) and D[H // 2, -1] == pytest.approx(3.0)
    uv = np.array([[2.0, 10.0], [edge_col + 0.4, 20.0], [edge_col + 1.0, 5.0], [W - 3.0, 40.0], [-5.0, 3.0]])
    e = depth_edge_ratio(D, uv)
    np.testing.assert_allclose(e, [0.0, 0.5, 0.5, 0.0, 0.0], atol=1e-12)  # (3 - 2) / 2 next to the edge
    assert depth_edge_ratio(np.where(D > 2.5, 0.0, D), uv)[3] == np.inf  # an invalid depth nearby


def test_depth_edge_ratio_is_the_3x3_range_over_its_minimum_at_the_nearest_pixel():
    rng = np.random.default_rng(3)
    D = rng.uniform(0.5, 5.0, (12, 9))
    D[4, 4], D[7, 1], D[0, 8] = np.nan, 0.0, np.inf
    uv = np.c_[rng.uniform(-3, 12, 400), rng.uniform(-3, 15, 400)]
    u = np.clip(np.floor(uv[:, 0] + 0.5), 0, 8).astype(int)
    v = np.clip(np.floor(uv[:, 1] + 0.5), 0, 11).astype(int)
    want = []
    for ui, vi in zip(u, v, strict=True):  # the 3x3 neighbourhood, clamped at the border
        d = D[np.clip([vi - 1, vi, vi + 1], 0, 11)][:, np.clip([ui - 1, ui, ui + 1], 0, 8)]
        want.append((d.max() - d.min()) / d.min() if np.isfinite(d).all() and d.min() > 0 else np.inf)
    np.testing.assert_allclose(depth_edge_ratio(D, uv), want, rtol=1e-12)


def test_geometric_rows_on_a_depth_edge_are_dropped():
    T = body_pose(t=(0.0, 0.0, 0.0))
    D = board_depth(T)
    edge_col = int(np.argmax(np.diff(D[H // 2]) != 0))
    uv = np.array([[5.0, 10.0], [edge_col + 0.5, 20.0], [W - 5.0, 30.0], [edge_col, 40.0], [edge_col + 2.0, 8.0]])
    X_w = wall_points(T, uv, Bilinear(uv, D.shape).sample(D))
    prov = LinearDepth(D, np.zeros((CD, H, W)))
    keys = [L(j) for j in range(len(X_w))]
    cfg = fcfg(geo_huber_k=None, edge_rel=0.05)
    (f,) = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, keys, cfg=cfg, depth_map=D)
    assert f.dim() == 3  # the two observations whose nearest pixel is next to the edge are gone
    (g,) = make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, keys, cfg=NO_ROBUST)
    assert g.dim() == 5
    with pytest.raises(ValueError, match="depth_map"):
        make_geometric_depth_factors(X(0), C(0), uv, prov, T_B_C, keys, cfg=cfg)
    with pytest.raises(ValueError, match="edge_rel"):
        DepthFactorConfig(edge_rel=0.0)


def test_consistency_rows_on_a_depth_edge_are_silent_or_dropped():
    """At the true poses Eq. 14 on a board in front of a wall is exact except at the occlusion edge, where
    rows are off by up to the 1 m step; the edge test removes exactly those."""
    T1 = body_pose(t=(0.0, 0.0, 0.0))
    T2 = body_pose(t=(-0.3, 0.25, 0.05))  # k2 further back and to the left
    D1, D2 = board_depth(T1), board_depth(T2)
    v, u = np.mgrid[1 : H - 1, 1 : W - 1]
    uv2 = np.stack([u.ravel(), v.ravel()], -1).astype(np.float64)  # every pixel of k2 off the border
    fx, fy, cx, cy = K
    rays = np.stack([(uv2[:, 0] - cx) / fx, (uv2[:, 1] - cy) / fy, np.ones(len(uv2))], -1)
    lk = Bilinear(uv2, (H, W))
    plain = consistency_residuals(T1, T2, T_B_C, K, lk, rays, D1, D2)
    assert np.abs(plain.r).max() > 0.3 and plain.valid.mean() > 0.7
    edged = consistency_residuals(T1, T2, T_B_C, K, lk, rays, D1, D2, edge_rel=0.05)
    assert not np.any(edged.valid & ~plain.valid)
    np.testing.assert_allclose(edged.r[edged.valid], 0.0, atol=1e-9)  # only P1 on k1's edge is left out ...
    off_edge1 = depth_edge_ratio(D1, plain.uv1) <= 0.05
    assert np.array_equal(edged.valid, plain.valid & off_edge1)
    big = np.abs(plain.r) > 1e-6
    assert big.sum() >= 5 and not np.any(edged.valid & big)
    # ... and the factor drops k2's samples on k2's edge when it is built
    provs = (LinearDepth(D1, np.zeros((CD, H, W))), LinearDepth(D2, np.zeros((CD, H, W))))
    zero = (np.zeros(CD), np.zeros(CD))
    cfg = fcfg(consis_huber_k=None, edge_rel=0.05)
    f = make_consistency_factor((X(0), X(1)), (C(0), C(1)), provs, uv2, K, T_B_C, (T1, T2), zero, cfg)
    n_edge2 = int(np.sum(depth_edge_ratio(D2, uv2) > 0.05))
    assert n_edge2 >= H - 2 and f.dim() == len(uv2) - n_edge2
    vals = pair_values((T1, T2), zero)
    np.testing.assert_allclose(f.unwhitenedError(vals), 0.0, atol=1e-9)
    # away from the truth the rows off the edges are smooth in the poses: analytic = numerical Jacobians
    T2b = T2 @ gtsam.Pose3.Expmap(np.array([0.002, -0.001, 0.001, 0.004, -0.003, 0.002])).matrix()
    assert_jacobians_match(f, pair_values((T1, T2b), zero), rtol=1e-4)


# --------------------------------------------------------------------------- code recovery (LM)
def test_lm_recovers_known_codes():
    """3 keyframes with fixed poses see a wall; depth providers are linear in the code, exact at c*."""
    rng = np.random.default_rng(3)
    plane_x = 3.0
    Ts = [body_pose((0.05 * k - 0.05, 0.02, 0.0), (0.1 * k, 0.25 * k - 0.25, 0.05 * k)) for k in range(3)]
    c_true = [rng.normal(0, 0.7, CD) for _ in range(3)]
    provs = []
    for k in range(3):
        Bk = dct_bases(CD, H, W, amplitude=0.1)
        true = plane_depth(Ts[k], K, (H, W), plane_x)
        provs.append(LinearDepth(true - np.tensordot(c_true[k], Bk, 1), Bk, np.full((H, W), 0.02)))
    # landmarks on the wall seen from keyframe 0, with 5 mm depth noise
    n_lm = 40
    uv0 = np.stack([rng.uniform(3, W - 4, n_lm), rng.uniform(3, H - 4, n_lm)], -1)
    d0 = Bilinear(uv0, (H, W)).sample(plane_depth(Ts[0], K, (H, W), plane_x))
    X_true = wall_points(Ts[0], uv0, d0)
    X_noisy = wall_points(Ts[0], uv0, d0 + rng.normal(0, 0.005, n_lm))
    fx, fy, cx, cy = K
    graph = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    cfg = fcfg(geo_huber_k=1.5, chunk_size=8)
    for k in range(3):
        v.insert(X(k), to_pose3(Ts[k]))
        graph.add(gtsam.PriorFactorPose3(X(k), to_pose3(Ts[k]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        v.insert(C(k), c_true[k] + rng.normal(0, 0.6, CD))
        graph.add(gtsam.PriorFactorVector(C(k), np.zeros(CD), gtsam.noiseModel.Unit.Create(CD)))  # CVAE prior
    for j in range(n_lm):
        v.insert(L(j), X_noisy[j])
        graph.add(gtsam.PriorFactorPoint3(L(j), X_noisy[j], gtsam.noiseModel.Isotropic.Sigma(3, 0.005)))
    for k in range(3):
        T_c_w = inv_T(Ts[k] @ T_B_C)
        p = X_true @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        uv = np.stack([fx * p[:, 0] / p[:, 2] + cx, fy * p[:, 1] / p[:, 2] + cy], -1)
        ok = inside_image(uv, (H, W))
        keys = [L(j) for j in np.nonzero(ok)[0]]
        for f in make_geometric_depth_factors(X(k), C(k), uv[ok], provs[k], T_B_C, keys, cfg=cfg):
            graph.add(f)
    for k1, k2 in [(0, 1), (1, 2), (2, 0)]:
        s = sample_consistency_pixels(np.zeros((0, 2)), W, H, 150, rng=k2)
        graph.add(
            make_consistency_factor(
                (X(k1), X(k2)),
                (C(k1), C(k2)),
                (provs[k1], provs[k2]),
                s.uv,
                K,
                T_B_C,
                (Ts[k1], Ts[k2]),
                (v.atVector(C(k1)), v.atVector(C(k2))),
                cfg,
            )
        )
    err0 = [np.abs(v.atVector(C(k)) - c_true[k]).max() for k in range(3)]
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(30)
    res = gtsam.LevenbergMarquardtOptimizer(graph, v, params).optimize()
    err1 = [np.abs(res.atVector(C(k)) - c_true[k]).max() for k in range(3)]
    assert min(err0) > 0.3
    assert max(err1) < 0.06, (err0, err1)
    for k in range(3):  # the decoded maps match the true wall depth to millimetres
        rmse = np.sqrt(np.mean((provs[k].depth(res.atVector(C(k))) - plane_depth(Ts[k], K, (H, W), plane_x)) ** 2))
        assert rmse < 0.005
    # LM reached the optimum: the true codes (a point near it, given the noise) cost more
    at_truth = gtsam.Values(res)
    for k in range(3):
        at_truth.update(C(k), c_true[k])
    assert graph.error(res) <= graph.error(at_truth)


# --------------------------------------------------------------------------- cost
class CachedDepth:
    """A provider that, like KeyframeDepth's cache, returns precomputed float32 maps."""

    def __init__(self, D, J, B):
        self.D, self.J, self.uncertainty, self.code_dim = D, J, B, J.shape[-1]

    def depth(self, code):
        return self.D

    def jacobian(self, code):
        return self.D, self.J


def test_linearisation_cost_at_realistic_sizes():
    """224 x 224 maps, C = 8: 150 landmarks (Eq. 13) and 600 samples (Eq. 14); no per-point Python work."""
    rng = np.random.default_rng(0)
    h = w = 224
    Kn = network_K(h, w)
    D = (2.5 + smooth_bases(1, h, w, amplitude=0.3)[0]).astype(np.float32)
    J = smooth_bases(CD, h, w, seed=1).transpose(1, 2, 0).astype(np.float32).copy()
    prov = [CachedDepth(D, J, np.full((h, w), 0.03, np.float32)) for _ in range(2)]
    T1 = body_pose(t=(0.0, 0.0, 0.0))
    T2 = body_pose((0.02, 0.0, 0.0), (0.05, 0.1, 0.0))
    uv = np.stack([rng.uniform(0, w - 1, 150), rng.uniform(0, h - 1, 150)], -1)
    fx, fy, cx, cy = Kn
    d = rng.uniform(2, 3, 150)
    p_c = np.stack([(uv[:, 0] - cx) / fx * d, (uv[:, 1] - cy) / fy * d, d], -1)
    T_w_c = T1 @ T_B_C
    X_w = p_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    v = pair_values((T1, T2), (np.zeros(CD), np.zeros(CD)))
    for j in range(150):
        v.insert(L(j), X_w[j])
    s = sample_consistency_pixels(uv, w, h, 600, rng=0)
    geo_var = make_geometric_depth_factors(X(0), C(0), uv, prov[0], T_B_C, [L(j) for j in range(150)], cfg=PLAIN)
    cons = [
        make_consistency_factor(
            (X(0), X(1)), (C(0), C(1)), prov, s.uv, Kn, T_B_C, (T1, T2), (np.zeros(CD), np.zeros(CD)), PLAIN
        )
    ]

    def per_call(facs, reps=10):
        best = np.inf
        for _ in range(reps):  # best of reps: the machine is shared
            t = time.perf_counter()
            for f in facs:
                f.linearize(v)
            best = min(best, time.perf_counter() - t)
        return best * 1e3

    ms = {
        "geo_var_150_chunk32": per_call(geo_var),
        "consis_600": per_call(cons),
    }
    print("linearize [ms]:", {k: round(x, 3) for k, x in ms.items()})
    assert ms["consis_600"] < 20 and ms["geo_var_150_chunk32"] < 30


# ------------------------------------------------------------------- with runtime.network.KeyframeDepth
class LinearNet:
    """Stands in for ``DepthNetwork``: a float32 decoder linear in the code (so Eq. 17 is exact)."""

    code_dim, delta = CD, 1e-2

    class session_config:  # noqa: N801 - mimics the dataclass attribute
        nominal_in_batch = True

    def __init__(self, D0, bases):
        self.D0, self.bases = D0.astype(np.float32), bases.astype(np.float32)
        self.decoder_calls = 0

    def decode(self, codes, features):
        self.decoder_calls += 1
        return self.D0[None] + np.tensordot(np.atleast_2d(codes).astype(np.float32), self.bases, 1)


def test_keyframe_depth_provider_is_decoded_once_per_code():
    from runtime.network import KeyframeDepth

    T, uv, X_w, _, code = geometric_setup(n=40)
    bases = smooth_bases(CD, H, W, seed=4)
    net = LinearNet(np.full((H, W), 2.0), bases)
    kf = KeyframeDepth(net, np.full((H, W), 0.03, np.float32), {})
    v = gtsam.Values()
    v.insert(X(0), to_pose3(T))
    v.insert(C(0), code)
    for j, p in enumerate(X_w):
        v.insert(L(j), p)
    cfg = fcfg(geo_huber_k=None, chunk_size=10)
    facs = make_geometric_depth_factors(X(0), C(0), uv, kf, T_B_C, landmark_keys=[L(j) for j in range(40)], cfg=cfg)
    assert len(facs) == 4
    for f in facs:
        jac = analytic_jacobians(f, v)
        # d r / d c = -J at the observed pixels (Eq. 16-17); exact here up to float32
        rows = [i for i in range(40) if L(i) in f.keys()]
        expect = -Bilinear(uv[rows], (H, W)).sample(bases.transpose(1, 2, 0))
        np.testing.assert_allclose(jac[1], expect, atol=2e-4)
    assert net.decoder_calls == 1  # one batch of 1 + 8 codes for all four chunks
    for f in facs:
        f.error(v)
    assert net.decoder_calls == 1  # errors at the same code reuse the cache
    v.update(C(0), code + 0.1)
    for f in facs:
        f.error(v)
    assert net.decoder_calls == 2  # a new code: one more decode (depth only)
