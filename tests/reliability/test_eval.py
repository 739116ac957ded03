"""dit-eval: a time offset between estimate and ground truth is found and reported, dropped poses are counted,
and nanosecond timestamps in a TUM file are one clear error."""

import json

import pytest

from apps.evaluate import main as eval_main
from runtime import eval as ev
from runtime.io.tum import write_tum
from tests.reliability.fakes import circle_trajectory


def test_shifted_estimate_gives_its_offset_and_the_dropped_poses(tmp_path, capsys):
    ts, T = circle_trajectory(141)
    write_tum(tmp_path / "gt.txt", ts, T)
    write_tum(tmp_path / "est.txt", ts + 500_000_000, T)  # the estimate's clock is 0.5 s late
    eval_main(["trajectory", f"est={tmp_path / 'est.txt'}", f"gt={tmp_path / 'gt.txt'}", f"out={tmp_path / 'ev'}"])
    cap = capsys.readouterr()
    m = json.loads((tmp_path / "ev" / "trajectory_metrics.json").read_text())
    assert m["time_offset_s"] == pytest.approx(-0.5, abs=0.003)
    assert m["ate_se3_rmse_at_offset_m"] < 1e-3 < m["ate_se3_rmse_at_zero_m"]
    assert m["dropped_poses"] == 10 and m["eval_frames"] == 131
    assert "10 of 141 estimated poses lie outside the ground truth's time range" in cap.err
    assert "matches the ground truth best -0.500 s later" in cap.err


def test_aligned_estimate_gives_no_warning():
    ts, T = circle_trajectory(141)
    m = ev.trajectory_metrics(ts, T, ts, T)
    m.update(ev.best_time_offset(ts, T, ts, T))
    assert m["time_offset_s"] == 0.0 and ev.evaluation_warnings(m, len(ts)) == []


def test_partly_overlapping_estimate_is_scored_on_the_overlap():
    ts, T = circle_trajectory(141)
    m = ev.trajectory_metrics(ts + 1_000_000_000, T, ts, T)  # the last 20 poses lie past the ground truth
    assert m["eval_frames"] == 121


def test_nanosecond_timestamps_in_a_tum_file_are_one_clear_error(tmp_path, capsys):
    ts, T = circle_trajectory(20, t0_ns=1_403_636_579_763_555_584)
    lines = [f"{t} " + " ".join(["0"] * 6) + " 1" for t in ts]
    (tmp_path / "ns.txt").write_text("\n".join(lines) + "\n")
    write_tum(tmp_path / "gt.txt", ts, T)
    with pytest.raises(SystemExit) as e:
        eval_main(["trajectory", f"est={tmp_path / 'ns.txt'}", f"gt={tmp_path / 'gt.txt'}"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err
    assert "ns.txt:1: timestamp 1403636579763555584 is not in seconds (nanoseconds?)" in err


def test_segments_in_their_own_frames_are_scored_one_by_one(tmp_path, capsys):
    """After a re-initialisation from scratch the estimate continues in a new frame: the whole-trajectory ATE
    mixes frames, each segment alone is exact."""
    import numpy as np

    from runtime.geometry import make_T

    ts, T = circle_trajectory(141)
    write_tum(tmp_path / "gt.txt", ts, T)
    est = T.copy()
    est[70:] = make_T(t=[3.0, -2.0, 0.5]) @ T[70:]  # segment 1 in another frame
    write_tum(tmp_path / "trajectory.txt", ts, est)
    seg = np.r_[np.zeros(70), np.ones(71)]
    (tmp_path / "trajectory_segments.txt").write_text(
        "".join(f"{t * 1e-9:.9f} {int(s)}\n" for t, s in zip(ts, seg, strict=True))
    )
    eval_main(
        ["trajectory", f"est={tmp_path / 'trajectory.txt'}", f"gt={tmp_path / 'gt.txt'}", f"out={tmp_path / 'ev'}"]
    )
    m = json.loads((tmp_path / "ev" / "trajectory_metrics.json").read_text())
    assert m["ate_se3_rmse_m"] > 0.5  # mixed frames
    assert [s["segment"] for s in m["segments"]] == [0, 1]
    assert all(s["ate_se3_rmse_m"] < 1e-6 for s in m["segments"])
    assert "2 segments, each in its own frame" in capsys.readouterr().out
