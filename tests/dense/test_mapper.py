"""The dense (tightly coupled) system end to end on a short rendered sequence with the shipped model, and the
mapper's parts: the decoder cache, the depth sources, the code keyframes and the start wait."""

import json
import threading
import time
from collections import defaultdict
from concurrent.futures import Future
from dataclasses import replace
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

import runtime.dense
from apps.slam import main as slam_main
from runtime.dense import DenseConfig, DenseMapper, LinearizedDepth
from runtime.dense.mapper import _Stats
from runtime.diagnostics.oracle_depth import GroundTruthDepth, oracle_depth_source
from runtime.io.euroc import read_euroc
from runtime.io.ply import read_ply
from runtime.io.tum import read_tum
from runtime.network import DepthNetwork, default_model_dir
from runtime.run import run_sequence
from tests.dense.fakes import T_B_C, ExpDepth

sim_euroc = pytest.importorskip("sim.euroc")


@pytest.fixture(scope="module")
def seq8(tmp_path_factory):
    """8 s textured sequence at half resolution (376x240) with depth0, IMU noise on."""
    out = tmp_path_factory.mktemp("seq") / "seq8"
    return sim_euroc.write_euroc_sequence(
        out, "textured", duration=8.0, seed=3, imu_noise=True, progress=False, scale=0.5, realism=False
    )


#: the backend's read interface for factor providers: all that the mapper may use
BACKEND_READ = {"window_ids", "has_keyframe", "keyframe", "observations", "covisible_keyframes", "latest", "init_kf_id"}


class ReadInterface:
    """A backend seen through its read interface only: any other member is an error."""

    def __init__(self, backend):
        self._backend = backend

    def __getattr__(self, name):
        if name not in BACKEND_READ:
            raise AttributeError(f"the dense mapper read backend.{name}, outside the backend's read interface")
        return getattr(self._backend, name)


class InterfaceOnlyMapper(DenseMapper):
    """A DenseMapper that gets the backend through :class:`ReadInterface` in every call."""

    def on_keyframe(self, backend, *a):
        return super().on_keyframe(ReadInterface(backend), *a)

    def add_factors(self, backend, graph, values):
        return super().add_factors(ReadInterface(backend), graph, values)

    def on_optimized(self, backend, result):
        return super().on_optimized(ReadInterface(backend), result)

    def on_marginalize(self, backend, kf_id):
        return super().on_marginalize(ReadInterface(backend), kf_id)

    def finish(self, backend, out_dir):
        return super().finish(ReadInterface(backend), out_dir)


@pytest.fixture(scope="module")
def runs(seq8, tmp_path_factory):
    """A sparse run and a dense run (Eq. 13 + 14) recording every decoder batch, the mapper reading the backend
    through its read interface only."""
    sparse_out = tmp_path_factory.mktemp("sparse")
    m_sparse = run_sequence(read_euroc(seq8), sparse_out, progress=False, plot=False)
    dense_out = tmp_path_factory.mktemp("dense")
    calls = []
    orig = DepthNetwork.decode

    def spy(self, codes, features):
        codes = np.atleast_2d(np.asarray(codes, np.float32))
        calls.append((id(features), codes.shape[0], codes[0].tobytes()))
        return orig(self, codes, features)

    DepthNetwork.decode = spy
    runtime.dense.DenseMapper = InterfaceOnlyMapper
    try:
        cfg = DenseConfig(use_depth_residual=True, n_consis=200, start_after_s=2.0)
        m_dense = run_sequence(read_euroc(seq8), dense_out, dense=cfg, progress=False, plot=False)
    finally:
        DepthNetwork.decode = orig
        runtime.dense.DenseMapper = DenseMapper
    return sparse_out, m_sparse, dense_out, m_dense, calls


