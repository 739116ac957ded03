"""``benchmarks/bench_imu_completion.py``: the NEES of the runtime's ImuFactor is about 9 for an IMU whose noise
matches its stated densities, and falls as the square of the raise."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_imu_completion import preintegration_errors
from sim.complete import complete_imu
from sim.imu import ImuNoise
from tests.sim.test_complete_imu import _write_source


def test_nees_is_consistent_for_white_noise_at_the_stated_densities(tmp_path):
    _write_source(tmp_path / "src")
    noise = ImuNoise(2e-3, 1e-9, 2e-2, 1e-9)  # white noise well above the fit's error, no bias walk
    rows = []
    for seed in range(4):
        out = tmp_path / f"out{seed}"
        complete_imu(tmp_path / "src", out, noise=noise, errors=None, use_gt_bias=False, seed=seed)
        rows.append(preintegration_errors(out, 0.25, raises=(1.0, 5.0)))
    x1 = np.mean([r["nees_mean"]["x1"] for r in rows])
    x5 = np.mean([r["nees_mean"]["x5"] for r in rows])
    assert sum(r["windows"] for r in rows) >= 40
    assert 6.0 < x1 < 12.5  # 9 degrees of freedom
    assert abs(x5 * 25 / x1 - 1) < 0.05  # the whitened error scales as 1 / raise
