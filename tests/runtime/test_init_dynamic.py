"""In-motion initialisation: known answers from exact synthetic features and IMU."""

import numpy as np
import pytest

from runtime.backend.imu import ImuStream
from runtime.geometry import GRAVITY, so3_exp, so3_log
from runtime.init import DynamicInitConfig, InitFailed, initialize_in_motion
from runtime.init.dynamic import BiasDisagrees, estimate_gyro_bias, initialize_hovering, rotation_only
from tests.runtime.synth import EUROC_CAM, EUROC_T_BS, FakeTracker, Motion, make_imu, room_points

T0 = 10**9


def _frames(motion, t_end, sigma_px=0.0, bias=None, seed=0):
    ts, g, a = make_imu(motion, t_end + 0.2, t0_ns=T0)
    if bias is not None:
        g = g + bias
    imu = ImuStream(ts, g, a, 200.0)
    trk = FakeTracker(EUROC_CAM, EUROC_T_BS, room_points(seed=seed), motion, T0, sigma_px=sigma_px, seed=seed)
    frames = []
    for f in T0 + np.arange(0, int(t_end * 20) + 1) * 50_000_000:
        trk.track(int(f), None)
        frames.append(trk.replenish(int(f), None))
    return frames, imu


def _tilt_deg(R_est, R_true):
    up = np.array([0.0, 0.0, 1.0])
    return np.degrees(np.arccos(np.clip((R_est.T @ up) @ (R_true.T @ up), -1, 1)))


def test_noiseless_motion_gives_gravity_scale_and_velocity():
    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0)
    frames, imu = _frames(m, 1.6, bias=np.array([0.01, -0.02, 0.015]))
    sel = frames[4::3][:10]
    r = initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig())
    t = (r.ts - T0) * 1e-9
    T_true = m.body(t)
    v_true = m.velocity(t)
    # gravity: roll and pitch of every frame
    assert max(_tilt_deg(r.T_w_b[k, :3, :3], T_true[k, :3, :3]) for k in range(len(t))) < 0.1
    # scale: relative positions in the true world up to yaw (compare lengths of the displacements)
    d_est = np.linalg.norm(r.T_w_b[:, :3, 3] - r.T_w_b[0, :3, 3], axis=1)
    d_true = np.linalg.norm(T_true[:, :3, 3] - T_true[0, :3, 3], axis=1)
    assert np.abs(d_est - d_true).max() < 0.01 * d_true.max() + 1e-3
    # velocities in the body frame (yaw-free)
    vb_est = np.einsum("fji,fj->fi", r.T_w_b[:, :3, :3], r.v_w)
    vb_true = np.einsum("fji,fj->fi", T_true[:, :3, :3], v_true)
    assert np.abs(vb_est - vb_true).max() < 0.02, (vb_est, vb_true)
    assert np.allclose(r.bg, [0.01, -0.02, 0.015], atol=1e-3)
    assert r.info["scale"] > 0 and abs(r.info["gravity_free"] - GRAVITY) < 0.2


def test_too_little_translation_is_refused_and_turning_in_place_initialises():
    m = Motion(seed=1, t_rest=0.0, t_ramp=0.2, amp=0.0, rate=0.6)  # rotation only
    frames, imu = _frames(m, 1.2)
    sel = frames[2::2][:10]
    with pytest.raises(InitFailed, match="essential matrix|parallax"):  # a refusal, not an OpenCV error
        initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig())
    r = initialize_hovering(sel, imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig())
    T_true = m.body((r.ts - T0) * 1e-9)
    assert max(_tilt_deg(r.T_w_b[k, :3, :3], T_true[k, :3, :3]) for k in range(len(sel))) < 0.2
    assert np.allclose(r.v_w, 0)


def test_hovering_refuses_translation():
    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0)
    frames, imu = _frames(m, 1.6)
    with pytest.raises(InitFailed, match="translates"):
        initialize_hovering(frames[4::3][:10], imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig())