def test_dense_run_completes_writes_outputs_and_keeps_the_ate_bounded(runs):
    sparse_out, m_sparse, out, m, _ = runs
    assert m["ate_se3_rmse_m"] < 0.03, m["ate_se3_rmse_m"]
    assert m["ate_se3_rmse_m"] < 2.0 * m_sparse["ate_se3_rmse_m"] + 0.005
    xyz, rgb = read_ply(out / "dense_map.ply")
    assert xyz.shape[0] == m["dense_map_points"] > 1000 and rgb is not None
    assert np.isfinite(xyz).all()
    maps = sorted((out / "keyframe_depth").glob("kf*.npz"))
    assert len(maps) == m["dense_window_keyframes"] >= 3
    with np.load(maps[0]) as z:
        assert z["depth"].shape == (128, 128) and (z["depth"] > 0).all() and (z["uncertainty"] > 0).all()
    saved = json.loads((out / "metrics.json").read_text())
    dm = saved["depth_metrics"]
    assert saved["depth_metrics_keyframes"] >= 5
    for stage in ("sparse", "prior", "optimised", "map", "interpolated", "median"):
        assert np.isfinite(dm[stage]["rmse"]) and dm[stage]["n"] > 0
    # the references score the same keyframes as the network (every keyframe with a code took map points)
    assert dm["interpolated"]["images"] == dm["median"]["images"] == dm["prior"]["images"]
    assert dm["prior"]["coverage"] == pytest.approx(1.0) and dm["sparse"]["coverage"] < 0.1
    # the optimised codes must not make the depth worse than the c = 0 prior on this sequence
    assert dm["optimised"]["rmse"] < dm["prior"]["rmse"] + 0.01
    # the map's codes were refined at fixed poses (runtime.dense.refine): another depth than the window's codes,
    # and not far from the prior's. Eq. 14 alone cannot tell a self-consistent scene from the true one, so on a
    # few keyframes the map code is worse: on a Zen 3 EPYC 2 of this run's 9 keyframes lose 0.06-0.08 m and the
    # mean is 1.04x the prior's (0.2686 against 0.2584 m). On an AMD EPYC family 26 it was 1.03x, and 1.13x
    # (0.2892 against 0.2553 m) once the guided search re-found the window's lost landmarks, which changes the
    # keyframes' co-visibility and so the map code's neighbours; over 17 realistic dense runs that change moved the
    # map code from 0.978x to 0.971x the prior (slam_ablations/guided_window_4px.json). The benchmark measures the
    # gain (reports/ablations.md); this run checks that the map code stays near the prior
    assert dm["map"]["rmse"] != dm["optimised"]["rmse"] and dm["map"]["rmse"] < 1.2 * dm["prior"]["rmse"]
    t = saved["timing_dense_ms_per_frame"]
    assert set(t) >= {"network", "factor_building", "optimisation"} and all(v >= 0 for v in t.values())
    assert t["map_codes"] > 0
    assert saved["dense_mean_code_keyframes"] > 2 and saved["dense_mean_consis_rows"] > 0
    assert saved["dense_mean_geo_rows"] > 0
    assert saved["dense_optimisations_before_start"] > 0 and saved["dense_optimisations"] > 0  # 2 s waited
    # the sparse run writes none of the dense outputs
    assert not (sparse_out / "dense_map.ply").exists() and "depth_metrics" not in m_sparse
    # both systems refine the camera over the same first sparse pass (here the whole 8 s), to the same calibration
    timing = {"seconds", "seconds_total", "marginals_s"}
    intr, intr_sparse = ({k: v for k, v in x["intrinsics"].items() if k not in timing} for x in (m, m_sparse))
    assert intr["first_pass_frames"] == m["frames"] and "estimated" in intr and intr == intr_sparse, intr


def test_decoder_runs_once_per_code(runs):
    *_, m, calls = runs
    assert m["decoder_calls"] == len(calls) > 0
    jac = [(f, c) for f, b, c in calls if b > 1]  # Jacobian batches (Eq. 17): one per (keyframe, code)
    assert len(jac) == len(set(jac)), "a keyframe's Jacobian was computed twice for the same code"
    assert all(b == 9 for _, b, _ in calls if b > 1)  # nominal + 8 perturbed codes in one batch
    # at most one relinearisation per code keyframe and optimisation, plus two decodes per evaluated keyframe
    bound = m["dense_optimisations"] * m["dense_mean_code_keyframes"] + 2 * (m["keyframes"] + 1)
    assert len(calls) <= bound + 1e-9, (len(calls), bound)


