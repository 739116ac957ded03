"""The SLAM system at feature level (exact synthetic features, no rendering): accuracy, rest, robustness."""

import logging
import subprocess
import sys

import numpy as np
import pytest

from runtime import eval as ev
from runtime.backend.imu import ImuStream
from runtime.slam import SlamConfig, SlamSystem
from runtime.trajectory import FrameRecord, frame_status
from tests.runtime.synth import EUROC_CAM, EUROC_T_BS, FakeTracker, ImuNoise, Motion, make_imu, room_points

T0 = 10**9
IMG = np.zeros((480, 752), np.uint8)


def run(duration, motion=None, imu_noise=True, nan_rows=(), gap=None, blank=None, no_image=(), cfg=None, seed=0):
    m = motion or Motion(seed=seed)
    ts, g, a = make_imu(m, duration + 0.2, noise=ImuNoise() if imu_noise else None, seed=seed, t0_ns=T0)
    for k in nan_rows:
        g[k] = np.nan
    if gap is not None:
        keep = (ts < T0 + int(gap[0] * 1e9)) | (ts >= T0 + int(gap[1] * 1e9))
        ts, g, a = ts[keep], g[keep], a[keep]
    imu = ImuStream(ts, g, a, 200.0)
    trk = FakeTracker(EUROC_CAM, EUROC_T_BS, room_points(seed=seed), m, T0, seed=seed)
    frames = T0 + np.arange(int(duration * 20)) * 50_000_000
    if blank is not None:
        trk.blank = {int(f) for f in frames if blank[0] <= (f - T0) * 1e-9 < blank[1]}
    system = SlamSystem(EUROC_CAM, EUROC_T_BS, imu, ImuNoise(), cfg or SlamConfig(), tracker=trk)
    for i, f in enumerate(frames):
        system.process(i, int(f), None if i in no_image else IMG)
    return system, m


def ate(system, m):
    ts, T = system.trajectory()
    return ev.trajectory_metrics(ts, T, ts, m.body((ts - T0) * 1e-9))


def test_pipeline_on_a_10s_sequence_reaches_a_bounded_ate():
    system, m = run(10.0)
    met = ate(system, m)
    assert met["ate_se3_rmse_m"] < 0.02, met
    assert met["path_length_m"] > 3.0
    assert abs(met["sim3_scale"] - 1) < 0.02  # metric scale from the IMU
    assert len(system.map.history) > 15
    ids, P = system.map.all_points()
    assert len(ids) > 200
    assert system.records[0].ts - T0 < 2.0e9  # initialised within the 1.5 s rest + 0.5 s
    status, imu_s = frame_status(system.records)
    assert set(status) <= {"tracking", "still", "init", "building"}
    # leaving rest, the map has no landmark until the parallax grows: those poses are the IMU's alone, and say so
    building = [i for i, s in enumerate(status) if s == "building"]
    assert building and len(building) == building[-1] - building[0] + 1  # one stretch, then tracking
    assert status[building[-1] + 1] == "tracking" and status[building[0] - 1] in ("still", "init", "tracking")
    assert 0 < imu_s[building[0]] < imu_s[building[-1]] < 2.0


def test_still_camera_gives_a_still_trajectory():
    system, m = run(6.0, motion=Motion(seed=0, still=True))
    ts, T = system.trajectory()
    assert len(ts) > 90
    drift = np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1).max()
    assert drift < 5e-3, drift
    rot = max(np.degrees(np.arccos(np.clip((np.trace(T[0, :3, :3].T @ Ti[:3, :3]) - 1) / 2, -1, 1))) for Ti in T)
    assert rot < 0.2