def test_rotation_only_fit_and_gyro_bias_known_answers():
    rng = np.random.default_rng(0)
    R_true = so3_exp(np.array([0.02, -0.05, 0.1]))

    class F:  # minimal stand-in for FrameFeatures
        def __init__(self, ids, xn):
            self.ids, self.xn = ids, xn

    b = rng.normal(size=(50, 3)) + [0, 0, 5]
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    b1 = b @ R_true  # rows: R_true^T b
    a_ = F(np.arange(50), b[:, :2] / b[:, 2:])
    c_ = F(np.arange(50), b1[:, :2] / b1[:, 2:])
    R, res, n = rotation_only(a_, c_, 500.0)
    assert n == 50 and res < 1e-6 and np.allclose(R, R_true, atol=1e-9)
    # gyro bias: rotations from a constant rate plus a bias
    w, bg = np.array([0.1, 0.3, -0.2]), np.array([0.004, -0.003, 0.002])
    dt = np.full(10, 0.005)
    segs = [(np.tile(w + bg, (10, 1)), np.zeros((10, 3)), dt) for _ in range(5)]
    R_w_b = np.stack([so3_exp(w * 0.05 * k) for k in range(6)])
    assert np.allclose(estimate_gyro_bias(R_w_b, segs), bg, atol=1e-7)
    assert np.linalg.norm(so3_log(R_w_b[1])) == pytest.approx(np.linalg.norm(w) * 0.05)


def test_frame_alignment_is_a_yaw_and_a_translation():
    from runtime.geometry import make_T
    from runtime.start import frame_alignment

    T_new = make_T(so3_exp(np.array([0.1, -0.05, 0.7])), [1.0, 2.0, 0.5])
    yaw = so3_exp(np.array([0.0, 0.0, -1.2]))
    T_old = make_T(yaw @ T_new[:3, :3], [4.0, -1.0, 2.0])
    A = frame_alignment(T_old, T_new)
    assert np.allclose(A @ T_new, T_old, atol=1e-12)
    assert np.allclose(A[:3, :3], yaw, atol=1e-12) and np.allclose(A[2, :3], [0, 0, 1])


def _steps(runner, frames, t_end):
    """Feed ``frames`` (20 Hz from T0) to ``runner`` until a start or ``t_end`` [s]; returns the StartState or None."""
    from runtime.init.runner import Snapshot

    for k, f in enumerate(frames):
        if (f.ts - T0) * 1e-9 > t_end + 1e-9:
            return None
        runner.add(Snapshot(k, f.ts, f))
        st = runner.step(f.ts)
        if st is not None:
            return st
    return None


def test_alignment_solves_the_accelerometer_bias():
    """A 0.15-0.12 m/s^2 accelerometer bias over 2 s: taken as 0 (VINS-Mono) the scale is 10-30 % off; solved with
    its zero prior it is within 2 % (default weight) and, with a weak prior, the bias itself is recovered."""
    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0, rate=0.4)
    ts, g, a = make_imu(m, 2.2, t0_ns=T0)
    ba = np.array([0.15, -0.1, 0.12])
    imu = ImuStream(ts, g, a + ba, 200.0)
    frames, _ = _frames(m, 2.0)
    sel = frames[0::4][:11]
    T_true = m.body((np.array([f.ts for f in sel]) - T0) * 1e-9)
    d_true = np.linalg.norm(T_true[:, :3, 3] - T_true[0, :3, 3], axis=1).max()

    def run(w):
        r = initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig(accel_bias_weight=w))
        return np.linalg.norm(r.T_w_b[:, :3, 3] - r.T_w_b[0, :3, 3], axis=1).max() / d_true, r

    s0, r0 = run(0.0)
    assert abs(s0 - 1) > 0.1 and np.all(r0.ba == 0)
    s_def, r_def = run(DynamicInitConfig().accel_bias_weight)
    assert abs(s_def - 1) < 0.02 and r_def.info["accel_bias"] == np.round(r_def.ba, 4).tolist()
    s_weak, r_weak = run(1e-3)
    assert abs(s_weak - 1) < 0.01 and np.abs(r_weak.ba - ba).max() < 0.03


