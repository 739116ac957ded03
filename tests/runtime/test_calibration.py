"""The intrinsics refinement (runtime.calibration): known answers on exact synthetic features and IMU."""

from dataclasses import replace

import numpy as np
import pytest

from runtime.backend.imu import ImuStream
from runtime.calibration import IntrinsicsConfig, not_refined, refine_intrinsics, tracks_from_features
from runtime.frontend.tracking import FrameFeatures
from runtime.geometry import so3_exp
from tests.runtime.synth import EUROC_CAM, EUROC_T_BS, FakeTracker, ImuNoise, Motion, make_imu, room_points

T0 = 10**9


def _first_pass(written, seconds=6.0, sigma_px=0.3, seed=1, time_offset_s=0.0):
    """Features as the front end would give them with the ``written`` camera (raw pixels of the true camera,
    normalised with the written one), the exact IMU, and poses off the truth by a few mm and mrad; with
    ``time_offset_s`` the image stamped ``t`` shows the scene at ``t + time_offset_s``."""
    m = Motion(seed=seed, t_rest=0.0, t_ramp=0.3, amp=1.0, rate=0.6)
    ts, g, a = make_imu(m, seconds + 0.2, t0_ns=T0)
    imu = ImuStream(ts, g, a, 200.0)
    trk = FakeTracker(EUROC_CAM, EUROC_T_BS, room_points(seed=seed), m, T0, sigma_px=sigma_px, seed=seed)
    feats = []
    frame_ts = T0 + np.arange(0, int(seconds * 20) + 1) * 50_000_000
    for f in frame_ts:
        seen = int(f + round(time_offset_s * 1e9))
        trk.track(seen, None)
        t = trk.replenish(seen, None)
        xn = written.pixel_to_normalized(t.uv)
        feats.append(FrameFeatures(int(f), t.ids, t.uv, xn, t.uv_u, 0.0, 0, 0))
    rng = np.random.default_rng(seed)
    T = m.body((frame_ts - T0) * 1e-9)
    for k in range(len(T)):
        T[k, :3, :3] = T[k, :3, :3] @ so3_exp(rng.normal(0, 2e-3, 3))
        T[k, :3, 3] += rng.normal(0, 5e-3, 3)
    return imu, feats, frame_ts, T


def _refine(written, cfg=None, **kw):
    imu, feats, ts, T = _first_pass(written, **kw)
    return refine_intrinsics(written, EUROC_T_BS, ImuNoise(), imu, feats, ts, T, None, cfg or IntrinsicsConfig())


def test_a_wrong_calibration_is_recovered():
    d = EUROC_CAM.dist
    written = replace(
        EUROC_CAM,
        fx=EUROC_CAM.fx * 1.010,
        fy=EUROC_CAM.fy * 0.992,
        cx=EUROC_CAM.cx + 1.5,
        cy=EUROC_CAM.cy - 1.0,
        dist=(d[0] * 1.03, d[1], d[2], d[3]),
    )
    res = _refine(written)
    assert res.accepted, res.report
    cam = res.camera
    assert abs(cam.fx / EUROC_CAM.fx - 1) < 1e-3 and abs(cam.fy / EUROC_CAM.fy - 1) < 1e-3, res.report
    # the principal point, weakly seen, moves towards the truth (written 1.8 px off)
    assert np.hypot(cam.cx - EUROC_CAM.cx, cam.cy - EUROC_CAM.cy) < 0.7 * np.hypot(1.5, 1.0), res.report
    assert abs(cam.dist[0] / d[0] - 1) < 0.015, res.report  # written: 3 % off
    assert res.report["focal_change_rel"][0] < -0.008 and res.report["focal_change_rel"][1] > 0.006
    assert res.report["error_after"] < res.report["error_before"]
    assert 1 < res.report["iterations"] < IntrinsicsConfig().iterations  # converged by itself, in several steps
    # the reported standard deviations: below the prior's, and the truth within four of them
    sd = res.report["std"]["focal_rel"]
    assert 0 < sd[0] < 0.01 and 0 < sd[1] < 0.01
    assert abs(cam.fx / EUROC_CAM.fx - 1) < 4 * sd[0] and abs(cam.fy / EUROC_CAM.fy - 1) < 4 * sd[1], res.report


def test_a_right_calibration_stays_where_it_is():
    res = _refine(EUROC_CAM)
    assert res.accepted
    assert max(abs(v) for v in res.report["focal_change_rel"]) < 1e-3


def test_too_little_data_keeps_the_written_calibration():
    res = _refine(EUROC_CAM, cfg=IntrinsicsConfig(min_frames=100), seconds=2.0)
    assert not res.accepted and res.camera is EUROC_CAM
    assert "fewer than 100" in res.report["reason"]
    fish = replace(EUROC_CAM, model="equidistant")
    res = refine_intrinsics(fish, EUROC_T_BS, ImuNoise(), None, [], np.zeros(0), np.zeros((0, 4, 4)), None)
    assert not res.accepted and "radial-tangential only" in res.report["reason"]