def test_a_vibrating_resting_sensor_initialises_and_holds_still():
    """Zero-velocity constraints under rotor vibration: the rest rule of the initialiser also drives the
    zero-motion factors, so a resting MAV with its rotors on neither waits forever nor drifts."""
    from tests.runtime.test_init import _vibration

    m = Motion(seed=0, still=True)
    ts, g, a = make_imu(m, 6.2, noise=ImuNoise(), t0_ns=T0)
    vg, va = _vibration(ts)
    imu = ImuStream(ts, g + vg, a + va, 200.0)
    trk = FakeTracker(EUROC_CAM, EUROC_T_BS, room_points(), m, T0)
    system = SlamSystem(EUROC_CAM, EUROC_T_BS, imu, ImuNoise(), SlamConfig(), tracker=trk)
    for i, f in enumerate(T0 + np.arange(120) * 50_000_000):
        system.process(i, int(f), IMG)
    assert system.init_info["method"] == "static" and system.init_info["after_s"] < 1.5
    _, T = system.trajectory()
    drift = np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1).max()
    assert drift < 0.01, drift  # < 1 cm over the 6 s at rest
    assert system.kf_reasons.get("init", 0) >= 1


def test_a_sequence_that_starts_moving_initialises_in_motion(caplog):
    with caplog.at_level(logging.WARNING):
        system, m = run(6.0, motion=Motion(seed=0, t_rest=0.0, t_ramp=0.3, amp=2.0))
    assert system.initialized
    info = system.init_info
    assert info["method"] == "dynamic", info
    assert info["after_s"] <= 2.0, info
    met = ate(system, m)
    n_frames = 6.0 * 20
    assert len(system.records) >= 0.97 * n_frames  # the frames before initialisation have poses too
    assert met["ate_se3_rmse_m"] < 0.03, met
    assert abs(met["sim3_scale"] - 1) < 0.03, met


def test_frames_kept_from_before_an_in_motion_start_are_marked_as_the_imus_alone():
    # no features over the first 1.5 s: the start comes after them, and they are integrated back from it
    system, m = run(6.0, motion=Motion(seed=0, t_rest=0.0, t_ramp=0.3, amp=2.0), blank=(0.0, 1.5))
    info = system.init_info
    status, imu_s = frame_status(system.records)
    back = np.array([s == "imu_backfill" for s in status])
    assert info["method"] == "dynamic" and info["backfilled_frames"] == 30 and back.sum() == 30
    assert back[:30].all() and not back[30:].any()  # the oldest ones
    assert imu_s[back].max() == pytest.approx(info["backfilled_s"]) == pytest.approx(1.5)
    assert np.all(np.diff(imu_s[back]) < 0)  # the older, the longer on the IMU
    assert all(imu_s[i] == 0 for i, s in enumerate(status) if s in ("init", "tracking"))


def test_frame_status_gives_the_seconds_each_pose_rests_on_the_imu_alone():
    def rec(t_s, status, imu_s=0.0):
        return FrameRecord(T0 + int(t_s * 1e9), 0, 0, np.eye(4), np.eye(4), False, status, imu_s=imu_s)

    recs = [rec(0.0, "imu_backfill", 1.0), rec(0.5, "imu_backfill", 0.5), rec(1.0, "init"), rec(1.5, "tracking")]
    recs += [rec(2.0, "coasting"), rec(2.5, "no_image"), rec(3.0, "coasting"), rec(3.5, "still"), rec(4.0, "coasting")]
    status, imu_s = frame_status(recs)
    assert status == [r.status for r in recs]
    assert np.allclose(imu_s, [1.0, 0.5, 0, 0, 0.5, 1.0, 1.5, 0, 0.5])


def test_textureless_period_coasts_on_imu_and_recovers():
    system, m = run(12.0, blank=(5.0, 6.5))
    msgs = " | ".join(msg for _, msg in system.events)
    assert "visual tracking lost" in msgs and "visual tracking regained" in msgs
    statuses = [r.status for r in system.records]
    assert "coasting" in statuses and statuses[-1] == "tracking"
    assert len(system.records) == 240 - system.records[0].frame_idx  # a pose for every frame after init
    assert ate(system, m)["ate_se3_rmse_m"] < 0.1


