"""Camera physics and the realistic presets (flight, handheld, tabletop), realism / ideal switches."""

from __future__ import annotations

import json

import numpy as np
import pytest

from runtime.io.euroc import read_euroc
from sim.camera import CameraPhysics, auto_exposure, expose, vignetting
from sim.euroc import EUROC_CAM0, simulate_sequence, write_euroc_sequence


def test_auto_exposure_follows_a_sudden_light_change():
    phys = CameraPhysics()
    previews = np.full((40, 6, 8), 0.5, np.float32)
    illum = np.where(np.arange(40) < 20, 1.0, 3.0)  # a lamp switched on at frame 20
    exp_s, gain = auto_exposure(previews, illum, phys)
    signal = 0.5 * illum * phys.electrons_per_s * exp_s * gain / phys.full_well_e
    assert signal[:20] == pytest.approx(phys.ae_target, rel=1e-6)  # settled
    assert signal[20] > 2.5 * phys.ae_target  # the frame after the change is overexposed
    assert signal[30] == pytest.approx(phys.ae_target, rel=0.02)  # ... and the controller recovers
    assert np.all(exp_s <= phys.exposure_max_s) and np.all(gain >= 1.0)
    dark = auto_exposure(np.full((5, 6, 8), 1e-3, np.float32), np.ones(5), phys)
    assert dark[0][-1] == phys.exposure_max_s and dark[1][-1] == phys.gain_max  # time first, then gain


def test_expose_noise_and_motion_blur():
    phys = CameraPhysics(vignetting=0.0, gamma=1.0)
    H, W = 64, 96
    vig = vignetting((H, W), 0.0)
    flat = np.full((H, W), 0.4, np.float32)
    exp_s = 0.005
    img = expose(flat, None, exp_s, 1.0, 1.0, phys, vig, np.random.default_rng(0)).astype(float)
    e = 0.4 * phys.electrons_per_s * exp_s
    assert img.mean() == pytest.approx(255 * e / phys.full_well_e, rel=0.01)
    assert img.std() == pytest.approx(255 * np.sqrt(e + phys.read_noise_e**2) / phys.full_well_e, rel=0.15)
    # a vertical edge moving right at 1000 px/s during 8 ms: an 8 px ramp
    edge = np.zeros((H, W), np.float32)
    edge[:, 48:] = 1.0
    vel = np.zeros((H, W, 2), np.float32)
    vel[..., 0] = 1000.0
    quiet = CameraPhysics(vignetting=0.0, gamma=1.0, read_noise_e=0.0, electrons_per_s=1e6)
    sharp = expose(edge, None, 0.008, 1.0, 1.0, quiet, vig, np.random.default_rng(1))[32].astype(float)
    blur = expose(edge, vel, 0.008, 1.0, 1.0, quiet, vig, np.random.default_rng(1))[32].astype(float)

    def ramp(r):
        lo, hi = np.median(r[:20]), np.median(r[-20:])
        return int(np.sum((r > lo + 0.1 * (hi - lo)) & (r < hi - 0.1 * (hi - lo))))

    assert ramp(sharp) <= 1 and 6 <= ramp(blur) <= 9


@pytest.fixture(scope="module")
def flight_seq(tmp_path_factory):
    out = tmp_path_factory.mktemp("flight")
    return write_euroc_sequence(out, "flight", duration=5.0, seed=0, progress=False, scale=0.25)


