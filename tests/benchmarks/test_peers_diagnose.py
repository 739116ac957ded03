"""benchmarks/peers/diagnose.py: the alignment, the yaw/tilt split and the relative drift on known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks.peers.diagnose import aligned_error, relative_drift, trajectory_report, umeyama, yaw_tilt_deg


def _path(n=240, seed=0):
    rng = np.random.default_rng(seed)
    ts = 10**18 + np.arange(n, dtype=np.int64) * 50_000_000  # 20 Hz, 12 s
    t = np.linspace(0.0, 4.0 * np.pi, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.column_stack([2 * np.cos(t), np.sin(2 * t), 0.2 * t]) + 1e-4 * rng.standard_normal((n, 3))
    T[:, :3, :3] = Rotation.from_euler("zyx", np.column_stack([0.5 * t, 0.1 * np.sin(t), 0.05 * t])).as_matrix()
    return ts, T


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(1)
    P = rng.standard_normal((50, 3))
    R = Rotation.from_rotvec([0.3, -1.0, 0.4]).as_matrix()
    Q = 2.5 * P @ R.T + np.array([1.0, -2.0, 0.5])
    s, R_, t = umeyama(P, Q)
    assert s == pytest.approx(2.5) and np.allclose(R_, R) and np.allclose(t, [1.0, -2.0, 0.5])
    e, s2 = aligned_error(P, Q)
    assert e.max() < 1e-9 and s2 == pytest.approx(2.5)
    e_se3, s3 = aligned_error(P, Q, with_scale=False)  # without the scale the error is large
    assert s3 == 1.0 and e_se3.mean() > 0.5
    with pytest.raises(ValueError, match="N >= 3"):
        umeyama(P[:2], Q[:2])


def test_yaw_tilt_split():
    yaw, tilt = yaw_tilt_deg(Rotation.from_euler("z", 7.0, degrees=True).as_matrix())
    assert yaw == pytest.approx(7.0) and tilt == pytest.approx(0.0, abs=1e-9)
    yaw, tilt = yaw_tilt_deg(Rotation.from_euler("x", -3.0, degrees=True).as_matrix())
    assert yaw == pytest.approx(0.0, abs=1e-9) and tilt == pytest.approx(3.0)
    R = Rotation.from_euler("z", 5.0, degrees=True) * Rotation.from_euler("y", 2.0, degrees=True)
    yaw, tilt = yaw_tilt_deg(R.as_matrix())
    assert yaw == pytest.approx(5.0) and tilt == pytest.approx(2.0)


def test_relative_drift_sees_yaw_drift_and_scale():
    ts, T = _path()
    # an estimate in another frame and scale: no drift once the scale is given
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.0, 0.4, 1.0]).as_matrix()
    est = np.einsum("ij,njk->nik", G, T)
    est[:, :3, 3] *= 0.5
    d = relative_drift(ts, est, T, 1.0, 2.0)
    assert len(d) == 240 - 20 and d[:, 1].max() < 1e-9 and d[:, 3].max() < 1e-6
    # a yaw rate error of 0.5 deg/s about the world z axis: 5 deg over 10 s, no tilt
    t = (ts - ts[0]) * 1e-9
    yaw_err = Rotation.from_euler("z", (0.5 * t)[:, None], degrees=True).as_matrix()
    drifted = T.copy()
    drifted[:, :3, :3] = yaw_err @ T[:, :3, :3]
    d = relative_drift(ts, drifted, T, 10.0, 1.0)
    assert np.allclose(d[:, 3], 5.0, atol=1e-6) and d[:, 4].max() < 1e-6


def test_trajectory_report_finds_scale_drift():
    ts, T = _path()
    t = (ts - ts[0]) * 1e-9
    est = T.copy()
    est[:, :3, 3] *= np.where(t < 6.0, 1.0, 1.05)[:, None]  # the second half 5 % larger
    r = trajectory_report(ts, est, T, int(ts[0]), (int(ts[0]), int(ts[-1])))
    scales = [w["sim3_scale"] for w in r["windows"]]
    assert len(scales) == 2 and scales[0] == pytest.approx(1.0, abs=1e-3) and scales[1] == pytest.approx(1 / 1.05)
    assert r["window_scale_spread"] == pytest.approx(0.05, abs=0.005) and r["window_ate_median_m"] < 1e-3
    assert r["ate_sim3_m"] > 0.01 and math.isclose(r["ate_sim3_m"], r["ate_sim3_common_m"])