def test_a_slow_start_after_rest_builds_the_map_without_a_false_loss():
    """After a static start the map is empty and its first landmarks come one triangulation at a time as the
    parallax grows (here 1-2, then ~100 a keyframe later): tracking is acquired then, it was never lost."""
    system, m = run(6.0, motion=Motion(seed=0, t_ramp=3.0))
    assert system.init_info["method"] == "static"
    msgs = [msg for _, msg in system.events]
    assert not any("visual tracking lost" in s for s in msgs), msgs
    assert sum("visual tracking acquired" in s for s in msgs) == 1, msgs
    assert "coasting" not in {r.status for r in system.records}
    assert len(system.map.all_points()[0]) > 50  # the map was built
    assert ate(system, m)["ate_se3_rmse_m"] < 0.02


def test_imu_nan_and_gaps_keep_the_run_going(caplog):
    with caplog.at_level(logging.WARNING):
        system, m = run(10.0, nan_rows=(900, 901, 1300), gap=(6.0, 6.08))
    assert "non-finite" in caplog.text and "gap" in caplog.text
    assert ate(system, m)["ate_se3_rmse_m"] < 0.05
    with caplog.at_level(logging.WARNING):
        system, m = run(10.0, gap=(6.0, 6.5))  # long gap: re-initialise from the propagated state
    assert any("IMU gap of 0.505 s" in msg and "re-initialising" in msg for _, msg in system.events)
    ts, T = system.trajectory()
    assert ts[-1] == T0 + 199 * 50_000_000 and np.isfinite(T).all()
    assert ate(system, m)["ate_se3_rmse_m"] < 0.3


def test_missing_images_give_imu_poses_and_are_logged():
    system, m = run(8.0, no_image={80, 81, 82, 120})
    recs = {r.frame_idx: r for r in system.records}
    assert all(recs[i].status == "no_image" for i in (80, 81, 82, 120))
    assert sum("no usable image" in msg for _, msg in system.events) == 4
    assert ate(system, m)["ate_se3_rmse_m"] < 0.03


def test_config_from_dict_checks_keys_and_types():
    c = SlamConfig.from_dict({"backend": {"window_size": 7}, "features": {"detector": "fast"}, "refine_iterations": 3})
    assert c.backend.window_size == 7 and c.features.detector == "fast" and c.refine_iterations == 3
    with pytest.raises(ValueError, match="runtime.backend.windowsize"):
        SlamConfig.from_dict({"backend": {"windowsize": 7}})
    with pytest.raises(ValueError, match="must be a number"):
        SlamConfig.from_dict({"backend": {"window_size": "x"}})
    with pytest.raises(ValueError, match="integer"):
        SlamConfig.from_dict({"backend": {"window_size": 2.5}})


def test_runtime_does_not_import_torch():
    code = "import sys, runtime.slam, runtime.run, runtime.eval, apps.slam; assert 'torch' not in sys.modules, 'torch!'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_runtime_presets_match_the_typed_config():
    import dataclasses
    from pathlib import Path

    import yaml
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from runtime.presets import presets

    conf = Path(__file__).resolve().parents[2] / "conf"
    text = (conf / "slam" / "runtime" / "default.yaml").read_text()
    assert text == presets()["runtime/default.yaml"]  # generated from the dataclasses, every key
    d = yaml.safe_load(text)
    assert dataclasses.asdict(SlamConfig.from_dict(d)) == dataclasses.asdict(SlamConfig())

    def flat(x, path=""):
        if not isinstance(x, dict):
            return {path: x}
        return {k: v for name, sub in x.items() for k, v in flat(sub, f"{path}.{name}").items()}

    fast = yaml.safe_load((conf / "slam" / "runtime" / "fast.yaml").read_text())
    assert fast.pop("defaults") == ["default", "_self_"]  # the fast preset states only what differs
    changed = flat(fast)
    assert set(changed) < set(flat(d)) and all(flat(d)[k] != v for k, v in changed.items())
    with initialize_config_dir(config_dir=str(conf / "slam"), version_base=None):
        composed = OmegaConf.to_container(compose("slam", overrides=["runtime=fast"]).runtime)
    assert flat(dataclasses.asdict(SlamConfig.from_dict(composed))) == {**flat(d), **changed}