def test_frames_before_an_in_motion_start_follow_the_first_keyframes_state():
    """The frames older than an in-motion start's first keyframe are integrated backwards from that keyframe's
    state as the window holds it (here the true one), not from the alignment's; once it has left the window they
    stay as they are."""
    from types import SimpleNamespace

    from runtime.backend.state import Keyframe
    from runtime.init.runner import Snapshot, StartState, propagate_back
    from runtime.start import backfill_records, repose_older

    m = Motion(seed=3, t_rest=0.0, t_ramp=0.5)
    ba, bg = np.array([0.15, -0.1, 0.05]), np.array([0.004, -0.003, 0.002])
    ts, g, a = make_imu(m, 3.0, t0_ns=T0)
    imu = ImuStream(ts, g + bg, a + ba, 200.0)
    t_kf, t_old = 2.0, 1.0 + np.arange(20) * 0.05  # the first keyframe; 1 s of frames before it
    T_kf, v_kf = m.body(t_kf)[0], m.velocity(t_kf)[0]
    snap = Snapshot(40, T0 + int(t_kf * 1e9), None)
    old = [Snapshot(20 + k, T0 + int(round(t * 1e9)), None) for k, t in enumerate(t_old)]
    v_aligned = v_kf + np.array([0.2, 0.0, 0.0])  # the alignment's velocity, 0.2 m/s off, and no bias
    st = StartState("dynamic", [(snap, T_kf, v_aligned)], np.zeros(6), [(s, T_kf) for s in old])
    true_kf = Keyframe(7, snap.ts, 40, T_kf, v_kf, np.concatenate([ba, bg]))
    window = {7: true_kf}
    backend = SimpleNamespace(has_keyframe=lambda k: k in window, keyframe=lambda k: window[k])
    system = SimpleNamespace(records=[], segment=0, imu=imu, backend=backend, older_pending=None)

    backfill_records(system, st, [7])
    recs = {r.frame_idx: r for r in system.records}
    assert sorted(recs) == [20 + k for k in range(20)] + [40]
    err = [np.linalg.norm((T_kf @ recs[20 + k].T_rel)[:3, 3] - m.body(t)[0][:3, 3]) for k, t in enumerate(t_old)]
    assert max(err) < 2e-3  # m, over 1 s (discretisation only)
    assert system.older_pending is not None

    aligned = propagate_back(imu, old, snap.ts, T_kf, v_aligned, np.zeros(6))  # what the alignment's state gives
    assert np.linalg.norm(aligned[-1][1][:3, 3] - m.body(t_old[0])[0][:3, 3]) > 0.15

    before = recs[20].T_rel.copy()
    window.clear()  # the keyframe left the window: nothing moves any more
    repose_older(system)
    assert system.older_pending is None and np.array_equal(recs[20].T_rel, before)


def _span_gated(runner_mod, ok, message: str):
    """A stand-in for ``initialize_in_motion`` that records each window's span [s] and fails with ``message`` where
    ``ok(span)`` is false; returns it, the list of spans and the real function."""
    real, spans = runner_mod.initialize_in_motion, []

    def gated(feats, *a, **k):
        span = (feats[-1].ts - feats[0].ts) * 1e-9
        spans.append(round(span, 2))
        if not ok(span):
            raise InitFailed(message)
        return real(feats, *a, **k)

    return gated, spans, real


def test_a_failed_alignment_is_tried_again_on_the_longest_window(monkeypatch):
    """When the alignment fails on the 1 s window (slow motion: the accelerometer bias outweighs the acceleration),
    the start is tried once more over the longest window of kept frames up to ``max_window_s``, and takes it; a
    window that aligns is never replaced."""
    import runtime.init.runner as runner_mod
    from runtime.init.runner import InitRunner
    from runtime.init.static import InitConfig

    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0, rate=0.4)
    frames, imu = _frames(m, 3.0)
    needs_two_seconds, spans, real = _span_gated(
        runner_mod, lambda span: span >= 2.0 - 1e-6, "alignment scale -0.2 is not positive"
    )

    monkeypatch.setattr(runner_mod, "initialize_in_motion", needs_two_seconds)
    run = InitRunner(InitConfig(), DynamicInitConfig(max_window_s=3.0), imu, EUROC_T_BS, EUROC_CAM.fx, GRAVITY)
    st = _steps(run, frames, 3.0)
    assert st is not None and st.method == "dynamic" and st.info["span_s"] >= 2.0
    assert spans[-2:] == [1.0, st.info["span_s"]]  # the 1 s window failed, then the longest one was tried
    t_start = (st.keyframes[-1][0].ts - T0) * 1e-9
    assert t_start < 2.5  # not waiting for a 1 s window that aligns (there is none)

    spans.clear()
    monkeypatch.setattr(runner_mod, "initialize_in_motion", lambda f, *a, **k: spans.append(1) or real(f, *a, **k))
    run = InitRunner(InitConfig(), DynamicInitConfig(max_window_s=3.0), imu, EUROC_T_BS, EUROC_CAM.fx, GRAVITY)
    st = _steps(run, frames, 3.0)
    assert st is not None and st.info["span_s"] <= 1.0 + 1e-6 and len(spans) == run.tries  # one try each

    old = InitRunner(InitConfig(), DynamicInitConfig(max_window_s=1.0), imu, EUROC_T_BS, EUROC_CAM.fx, GRAVITY)
    monkeypatch.setattr(runner_mod, "initialize_in_motion", needs_two_seconds)
    assert _steps(old, frames, 3.0) is None  # without a longer window there is no start


