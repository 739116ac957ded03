"""benchmarks/depth_by_distance.py: errors by distance to the nearest sample, and the departure at the samples."""

import json

import numpy as np

from benchmarks.depth_by_distance import (
    main,
    sample_departure,
    scaled_correction,
    squared_errors_binned,
    squared_errors_by_distance,
)
from runtime.network import default_model_dir
from tests.train.test_evaluate_protocol import _folder


def test_errors_fall_into_the_bins_of_their_distance():
    gt = np.full((21, 21), 2.0)
    sparse = np.zeros_like(gt)
    sparse[10, 10] = 2.0
    yy, xx = np.mgrid[:21, :21]
    dist = np.hypot(yy - 10, xx - 10)
    pred = gt + np.where(dist < 2, 1.0, 0.0) + np.where(dist >= 5, 3.0, 0.0)
    gt[0, 0] = 0.0  # invalid: counted nowhere
    bins, bins_gt = squared_errors_by_distance([pred, gt], gt, sparse, edges=(0.0, 2.0, 5.0, np.inf))
    assert [b.size for b in bins_gt] == [b.size for b in bins] and all(np.all(b == 0.0) for b in bins_gt)
    assert [b.size for b in bins] == [
        int((dist < 2).sum()),
        int(((dist >= 2) & (dist < 5)).sum()),
        int((dist >= 5).sum()) - 1,
    ]
    assert np.all(bins[0] == 1.0) and np.all(bins[1] == 0.0) and np.all(bins[2] == 9.0)
    assert sum(b.size for b in bins) == int((gt > 0).sum())


def test_errors_fall_into_the_bins_of_their_key():
    gt = np.array([[1.0, 2.0, 0.0], [4.0, 5.0, 6.0]])
    key = np.array([[0.01, 0.2, 0.01], [0.07, 0.5, 0.3]])
    pred = gt + np.array([[1.0, 2.0, 9.0], [3.0, 4.0, 5.0]])
    (bins,) = squared_errors_binned([pred], gt, key, (0.0, 0.05, 0.25, np.inf))
    assert [b.tolist() for b in bins] == [[1.0], [4.0, 9.0], [16.0, 25.0]]  # gt 0 counted nowhere


def test_departure_is_zero_for_a_depth_that_keeps_its_samples():
    sparse = np.zeros((4, 4))
    sparse[1, 2], sparse[3, 0] = 1.5, 4.0
    assert np.all(sample_departure(np.where(sparse > 0, sparse, 9.0), sparse) == 0.0)
    np.testing.assert_allclose(sample_departure(np.full((4, 4), 3.0), sparse), np.abs(np.log([2.0, 0.75])))


def test_scaled_correction_runs_from_the_fill_to_the_network():
    rng = np.random.default_rng(0)
    depth, fill = rng.uniform(0.2, 8.0, (5, 7)), rng.uniform(0.2, 8.0, (5, 7))
    np.testing.assert_allclose(scaled_correction(depth, fill, 0.0), fill)
    np.testing.assert_allclose(scaled_correction(depth, fill, 1.0), depth)
    half = scaled_correction(depth, fill, 0.5)
    np.testing.assert_allclose(half, np.sqrt(depth * fill))  # halfway in log depth
    assert np.all((half - fill) * (depth - fill) >= 0)  # on the network's side of the fill


def test_main_on_a_frame_folder(tmp_path, capsys):
    folder = _folder(tmp_path / "frames", n=2)
    out = tmp_path / "d.json"
    doc = main(["--model", str(default_model_dir()), "--real", str(folder), "--out", str(out)])
    r = doc["sets"]["real frames"]
    assert r["frames"] == 2 and len(r["by_distance"]) == 5
    # both binnings partition the same valid pixels (the uncertainty is positive)
    assert sum(b["pixels"] for b in r["by_relative_uncertainty"]) == sum(b["pixels"] for b in r["by_distance"]) > 0
    # a slanted plane: the interpolation is exact next to its samples
    assert r["by_distance"][0]["interpolation_rmse_m"] < 0.02
    assert json.loads(out.read_text())["sets"]["real frames"]["by_distance"] == r["by_distance"]
    # the scaled corrections' ends are the interpolation and the network, pooled over the distance bins
    scaled = {c["alpha"]: c for c in r["correction_scaled"]}

    def pooled(key):
        bins = r["by_distance"]
        return np.sqrt(sum(b["pixels"] * b[key] ** 2 for b in bins) / sum(b["pixels"] for b in bins))

    assert scaled[0.0]["ratio_to_interpolation"] == 1.0
    np.testing.assert_allclose(scaled[0.0]["rmse_m"], pooled("interpolation_rmse_m"), rtol=1e-5)
    np.testing.assert_allclose(scaled[1.0]["rmse_m"], pooled("network_rmse_m"), rtol=1e-5)
    assert r["best_alpha"] in scaled and scaled[r["best_alpha"]]["rmse_m"] == min(c["rmse_m"] for c in scaled.values())
    text = capsys.readouterr().out
    assert "| 0-2 |" in text and "best alpha" in text
