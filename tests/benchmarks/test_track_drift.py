"""benchmarks/track_drift.py: track error against the true projection, with and without the shutter correction."""

import json

import numpy as np
import pytest

from benchmarks.track_drift import main, summarise, track_errors
from runtime.io.euroc import read_euroc

sim_euroc = pytest.importorskip("sim.euroc")


@pytest.fixture(scope="module")
def rolling(tmp_path_factory):
    """4 s of realistic `handheld` at half resolution: a 15 ms rolling shutter, stated in cam0's sensor.yaml."""
    out = tmp_path_factory.mktemp("seq") / "hh"
    return sim_euroc.write_euroc_sequence(out, "handheld", duration=4.0, seed=1, progress=False, scale=0.5)


def test_the_rolling_shutter_correction_brings_old_tracks_closer_to_their_points(rolling):
    seq = read_euroc(rolling)
    assert seq.camera.line_delay_s == pytest.approx(0.015 / 240)  # dit-sim states its read-out
    errs = {d: track_errors(seq, d) for d in (0.0, seq.camera.line_delay_s)}
    old = {d: np.concatenate([e[a] for a in e if a >= 10]) for d, e in errs.items()}
    assert old[0.0].size > 100 and old[seq.camera.line_delay_s].size > 100
    assert np.median(old[seq.camera.line_delay_s]) < 0.8 * np.median(old[0.0])
    rows = summarise(errs[0.0])
    assert [r["age"] for r in rows][:3] == [1, 2, 5] and all(r["p90_px"] >= r["median_px"] for r in rows)


def test_main_writes_a_row_per_line_delay_and_refuses_a_folder_without_depth(rolling, tmp_path, capsys):
    out = tmp_path / "d.json"
    doc = main(["--sequence", str(rolling), "--line-delay", "0", "--frames", "20", "--out", str(out)])
    assert list(doc["by_line_delay"]) == ["0"] and json.loads(out.read_text())["frames"] == 20
    assert "| age [frames] |" in capsys.readouterr().out
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        main(["--sequence", str(tmp_path / "empty")])
