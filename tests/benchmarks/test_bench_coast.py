"""benchmarks/bench_coast.py: the driver prints both tables and writes its JSON (the oracles and the split of a
run's ATE are tested in tests/runtime/diagnostics/test_coast.py)."""

from __future__ import annotations

import json

from benchmarks import bench_coast
from runtime.io.euroc import read_euroc
from runtime.io.tum import write_tum
from sim.euroc import write_euroc_sequence
from sim.trajectory import whitewall_min_duration

DURATION = whitewall_min_duration()  # 24 s, the shortest whitewall sequence
SCALE = 0.1  # 75x48 images: the oracles and the run split read only the IMU and the ground truth


def test_main_prints_both_tables_and_writes_json(tmp_path, capsys):
    data = tmp_path / "data"
    root = write_euroc_sequence(
        data / f"euroc_whitewall_{DURATION:g}s_s0_x{SCALE:g}", "whitewall", DURATION, 0, imu_noise=True,
        progress=False, scale=SCALE, realism=False,
    )  # fmt: skip
    seq = read_euroc(root)
    runs = tmp_path / "runs"
    write_tum(runs / "whitewall_s0_sparse" / "trajectory.txt", seq.frame_ts, seq.gt.pose_at(seq.frame_ts))
    assert bench_coast.main(
        ["--seeds", "0", "--duration", f"{DURATION:g}", "--scale", f"{SCALE:g}", "--data", str(data),
         "--runs", str(runs), "--out", str(tmp_path / "out")]
    ) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "exact end states" in printed and "jump" in printed
    res = json.loads((tmp_path / "out" / "bench_coast.json").read_text())
    (row,) = res["rows"]
    assert set(row["runs"]) == {"sparse"}
    assert row["runs"]["sparse"]["ate"] < 1e-6  # the ground truth itself
    assert row["source"] == "white-wall hold +- 2 s"  # no metrics.json with events beside the run
    assert row["end pose"] > row["end pose+vel"]