def test_the_outputs_do_not_depend_on_when_the_network_thread_runs_its_later_work(seq8, tmp_path, monkeypatch):
    """The network thread runs the jobs tracking waits for (network passes, relinearisations) before the map codes,
    depth metrics and fusion queued earlier. Holding each of the latter back until three more urgent jobs have
    been submitted (so that relinearisations submitted after a map-code fit run before it) changes no output: the
    fit sees the linearisation it was submitted at."""
    from runtime.dense.worker import PriorityWorker
    from runtime.slam import SlamConfig

    base = SlamConfig()
    # keyframes leave the window (map codes, metrics, fusion) from the first seconds; no first pass
    cfg = replace(base, backend=replace(base.backend, window_size=8), intrinsics=replace(base.intrinsics, refine=False))
    dense = DenseConfig(n_consis=150, start_after_s=1.0, relin_tol=1e-3)  # a relinearisation at nearly every step
    outs = [tmp_path / "as_scheduled", tmp_path / "later_work_held"]
    ms = [run_sequence(read_euroc(seq8), outs[0], cfg, dense=dense, progress=False, plot=False)]
    submit, shutdown = PriorityWorker.submit, PriorityWorker.shutdown
    held, n_urgent, log = [], [0], {"released_late": 0}

    class Held(Future):
        def result(self, timeout=None):  # a reader releases it (and what is held before it) at once
            release(lambda job: job is self or self in [h[1] for h in held])
            return super().result(timeout)

    def release(due):
        while held and due(held[0][1]):
            worker, proxy, fn, args, at = held.pop(0)
            log["released_late"] += n_urgent[0] - at >= 3

            def run(proxy=proxy, fn=fn, args=args):
                try:
                    proxy.set_result(fn(*args))
                except Exception as e:  # noqa: BLE001
                    proxy.set_exception(e)

            submit(worker, run, urgent=False)

    def holding_submit(self, fn, *args, urgent=True):
        if urgent:
            n_urgent[0] += 1
            release(lambda job: n_urgent[0] - job.at >= 3)
            return submit(self, fn, *args)
        proxy = Held()
        proxy.at = n_urgent[0]
        held.append((self, proxy, fn, args, proxy.at))
        return proxy

    def releasing_shutdown(self, wait=True):
        release(lambda job: True)
        shutdown(self, wait)

    monkeypatch.setattr(PriorityWorker, "submit", holding_submit)
    monkeypatch.setattr(PriorityWorker, "shutdown", releasing_shutdown)
    ms.append(run_sequence(read_euroc(seq8), outs[1], cfg, dense=dense, progress=False, plot=False))
    assert log["released_late"] > 0  # later work did wait for urgent jobs submitted after it
    assert ms[0]["dense_map_points"] > 0 and ms[0]["depth_metrics_keyframes"] > 0
    for key in ("keyframes", "decoder_calls", "dense_map_points", "depth_metrics"):
        assert ms[0][key] == ms[1][key], key
    for name in ("trajectory.txt", "dense_map.ply"):
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name


def test_a_map_code_fit_sees_the_linearisation_it_was_submitted_at():
    """A leaving keyframe's map-code fit is later work: a relinearisation of one of its group submitted after it
    runs first on the network thread. The fit still gives the code it gives when run at once, where the same fit
    on the relinearised group gives another."""
    from runtime.dense.mapper import _KfDense
    from tests.dense.test_refine import CD, H, K, W, _wall

    backend = SimpleNamespace(covisible_keyframes=lambda k, n: [j for j in range(3) if j != k])

    def mapper(background: bool):
        lin, Ts, *_ = _wall(3, seed=2, kind=ExpDepth)
        backend.keyframe = lambda k: SimpleNamespace(T_w_b=Ts[k])
        m = DenseMapper.__new__(DenseMapper)
        m.cfg, m.T_b_c, m.K_net, m._pool = DenseConfig(background=background), T_B_C, K, None
        m.timers = defaultdict(float)
        m.net = SimpleNamespace(width=W, height=H)
        codes = [np.zeros(CD), np.full(CD, 0.2), np.full(CD, -0.2)]
        m.kfs = {k: _KfDense(k, k, _done(lin[k]), np.zeros((0, 2)), None, codes[k], had_code=True) for k in range(3)}
        return m, lin

    m, _ = mapper(background=False)
    m._refine(backend, m.kfs[0])
    at_once = m.kfs[0].map_code.result()
    m, lin = mapper(background=True)
    gate, started = threading.Event(), threading.Event()
    m._submit(lambda: (started.set(), gate.wait()))  # the network thread busy while both are queued
    assert started.wait(10)
    m._refine(backend, m.kfs[0])
    m._submit(m._relinearize, lin[1], np.full(CD, 0.6))  # urgent: runs before the fit
    gate.set()
    np.testing.assert_array_equal(m.kfs[0].map_code.result(timeout=60), at_once)
    assert lin[1].n_relin == 2  # the relinearisation did run, and it matters:
    m.kfs[0].map_code = None
    m._refine(backend, m.kfs[0])
    assert np.abs(m.kfs[0].map_code.result(timeout=60) - at_once).max() > 1e-3
    m.close()


