"""``benchmarks/imu_scale.py``: an exact IMU gives its true trajectory the scale 1 and a scaled copy the inverse
scale; a noisy one strays from 1 by about the standard deviation the profile reports."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.imu_scale import main, scale_profile
from runtime.geometry import so3_exp
from runtime.io.euroc import read_euroc
from sim.complete import complete_imu
from sim.imu import ImuNoise
from tests.sim.test_complete_imu import _write_source


def _wander(t):
    """A path whose acceleration changes direction and size in the body (a circle flown yawing with it would
    look like an accelerometer bias), with a slow wobble of the attitude."""
    w = np.array([0.9, 1.3, 0.7])
    p = np.stack([1.5 * np.sin(w[0] * t), 1.0 * np.sin(w[1] * t + 0.5), 1.0 + 0.4 * np.sin(w[2] * t)], -1)
    v = np.stack(
        [1.5 * w[0] * np.cos(w[0] * t), 1.0 * w[1] * np.cos(w[1] * t + 0.5), 0.4 * w[2] * np.cos(w[2] * t)], -1
    )
    Rw = np.stack([so3_exp(np.array([0.1 * np.sin(0.8 * ti), 0.1 * np.cos(0.6 * ti), 0.3 * ti])) for ti in t])
    return Rw, p, v


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    root = tmp_path_factory.mktemp("posed")
    _write_source(root, truth=_wander)
    return root


def _poses(seq, step: int = 5):
    ts = seq.frame_ts[::step]
    return ts, seq.gt_pose_at(ts)


def test_an_exact_imu_gives_the_true_scale_and_the_inverse_of_a_scaled_copy(source, tmp_path):
    complete_imu(source, tmp_path / "exact", ideal=True)
    seq = read_euroc(tmp_path / "exact")
    ts, T = _poses(seq)
    s, sd = scale_profile(seq, ts, T)
    assert abs(s - 1.0) < 2e-3 and 0 < sd < 0.05
    T2 = T.copy()
    T2[:, :3, 3] *= 1.05  # the same shape, 5 % long: the IMU asks for it shrunk back
    s2, _ = scale_profile(seq, ts, T2)
    assert abs(s2 * 1.05 - 1.0) < 2e-3


def test_a_noisy_imu_strays_by_about_its_standard_deviation(source, tmp_path):
    # white accelerometer noise well above the fit's error, EuRoC's bias random walks (with none, the bias cannot
    # take up the sample hold's tiny misfit and the scale does: 1.06 with near-exact samples and walks of 1e-12)
    noise = ImuNoise(1.7e-4, 1.9e-5, 5e-2, 3e-3)
    dev = []
    for seed in range(3):
        complete_imu(source, tmp_path / f"n{seed}", noise=noise, errors=None, use_gt_bias=False, seed=seed)
        seq = read_euroc(tmp_path / f"n{seed}")
        s, sd = scale_profile(seq, *_poses(seq))
        dev.append((s - 1.0) / sd)
    dev = np.array(dev)
    assert np.all(np.abs(dev) < 4.0)  # consistent: within 4 standard deviations
    assert np.any(np.abs(dev) > 0.05)  # and noisy: not the exact answer


def test_the_command_writes_whole_and_piecewise_profiles(source, tmp_path, capsys):
    complete_imu(source, tmp_path / "exact", ideal=True)
    doc = main(
        ["--sequences", str(tmp_path / "exact"), "--segment", "2", "--raise", "1", "--out", str(tmp_path / "r.json")]
    )
    row = doc["rows"]["exact"]["raises"]["x1"]
    assert abs(row["whole"][0] - 1.0) < 2e-3 and len(row["segments"]) == 2
    assert (tmp_path / "r.json").is_file() and "| exact | x1 |" in capsys.readouterr().out


def test_a_folder_without_imu_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="no mav0/imu0"):
        main(["--sequences", str(tmp_path)])


def test_a_run_at_a_wrong_scale_in_its_own_frame_is_asked_back_to_the_truth(source, tmp_path):
    # a "run" whose keyframes are the truth 4 % short, yawed and moved: its Sim(3) scale is 1.04, and the exact
    # IMU asks every variant of it (as it is, true rotations, true positions at its scale) to grow by 1.04
    import json

    from runtime.io.tum import write_tum

    complete_imu(source, tmp_path / "exact", ideal=True)
    seq = read_euroc(tmp_path / "exact")
    ts, T = _poses(seq)
    yaw = so3_exp(np.array([0.0, 0.0, 0.7]))
    E = T.copy()
    E[:, :3, :3] = yaw @ T[:, :3, :3]
    E[:, :3, 3] = (T[:, :3, 3] @ yaw.T) / 1.04 + np.array([0.3, -1.0, 0.2])
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "keyframes.txt", ts, E)
    (run / "metrics.json").write_text(json.dumps({"sequence": str(tmp_path / "exact")}))
    doc = main(["--runs", str(run), "--raise", "1"])
    row = doc["rows"][str(run)]
    assert abs(row["sim3_scale"] - 1.04) < 1e-6 and row["keyframes"] == ts.size
    for name in ("ours", "true_R", "true_p"):
        assert abs(row["raises"]["x1"][name][0] - 1.04) < 3e-3, name
    assert abs(row["raises"]["x1"]["truth"][0] - 1.0) < 2e-3


def test_a_folder_that_is_not_a_run_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="not a dit-slam output folder"):
        main(["--runs", str(tmp_path)])