def test_a_restart_whose_frames_since_the_start_fail_takes_a_recent_window(monkeypatch):
    """After a start turning in place, the restart tries every frame since the first (``since``). When that fails
    (here: any window over 2 s, as the few common tracks of a bare wall make it) at or after ``recent_from``, it
    also tries the recent window a first start would take, the frames before it integrated back; before
    ``recent_from``, or without it, it does not."""
    import runtime.init.runner as runner_mod
    from runtime.init.runner import InitRunner, Snapshot
    from runtime.init.static import InitConfig

    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0, rate=0.4)
    frames, imu = _frames(m, 4.0)
    short_only, spans, _ = _span_gated(
        runner_mod, lambda span: span <= 2.0, "at most 12 tracks common with the newest frame (< 30)"
    )

    monkeypatch.setattr(runner_mod, "initialize_in_motion", short_only)
    ts = frames[-1].ts
    for recent_from in (None, ts + 1, ts):
        spans.clear()
        run = InitRunner(InitConfig(), DynamicInitConfig(), imu, EUROC_T_BS, EUROC_CAM.fx, GRAVITY)
        for k, f in enumerate(frames):
            run.add(Snapshot(k, f.ts, f), keep_since=T0)
        st = run.try_motion(ts, allow_hover=False, since=T0, recent_from=recent_from)
        assert spans[0] == 4.0  # the frames since the start were tried first
        if recent_from is None or recent_from > ts:
            assert st is None and spans == [4.0] and "tracks common" in run.last_reason
            continue
        assert st is not None and st.method == "dynamic" and spans[-1] <= 1.0 + 1e-6
        assert st.keyframes[0][0].ts >= ts - 1_000_000_000  # the recent window
        assert st.info["backfilled_frames"] >= 59  # every frame since the start before that window
        snap0, T_kf0, _ = st.keyframes[0]
        assert _tilt_deg(T_kf0[:3, :3], m.body((snap0.ts - T0) * 1e-9)[0][:3, :3]) < 0.5
        p_kf0 = m.body((snap0.ts - T0) * 1e-9)[0][:3, 3]
        for snap, T in st.frames:  # the frames since the start: distances to the window's first keyframe (yaw-free)
            true = np.linalg.norm(m.body((snap.ts - T0) * 1e-9)[0][:3, 3] - p_kf0)
            assert abs(np.linalg.norm(T[:3, 3] - T_kf0[:3, 3]) - true) < 0.05 + 0.02 * true