def test_drain_returns_once_the_later_work_queued_so_far_has_run():
    """``wall_s`` is measured after :meth:`DenseMapper.drain`: the later work of the frames run counts in it."""
    m = DenseMapper.__new__(DenseMapper)
    m.cfg, m._pool, done = DenseConfig(), None, []
    gate = threading.Event()
    m._submit(gate.wait, 10)
    m._submit(done.append, "map code", urgent=False)
    m._submit(done.append, "network pass")
    threading.Timer(0.2, gate.set).start()
    m.drain()
    assert done == ["network pass", "map code"]
    m.close()


def test_the_later_work_backlog_goes_into_the_metrics():
    """``dense_later_jobs_peak``: most later-work jobs waiting at once; ``dense_later_jobs_at_last_frame``: those
    still waiting when the run drains the network thread after its last frame (known answers, the thread held)."""
    m = DenseMapper.__new__(DenseMapper)
    m.cfg, m._pool = DenseConfig(), None
    gate, done = threading.Event(), []
    m._submit(gate.wait, 10)  # urgent: holds the network thread
    for i in range(3):
        m._submit(done.append, i, urgent=False)
    m._submit(done.append, "urgent")
    assert m.later_peak == 3
    drain = threading.Thread(target=m.drain)
    drain.start()
    deadline = time.monotonic() + 10
    while m.later_at_drain is None and time.monotonic() < deadline:  # a failing drain fails here, not hangs
        threading.Event().wait(0.01)
    gate.set()
    drain.join(10)
    assert m.later_at_drain == 3 and m.later_peak == 3  # the drain's own marker is not later work
    assert done == ["urgent", 0, 1, 2]
    m.close()


def test_linearized_depth_is_exact_at_its_point_and_first_order_near_it():
    class Lin:
        """Quadratic decoder D(c) = D0 + B c + 0.5 (c.c) Q."""

        def __init__(self):
            rng = np.random.default_rng(0)
            self.D0 = rng.uniform(1, 3, (4, 5))
            self.B = rng.normal(size=(4, 5, 3)) * 0.1
            self.Q = rng.normal(size=(4, 5)) * 0.01
            self.net = type("N", (), {"code_dim": 3})()
            self.uncertainty = np.full((4, 5), 0.1)
            self.calls = 0

        def depth(self, c):
            return self.D0 + self.B @ c + 0.5 * float(c @ c) * self.Q

        def jacobian(self, c):
            self.calls += 1
            return self.depth(c), self.B + self.Q[..., None] * c[None, None, :]

    kd = Lin()
    p = LinearizedDepth(kd)
    c0 = np.array([0.1, -0.2, 0.3])
    p.relinearize(c0)
    p.relinearize(c0)  # same code: no new evaluation
    assert kd.calls == 1
    np.testing.assert_allclose(p.depth(c0), kd.depth(np.float32(c0).astype(np.float64)), atol=1e-6)
    dc = np.array([0.01, 0.02, -0.01])
    err = np.abs(p.depth(c0 + dc) - kd.depth(c0 + dc)).max()
    assert err < 0.5 * np.abs(kd.Q).max() * float(dc @ dc) + 1e-6  # second-order remainder only
    assert kd.calls == 1
    far = c0 + np.array([1.0, 0.0, 0.0])
    p.depth(far)  # during LM a code stays on the expansion however far it moved
    assert kd.calls == 1
    p.relinearize(far)  # the next optimisation relinearises exactly
    assert kd.calls == 2
    np.testing.assert_allclose(p.depth(far), kd.depth(np.float32(far).astype(np.float64)), atol=1e-6)


