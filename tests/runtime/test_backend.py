"""Backend: GT recovery from perturbed values on a small window, marginalisation, factors and Jacobians."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from runtime.backend.factors import (
    analytic_jacobians,
    custom_factor,
    numerical_jacobians,
    refine_pose,
    reprojection_residuals,
)
from runtime.backend.imu import ImuStream, integrate, make_bias, preintegration_params
from runtime.backend.state import Keyframe
from runtime.backend.window import BackendConfig, SlidingWindowBackend
from runtime.geometry import inv_T, make_T, pose_error, so3_exp, to_pose3
from tests.runtime.synth import EUROC_CAM, EUROC_T_BS, ImuNoise, Motion, make_imu, room_points

K = EUROC_CAM.pinhole().K


class Scenario:
    """Exact keyframe states, IMU and pinhole observations of room points along a smooth motion."""

    def __init__(self, n_kf=6, dt_kf=0.3, t_first=1.0, seed=0):
        self.m = Motion(seed=seed, t_rest=0.0, t_ramp=0.5)
        ts, g, a = make_imu(self.m, t_first + n_kf * dt_kf + 1.0, t0_ns=0)
        self.imu = ImuStream(ts, g, a, 200.0)
        self.params = preintegration_params(ImuNoise())
        self.t = t_first + dt_kf * np.arange(n_kf)
        self.T = self.m.body(self.t)
        self.v = self.m.velocity(self.t)
        self.pts = room_points(1500, seed=seed)
        self.obs = []  # per keyframe: (point ids, uv)
        for T in self.T:
            T_c_w = inv_T(T @ EUROC_T_BS)
            p = self.pts @ T_c_w[:3, :3].T + T_c_w[:3, 3]
            uv = p[:, :2] / p[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
            ok = (p[:, 2] > 0.3) & (uv[:, 0] > 5) & (uv[:, 0] < 747) & (uv[:, 1] > 5) & (uv[:, 1] < 475)
            self.obs.append((np.nonzero(ok)[0], uv[ok]))

    def pim(self, i, j):
        p = gtsam.PreintegratedCombinedMeasurements(self.params, make_bias(np.zeros(6)))
        integrate(p, *self.imu.segment(int(self.t[i] * 1e9), int(self.t[j] * 1e9)))
        return p

    def kf(self, i, T=None, v=None):
        return Keyframe(
            i,
            int(self.t[i] * 1e9),
            i,
            self.T[i] if T is None else T,
            self.v[i] if v is None else v,
            np.zeros(6),
        )


def _perturb(T, rng, rot=0.03, trans=0.05):
    return T @ make_T(so3_exp(rng.normal(0, rot, 3)), rng.normal(0, trans, 3))


def _build(sc, backend, n, rng, noise_px=0.0):
    backend.initialize(sc.kf(0))
    for i in range(1, n):
        backend.add_keyframe(sc.kf(i, _perturb(sc.T[i], rng), sc.v[i] + rng.normal(0, 0.1, 3)), sc.pim(i - 1, i))
    seen = {}
    for i in range(n):
        for j, uv in zip(*sc.obs[i], strict=False):
            seen.setdefault(int(j), {})[i] = uv + rng.normal(0, noise_px, 2)
    ids = [j for j, o in seen.items() if len(o) >= 2][:300]
    X0 = sc.pts[ids] + rng.normal(0, 0.1, (len(ids), 3))
    backend.add_landmarks(np.array(ids), X0, [seen[j] for j in ids])
    return ids


def test_backend_recovers_ground_truth_from_perturbed_values():
    sc = Scenario()
    backend = SlidingWindowBackend(EUROC_CAM.intrinsics, EUROC_T_BS, sc.params, BackendConfig(lm_max_iterations=20))
    rng = np.random.default_rng(0)
    ids = _build(sc, backend, 6, rng)
    before = max(pose_error(backend.map.keyframes[i].T_w_b, sc.T[i])[0] for i in range(6))
    assert before > 0.03
    stats = backend.optimize()
    assert stats["ok"] and stats["error_after"] < 1e-3 * stats["error_before"]
    for i in range(6):
        dp, dr = pose_error(backend.map.keyframes[i].T_w_b, sc.T[i])
        assert dp < 2e-3 and np.degrees(dr) < 0.05, (i, dp, np.degrees(dr))
        assert np.linalg.norm(backend.map.keyframes[i].v_w - sc.v[i]) < 5e-3
    P, ok = backend.map.landmark_positions(np.array(ids))
    assert ok.all() and np.median(np.linalg.norm(P - sc.pts[ids], axis=1)) < 2e-3
    drop, n_out = backend.remove_outliers()
    assert n_out == 0 and drop.size == 0
    assert backend.init_kf_id == 0  # the window's first keyframe; a reset forgets it, a new window names its own
    backend.clear_window()
    assert backend.init_kf_id is None
    backend.initialize(sc.kf(3))
    assert backend.init_kf_id == 3 and backend.map.active == [3]


def test_reprojection_errors_are_per_observation_pixel_distances():
    sc = Scenario()
    backend = SlidingWindowBackend(EUROC_CAM.intrinsics, EUROC_T_BS, sc.params, BackendConfig())
    ids = _build(sc, backend, 4, np.random.default_rng(1))
    m = backend.map
    for i in range(4):
        m.keyframes[i].T_w_b = sc.T[i].copy()
    for j in ids:
        m.landmarks[j].X_w = sc.pts[j].copy()
    j0, k0 = ids[7], sorted(m.landmarks[ids[7]].obs)[-1]
    m.landmarks[j0].obs[k0] = m.landmarks[j0].obs[k0] + np.array([3.0, -4.0])
    kfs, lms, err, z = backend.reprojection_errors()
    pairs = [(int(k), int(j)) for k, j in zip(kfs, lms, strict=True)]
    assert pairs == [(k, j) for j, lm in m.landmarks.items() for k in lm.obs]  # one row per observation, in order
    hit = (kfs == k0) & (lms == j0)
    assert hit.sum() == 1 and err[hit][0] == pytest.approx(5.0, abs=1e-6)
    assert np.abs(err[~hit]).max() < 1e-6
    T_c_w = [inv_T(sc.T[int(k)] @ EUROC_T_BS) for k in kfs]
    z_true = [(T[:3, :3] @ sc.pts[j] + T[:3, 3])[2] for T, j in zip(T_c_w, lms, strict=True)]
    np.testing.assert_allclose(z, z_true, rtol=1e-12)


def test_outliers_are_removed_and_marginalisation_keeps_the_estimate():
    sc = Scenario(n_kf=9, seed=1)
    cfg = BackendConfig(window_size=4, lm_max_iterations=15)
    backend = SlidingWindowBackend(EUROC_CAM.intrinsics, EUROC_T_BS, sc.params, cfg)
    rng = np.random.default_rng(1)
    backend.initialize(sc.kf(0))
    lm_obs = {}
    for i in range(9):
        if i > 0:
            backend.add_keyframe(sc.kf(i, _perturb(sc.T[i], rng, 0.01, 0.02)), sc.pim(i - 1, i))
        ids, uv = sc.obs[i]
        uv = uv + rng.normal(0, 0.3, uv.shape)
        if i == 3:
            uv[:5] += 40.0  # gross outliers
            bad = set(ids[:5].tolist())
        known = np.array([j for j in ids if j in backend.map.landmarks])
        sel = np.isin(ids, known)
        backend.add_observations(i, ids[sel], uv[sel])
        for j, u in zip(ids[~sel], uv[~sel], strict=False):
            lm_obs.setdefault(int(j), {})[i] = u
        new = [j for j, o in lm_obs.items() if len(o) >= 2 and j not in backend.map.landmarks][:80]
        backend.add_landmarks(
            np.array(new, dtype=np.int64),
            sc.pts[new] + rng.normal(0, 0.05, (len(new), 3)),
            [lm_obs.pop(j) for j in new],
        )
        backend.optimize()
        drop, n_out = backend.remove_outliers()
        if i == 3:
            assert set(drop.tolist()) & bad and n_out >= 3
            backend.optimize()
        backend.marginalize()
        assert len(backend.map.active) <= 4
    assert backend.map.anchors and backend.prior_factors
    for i in backend.map.active:
        dp, dr = pose_error(backend.map.keyframes[i].T_w_b, sc.T[i])
        assert dp < 0.01 and np.degrees(dr) < 0.2, (i, dp)
    for i, (_, T) in backend.map.history.items():
        assert pose_error(T, sc.T[i])[0] < 0.01
    ids, P = backend.map.all_points()
    assert np.median(np.linalg.norm(P - sc.pts[ids], axis=1)) < 0.05  # short baselines, 0.3 px noise


def test_numpy_reprojection_matches_gtsam_factor_and_its_jacobian():
    rng = np.random.default_rng(3)
    T = make_T(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 0.5, 3))
    T_c_w = inv_T(T @ EUROC_T_BS)
    Xc = np.concatenate([rng.uniform(-1, 1, (10, 2)), rng.uniform(2, 5, (10, 1))], 1)
    Xw = (Xc - T_c_w[:3, 3]) @ T_c_w[:3, :3]
    uv = rng.uniform(100, 600, (10, 2))
    r, J = reprojection_residuals(T, EUROC_T_BS, Xw, uv, K, jacobian=True)
    cal = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(T))
    for n in range(10):
        f = gtsam.GenericProjectionFactorCal3_S2(
            uv[n], gtsam.noiseModel.Unit.Create(2), X(0), L(n), cal, gtsam.Pose3(EUROC_T_BS)
        )
        if not vals.exists(L(n)):
            vals.insert(L(n), Xw[n])
        e = f.unwhitenedError(vals)  # GTSAM: prediction - measurement
        assert np.allclose(-e, r[n], atol=1e-9)
        Hx = analytic_jacobians(f, vals)[0]
        assert np.allclose(-Hx, J[n], atol=1e-6 * np.abs(J[n]).max())
    # and against numerical differentiation of the numpy residual
    eps = 1e-6
    from runtime.backend.factors import retract_pose

    Jn = np.stack(
        [
            (
                reprojection_residuals(retract_pose(T, eps * e), EUROC_T_BS, Xw, uv, K)[0]
                - reprojection_residuals(retract_pose(T, -eps * e), EUROC_T_BS, Xw, uv, K)[0]
            )
            / (2 * eps)
            for e in np.eye(6)
        ],
        -1,
    )
    assert np.allclose(Jn, J, atol=1e-4 * np.abs(J).max())


def test_refine_pose_recovers_the_pose_and_flags_outliers():
    rng = np.random.default_rng(4)
    T = make_T(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 0.5, 3))
    T_c_w = inv_T(T @ EUROC_T_BS)
    Xc = np.concatenate([rng.uniform(-2, 2, (60, 2)), rng.uniform(2, 6, (60, 1))], 1)
    Xw = (Xc - T_c_w[:3, 3]) @ T_c_w[:3, :3]
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2] + rng.normal(0, 0.3, (60, 2))
    uv[:4] += 30.0
    T0 = _perturb(T, rng, 0.01, 0.03)
    T1, inl, err = refine_pose(T0, Xw, uv, K, EUROC_T_BS, iterations=8)
    dp, dr = pose_error(T1, T)
    assert dp < 5e-3 and np.degrees(dr) < 0.1
    assert not inl[:4].any() and inl[4:].mean() > 0.95
    # a strong prior keeps the pose at the prior
    T2, _, _ = refine_pose(T0, Xw, uv, K, EUROC_T_BS, T_prior=T0, prior_sigmas=np.full(6, 1e-7), iterations=4)
    assert pose_error(T2, T0)[0] < 1e-5


def test_custom_factor_jacobians_match_numerical_and_shapes_are_checked():
    """The stacked-factor wrapper: a 'point in the body frame' residual over one pose and one point."""
    meas = np.array([0.3, -0.2, 1.5])

    def err(values, want_J):
        T = values.atPose3(X(0)).matrix()
        P = values.atPoint3(L(0))
        R, t = T[:3, :3], T[:3, 3]
        p_b = R.T @ (P - t)
        r = p_b - meas
        if not want_J:
            return r, None
        from runtime.geometry import skew

        return r, [np.concatenate([skew(p_b), -np.eye(3)], 1), R.T]

    f = custom_factor(gtsam.noiseModel.Unit.Create(3), [X(0), L(0)], err, dims=[6, 3])
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(make_T(so3_exp(np.array([0.2, -0.1, 0.4])), [0.5, 1.0, -0.3])))
    vals.insert(L(0), np.array([1.0, 2.0, 3.0]))
    for A, N in zip(analytic_jacobians(f, vals), numerical_jacobians(f, vals), strict=False):
        assert np.allclose(A, N, atol=1e-6)

    def bad(values, want_J):
        r, J = err(values, want_J)
        return r, (None if J is None else [J[0][:, :3], J[1]])

    fb = custom_factor(gtsam.noiseModel.Unit.Create(3), [X(0), L(0)], bad, dims=[6, 3])
    with pytest.raises(Exception, match="shape"):
        fb.linearize(vals)


def _coasted_backend(n_kf=14, window=4, drift=0.4, seed=3, n_total=None):
    """A window that coasted on exact IMU links from keyframe 2 on, its estimates drifting quadratically in
    time (position) and linearly (velocity), marginalising as it went (no landmarks: a blank wall); the
    scenario holds ``n_total`` keyframes (default ``n_kf``), the backend the first ``n_kf``."""
    sc = Scenario(n_kf=n_total or n_kf, dt_kf=0.3, seed=seed)
    be = SlidingWindowBackend(EUROC_CAM.intrinsics, EUROC_T_BS, sc.params, BackendConfig(window_size=window))
    be.initialize(sc.kf(0))
    d = np.array([1.0, -0.6, 0.3]) * drift
    span = sc.t[n_kf - 1] - sc.t[2]
    for i in range(1, n_kf):
        a = max(sc.t[i] - sc.t[2], 0.0) / span
        T = sc.T[i].copy()
        T[:3, 3] += d * a**2
        be.add_keyframe(sc.kf(i, T, sc.v[i] + 2 * d * a / span), sc.pim(i - 1, i))
        be.marginalize()
    return sc, be


def test_coast_bridge_recovers_the_coasted_states_from_the_imu_links():
    sc, be = _coasted_backend()
    last = len(sc.t) - 1
    assert sorted(be.archive.states) == list(range(last - 3))
    assert be.map.active == list(range(last - 3, last + 1))
    before = [pose_error(be.map.history[i][1], sc.T[i])[0] for i in range(len(sc.t))]
    assert max(before) > 0.35
    _set_bridge_sigmas(be, fix=(1e-3, 1e-3), anchor=(1e-3, 1e-3, 1e-2, 0.05, 2e-3))
    corr = be.bridge(int(sc.t[2] * 1e9) + 1, last, sc.T[last])
    assert sorted(corr) == list(range(2, last + 1))  # from the anchor (the last keyframe before the loss)
    for i in range(len(sc.t)):
        T = be.map.history[i][1]
        assert pose_error(T, sc.T[i])[0] < 0.01, (i, pose_error(T, sc.T[i]))  # exact IMU: the path itself
        state = be.map.keyframes[i] if i in be.map.active else be.archive.states[i]
        assert np.allclose(state.T_w_b, T)
        assert np.linalg.norm(state.v_w - sc.v[i]) < 0.03, i
    # the window's marginal prior now comes from the anchor over the archived links, at the bridged state
    assert all(isinstance(f, gtsam.LinearContainerFactor) for f in be.prior_factors)
    st = be.optimize()
    assert st["ok"]
    for i in be.map.active:
        assert pose_error(be.map.keyframes[i].T_w_b, sc.T[i])[0] < 0.01, i


def test_coast_bridge_declines_without_an_inertial_chain():
    sc, be = _coasted_backend()
    last = len(sc.t) - 1
    _set_bridge_sigmas(be, fix=(1e-3, 1e-3), anchor=(1e-3, 1e-3, 1e-2, 0.05, 2e-3))
    # the archive does not reach back before the loss
    assert be.bridge(-1, last, sc.T[last]) is None
    gap = Keyframe(last + 1, int((sc.t[last] + 0.3) * 1e9), last + 1, sc.T[last], sc.v[last], np.zeros(6))
    be.add_keyframe(gap, None)  # an IMU gap: no inertial link
    before = {k: T.copy() for k, (_, T) in be.map.history.items()}
    assert be.bridge(int(sc.t[2] * 1e9) + 1, last + 1, sc.T[last]) is None
    assert all(np.array_equal(be.map.history[k][1], before[k]) for k in before)  # nothing moved


class _PosePriors:
    """A provider standing in for the visual tracking after a relocalisation: tight true pose priors on the
    keyframes from ``first`` on."""

    def __init__(self, sc, first):
        self.sc, self.first = sc, first

    def add_factors(self, backend, graph, values):
        for k in backend.window_ids():
            if k >= self.first:
                graph.push_back(
                    gtsam.PriorFactorPose3(X(k), to_pose3(self.sc.T[k]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4))
                )

    def on_optimized(self, backend, result):
        pass

    def on_marginalize(self, backend, kf_id):
        pass


def _set_bridge_sigmas(be, fix, anchor):
    c = be.cfg.coast
    c.fix_rot_sigma, c.fix_pos_sigma = fix
    c.anchor_rot_sigma, c.anchor_pos_sigma, c.anchor_vel_sigma, c.anchor_acc_bias_sigma = anchor[:4]
    c.anchor_gyro_bias_sigma = anchor[4]


def _smoothed_coast_errors():
    """Coast, bridge with a wrong accelerometer bias in the anchor prior, then five tracked keyframes."""
    n_coast, n_after, window = 14, 5, 4
    sc, be = _coasted_backend(n_kf=n_coast, window=window, n_total=n_coast + n_after)
    last = n_coast - 1
    be.archive.states[2].bias[:3] += [0.06, -0.04, 0.03]  # what the window believed at the loss
    del be.archive.priors[2]  # the anchor prior is then the configured sigmas around that state
    _set_bridge_sigmas(be, fix=(1e-3, 1e-3), anchor=(1e-3, 1e-3, 0.05, 0.05, 2e-3))
    be.bridge(int(sc.t[2] * 1e9) + 1, last, sc.T[last])
    coast = range(3, last)
    after_bridge = max(pose_error(be.map.history[i][1], sc.T[i])[0] for i in coast)
    be.add_provider(_PosePriors(sc, n_coast))
    in_smoother = []
    for i in range(n_coast, n_coast + n_after):
        be.add_keyframe(sc.kf(i), sc.pim(i - 1, i))
        in_smoother.append(be.optimize().get("coast_keyframes", 0))
        be.marginalize()
    final = max(pose_error(be.map.history[i][1], sc.T[i])[0] for i in coast)
    return after_bridge, final, in_smoother, be


def test_the_bridged_coast_stays_in_the_smoother_until_the_relocalised_keyframe_leaves():
    after_bridge, final, in_smoother, be = _smoothed_coast_errors()
    assert after_bridge > 0.02  # the PnP pose alone cannot tell the bias error from a velocity error
    assert final < 0.2 * after_bridge and final < 5e-3, (after_bridge, final)
    # the coast (anchor 2 up to the oldest active keyframe) is in every optimisation while the relocalised
    # keyframe 13 is in the window, then leaves with it
    assert in_smoother == [8, 9, 10, 11, 0], in_smoother
    assert be.archive.coast is None


def test_the_coast_anchor_prior_is_what_the_window_knew_when_the_anchor_left():
    sc, be = _coasted_backend()
    last = len(sc.t) - 1
    # every marginalised keyframe keeps the prior it was marginalised with: factors on its own X, V, B only
    assert sorted(be.archive.priors) == sorted(be.archive.states)
    for k, facs in be.archive.priors.items():
        keys = {key for f in facs for key in f.keys()}
        assert keys <= {X(k), gtsam.symbol("v", k), gtsam.symbol("b", k)} and X(k) in keys, k
    _set_bridge_sigmas(be, fix=(1e-3, 1e-3), anchor=(1e-3, 1e-3, 1e-2, 0.05, 2e-3))
    corr = be.bridge(int(sc.t[2] * 1e9) + 1, last, sc.T[last])
    assert corr is not None and be.archive.coast.anchor == 2 and be.archive.coast.until == last
    assert be.archive.coast.anchor_priors is be.archive.priors[2]
    for i in range(len(sc.t)):
        assert pose_error(be.map.history[i][1], sc.T[i])[0] < 0.01, i
    # the archive forgets the priors with the states
    be.cfg.coast.archive_s = 1.5
    t_next = int((sc.t[last] + 0.3) * 1e9)
    be.add_keyframe(Keyframe(last + 1, t_next, last + 1, sc.T[last], sc.v[last], np.zeros(6)), None)
    be.marginalize()
    assert sorted(be.archive.priors) == sorted(be.archive.states)
    assert min(be.archive.states) > 2