def test_the_runner_counts_why_attempts_failed_by_kind(monkeypatch):
    """Every failed attempt is counted by kind (its text before a colon, numbers as N); the start's info in
    metrics.json carries the counts."""
    import runtime.init.runner as runner_mod
    from runtime.init.runner import InitRunner, Snapshot, reason_kind
    from runtime.init.static import InitConfig

    assert reason_kind("median scene depth 0.050 m (< 0.2): tracks or scale implausible") == "median scene depth N m"
    assert reason_kind("structure from motion implausible: gyroscope bias [-0.3, 0.05, 0.0] rad/s") == (
        "structure from motion implausible"
    )
    assert reason_kind("PnP failed") == "PnP failed"
    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0, rate=0.4)
    frames, imu = _frames(m, 2.0)
    after_1s, spans, _ = _span_gated(
        runner_mod, lambda span: span > 1.05, "median scene depth 0.1 m (< 0.2): implausible"
    )
    early = []

    def two_kinds(feats, *a, **k):  # the shortest windows fail on another kind
        if (feats[-1].ts - feats[0].ts) * 1e-9 < 0.75:
            early.append(1)
            raise InitFailed("median parallax 1.20 deg (< 1.5): not enough translation")
        return after_1s(feats, *a, **k)

    monkeypatch.setattr(runner_mod, "initialize_in_motion", two_kinds)
    dyn = DynamicInitConfig(window_s=1.0, max_window_s=1.0, try_every_s=0.0)
    run = InitRunner(InitConfig(), dyn, imu, EUROC_T_BS, EUROC_CAM.fx, GRAVITY)
    st = None
    for k, f in enumerate(frames):
        run.add(Snapshot(k, f.ts, f))
        if k >= 10 and st is None:
            st = run.try_motion(f.ts, allow_hover=False, since=T0)
    assert st is not None and st.method == "dynamic"
    refused = sum(span <= 1.05 for span in spans)  # the failures of the second kind
    assert refused >= 1 and early
    assert run.failures == {"median scene depth N m": refused, "median parallax N deg": len(early)}
    assert st.info["failures"] == dict(run.failures) and st.info["attempts"] == refused + len(early) + 1


@pytest.mark.parametrize("after_s", [3.0, 0.5, float("inf")])
def test_a_restart_may_take_a_recent_window_from_restart_recent_after_s_on(after_s):
    """``try_restart`` hands the runner the time from which a recent window may replace every frame since the first:
    ``restart_recent_after_s`` after the start turning in place (never when infinite)."""
    from types import SimpleNamespace

    from runtime.slam import SlamConfig
    from runtime.start import try_restart

    calls = []
    run = SimpleNamespace(add=lambda *a, **k: None, try_motion=lambda ts, **k: calls.append(k))
    cfg = SlamConfig()
    cfg.dynamic_init.restart_recent_after_s = after_s
    t_hover = 5 * 10**9
    system = SimpleNamespace(
        cfg=cfg,
        restart_until=t_hover + int(cfg.dynamic_init.refine_within_s * 1e9),
        restart_why=None,
        initializer=run,
        t_first=10**9,
        dense=None,
    )
    assert try_restart(system, 7, t_hover + 10**9, None, None) is False  # the runner found no start
    (k,) = calls
    assert k["since"] == 10**9 and k["allow_hover"] is False
    assert k["recent_from"] == (None if after_s == float("inf") else t_hover + int(after_s * 1e9))


def test_backfill_reaches_every_kept_frame_and_is_reported():
    """The frames before a start are integrated back from it as far as ``backfill_s`` reaches (the default: every
    kept frame); metrics.json's ``initialisation`` says how many and how far back (known answers)."""
    from collections import deque
    from types import SimpleNamespace

    from runtime.init.runner import InitRunner, Snapshot, backfill_info

    m = Motion(seed=3, t_rest=0.0, t_ramp=0.5)
    ts, g, a = make_imu(m, 5.0, t0_ns=T0)
    run = InitRunner.__new__(InitRunner)  # only what _before reads
    run.imu = ImuStream(ts, g, a, 200.0)
    run.frames = deque(Snapshot(k, T0 + k * 50_000_000, None) for k in range(100))  # 0 - 4.95 s, 20 Hz
    first = run.frames[80]  # the start window's first frame, 4.0 s
    T, v = m.body(4.0)[0], m.velocity(4.0)[0]
    for back_s, n, span in ((2.0, 40, 2.0), (DynamicInitConfig().backfill_s, 80, 4.0)):
        run.dyn = SimpleNamespace(backfill_s=back_s)
        before = run._before(first, T, v, np.zeros(6))
        assert sorted(s.frame_idx for s, _ in before) == list(range(80 - n, 80))
        assert backfill_info(before, first.ts) == {"backfilled_frames": n, "backfilled_s": span}
        err = max(np.linalg.norm(Tb[:3, 3] - m.body((s.ts - T0) * 1e-9)[0][:3, 3]) for s, Tb in before)
        assert err < 0.01  # m: an exact IMU and the true start state, discretisation only
    assert DynamicInitConfig().backfill_s >= DynamicInitConfig().refine_within_s  # the default reaches every kept one
    assert backfill_info([], first.ts) == {"backfilled_frames": 0, "backfilled_s": 0.0}