def test_ground_truth_depth_source_keeps_the_code_part_of_the_network():
    rng = np.random.default_rng(1)
    d0 = rng.uniform(1, 3, (4, 5))
    B = rng.normal(size=(4, 5, 3)) * 0.1

    class Lin:
        net = type("N", (), {"code_dim": 3})()
        uncertainty = np.full((4, 5), 0.3, np.float32)

        def depth(self, c):
            return d0 + B @ c

        def jacobian(self, c):
            return self.depth(c), B

    gt = rng.uniform(1, 3, (4, 5))
    gt[0, 0] = 0.0  # a hole: the network's depth stays there
    g = GroundTruthDepth(Lin(), gt, b=0.05)
    c = np.array([0.3, -0.1, 0.2])
    want = np.where(gt > 0, gt, d0) + B @ c
    np.testing.assert_allclose(g.depth(np.zeros(3)), np.where(gt > 0, gt, d0), atol=1e-12)
    d, J = g.jacobian(c)
    np.testing.assert_allclose(d, want, atol=1e-12)
    np.testing.assert_allclose(J, B)
    assert g.uncertainty.shape == (4, 5) and np.all(g.uncertainty == np.float32(0.05))
    with pytest.raises(ValueError, match="does not match"):
        GroundTruthDepth(Lin(), np.ones((3, 3)), b=0.05)
    with pytest.raises(ValueError, match="ground-truth depth"):
        oracle_depth_source(None)
    with pytest.raises(ValueError, match="b="):
        oracle_depth_source(lambda i: gt, b=0.0)
    # as a depth source: the frame's ground truth on the camera grid, mapped to the network's (here the same)
    from runtime.geometry import Camera, NetworkMapping

    cam = Camera(4.0, 4.0, 2.0, 1.5, 5, 4)
    src = oracle_depth_source(lambda i: gt if i == 7 else None, b=0.05)
    g7 = src(Lin(), 7, cam, NetworkMapping.fit(5, 4, 5, 4))
    np.testing.assert_allclose(g7.depth(c), want, atol=1e-6)
    with pytest.raises(ValueError, match="frame 8"):
        src(Lin(), 8, cam, NetworkMapping.fit(5, 4, 5, 4))


def test_dense_config_holds_the_factor_and_map_settings_once():
    cfg = DenseConfig()
    f, m = cfg.factors, cfg.map  # the values the dense system runs with
    assert f.sigma_per_b == 16.0 * 2.0**0.5 and f.min_sigma == 0.02 and f.edge_rel == 0.05 and f.chunk_size == 32
    assert f.geo_huber_k == 1.5 and f.consis_huber_k == 1.5 and not f.check_shapes
    assert (m.max_rel_uncertainty, m.voxel, m.max_depth) == (0.1, 0.02, 10.0)
    cfg = DenseConfig.from_dict({"n_consis": 50, "factors": {"min_sigma": 0.03}, "map": {"voxel": 0.05}})
    assert (cfg.n_consis, cfg.factors.min_sigma, cfg.map.voxel) == (50, 0.03, 0.05)
    assert cfg.factors.edge_rel == 0.05  # the untouched keys keep their defaults
    with pytest.raises(ValueError, match="dense_settings.factors.bogus"):
        DenseConfig.from_dict({"factors": {"bogus": 1}})
    with pytest.raises(ValueError, match="edge_rel"):
        DenseConfig.from_dict({"factors": {"edge_rel": 0.0}})
    with pytest.raises(ValueError, match="n_consis"):
        DenseConfig(n_consis=0)


def test_code_keyframes_are_the_newest_and_its_covisible_ones():
    class Backend:
        def window_ids(self):
            return [3, 5, 6, 8, 9]

        def covisible_keyframes(self, kf, n):
            # only keyframe 6 shares landmarks with the newest; 8 shares with 9, 5 and 3
            return {9: [6], 8: [5, 9, 3]}.get(kf, [])

    def selection(background, min_sparse=0, n_sparse=None):
        m = DenseMapper.__new__(DenseMapper)
        m.cfg = DenseConfig(n_code_keyframes=4, background=background, min_sparse_points=min_sparse)
        m.timers = defaultdict(float)
        n_sparse = n_sparse or {}
        m.kfs = {
            k: SimpleNamespace(job=_done(k), relin=None, n_sparse=n_sparse.get(k, -1)) for k in Backend().window_ids()
        }
        return m._select(Backend())

    assert selection(False) == [9, 6]
    # in the background the newest keyframe's network pass is still running: the one before it anchors, and the
    # newest never joins (whatever the thread's timing)
    assert selection(True) == [8, 5, 3]
    # keyframes whose network input held fewer map points than min_sparse_points take no code: 8 (none) and 5
    # (19) drop out, 6 becomes the newest; -1 (a network without a sparse input) is never dropped
    counts = {3: 20, 5: 19, 6: 120, 8: 0, 9: -1}
    assert selection(True, 20, counts) == [6]
    assert selection(False, 20, counts) == [9, 6]
    assert selection(True, 0, counts) == [8, 5, 3]
    with pytest.raises(ValueError, match="min_sparse_points"):
        DenseConfig(min_sparse_points=-1)


