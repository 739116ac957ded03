"""runtime.diagnostics.coast: the IMU-only coast oracles and the split of a run's ATE around the coast."""

from __future__ import annotations

import json

import numpy as np
import pytest

from runtime.diagnostics import coast
from runtime.geometry import make_T, so3_exp
from runtime.io.euroc import read_euroc
from runtime.io.tum import write_tum
from sim.euroc import write_euroc_sequence
from sim.trajectory import whitewall_min_duration

DURATION = whitewall_min_duration()  # 24 s, the shortest whitewall sequence
SCALE = 0.1  # 75x48 images: the oracles and the run split read only the IMU and the ground truth


def _folder(root, seed: int = 0):
    return root / f"euroc_whitewall_{DURATION:g}s_s{seed}_x{SCALE:g}"


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """The same whitewall trajectory with exact IMU and with noisy IMU (folder names as bench_coast reads them)."""
    base = tmp_path_factory.mktemp("coast")
    exact = write_euroc_sequence(
        _folder(base / "exact"), "whitewall", DURATION, 0, imu_noise=False, progress=False, scale=SCALE, realism=False
    )
    noisy = write_euroc_sequence(
        _folder(base / "noisy"), "whitewall", DURATION, 0, imu_noise=True, progress=False, scale=SCALE, realism=False
    )
    return exact, noisy


def _coast(root):
    seq = read_euroc(root)
    t0, t1, source = coast.coast_interval(root, None, 2.0)
    wall_x = float(json.loads((root / "sim_info.json").read_text())["room_size_m"][0])
    return seq, t0, t1, source, wall_x


def test_coast_interval_without_a_run_is_the_widened_hold(sequences):
    root = sequences[1]
    seq, t0, t1, source, _ = _coast(root)
    w0, w1 = json.loads((root / "sim_info.json").read_text())["whitewall_window_ns"]
    assert (t0, t1) == (w0 - 2_000_000_000, w1 + 2_000_000_000)
    assert source == "white-wall hold +- 2 s"


def test_oracles_reproduce_the_truth_with_an_exact_imu(sequences):
    seq, t0, t1, _, wall_x = _coast(sequences[0])
    for mode in coast.ORACLES:
        e = coast.oracle_coast(seq, t0, t1, mode, 0.4, wall_x)
        assert e.shape == (int(round((t1 - t0) * 1e-9 / 0.4)) + 1, 3)
        assert np.abs(e).max() < 1e-3, mode  # exact IMU, exact end states: nothing to explain away


def test_end_velocity_and_wall_distance_each_shrink_the_coast_error(sequences):
    seq, t0, t1, _, wall_x = _coast(sequences[1])
    e = {mode: coast.oracle_coast(seq, t0, t1, mode, 0.4, wall_x) for mode in coast.ORACLES}
    rms = {m: np.sqrt(np.mean(np.sum(v**2, 1))) for m, v in e.items()}
    axis = {m: np.sqrt(np.mean(v**2, 0)) for m, v in e.items()}
    assert rms["end pose"] > 2.0 * rms["end pose+vel"]  # the end velocity pins the coast's velocity error
    # the distance to the wall x = wall_x (1 cm sigma) observes the normal (x) component, not the other two
    assert axis["+ wall distance"][0] < min(0.002, axis["end pose+vel"][0])
    assert np.allclose(axis["+ wall distance"][1:], axis["end pose+vel"][1:], rtol=0.25)


def test_wall_factor_jacobian_matches_numerical_differentiation():
    import gtsam
    from gtsam.symbol_shorthand import X

    from runtime.backend.factors import analytic_jacobians, numerical_jacobians
    from runtime.geometry import to_pose3

    T = make_T(so3_exp(np.array([0.1, -0.3, 1.2])), np.array([2.0, 1.0, 1.5]))
    t_b_c = np.array([-0.02, -0.06, 0.01])
    f = coast.wall_distance_factor(X(0), 1.2, 3.5, t_b_c)
    values = gtsam.Values()
    values.insert(X(0), to_pose3(T))
    p_c = T[:3, :3] @ t_b_c + T[:3, 3]
    assert np.allclose(f.unwhitenedError(values), [3.5 - p_c[0] - 1.2])
    (A,), (N,) = analytic_jacobians(f, values), numerical_jacobians(f, values)
    assert A.shape == (1, 6)
    assert np.allclose(A, N, atol=1e-6)


def test_run_segments_finds_a_known_jump_between_the_two_sides(sequences, tmp_path):
    """A run exact before the coast and moved by a known rigid motion G from the coast on: each side aligned
    alone is exact, and the two alignments disagree at the relocalisation by G itself."""
    seq, t0, t1, _, _ = _coast(sequences[1])
    ts = seq.frame_ts
    T = seq.gt.pose_at(ts)
    G = make_T(so3_exp(np.radians([0.0, 0.0, 0.4])), np.array([0.01, -0.02, 0.005]))
    moved = ts >= t0
    T[moved] = G @ T[moved]
    run = tmp_path / "whitewall_s0_sparse"
    write_tum(run / "trajectory.txt", ts, T)
    s = coast.run_segments(seq, run, t0, t1)
    assert s["pre_only"] < 1e-6 and s["post_only"] < 1e-6
    assert s["jump_deg"] == pytest.approx(0.4, abs=1e-4)
    q = T[(ts >= t0) & (ts <= t1)][-1, :3, 3]  # the last coasted pose, as estimated (moved by G)
    assert s["jump_m"] == pytest.approx(np.linalg.norm(q - np.linalg.solve(G, np.append(q, 1.0))[:3]), rel=1e-4)
    assert s["ate"] > 0.005 and s["coast"] > 0.0  # the whole alignment cannot absorb the jump


def test_the_module_does_not_import_torch():
    import subprocess
    import sys

    code = "import sys, runtime.diagnostics.coast; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