def test_flight_preset_realistic_by_default(flight_seq):
    info = json.loads((flight_seq / "sim_info.json").read_text())
    assert info["realism"] is True and info["preset"] == "flight" and 1.0 <= info["rest_s"] <= 3.0
    seq = read_euroc(flight_seq)
    # the written calibration differs from the rendering camera, by a realistic amount
    fx_true = EUROC_CAM0.fx / 4
    assert seq.camera.fx != fx_true and abs(seq.camera.fx / fx_true - 1) < 0.03
    assert info["written_camera"][0] == seq.camera.fx and info["render_camera"][0] == fx_true
    # resting on the floor with the rotors on: the IMU vibrates (EuRoC-like std), the ground truth is still
    rest = seq.imu_ts < seq.imu_ts[0] + int((info["rest_s"] - 0.05) * 1e9)
    np.testing.assert_allclose(seq.gt.v_w[rest], 0.0, atol=1e-9)
    assert np.all(seq.gyro[rest].std(0) > 0.012) and np.all(seq.gyro[rest].std(0) < 0.065)
    assert np.all(seq.accel[rest].std(0) > 0.14) and np.all(seq.accel[rest].std(0) < 0.9)
    assert seq.gt.p_w_b[:, 2].max() - seq.gt.p_w_b[0, 2] > 0.3  # it took off
    frames = np.loadtxt(flight_seq / "sim_frames.csv", delimiter=",")
    assert frames.shape == (100, 4) and np.all(frames[:, 1] <= 0.01)


@pytest.mark.parametrize("preset", ["handheld", "tabletop"])
def test_handheld_presets_move_from_the_start(tmp_path, preset):
    d = simulate_sequence(preset, 3.0, 1, imu_noise=True, realism=True)
    assert np.linalg.norm(d.v_w[0]) > 0.02  # no still period
    assert np.all(np.abs(d.bg[0]) <= 0.1)
    if preset == "tabletop":
        from sim.render import Renderer

        r = Renderer(d.scene, EUROC_CAM0.pinhole())
        depth = r.trace(d.trajectory.camera_T(np.array([1.0]))[0])[0]
        assert 0.2 < np.median(depth[200:280, 330:420]) < 1.5


def test_ideal_and_realism_switches_on_textured():
    exact = simulate_sequence("textured", 3.0, 4, imu_noise=False)
    real = simulate_sequence("textured", 3.0, 4, imu_noise=True, realism=True)
    np.testing.assert_allclose(real.p_w_b, exact.p_w_b, atol=1e-5)  # same path (continuous vs trapezoidal)
    rest = slice(0, 400)
    assert real.gyro[rest].std(0).min() > 0.01  # vibration
    assert np.abs(real.bg[0]).max() > 0.005


def test_ideal_flag_writes_exact_data(tmp_path):
    a = write_euroc_sequence(tmp_path / "a", "flight", duration=3.5, seed=2, progress=False, scale=0.125, ideal=True)
    seq = read_euroc(a)
    exact = simulate_sequence("flight", 3.5, 2, imu_noise=False)
    np.testing.assert_array_equal(seq.gyro, exact.gyro)
    np.testing.assert_array_equal(seq.gt.bg, 0.0)
    assert json.loads((a / "sim_info.json").read_text())["ideal"] is True


def test_nyu_realism_option(tmp_path):
    import h5py

    from sim.nyu import write_nyu_dataset

    root = write_nyu_dataset(
        tmp_path / "nyu", n_train=1, n_val=1, seed=1, progress=False, frames_per_scene=1, realism=True
    )
    assert json.loads((root / "sim_info.json").read_text())["realism"] is True
    files = sorted(root.glob("*/*/*.h5"))
    assert len(files) == 2
    with h5py.File(files[0]) as f:
        rgb, depth = f["rgb"][:], f["depth"][:]
    assert rgb.shape == (3, 480, 640) and rgb.dtype == np.uint8 and depth.shape == (480, 640)
    assert 0.1 < depth.min() and depth.max() < 15.0 and 10 < rgb.mean() < 245


def test_textured_with_realism_writes_physics(tmp_path):
    root = write_euroc_sequence(
        tmp_path / "t", "textured", duration=3.0, seed=5, progress=False, scale=0.125, realism=True
    )
    info = json.loads((root / "sim_info.json").read_text())
    assert info["realism"] is True and info["time_offset_s"] == pytest.approx(0.003)
    seq = read_euroc(root)
    assert seq.camera.fx != EUROC_CAM0.fx / 8  # the written calibration is off
    assert np.abs(seq.gt.bg[0]).max() > 0.005 and seq.gyro[:400].std(0).min() > 0.01  # real IMU
    img = seq.image(30)
    assert img.dtype == np.uint8 and 5 < img.mean() < 250