def _done(value) -> Future:
    f = Future()
    f.set_result(value)
    return f


def test_depth_factors_wait_start_after_s_from_the_first_keyframe():
    class Kf:
        def __init__(self, ts):
            self.ts = ts

    class Backend:
        keyframes = {0: Kf(10**9), 1: Kf(3 * 10**9), 2: Kf(6 * 10**9 - 1), 3: Kf(6 * 10**9)}
        active = [0]

        def window_ids(self):
            return list(self.active)

        @property
        def latest(self):
            return self.keyframes[self.active[-1]]

        def covisible_keyframes(self, kf, n):
            return []

    m = DenseMapper.__new__(DenseMapper)
    m.cfg = DenseConfig(start_after_s=5.0)
    m.net = type("Net", (), {"code_dim": 8})()
    m.kfs, m.stats, m.timers, m.t_first_ns = {}, _Stats(), defaultdict(float), 10**9
    b = Backend()
    for newest, started in ((1, False), (2, False), (3, True)):
        b.active = [0, newest]
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        m.add_factors(b, graph, values)
        assert m._started(b) is started
    assert (m.stats.n_skipped, m.stats.n_optim) == (2, 1)  # 4.999999999 s after the first keyframe: not yet
    m.cfg = DenseConfig(start_after_s=0.0)  # from the first optimisation on
    b.active = [0, 1]
    m.add_factors(b, gtsam.NonlinearFactorGraph(), gtsam.Values())
    assert (m.stats.n_skipped, m.stats.n_optim) == (2, 2)
    with pytest.raises(ValueError, match="start_after_s"):
        DenseConfig(start_after_s=-1.0)


def test_depth_factors_wait_again_after_a_reset():
    class Kf:
        def __init__(self, ts):
            self.ts = ts

    class Backend:  # keyframe 0 initialised the first window, keyframe 5 the one after a reset
        keyframes = {k: Kf(t * 10**9) for k, t in ((1, 1), (2, 3), (6, 20), (7, 24), (8, 25))}
        init_kf_id = 0
        active = [1]

        def keyframe(self, k):
            return self.keyframes[k]

        @property
        def latest(self):
            return self.keyframes[self.active[-1]]

    m = DenseMapper.__new__(DenseMapper)
    m.cfg = DenseConfig(start_after_s=5.0)
    m.t_first_ns = m.armed_for = None
    b = Backend()
    for k, want_first in ((1, 1), (2, 1)):  # the first keyframe after the initialisation starts the wait
        m._arm_start(b, k)
        assert m.t_first_ns == want_first * 10**9
    b.active = [2]
    assert not m._started(b)
    b.init_kf_id = 5  # reset and re-initialised: the wait starts again at the next keyframe
    for k, want_first, started in ((6, 20, False), (7, 20, False), (8, 20, True)):
        m._arm_start(b, k)
        b.active = [k]
        assert (m.t_first_ns, m._started(b)) == (want_first * 10**9, started)


