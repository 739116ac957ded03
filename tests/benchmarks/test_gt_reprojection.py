"""``benchmarks/gt_reprojection.py``: tracks triangulated from the true poses reproject exactly; from poses with a
time offset in their positions, they do not."""

from __future__ import annotations

import numpy as np

from benchmarks.gt_reprojection import reprojection
from runtime.geometry import inv_T, make_T, so3_exp


def _scene(n_frames=12, n_points=40, seed=0):
    """A camera moving sideways and yawing in front of points 3-6 m away: poses (N, 4, 4) and point tracks."""
    rng = np.random.default_rng(seed)
    T = np.stack([make_T(so3_exp(np.array([0.0, 0.02 * k, 0.0])), [0.1 * k, 0.0, 0.0]) for k in range(n_frames)])
    X = np.c_[rng.uniform(-2, 3, n_points), rng.uniform(-1, 1, n_points), rng.uniform(3, 6, n_points)]
    tracks = []
    for x in X:
        pc = np.array([(inv_T(Tk) @ np.r_[x, 1.0])[:3] for Tk in T])
        tracks.append((np.arange(n_frames), pc[:, :2] / pc[:, 2:3]))
    return T, tracks


def test_true_poses_reproject_exactly_and_disturbed_ones_do_not():
    T, tracks = _scene()
    exact = reprojection(tracks, T, 450.0)
    assert exact["tracks"] == 40 and exact["outlier_tracks"] == 0
    assert exact["rms_px"] < 1e-6
    late = T.copy()
    late[:, :3, 3] += np.array([0.1, 0.0, 0.0]) * np.sin(np.arange(len(T)))[:, None] * 0.05  # 5 mm wobble
    off = reprojection(tracks, late, 450.0)
    assert 0.05 < off["median_px"] < 5.0


def test_tracks_beyond_the_bound_are_counted_as_outliers():
    T, tracks = _scene()
    frames, xn = tracks[0]
    bad = xn.copy()
    bad[3] += 20.0 / 450.0  # one view 20 px off
    res = reprojection([(frames, bad)] + tracks[1:], T, 450.0)
    assert res["outlier_tracks"] == 1 and res["tracks"] == 39
