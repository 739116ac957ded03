"""Trajectory metrics (evo) on known answers, and the top-view plot."""

import numpy as np
import pytest

from runtime import eval as ev
from runtime.geometry import make_T, so3_exp
from runtime.io.tum import write_tum


def _gt(n=400, rate=200.0):
    t = np.arange(n) / rate
    ts = (1_000_000_000 + np.round(t * 1e9)).astype(np.int64)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.cos(t)
    T[:, 1, 3] = np.sin(1.3 * t)
    T[:, 2, 3] = 0.1 * t
    T[:, :3, :3] = so3_exp(np.stack([0.1 * t, 0.05 * t, 0.4 * t], 1))
    return ts, T


def test_identical_and_rigidly_moved_estimates_have_zero_error():
    ts, T = _gt()
    m = ev.trajectory_metrics(ts[::10], T[::10], ts, T)  # estimate at 20 Hz, exact GT samples
    assert m["ate_se3_rmse_m"] < 1e-9 and m["rpe_trans_rmse_m"] < 1e-9 and m["eval_frames"] == 40
    G = make_T(so3_exp(np.array([0.0, 0.0, 1.2])), [3.0, -1.0, 0.5])
    m = ev.trajectory_metrics(ts, G @ T, ts, T)
    assert m["ate_se3_rmse_m"] < 1e-9 and m["ate_sim3_rmse_m"] < 1e-9
    assert m["rpe_trans_rmse_m"] < 1e-9 and m["rpe_rot_rmse_deg"] < 1e-6


def test_scale_error_is_removed_by_sim3_only():
    ts, T = _gt()
    S = T.copy()
    S[:, :3, 3] *= 1.1
    m = ev.trajectory_metrics(ts, S, ts, T)
    assert m["ate_se3_rmse_m"] > 0.01
    assert m["ate_sim3_rmse_m"] < 1e-9 and m["sim3_scale"] == pytest.approx(1 / 1.1)


def test_known_position_noise_gives_its_rmse():
    ts, T = _gt(2000)
    rng = np.random.default_rng(0)
    E = T.copy()
    E[:, :3, 3] += rng.normal(0, 0.01, (2000, 3))
    m = ev.trajectory_metrics(ts, E, ts, T)
    assert m["ate_se3_rmse_m"] == pytest.approx(0.01 * np.sqrt(3), rel=0.05)


def test_interpolation_and_loading(tmp_path):
    ts, T = _gt()
    mid = (ts[:-1] + ts[1:]) // 2
    P, inside = ev.interpolate_poses(mid, ts, T)
    assert inside.all() and np.allclose(P[:, :3, 3], 0.5 * (T[:-1, :3, 3] + T[1:, :3, 3]), atol=1e-12)
    _, inside = ev.interpolate_poses(np.array([ts[0] - 1, ts[-1] + 1]), ts, T)
    assert not inside.any()
    write_tum(tmp_path / "t.txt", ts, T)
    ts2, T2 = ev.load_trajectory(tmp_path / "t.txt")
    assert np.array_equal(ts, ts2) and np.allclose(T, T2, atol=1e-9)
    with pytest.raises(FileNotFoundError):
        ev.load_trajectory(tmp_path / "missing.txt")
    with pytest.raises(ValueError, match="within the ground truth"):
        ev.trajectory_metrics(ts + 10**12, T, ts, T)
    p = ev.plot_top_view(tmp_path / "top.png", ts, T, ts, T, title="x")
    assert p.stat().st_size > 1000


def test_scale_by_piece_finds_a_scale_drift():
    """An estimate 10 % long over its first half and exact over the second: each 1 s piece aligned alone gives
    1/1.1, then 1 (a known answer), while the whole run's one Sim(3) scale lies between; a piece without motion
    gets None."""
    ts, T = _gt(800)  # 4 s at 200 Hz
    E = T.copy()
    first = ns_s(ts - ts[0]) < 2.0
    E[first, :3, 3] = 1.1 * T[first, :3, 3]
    pieces = ev.scale_by_piece(ts, E[:, :3, 3], T[:, :3, 3], piece_s=1.0)
    assert len(pieces) == 4
    assert pieces[:2] == pytest.approx([1 / 1.1] * 2, abs=1e-4) and pieces[2:] == pytest.approx([1.0, 1.0], abs=1e-4)
    m = ev.trajectory_metrics(ts, E, ts, T)
    assert 1 / 1.1 < m["sim3_scale"] < 1.0 and len(m["scale_by_piece"]) == 1  # one 5 s piece
    still = np.tile(T[:1, :3, 3], (400, 1))  # 2 s at rest
    assert ev.scale_by_piece(ts[:400], still, still, piece_s=1.0) == [None, None]