def test_a_start_whose_gyro_bias_disagrees_with_the_earlier_attempts_is_refused_and_failures_carry_it():
    bias = np.array([0.01, -0.02, 0.015])
    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0)
    frames, imu = _frames(m, 1.6, bias=bias)
    sel = frames[4::3][:10]
    cfg = DynamicInitConfig()
    r = initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, cfg, earlier_bias=bias + 0.01)  # within 0.03
    assert np.allclose(r.bg, bias, atol=1e-3)
    with pytest.raises(BiasDisagrees, match="disagrees with the earlier attempts") as e:
        initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, cfg, earlier_bias=bias + [0.05, 0.0, 0.0])
    assert e.value.gyro_bias is None  # a refused bias is not one to remember
    off = DynamicInitConfig(bias_agree=0.0)  # the check off
    assert initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, off, earlier_bias=bias + 1.0).scale > 0
    # a start that fails after its structure from motion (here the depth bound) carries the bias it found
    with pytest.raises(InitFailed, match="median scene depth") as e:
        initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig(min_depth_m=1e3))
    assert np.allclose(e.value.gyro_bias, bias, atol=1e-3)
    with pytest.raises(InitFailed, match="essential-matrix inliers") as e:  # before structure from motion: no bias
        initialize_in_motion(frames[4:6], imu, EUROC_T_BS, EUROC_CAM.fx, cfg)
    assert e.value.gyro_bias is None


def test_a_start_whose_gyro_bias_exceeds_max_gyro_bias_is_refused_and_not_remembered():
    """No gyroscope has a bias beyond ``max_gyro_bias``: a structure from motion that gives one is refused as a
    :class:`BiasDisagrees` (so the runner does not remember its bias), whatever the earlier attempts agree on."""
    bias = np.array([0.01, -0.02, 0.015])  # |b| = 0.027 rad/s
    m = Motion(seed=3, t_rest=0.0, t_ramp=0.2, amp=2.0)
    frames, imu = _frames(m, 1.6, bias=bias)
    sel = frames[4::3][:10]
    assert DynamicInitConfig().max_gyro_bias >= 0.25  # the default takes any MEMS gyroscope's bias
    r = initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig(max_gyro_bias=0.03))
    assert np.allclose(r.bg, bias, atol=1e-3)
    with pytest.raises(BiasDisagrees, match="larger than max_gyro_bias 0.02") as e:
        initialize_in_motion(sel, imu, EUROC_T_BS, EUROC_CAM.fx, DynamicInitConfig(max_gyro_bias=0.02), bias)
    assert e.value.gyro_bias is None


