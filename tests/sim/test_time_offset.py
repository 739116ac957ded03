"""Time offsets between a camera and a ground truth, from the motion the images show (``sim.time_offset``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from runtime.geometry import so3_exp
from sim.euroc import EUROC_T_B_C0
from sim.time_offset import RelativeMotions, position_offset, rotation_offset

T_B_C = EUROC_T_B_C0


def _truth(t: np.ndarray):
    """A wavy flight: rotation rates and accelerations that change within a second."""
    w = np.stack([0.4 * np.sin(1.3 * t) + 0.05, 0.3 * np.cos(0.9 * t + 0.5), 0.5 * np.sin(0.7 * t + 1.0)], -1)
    R = so3_exp(w)
    p = np.stack([1.5 * np.sin(0.8 * t), 1.0 * np.cos(0.6 * t), 0.3 * np.sin(1.7 * t)], -1)
    return R, p


def _motions(t: np.ndarray, step: int, rng, rot_noise_deg: float = 0.02, dir_noise_deg: float = 2.0):
    """What an image pipeline would measure between images ``step`` apart, with noise and a few wrong pairs."""
    R, p = _truth(t)
    R_bc, p_bc = T_B_C[:3, :3], T_B_C[:3, 3]
    idx = np.arange(len(t) - step)
    R_wc = R @ R_bc
    c = p + R @ p_bc
    R_rel = np.swapaxes(R_wc[idx], -1, -2) @ R_wc[idx + step]
    R_rel = R_rel @ so3_exp(np.radians(rot_noise_deg) * rng.standard_normal((idx.size, 3)))
    d = np.einsum("nji,nj->ni", R_wc[idx], c[idx + step] - c[idx])
    d = d / np.linalg.norm(d, axis=1, keepdims=True) + np.radians(dir_noise_deg) * rng.standard_normal(d.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    bad = rng.random(idx.size) < 0.05
    d[bad] = -d[bad]  # the essential matrix's occasional wrong solution
    return RelativeMotions(idx, step, R_rel, d)


@pytest.mark.parametrize(("d_rot", "d_pos"), [(0.0, 0.0), (0.012, 0.0), (-0.004, 0.018), (0.0, -0.025)])
def test_offsets_of_a_delayed_ground_truth_are_recovered(d_rot, d_pos):
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 25.0, 0.05)  # images at 20 Hz

    def rotation(ts):  # the recorded rotation lags the truth by d_rot: it reads R(t - d_rot) at time t
        return _truth(ts - d_rot)[0]

    def position(ts):
        return _truth(ts - d_pos)[1]

    rot = rotation_offset(t, _motions(t, 1, rng), T_B_C[:3, :3], rotation)
    pos = position_offset(t, _motions(t, 2, rng), T_B_C, rotation, position)
    assert rot.offset_s == pytest.approx(d_rot, abs=1.5e-3)
    # the position cost uses the rotation at the image times: with a rotation lag the directions are rotated a
    # little, which the tolerance covers
    assert pos.offset_s == pytest.approx(d_pos, abs=3e-3)
    assert rot.residual_deg <= rot.residual_zero_deg and pos.residual_deg <= pos.residual_zero_deg


def test_too_few_pairs_is_an_error():
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 0.4, 0.05)
    with pytest.raises(ValueError, match="too few"):
        rotation_offset(t, _motions(t, 1, rng), T_B_C[:3, :3], lambda ts: _truth(ts)[0])


MH05 = Path(__file__).resolve().parents[3] / "shared" / "data" / "euroc_MH_05_excerpt"


@pytest.mark.skipif(not (MH05 / "mav0" / "cam0").is_dir(), reason=f"real EuRoC MH_05 excerpt not found at {MH05}")
def test_mh05_ground_truth_rotation_is_on_the_camera_clock_and_its_positions_lag():
    from benchmarks.bench_time_offset import estimate

    r = estimate(MH05)
    assert abs(r["rotation"]["offset_s"]) < 0.003 and r["rotation"]["residual_deg"] < 0.2
    assert 0.010 < r["position"]["offset_s"] < 0.025
    assert r["position"]["residual_deg"] < r["position"]["residual_zero_deg"]