def test_tracks_are_gathered_on_the_adjustment_frames_in_raw_pixels():
    imu, feats, ts, T = _first_pass(EUROC_CAM, seconds=1.0, sigma_px=0.0)
    sel = ts[::3]
    tracks, xn = tracks_from_features(EUROC_CAM, feats, sel, 3)
    assert tracks and all(len(t) >= 3 for t in tracks)
    by_ts = {int(f.ts): f for f in feats}
    n, q = tracks[0][0]
    f = by_ts[int(sel[n])]
    # the raw pixel comes back from the normalised coordinate: it is one of the frame's pixels
    assert np.min(np.linalg.norm(f.uv - q, axis=1)) < 1e-6
    assert xn[0].shape == (len(tracks[0]), 2)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="seconds"):
        IntrinsicsConfig(seconds=0)
    with pytest.raises(ValueError, match="pixel_sigma"):
        IntrinsicsConfig(pixel_sigma=0)


def test_the_timed_camera_tie_has_the_jacobians_of_its_error():
    """The factor of the time offset against central differences of its own error, off its zero."""
    import gtsam

    from runtime.calibration import timed_camera_tie

    rng = np.random.default_rng(3)
    T_bc = gtsam.Pose3(EUROC_T_BS)
    Xp = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.5, 3)), rng.normal(0, 1, 3))
    omega, v_w = np.array([0.4, -0.9, 0.3]), np.array([1.2, -0.2, 0.5])
    xi = np.concatenate([omega, Xp.rotation().matrix().T @ v_w])

    def camera(d, off=None):  # the camera at the image time, moved by ``off``
        move = gtsam.Pose3.Expmap(np.zeros(6) if off is None else off)
        return Xp.compose(gtsam.Pose3.Expmap(d * xi)).compose(T_bc).compose(move)

    f = timed_camera_tie(gtsam.noiseModel.Unit.Create(6), 1, 2, 3, 4, omega, T_bc)
    at = {1: Xp, 2: v_w, 3: camera(0.004, rng.normal(0, 0.02, 6)), 4: np.array([0.007])}

    def values(**moved):
        v = gtsam.Values()
        for k, x in at.items():
            v.insert(k, moved.get(f"k{k}", x))
        return v

    A = f.linearize(values()).jacobian()[0]  # (6, 16): X, V, C, d in key order
    e0 = f.unwhitenedError(values())
    num, h = np.zeros((6, 16)), 1e-6
    for j in range(16):
        out = []
        for sgn in (1.0, -1.0):
            s = np.zeros(16)
            s[j] = sgn * h
            out.append(
                f.unwhitenedError(
                    values(k1=Xp.retract(s[:6]), k2=v_w + s[6:9], k3=at[3].retract(s[9:15]), k4=at[4] + s[15:])
                )
            )
        num[:, j] = (out[0] - out[1]) / (2 * h)
    assert np.linalg.norm(e0) > 1e-3  # evaluated away from the tie's zero, where the Jacobians are not identities
    np.testing.assert_allclose(A, num, atol=1e-6)
    # the camera at the body's pose at the image time (d = 4 ms, no other offset): zero error
    assert np.linalg.norm(f.unwhitenedError(values(k3=camera(0.004), k4=np.array([0.004])))) < 1e-9


@pytest.mark.parametrize("offset_s", [0.006, -0.004])
def test_a_camera_imu_time_offset_is_recovered_with_the_intrinsics(offset_s):
    written = replace(EUROC_CAM, fx=EUROC_CAM.fx * 1.006, fy=EUROC_CAM.fy * 0.995)
    cfg = IntrinsicsConfig(time_offset=True)
    res = _refine(written, cfg=cfg, time_offset_s=offset_s)
    assert res.accepted, res.report
    d, sd = res.report["time_offset_s"], res.report["std"]["time_offset_s"]
    assert abs(d - offset_s) < 1e-3 and 0 < sd < 1e-3, res.report
    assert abs(d - offset_s) < 4 * sd + 2e-4, res.report
    assert abs(res.time_offset_ns - d * 1e9) < 1e3  # the stamps move by the estimate (reported to the microsecond)
    assert abs(res.camera.fx / EUROC_CAM.fx - 1) < 1.5e-3 and abs(res.camera.fy / EUROC_CAM.fy - 1) < 1.5e-3
    # without the offset in the solve the stamps stay as written
    plain = _refine(written, time_offset_s=offset_s)
    assert plain.time_offset_ns == 0 and "time_offset_s" not in plain.report


def test_no_offset_is_found_where_there_is_none():
    res = _refine(EUROC_CAM, cfg=IntrinsicsConfig(time_offset=True))
    assert res.accepted and abs(res.report["time_offset_s"]) < 5e-4, res.report


@pytest.mark.parametrize(
    "camera, reason",
    [
        (replace(EUROC_CAM, model="equidistant"), "camera model 'equidistant' is not refined"),
        (replace(EUROC_CAM, dist=(*EUROC_CAM.dist[:4], 0.01)), "more than four coefficients"),
    ],
)
def test_a_camera_outside_the_adjustment_gets_no_first_pass(camera, reason, monkeypatch):
    import runtime.run
    from runtime.slam import SlamConfig

    def first_pass(*a, **k):
        raise AssertionError("the first pass ran for a camera the adjustment cannot refine")

    monkeypatch.setattr(runtime.run, "_run_frames", first_pass)
    seq = type("Seq", (), {"camera": camera, "frame_ts": np.arange(400) * 50_000_000})()
    out, report = runtime.run._refine_intrinsics(seq, SlamConfig(), 400, False, None)
    assert out is seq and report["refined"] is False and reason in report["reason"], report
    assert EUROC_CAM.model == "radtan" and not_refined(EUROC_CAM) is None