def test_a_straight_piece_gets_no_scale_and_does_not_lose_the_run_metrics():
    """A piece moving on a straight line (a robot driving straight) has no unique Sim(3) rotation: evo's Umeyama
    raises on it, which lost every metric of the run. Now that piece gets None and the others their scale."""
    ts, T = _gt(2000)  # 10 s at 200 Hz
    t = ns_s(ts - ts[0])
    line = t < 5.0
    T[line, :3, 3] = np.stack([t[line], 0.5 * t[line], np.zeros(line.sum())], 1)  # 5 s straight
    T[~line, :3, 3] = T[~line, :3, 3] - T[~line][0, :3, 3] + T[line][-1, :3, 3]  # then the curve, joined on
    E = T.copy()
    E[:, :3, 3] *= 1.05
    m = ev.trajectory_metrics(ts, E, ts, T)
    assert m["scale_by_piece"][0] is None
    assert m["scale_by_piece"][1] == pytest.approx(1 / 1.05, abs=1e-4)
    assert m["sim3_scale"] == pytest.approx(1 / 1.05, abs=1e-6)
    frozen = np.tile(T[:1, :3, 3], (1000, 1))  # an estimate that does not move over a moving truth
    assert ev.scale_by_piece(ts[:1000], frozen, T[:1000, :3, 3]) == [None]


def test_a_segment_whose_score_fails_keeps_the_others_and_says_why(monkeypatch, tmp_path):
    """runtime.run scores each segment on its own; any failure there becomes the segment's eval_error (it used to
    catch only ValueError, and anything else from evo stopped the run before metrics.json)."""
    from types import SimpleNamespace

    from evo.core.geometry import GeometryException

    from runtime import run

    ts, T = _gt(400)
    system = SimpleNamespace(records=[SimpleNamespace(segment=int(i >= 200)) for i in range(400)])
    seq = SimpleNamespace(gt=SimpleNamespace(ts=ts, T_w_b=T))
    real = ev.trajectory_metrics

    def fails_on_the_second(est_ts, *a, **k):
        if est_ts[0] == ts[200]:
            raise GeometryException("Degenerate covariance rank, Umeyama alignment is not possible")
        return real(est_ts, *a, **k)

    monkeypatch.setattr(ev, "trajectory_metrics", fails_on_the_second)
    rows = run._segments(system, seq, ts, T, tmp_path)
    assert [r["poses"] for r in rows] == [200, 200]
    assert rows[0]["ate_se3_rmse_m"] == pytest.approx(0.0, abs=1e-9) and "eval_error" not in rows[0]
    assert rows[1]["eval_error"].startswith("GeometryException: Degenerate")
    assert (tmp_path / "trajectory_segments.txt").is_file()


def ns_s(ns):
    return np.asarray(ns, np.float64) * 1e-9


def test_top_view_marks_the_poses_on_the_imu_alone(tmp_path):
    """The poses that ``imu_only`` marks are drawn in orange (tab:orange pixels appear only with the mask, and more
    of them for more marked poses); a mask of another length is refused."""
    import matplotlib.image as mpimg

    ts, T = _gt(400)

    def orange(mask, name):
        img = mpimg.imread(ev.plot_top_view(tmp_path / name, ts, T, ts, T, imu_only=mask))[..., :3]
        return int((np.abs(img - np.array([255, 127, 14]) / 255).max(-1) < 0.08).sum())

    none = np.zeros(len(ts), bool)
    some, more = none.copy(), none.copy()
    some[100:140] = True
    more[100:300] = True
    assert orange(None, "a.png") == 0 and orange(none, "b.png") == 0
    assert 0 < orange(some, "c.png") < orange(more, "d.png")
    with pytest.raises(ValueError, match="imu_only"):
        ev.plot_top_view(tmp_path / "e.png", ts, T, ts, T, imu_only=none[:-1])