def test_cli_dense_true_runs_with_the_shipped_model(seq8, tmp_path, capsys):
    out = tmp_path / "cli"
    slam_main(  # returns on success, exits non-zero on errors
        [
            f"sequence={seq8}",
            f"out={out}",
            "dense=true",
            f"model={default_model_dir()}",
            "progress=false",
            "max_frames=110",
            "dense_settings.use_consistency=false",
            "dense_settings.save_maps=false",
            "dense_settings.start_after_s=0",  # 110 frames: the default wait would leave no dense optimisation
            "dense_settings.map_codes.neighbours=0",  # the map takes the window's codes
        ]
    )
    text = capsys.readouterr().out
    assert "dense_map.ply" in text and "window code" in text and "map code" in text
    assert "interpolated input" in text and "median of the true depth" in text
    # the picture of 4 window keyframes' depth: a title band and a row each, 5 panels (the sequence has depth)
    import cv2

    pic = cv2.imread(str(out / "keyframe_depth.png"))
    assert "keyframe_depth.png" in text and pic is not None and pic.shape[0] > 4 * 128 and pic.shape[1] % 5 == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["depth_metrics"]["map"] == m["depth_metrics"]["optimised"]
    assert m["timing_dense_ms_per_frame"]["map_codes"] == 0
    assert m["dense_config"]["use_consistency"] is False and m["dense_mean_consis_rows"] == 0
    assert (out / "dense_map.ply").is_file() and not (out / "keyframe_depth").exists()
    ts, _ = read_tum(out / "trajectory.txt")
    assert len(ts) == m["frames_with_pose"] > 0