def test_the_earlier_attempts_bias_needs_two_that_agree_within_the_window():
    from runtime.init import InitConfig
    from runtime.init.runner import InitRunner

    run = InitRunner(InitConfig(), DynamicInitConfig(), imu=None, T_b_c=np.eye(4), focal=460.0, gravity=GRAVITY)
    s = 10**9
    b = np.array([0.09, 0.09, -0.05])
    assert run.earlier_bias(s) is None
    run.biases.append((s, b))
    assert run.earlier_bias(s) is None  # one attempt is no agreement
    run.biases.append((s + s // 10, b + [0.01, 0.0, 0.0]))
    np.testing.assert_allclose(run.earlier_bias(s + s // 5), b + [0.005, 0.0, 0.0])
    run.biases.append((s + s // 5, b + [0.2, 0.1, 0.0]))  # one far off: no agreement any more
    assert run.earlier_bias(s + s // 5) is None
    # attempts older than max_window_s (3 s) are forgotten, and a reset forgets them all
    assert run.earlier_bias(s + 3 * s + s // 20) is None and len(run.biases) == 2
    run.reset()
    assert len(run.biases) == 0
    run.dyn = DynamicInitConfig(bias_agree=0.0)
    run.biases.extend([(s, b), (s, b)])
    assert run.earlier_bias(s) is None


def _lost_system(n_tracks: int, restart_until=None):
    """What ``SlamSystem._update_lost`` reads, tracking acquired and not lost."""
    from types import SimpleNamespace

    from runtime.slam import SlamConfig, SlamSystem

    events = []
    system = SimpleNamespace(
        cfg=SlamConfig(),
        acquired=True,
        lost=False,
        lost_since=None,
        coast_warned=False,
        reloc_pending=None,
        restart_until=restart_until,
        restart_why=None,
        tracker=SimpleNamespace(n_tracks=n_tracks),
        initializer=SimpleNamespace(reset=lambda: events.append("reset")),
        event=lambda ts, msg, level=None: events.append(msg),
        events=events,
    )
    system._arm_restart = lambda *a: SlamSystem._arm_restart(system, *a)
    return system


def test_a_loss_with_tracks_in_view_arms_a_restart_and_a_bare_view_does_not():
    """Visual tracking lost while the front end still holds ``restart_lost_min_tracks`` tracks: the estimate
    disagrees with a textured view, and an in-motion restart is tried for ``refine_within_s``; regaining tracking
    cancels it. With fewer tracks (a bare wall) the system coasts as before, and a pending restart after a start
    turning in place is left as it is."""
    from runtime.slam import SlamSystem

    ts = 7 * 10**9
    n = _lost_system(0).cfg.restart_lost_min_tracks
    textured = _lost_system(n)
    SlamSystem._update_lost(textured, ts, 3)
    assert textured.lost and textured.restart_why
    assert textured.restart_until == ts + int(textured.cfg.dynamic_init.refine_within_s * 1e9)
    assert "reset" in textured.events  # the restart's frames start at the loss
    SlamSystem._update_lost(textured, ts + 10**8, 30)  # regained: the images agree again
    assert not textured.lost and textured.restart_until is None and not textured.restart_why

    bare = _lost_system(n - 1)
    SlamSystem._update_lost(bare, ts, 3)
    assert bare.lost and bare.restart_until is None and not bare.restart_why

    pending = _lost_system(n, restart_until=ts + 5 * 10**9)
    SlamSystem._update_lost(pending, ts, 3)
    assert pending.restart_until == ts + 5 * 10**9 and not pending.restart_why


def test_a_start_that_acquires_no_visual_tracking_in_motion_arms_a_restart():
    """Frames recorded ``building`` (moving, visual tracking not acquired since the start) for ``building_restart_s``
    with ``restart_lost_min_tracks`` tracks in view arm an in-motion restart, as a loss with tracks in view does
    (MH_05 IMU seeds 352 and 360: 10-13 s of it, then 1.4 and 4.6 m); acquiring visual tracking first cancels it;
    fewer tracks, a shorter stretch, a restart already pending or the setting at 0 arm nothing."""
    from types import SimpleNamespace

    from runtime.slam import SlamSystem

    t0 = 3 * 10**9
    n = _lost_system(0).cfg.restart_lost_min_tracks
    wait = int(_lost_system(0).cfg.building_restart_s * 1e9)

    def building(n_tracks, **kw):
        system = _lost_system(n_tracks, **kw)
        system.acquired, system.building, system.building_since = False, False, t0
        system.map, system.init_info = SimpleNamespace(n_landmarks=0), {"t_s": t0 * 1e-9}
        system._restart_if_building = lambda ts: SlamSystem._restart_if_building(system, ts)
        return system

    early = building(n)
    SlamSystem._update_lost(early, t0 + wait - 10**8, 2)
    assert early.restart_until is None and not early.restart_why
    armed = building(n)
    SlamSystem._update_lost(armed, t0 + wait, 2)
    assert armed.restart_why == "after building without visual tracking" and "reset" in armed.events
    assert armed.restart_until == t0 + wait + int(armed.cfg.dynamic_init.refine_within_s * 1e9)
    SlamSystem._update_lost(armed, t0 + wait + 10**8, 30)  # acquired: the images agree after all
    assert armed.acquired and armed.restart_until is None and not armed.restart_why
    assert armed.building_since is None

    bare = building(n - 1)
    SlamSystem._update_lost(bare, t0 + 2 * wait, 2)
    assert bare.restart_until is None
    pending = building(n, restart_until=t0 + 10 * 10**9)  # a restart after a start turning in place
    SlamSystem._update_lost(pending, t0 + 2 * wait, 2)
    assert pending.restart_until == t0 + 10 * 10**9 and not pending.restart_why
    off = building(n)
    off.cfg.building_restart_s = 0.0
    SlamSystem._update_lost(off, t0 + 2 * wait, 2)
    assert off.restart_until is None


def test_a_restart_after_a_loss_takes_a_recent_window_and_reposes_the_lost_records(monkeypatch):
    """After a loss with tracks in view the restart takes a recent window (``since`` None), keeps the frames of the
    last ``backfill_s``, and every record of those seconds older than the new window is integrated back from the new
    state on the IMU (known answer: no rotation, the accelerometer reading gravity alone, so ``p(t) = p0 - v0 (t0 -
    t)``); the records' poses of the estimate that lost the view are replaced."""
    from types import SimpleNamespace

    import runtime.start as start
    from runtime.init.runner import Snapshot, StartState
    from runtime.slam import SlamConfig

    cfg = SlamConfig()
    t_first, ts = 10**9, 13 * 10**9
    keep = ts - int(cfg.dynamic_init.backfill_s * 1e9)
    t_imu = np.arange(0, 14 * 200) * 5_000_000 + 5 * 10**8
    imu = ImuStream(t_imu, np.zeros((t_imu.size, 3)), np.tile([0.0, 0.0, GRAVITY], (t_imu.size, 1)), 200.0)
    t_kf = 12 * 10**9
    T0, v0 = np.eye(4), np.array([1.0, 0.5, 0.0])
    T0[:3, 3] = [4.0, 2.0, 1.0]
    st = StartState("dynamic", [(Snapshot(240, t_kf, None), T0, v0)], np.zeros(6), [], info={"scale": 1.0})
    calls, added = [], []

    def try_motion(t, **k):
        calls.append(k)
        return st

    records = [SimpleNamespace(ts=int(t), frame_idx=i, ref_kf=0) for i, t in enumerate(range(t_first, ts, 10**9))]
    system = SimpleNamespace(
        cfg=cfg,
        restart_until=ts + 10**9,
        restart_why="after a loss with tracks in view",
        initializer=SimpleNamespace(
            add=lambda s, keep_since: added.append(keep_since), try_motion=try_motion, reset=lambda: None
        ),
        t_first=t_first,
        dense=None,
        imu=imu,
        records=records,
        T_cur=T0.copy(),
        backend=SimpleNamespace(clear_window=lambda: None),
        map=SimpleNamespace(history={}),
        diverged_pending=[],
        restarts=[],
        event=lambda *a, **k: None,
    )
    moved = []
    monkeypatch.setattr(start, "seed_window", lambda system, st, A: [7])
    monkeypatch.setattr(start, "backfill_records", lambda system, m, kf_ids: moved.append(m))
    assert start.try_restart(system, 260, ts, None, None) is True
    (k,) = calls
    assert k["since"] is None and k["recent_from"] is None and added == [keep]
    assert system.restarts[-1]["why"] == "after a loss with tracks in view" and not system.restart_why
    assert [r.ts for r in system.records] == [r.ts for r in records if r.ts < keep]  # older ones kept as they were
    (m,) = moved
    reposed = {s.ts: T for s, T in m.frames}
    assert sorted(reposed) == [r.ts for r in records if keep <= r.ts < t_kf]
    for t, T in reposed.items():
        np.testing.assert_allclose(T[:3, 3], T0[:3, 3] - v0 * (t_kf - t) * 1e-9, atol=1e-6)


def test_the_intrinsics_first_pass_never_restarts_for_want_of_visual_tracking(monkeypatch):
    """The first pass only feeds the calibration, which such a restart there moved by chance (MH_05 IMU seed 377):
    it runs with ``building_restart_s`` 0, the run's own setting untouched."""
    from types import SimpleNamespace

    import runtime.run as run_mod
    from runtime.slam import SlamConfig

    seen = []

    class Stop(Exception):
        pass

    def fake_live(camera, T_b_c, imu, cfg):
        seen.append(cfg)
        raise Stop

    monkeypatch.setattr(run_mod, "LiveSlam", fake_live)
    cfg = SlamConfig()
    seq = SimpleNamespace(frame_ts=np.arange(10) * 50_000_000, camera=None, T_b_c=None, imu=None)
    with pytest.raises(Stop):
        run_mod.first_pass(seq, cfg, 10)
    assert seen[0].building_restart_s == 0.0 and cfg.building_restart_s == 4.0
    assert seen[0].intrinsics == cfg.intrinsics and seen[0].restart_lost_min_tracks == cfg.restart_lost_min_tracks