def test_dense_preset_is_generated_from_the_typed_config():
    import dataclasses
    from pathlib import Path

    import yaml

    from runtime.dense import DenseConfig
    from runtime.presets import presets

    text = (Path(__file__).resolve().parents[2] / "conf" / "slam" / "dense_settings" / "default.yaml").read_text()
    assert text == presets()["dense_settings/default.yaml"]
    assert dataclasses.asdict(DenseConfig.from_dict(yaml.safe_load(text))) == dataclasses.asdict(DenseConfig())


def test_keyframe_trajectory_is_in_time_order_whatever_the_ids():
    """A keyframe made for frames before an in-motion start comes after the start's keyframe in id order."""
    from types import SimpleNamespace

    from runtime.slam import SlamSystem

    T = [np.eye(4) for _ in range(3)]
    for k, t in enumerate(T):
        t[0, 3] = k
    hist = {5: (1_800_000_000, T[0]), 6: (1_200_000_000, T[1]), 7: (2_300_000_000, T[2])}
    ts, Ts = SlamSystem.keyframe_trajectory(SimpleNamespace(map=SimpleNamespace(history=hist)))
    assert ts.tolist() == [1_200_000_000, 1_800_000_000, 2_300_000_000]
    assert Ts[:, 0, 3].tolist() == [1.0, 0.0, 2.0]


def test_a_start_turning_in_place_is_refined_in_motion():
    """The body only turns for the first 1.5 s: the system starts turning in place with zero velocity, then
    re-initialises in motion once structure from motion works, and the early frames take the new poses."""
    m = Motion(seed=0, t_rest=0.0, t_ramp=0.3, t_translate=1.5)
    system, _ = run(8.0, motion=m)
    assert system.init_info["method"] == "hover" and system.init_info["after_s"] < 1.5, system.init_info
    assert len(system.restarts) == 1 and system.restarts[0]["why"] == "after a start turning in place"
    assert len(system.records) >= 0.97 * 160
    ts, T = system.trajectory()
    assert np.all(np.diff(ts) > 0)
    kts, _ = system.keyframe_trajectory()  # the discarded start's keyframes are gone: one keyframe a time
    assert np.all(np.diff(kts) > 0)
    assert set(kts) == {r.ts for r in system.records if r.is_kf}
    met = ate(system, m)
    assert met["ate_se3_rmse_m"] < 0.05, met


def test_a_long_loss_is_bridged_reported_and_recovered():
    system, m = run(14.0, blank=(5.0, 9.0))
    msgs = [msg for _, msg in system.events]
    assert any("visual tracking lost" in s for s in msgs)
    assert sum("no visual constraints for 3 s" in s for s in msgs) == 1  # said once, while it lasts
    regained = [s for s in msgs if "visual tracking regained" in s or "re-initialised" in s]
    assert regained, msgs
    assert len(system.records) == 280 - system.records[0].frame_idx  # every frame with images and IMU
    assert system.records[-1].status == "tracking"
    assert ate(system, m)["ate_se3_rmse_m"] < 0.1


