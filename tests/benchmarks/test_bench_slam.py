"""benchmarks/bench_slam.py at a tiny size: the issue's bars, the JSON after every run, --resume, bad input."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks import bench_slam


def _row(preset: str, seed: int, **kw) -> dict:
    row = dict(preset=preset, seed=seed, ate_se3_rmse_m=0.02, path_length_m=10.0, posed_frac=1.0, fps=30.0)
    return {**row, "init_after_s": 1.0, **kw}


def test_bars_hold_a_preset_to_every_run_and_count_the_mh05_runs_at_the_bar():
    rows = [
        _row("flight", 0),
        _row("flight", 1, ate_se3_rmse_m=0.09),  # 0.9 % of the path: under the bar
        _row("whitewall", 0, ate_se3_rmse_m=0.11),  # 1.1 %
        _row("handheld", 0, posed_frac=0.99),  # a frame without a pose
        _row("textured", 0, fps=19.0),  # too slow
        _row("mh05", 0, ate_se3_rmse_m=0.049),
        _row("mh05", 1, ate_se3_rmse_m=0.051),
        _row("mh05", 2, init_after_s=None),  # never started
        _row("mh05_still2", 0, posed_frac=0.97),
    ]
    b = bench_slam.bars(rows)
    assert b["flight"]["met"] and b["flight"]["pct_path_max"] == pytest.approx(0.9)
    assert not b["whitewall"]["met"] and b["whitewall"]["seeds_missed"] == [0]
    assert not b["handheld"]["met"] and b["handheld"]["seeds_missed"] == [0]
    assert not b["textured"]["met"] and b["textured"]["seeds_missed"] == [] and b["textured"]["fps_min"] == 19.0
    assert (b["mh05"]["runs_met"], b["mh05"]["runs"], b["mh05"]["seeds_missed"]) == (1, 3, [1, 2])
    assert not b["mh05"]["met"] and b["mh05_still2"]["met"]


def test_mh05_runs_started_later_are_jobs_of_their_own_and_held_to_no_bar(tmp_path):
    (tmp_path / "mav0" / "cam0").mkdir(parents=True)
    args = SimpleNamespace(mh05=str(tmp_path), mh05_runs=["real"], mh05_starts=[5.0, 12.5])
    assert bench_slam.mh05_jobs(args) == [("mh05", 0.0, 0.0), ("mh05_from5", 0.0, 5.0), ("mh05_from12.5", 0.0, 12.5)]
    assert bench_slam.mh05_jobs(SimpleNamespace(mh05=str(tmp_path / "none"), mh05_runs=["real"], mh05_starts=[5])) == []
    b = bench_slam.bars([_row("mh05", 0), _row("mh05_from5", 0, ate_se3_rmse_m=0.2)])
    assert sorted(b) == ["mh05"] and b["mh05"]["met"]


def test_flights_bar_holds_a_resting_start_to_1_cm_of_drift():
    rows = [
        _row("flight", 0, rest_drift_m=0.004, rest_s=2.0),
        _row("flight", 1, rest_drift_m=None, rest_s=0.2),  # no rest to judge
        _row("textured", 0, rest_drift_m=0.02, rest_s=2.0),  # the bar is flight's
    ]
    b = bench_slam.bars(rows)
    assert b["flight"]["met"] and b["flight"]["rest_drift_m_max"] == 0.004 and b["flight"]["runs_at_rest"] == 1
    assert b["textured"]["met"] and "rest_drift_m_max" not in b["textured"]
    b = bench_slam.bars([*rows, _row("flight", 2, rest_drift_m=0.012, rest_s=2.0)])
    assert not b["flight"]["met"] and b["flight"]["seeds_missed"] == [2]
    b = bench_slam.bars([_row("flight", 3, rest_drift_m=0.001, rest_s=2.0, init_after_s=None)])  # never started
    assert not b["flight"]["met"]


def _resting_sequence(t_rest_s: float):
    """A stand-in for a sequence with ground truth: at rest until ``t_rest_s``, then 0.5 m/s along x."""
    t0 = 1_000_000_000_000

    def pose_at(ts):
        t = (np.asarray(ts) - t0) * 1e-9
        T = np.tile(np.eye(4), (t.size, 1, 1))
        T[:, 0, 3] = 0.5 * np.clip(t - t_rest_s, 0.0, None)
        return T

    gt_ts = t0 + np.arange(0, 6_000_000_001, 5_000_000, dtype=np.int64)
    return SimpleNamespace(gt=SimpleNamespace(ts=gt_ts), gt_pose_at=pose_at), t0


def test_rest_drift_is_the_estimates_largest_move_while_the_ground_truth_rests(tmp_path):
    seq, t0 = _resting_sequence(2.0)
    t = np.arange(0.0, 5.0, 0.05)  # 20 Hz frames
    p = np.zeros((t.size, 3))
    p[:, 1] = 0.003 * np.minimum(t, 2.0) / 2.0  # the estimate creeps 3 mm in y over the rest
    p[:, 0] = 0.5 * np.clip(t - 2.0, 0.0, None)
    tr = np.column_stack([(t0 + np.round(t * 1e9)) * 1e-9, p, np.zeros((t.size, 3)), np.ones(t.size)])
    np.savetxt(tmp_path / "trajectory.txt", tr, fmt="%.9f")
    rest_s, drift = bench_slam.rest_drift(seq, tmp_path / "trajectory.txt")
    assert rest_s == pytest.approx(2.0, abs=0.051) and drift == pytest.approx(0.003, abs=1e-4)
    seq_short, _ = _resting_sequence(0.2)  # too short a rest to judge
    assert bench_slam.rest_drift(seq_short, tmp_path / "trajectory.txt")[1] is None
    assert bench_slam.rest_drift(SimpleNamespace(gt=None), tmp_path / "trajectory.txt") == (0.0, None)


def _argv(tmp_path, *extra: str) -> list[str]:
    return [
        "--presets", "textured", "--seeds", "0", "1", "--duration", "6", "--mh05-runs",
        "--set", "intrinsics.refine=false",
        "--data", str(tmp_path / "data"), "--out", str(tmp_path / "out"), *extra,
    ]  # fmt: skip


def test_an_interrupted_invocation_keeps_its_runs_and_resume_runs_only_the_missing_ones(tmp_path, interrupt_second_run):
    argv = _argv(tmp_path)
    calls = interrupt_second_run(bench_slam)  # the second run is stopped by the user
    with pytest.raises(KeyboardInterrupt):
        bench_slam.main(argv)
    path = tmp_path / "out" / "bench_slam.json"
    part = json.loads(path.read_text())
    assert part["complete"] is False and [r["seed"] for r in part["runs"]] == [0]
    run = json.loads((tmp_path / "out" / "textured_s0" / "metrics.json").read_text())
    assert part["runs"][0]["ate_sim3_rmse_m"] == pytest.approx(run["ate_sim3_rmse_m"])
    assert part["runs"][0]["peak_rss_mb"] == run["peak_rss_mb"] > 0  # the run's own peak memory
    assert run["config"]["intrinsics"]["refine"] is False  # --set reaches the run
    with pytest.raises(ValueError, match="other arguments"):  # a resume must not mix settings
        bench_slam.main([*argv, "--resume", "--set", "backend.window_size=6"])
    calls.clear()
    assert bench_slam.main([*argv, "--resume"]) == 0
    assert calls == ["textured_s1"]  # seed 0 was kept, only seed 1 ran
    res = json.loads(path.read_text())
    assert res["complete"] is True and [r["seed"] for r in res["runs"]] == [0, 1]
    assert res["runs"][0] == part["runs"][0] and "resume" not in res["args"]
    assert res["bars"]["textured"]["runs"] == 2 and res["summary"]["textured"]["runs"] == 2
    assert res["summary"]["textured"]["ate_sim3_rmse_m_max"] >= res["summary"]["textured"]["ate_sim3_rmse_m_mean"]


def test_dense_hands_the_runs_the_dense_systems_settings(tmp_path, monkeypatch):
    from runtime.dense import DenseConfig

    real, seen = bench_slam.run_sequence, []

    def spy(seq, out, *a, dense=None, **kw):
        seen.append(dense)
        return real(seq, out, *a, **kw)  # sparse underneath: this checks the hand-over, not the dense system

    monkeypatch.setattr(bench_slam, "run_sequence", spy)
    assert bench_slam.main([*_argv(tmp_path), "--seeds", "0", "--dense"]) == 0
    assert len(seen) == 1 and isinstance(seen[0], DenseConfig) and seen[0] == DenseConfig()
    assert json.loads((tmp_path / "out" / "bench_slam.json").read_text())["system"] == "dense"


def test_an_unknown_preset_or_setting_is_refused_before_anything_is_rendered(tmp_path):
    with pytest.raises(SystemExit, match="unknown preset"):
        bench_slam.main(_argv(tmp_path, "--presets", "texturd"))
    with pytest.raises(ValueError, match="no_such_key"):
        bench_slam.main(_argv(tmp_path, "--set", "backend.no_such_key=1"))
    assert not (tmp_path / "data").exists() and not (tmp_path / "out").exists()
