"""``dit-sim imu``: completing a posed image sequence with an IMU (known answer, still period, real excerpt)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from runtime.geometry import GRAVITY_W, R_to_quat_wxyz, so3_exp
from runtime.io.euroc import GT_HEADER, read_euroc
from sim.complete import complete_imu, remove_steps
from sim.euroc import EUROC_T_B_C0, _cam_yaml, _write_csv, scaled_camera
from sim.imu import ImuNoise

MH05 = Path(__file__).resolve().parents[3] / "shared" / "data" / "euroc_MH_05_excerpt"
W, R = 0.6, 1.2  # yaw rate [rad/s], circle radius [m]
ZERO = ImuNoise(0.0, 0.0, 0.0, 0.0)


def _truth(t):
    """Body on a circle, yawing with it: R_w_b = Rz(w t), p = r (cos, sin, 0) + (0, 0, 1)."""
    Rw = np.stack([so3_exp(np.array([0.0, 0.0, W * ti])) for ti in t])
    p = np.stack([R * np.cos(W * t), R * np.sin(W * t), np.ones_like(t)], -1)
    v = np.stack([-R * W * np.sin(W * t), R * W * np.cos(W * t), np.zeros_like(t)], -1)
    return Rw, p, v


def _write_source(root: Path, step: np.ndarray | None = None, truth=_truth) -> int:
    """A 6 s circle at 200 Hz ground truth (biases 0.01 rad/s, 0.05 m/s^2) and 20 Hz tiny images (4 s); ``step``
    [m] is added to every ground-truth position from t = 3 s on (a recording glitch); ``truth``: ``t -> (R_w_b,
    p, v)`` in place of the circle. Returns t0 [ns]."""
    mav0 = root / "mav0"
    t0 = 1_600_000_000_000_000_000
    ts = t0 + 5_000_000 * np.arange(1200, dtype=np.int64)
    t = (ts - t0) * 1e-9
    Rw, p, v = truth(t)
    if step is not None:
        p = p + step * (t >= 3.0)[:, None]
    bias = np.tile([0.01, -0.01, 0.01, 0.05, -0.05, 0.05], (len(t), 1))
    gt = np.concatenate([p, R_to_quat_wxyz(Rw), v, bias], 1)
    _write_csv(mav0 / "state_groundtruth_estimate0" / "data.csv", GT_HEADER, ts, gt)
    (mav0 / "cam0" / "data").mkdir(parents=True)
    frames = ts[200:1000:10]
    for k, f in enumerate(frames):
        cv2.imwrite(str(mav0 / "cam0" / "data" / f"{f}.png"), np.full((10, 16), k, np.uint8))
    (mav0 / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{f},{f}.png\n" for f in frames))
    (mav0 / "cam0" / "sensor.yaml").write_text(_cam_yaml(scaled_camera(16 / 752), EUROC_T_B_C0, 20))
    return t0


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    root = tmp_path_factory.mktemp("posed")
    return root, _write_source(root)


def test_noiseless_completion_matches_the_truth(source, tmp_path):
    root, t0 = source
    info = complete_imu(root, tmp_path / "out", noise=ZERO, errors=None, sigma_p=1e-6, sigma_q=1e-7)
    assert info["fit"]["pos_err_median_mm"] < 0.05 and info["fit"]["rot_err_median_deg"] < 1e-3
    seq = read_euroc(tmp_path / "out")
    assert len(seq) == 80 and seq.imu.gyro_noise_density == 0.0
    img_link = tmp_path / "out" / "mav0" / "cam0" / "data" / f"{seq.frame_ts[5]}.png"
    assert img_link.is_symlink() and img_link.resolve().parent == (root / "mav0" / "cam0" / "data").resolve()
    assert seq.image(5)[0, 0] == 5
    t = (seq.imu_ts - t0) * 1e-9
    Rw, p, v = _truth(t)
    np.testing.assert_allclose(seq.gt.p_w_b, p, atol=1e-5)
    np.testing.assert_allclose(seq.gt.v_w, v, atol=1e-4)
    # instantaneous samples: gyro = (0, 0, w) + bias; accel = centripetal -w^2 r along body -x, plus gravity
    np.testing.assert_allclose(seq.gyro, np.tile([0.01, -0.01, W + 0.01], (len(t), 1)), atol=1e-4)
    expect = np.tile([-W * W * R + 0.05, -0.05, -GRAVITY_W[2] + 0.05], (len(t), 1))
    np.testing.assert_allclose(seq.accel, expect, atol=2e-3)
    np.testing.assert_array_equal(seq.gt.bg, np.tile([0.01, -0.01, 0.01], (len(t), 1)))
    assert seq.imu_ts[0] == seq.frame_ts[0] and seq.imu_ts[-1] <= seq.frame_ts[-1]


def test_ideal_completion_is_exact_with_zero_biases_and_keeps_the_noise_densities(source, tmp_path):
    """``ideal``: the exact samples of the motion (the ground truth's biases and every error left out), while
    ``imu0/sensor.yaml`` still carries the densities an estimator weighs the samples with."""
    root, t0 = source
    noise = ImuNoise(1.7e-4, 1.9e-5, 2.0e-3, 3.0e-3)
    info = complete_imu(root, tmp_path / "out", noise=noise, ideal=True, sigma_p=1e-6, sigma_q=1e-7)
    assert info["ideal"] and not info["vibration"] and not info["use_gt_bias"]
    seq = read_euroc(tmp_path / "out")
    assert seq.imu.gyro_noise_density == noise.gyro_noise_density
    assert seq.imu.accel_random_walk == noise.accel_random_walk
    t = (seq.imu_ts - t0) * 1e-9
    np.testing.assert_allclose(seq.gyro, np.tile([0.0, 0.0, W], (len(t), 1)), atol=1e-4)
    expect = np.tile([-W * W * R, 0.0, -GRAVITY_W[2]], (len(t), 1))
    np.testing.assert_allclose(seq.accel, expect, atol=2e-3)
    assert not seq.gt.bg.any() and not seq.gt.ba.any()


def test_ground_truth_step_is_spread_not_felt_as_an_impulse(tmp_path):
    """A 2 cm one-sample jump of the recorded ground truth: kept, the fit turns it into an accelerometer impulse of
    tens of g; removed, the IMU stays within a fraction of 1 m/s^2 of the true circle's, and the written ground
    truth equals the source outside the 2 s blend window."""
    step = np.array([0.004, 0.017, 0.007])
    root = tmp_path / "src"
    t0 = _write_source(root, step)
    kw = dict(noise=ZERO, errors=None, sigma_p=1e-6, sigma_q=1e-7)
    complete_imu(root, tmp_path / "kept", step_mps=None, **kw)
    info = complete_imu(root, tmp_path / "fixed", **kw)
    assert len(info["ground_truth_steps"]) == 1
    found = info["ground_truth_steps"][0]
    np.testing.assert_allclose(found["step_m"], step, atol=2e-4)
    assert abs(found["t_ns"] - (t0 + 2_997_500_000)) <= 5_000_000
    kept, fixed = read_euroc(tmp_path / "kept"), read_euroc(tmp_path / "fixed")
    t = (fixed.imu_ts - t0) * 1e-9
    true_accel = np.tile([-W * W * R + 0.05, -0.05, -GRAVITY_W[2] + 0.05], (len(t), 1))
    assert np.abs(kept.accel - true_accel).max() > 50.0
    assert np.abs(fixed.accel - true_accel).max() < 0.3
    _, p, _ = _truth(t)
    p_src = p + step * (t >= 3.0)[:, None]
    away = np.abs(t - 3.0) > 1.0
    np.testing.assert_allclose(fixed.gt.p_w_b[away], p_src[away], atol=1e-5)
    between = np.linalg.norm(fixed.gt.p_w_b - p, axis=1)
    assert np.all(between <= np.linalg.norm(step) + 1e-5)  # the blend lies between the two levels


def test_remove_steps_leaves_a_smooth_trajectory_alone():
    ts = 5_000_000 * np.arange(2000, dtype=np.int64)
    _, p, _ = _truth(ts * 1e-9)
    rng = np.random.default_rng(0)
    noisy = p + rng.normal(0.0, 3e-4, p.shape)  # EuRoC-like ground-truth noise
    out, steps = remove_steps(ts, noisy)
    assert steps == [] and np.array_equal(out, noisy)


def test_still_period_repeats_first_image_and_ramps(source, tmp_path):
    root, _ = source
    info = complete_imu(
        root, tmp_path / "still", noise=ZERO, errors=None, still=1.5, ramp=1.0, sigma_p=1e-6, sigma_q=1e-7
    )
    seq = read_euroc(tmp_path / "still")
    assert info["repeated_first_frames"] == 30 and len(seq) == 110
    assert all(seq.image(k)[0, 0] == 0 for k in range(31))  # 30 repeats + the original first frame
    rest = seq.imu_ts < seq.frame_ts[30]
    assert rest.sum() == 300
    np.testing.assert_allclose(seq.gt.v_w[rest], 0.0, atol=1e-9)
    np.testing.assert_allclose(seq.gyro[rest], np.tile([0.01, -0.01, 0.01], (rest.sum(), 1)), atol=1e-9)
    a_w = np.einsum("nij,nj->ni", seq.gt.T_w_b[rest][:, :3, :3], seq.accel[rest] - seq.gt.ba[rest])
    np.testing.assert_allclose(a_w, np.tile([0.0, 0.0, 9.81], (rest.sum(), 1)), atol=1e-6)
    speed = np.linalg.norm(seq.gt.v_w, axis=1)
    assert np.all(np.diff(speed[rest.sum() : rest.sum() + 200]) >= -1e-6)  # the ramp speeds up smoothly
    assert speed[-1] == pytest.approx(R * W, rel=1e-3)
    # after the ramp, images keep their poses: frame k shows the original frame k's pose
    k = 100
    np.testing.assert_allclose(
        seq.gt_pose_at(seq.frame_ts[k])[:3, 3],
        _truth(np.array([(int(seq.image(k)[0, 0]) * 50_000_000 + 1_000_000_000) * 1e-9]))[1][0],
        atol=1e-4,
    )


@pytest.mark.skipif(not (MH05 / "mav0").is_dir(), reason=f"real EuRoC MH_05 excerpt not found at {MH05}")
def test_real_mh05_excerpt_fit(tmp_path):
    info = complete_imu(MH05, tmp_path / "mh05")
    assert info["fit"]["pos_err_median_mm"] < 1.0 and info["fit"]["rot_err_median_deg"] < 0.05
    seq = read_euroc(tmp_path / "mh05")
    assert len(seq) == 585 and len(seq.imu_ts) > 5000
    # rotor vibration: the gyro's sample-to-sample jitter is far above the ADIS white noise
    assert np.std(np.diff(seq.gyro, axis=0)) > 0.01
    # the ground truth's 1.7-1.8 cm jumps (40.2 s and 46.6 s of MH_05) are spread, not felt as 10-20 g impulses
    big = [s for s in info["ground_truth_steps"] if np.linalg.norm(s["step_m"]) > 0.01]
    assert len(big) == 2
    assert np.linalg.norm(seq.accel, axis=1).max() < 3 * 9.81


def test_cli_imu(source, tmp_path, capsys):
    from sim.cli import main

    root, _ = source
    main(["imu", f"source={root}", f"out={tmp_path / 'cli'}", "still=1", "vibration=false"])
    out = capsys.readouterr().out
    assert "20 repeats of the first image" in out and "vibration=False" in out
    assert (tmp_path / "cli" / "mav0" / "imu0" / "data.csv").is_file()