def test_a_long_imu_gap_gives_no_poses_inside_and_a_new_segment():
    """A 2 s IMU gap: no poses while the IMU is missing (never dead-reckoned from a stale sample), then a new
    initialisation from the data after the gap, in its own trajectory segment, scored on its own."""
    system, m = run(12.0, gap=(5.0, 7.0))
    msgs = [msg for _, msg in system.events]
    assert any("IMU gap of" in s and "segment 1" in s for s in msgs), msgs
    t = np.array([(r.ts - T0) * 1e-9 for r in system.records])
    seg = np.array([r.segment for r in system.records])
    assert not np.any((t > 5.0 + 0.25 + 0.05) & (t < 7.0))  # nothing inside the gap
    assert set(seg) == {0, 1} and t[seg == 1].min() >= 7.0
    ts, T = system.trajectory()
    for k in (0, 1):  # each segment is accurate in its own frame
        mk = seg == k
        met = ev.trajectory_metrics(ts[mk], T[mk], ts[mk], m.body((ts[mk] - T0) * 1e-9))
        assert met["ate_se3_rmse_m"] < 0.05, (k, met)


def test_a_diverged_estimates_poses_are_withdrawn_and_posed_again_from_the_next_start(monkeypatch):
    """A divergence declared at 8.5 s, while coasting through 2 s without features (forced: the estimate itself is
    fine): the poses since visual tracking was lost are withdrawn and the next start, after the blank, integrates
    the IMU back over them (``imu_backfill``) in a new segment, its own frame. The poses before stay in segment 0,
    the failed window's keyframes at their poses before the failed solve. Both segments are accurate in their own
    frames, and no frame is posed twice."""
    from runtime.backend.window import SlidingWindowBackend

    fired = []

    def diverged(self):
        if not fired and self.latest.ts >= T0 + int(8.5e9):
            fired.append(self.latest.ts)
            return "forced"
        return None

    monkeypatch.setattr(SlidingWindowBackend, "diverged", diverged)
    system, m = run(16.0, blank=(7.0, 9.0))
    msgs = [msg for _, msg in system.events]
    assert any("estimate diverged (forced)" in s and "poses of the diverged estimate withdrawn" in s for s in msgs)
    seg = np.array([r.segment for r in system.records])
    t = np.array([r.ts for r in system.records])
    assert set(seg) == {0, 1}
    assert T0 + 6.5e9 <= t[seg == 0].max() < T0 + 7.0e9  # tracked up to the blank
    info = system.init_info
    assert info["method"] == "dynamic" and info["diverged_reposed"] > 10 and info["diverged_unposed"] == 0, info
    status, imu_s = frame_status(system.records)
    back = np.array([s == "imu_backfill" for s in status])
    assert back.sum() >= info["diverged_reposed"] and np.all(seg[back] == 1) and imu_s[back].max() > 1.5
    assert np.all(np.diff(t) > 0)  # one pose per frame, in time order
    assert (t[seg == 1] < fired[0]).sum() >= info["diverged_reposed"]  # those before the divergence, again
    kts, _ = system.keyframe_trajectory()
    assert set(kts) == {r.ts for r in system.records if r.is_kf}  # the withdrawn keyframes are gone
    ts, T = system.trajectory()
    for k, bound in ((0, 0.02), (1, 0.02)):
        mk = seg == k
        met = ev.trajectory_metrics(ts[mk], T[mk], ts[mk], m.body((ts[mk] - T0) * 1e-9))
        assert met["ate_se3_rmse_m"] < bound, (k, met)