def test_cli_rejects_a_bad_model_and_a_bad_dense_setting(seq8, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        slam_main([f"sequence={seq8}", f"out={tmp_path}", "dense=true", f"model={tmp_path}/nope"])
    assert e.value.code == 2 and "depth model" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        slam_main([f"sequence={seq8}", f"out={tmp_path}", "dense=true", "+dense_settings.bogus=1"])
    assert e.value.code == 2 and "dense_settings.bogus" in capsys.readouterr().err


def test_the_dense_map_goes_into_the_rerun_recording(seq8, tmp_path, monkeypatch):
    pytest.importorskip("rerun")
    from runtime import viz

    seen = {}
    orig = viz.RerunRecorder.log_final

    def spy(self, system, ts, T, points, dense_map=None):
        log = self.rec.log
        seen["paths"] = []
        self.rec.log = lambda path, *a, **k: (seen["paths"].append(path), log(path, *a, **k))[1]
        seen["dense_map"] = dense_map
        orig(self, system, ts, T, points, dense_map=dense_map)

    monkeypatch.setattr(viz.RerunRecorder, "log_final", spy)
    cfg = DenseConfig(n_consis=50, start_after_s=0.0, save_maps=False, use_consistency=False)
    run_sequence(read_euroc(seq8), tmp_path, dense=cfg, progress=False, plot=False, viz="rerun", max_frames=100)
    xyz, rgb = read_ply(tmp_path / "dense_map.ply")
    got_xyz, got_rgb = seen["dense_map"]
    assert got_xyz.shape == xyz.shape and xyz.shape[0] > 1000  # the map of dense_map.ply, point for point
    np.testing.assert_allclose(got_xyz, xyz, atol=1e-4)
    assert np.array_equal(got_rgb, rgb)
    assert {"world/sparse_map", "world/dense_map"} <= set(seen["paths"])
    assert (tmp_path / "slam.rrd").stat().st_size > 10_000


def test_keyframes_below_min_sparse_points_stay_out_of_the_dense_map():
    """A keyframe whose network input held fewer than ``min_sparse_points`` map points is not fused (its depth
    has the constant fill's scale); one with enough points, and any keyframe of a network without a sparse
    input (-1), is."""

    class Backend:
        def keyframe(self, k):
            return SimpleNamespace(T_w_b=np.eye(4))

    m = DenseMapper.__new__(DenseMapper)
    m.cfg, m.T_b_c = DenseConfig(min_sparse_points=20), np.eye(4)
    fused = []
    m._submit = lambda fn, provider, code, map_code, urgent=True: fused.append(provider)
    for k, n in ((1, 0), (2, 19), (3, 20), (4, -1)):
        d = SimpleNamespace(kf_id=k, fused=False, n_sparse=n, job=_done(k), code=np.zeros(8), map_code=None)
        d.provider = k
        m._fuse(Backend(), d)
        assert d.fused  # never tried again
    assert fused == [3, 4]


def test_a_failed_map_code_fit_leaves_the_window_code(monkeypatch, caplog):
    """A fit that raises (a singular system, a bad value) must not stop the run: the map keeps the window's code."""
    import runtime.dense.mapper as mapper_mod

    def boom(*a, **k):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(mapper_mod, "refine_codes", boom)
    m = DenseMapper.__new__(DenseMapper)
    m.cfg, m.T_b_c, m.K_net, m.timers = DenseConfig(), np.eye(4), (100.0, 100.0, 32.0, 32.0), defaultdict(float)
    code = np.arange(8, dtype=np.float64) * 0.1
    with caplog.at_level("WARNING"):
        out = m._fit_map_code(_done([1, 2]), [code, np.zeros(8)], [np.eye(4)] * 2, [np.zeros((4, 2))] * 2)
    np.testing.assert_array_equal(out, code)
    assert "map code fit failed" in caplog.text and m.timers["dense_map_codes"] >= 0


def test_depth_metrics_carry_the_interpolated_input_and_the_median_as_references(monkeypatch):
    """Beside the network's rows, each keyframe's depth metrics score the network's own sparse input interpolated
    and the constant image at the true depth's median. Known answers: a depth linear in the pixels, sampled at
    the image's four corners, is reproduced exactly by the interpolation over their triangles; the median row
    is the metrics of that constant."""
    import runtime.dense.mapper as mapper_mod
    from runtime.dense.map import depth_metrics

    monkeypatch.setattr(mapper_mod, "gt_depth_to_network", lambda gt, camera, mapping: gt)
    v, u = np.mgrid[0:16, 0:24].astype(np.float64)
    gt = 2.0 + 0.1 * u + 0.05 * v  # linear in the pixels: reproduced by the interpolation of the corners
    sparse_in = np.zeros_like(gt)
    for r, c in ((0, 0), (0, 23), (15, 0), (15, 23)):
        sparse_in[r, c] = gt[r, c]
    m = DenseMapper.__new__(DenseMapper)
    m.depth_gt, m.camera, m.mapping = (lambda idx: gt), None, None
    provider = SimpleNamespace(exact=lambda code: np.full(gt.shape, 3.0) + float(np.sum(code)))
    uv, z = np.array([[0.0, 0.0], [23.0, 15.0]]), np.array([gt[0, 0], gt[15, 23]])
    # what a keyframe keeps of its network input: the map points, from which the image comes back exactly
    m.net = SimpleNamespace(height=16, width=24)
    corners = np.array([[0.0, 0.0], [23.0, 0.0], [0.0, 15.0], [23.0, 15.0]])
    kept = (corners, gt[corners[:, 1].astype(int), corners[:, 0].astype(int)])
    assert np.array_equal(m._sparse_input(kept), sparse_in.astype(np.float32)) and m._sparse_input(None) is None
    out = m._depth_errors(provider, np.zeros(8), 0, uv, z, None, sparse_in)
    assert out["interpolated"]["rmse"] < 1e-6 and out["interpolated"]["coverage"] == 1.0
    assert out["prior"]["rmse"] > 0.3  # the constant 3 m: far from the plane
    assert out["median"] == depth_metrics(np.full(gt.shape, np.median(gt)), gt)
    assert out["median"]["rmse"] < out["prior"]["rmse"]
    # no sparse input (a network that takes none, or no map point in view): no interpolation row
    assert m._depth_errors(provider, np.zeros(8), 0, uv, z, None, None)["interpolated"] is None
    assert m._depth_errors(provider, np.zeros(8), 0, uv, z, None, np.zeros_like(gt))["interpolated"] is None
    # a network that took the interpolation as its fill input: its fill is the row (not interpolated again)
    provider.kd = SimpleNamespace(fill=np.full(gt.shape, 2.5, np.float32))
    out = m._depth_errors(provider, np.zeros(8), 0, uv, z, None, sparse_in)
    assert out["interpolated"] == depth_metrics(provider.kd.fill, gt)


def test_the_prior_keeps_its_fill_input_the_interpolation_of_its_sparse_points():
    """The shipped (relative) model's prior keeps the fill it was fed: the interpolation of its sparse input, the
    same array the depth metrics' reference row would compute again."""
    from runtime.densify import interpolate_sparse

    net = DepthNetwork(default_model_dir())
    rng = np.random.default_rng(6)
    sparse = np.zeros((net.height, net.width), np.float32)
    sparse[rng.integers(0, net.height, 60), rng.integers(0, net.width, 60)] = rng.uniform(1, 3, 60)
    kd = net.prior(rng.integers(0, 255, (net.height, net.width), dtype=np.uint8), sparse)
    assert net.takes_fill and kd.fill.dtype == np.float32
    np.testing.assert_array_equal(kd.fill, interpolate_sparse(sparse))