def test_what_a_divergence_withdraws():
    """Withdrawal rules on a bare system (keyframe k at k s, two frames each, segment 1 from keyframe 2, the failed
    window keyframes 4 and 5): with no frame ever tracked visually, every record of the current segment goes and the
    segment stays (none of it is left); with one, the records after it go, the failed window's keyframes that stay
    take their poses from after their own solve, and the segment moves on. Older segments are never touched."""
    from types import SimpleNamespace

    from runtime.start import withdraw_diverged

    def system(t_visual):
        kfs = {k: SimpleNamespace(ts=T0 + k * 10**9) for k in range(6)}
        recs = []
        for i in range(12):
            k = i // 2
            T = np.eye(4)
            T[0, 3] = i  # the online estimate
            recs.append(FrameRecord(T0 + i * 5 * 10**8, i, k, np.eye(4), T, i % 2 == 0, "tracking"))
            recs[-1].segment = 0 if k < 2 else 1
        hist = {k: (kf.ts, -np.eye(4)) for k, kf in kfs.items()}  # the failed solve's
        mp = SimpleNamespace(keyframes=kfs, active=[4, 5], history=hist, landmarks={7: None})
        return SimpleNamespace(map=mp, records=recs, segment=1, t_visual=t_visual, t_first=T0, diverged_pending=[])

    s = system(None)
    assert withdraw_diverged(s) == "8 poses of the diverged estimate withdrawn (2.00-5.50 s after the first frame)"
    assert [r.frame_idx for r in s.records] == [0, 1, 2, 3] and s.segment == 1 and s.map.landmarks == {}
    assert set(s.map.history) == {0, 1} and [p.frame_idx for p in s.diverged_pending] == list(range(4, 12))
    s = system(T0 + 3 * 10**9)  # frame 6 (keyframe 3) was the last one tracked
    assert withdraw_diverged(s).startswith("5 poses")
    assert [r.frame_idx for r in s.records] == list(range(7)) and s.segment == 2
    assert set(s.map.history) == {0, 1, 2, 3} and s.map.history[3][1][0, 0] == -1  # not in the failed window
    s = system(T0 + int(5.5e9))  # tracked to the end: nothing withdrawn
    assert withdraw_diverged(s) == "no pose withdrawn" and len(s.records) == 12 and s.segment == 2
    assert [s.map.history[k][1][0, 3] for k in (4, 5)] == [8, 10]  # the keyframes' online poses
    assert s.map.history[3][1][0, 0] == -1 and s.diverged_pending == []


@pytest.mark.parametrize("lead_ms, first", [(3, 0), (20, 1)])
def test_a_frame_within_one_imu_period_before_the_first_sample_is_taken(lead_ms, first):
    """An image a few ms before the IMU's first sample (a camera-IMU time offset moves it there) is processed with
    that sample held back over it; one further before is skipped, and said so."""
    m = Motion(seed=0, still=True)
    ts, g, a = make_imu(m, 3.0, noise=ImuNoise(), seed=0, t0_ns=T0 + lead_ms * 1_000_000)
    system = SlamSystem(EUROC_CAM, EUROC_T_BS, ImuStream(ts, g, a, 200.0), ImuNoise(), SlamConfig(),
                        tracker=FakeTracker(EUROC_CAM, EUROC_T_BS, room_points(seed=0), m, T0, seed=0))  # fmt: skip
    frames = T0 + np.arange(50) * 50_000_000
    for i, f in enumerate(frames):
        system.process(i, int(f), IMG)
    assert system.t_first == frames[first]
    skipped = [msg for _, msg in system.events if "before the first IMU sample" in msg]
    assert len(skipped) == first
    t_traj, _ = system.trajectory()
    assert t_traj.size > 0 and t_traj[0] == frames[first]  # the frame has its pose


def test_a_start_not_found_is_reported_every_5_s_with_the_last_attempts_reason():
    # moving from the first frame with nothing to track: neither start can be taken
    system, _ = run(11.0, motion=Motion(seed=0, t_rest=0.0, t_ramp=0.3, amp=2.0), blank=(0.0, 11.0))
    assert not system.initialized and system.init_info is None
    waits = [(t, msg) for t, msg in system.events if msg.startswith("not initialised")]
    assert [msg.split(" s after")[0] for _, msg in waits] == ["not initialised 5.0", "not initialised 10.0"]
    assert all("(the last attempt: " in msg for _, msg in waits)
    assert system.initializer.last_reason and system.initializer.last_reason in waits[-1][1]


def test_a_start_found_in_time_reports_no_wait():
    system, _ = run(6.0, motion=Motion(seed=0, t_rest=0.0, t_ramp=0.3, amp=2.0))
    assert system.initialized and not any(msg.startswith("not initialised") for _, msg in system.events)
