"""benchmarks/intrinsics_tracks.py: the intrinsics adjustment on exact tracks returns the true camera."""

import json

import numpy as np
import pytest

from benchmarks.intrinsics_tracks import in_pieces, main

sim_euroc = pytest.importorskip("sim.euroc")


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    """6 s of `textured` with exact sensors and calibration (the written camera is the rendered one)."""
    out = tmp_path_factory.mktemp("seq") / "tx"
    return sim_euroc.write_euroc_sequence(out, "textured", duration=6.0, seed=1, progress=False, ideal=True)


def test_exact_tracks_give_back_the_true_camera_and_the_tracks_do_not(ideal, tmp_path, capsys):
    out = tmp_path / "t.json"
    doc = main(["--sequences", str(ideal), "--pieces", "3", "--out", str(out)])
    rows = doc["per_sequence"][ideal.name]
    assert rows["written"] == [0.0, 0.0, 0.0, 0.0]
    # exact pixels: the adjustment's model has no bias (to 0.02 % and 0.1 px); from the true poses to the last digits
    assert np.abs(rows["exact"][:2]).max() < 0.02 and np.abs(rows["exact"][2:]).max() < 0.1, rows
    assert np.abs(rows["exact, true poses"]).max() < 1e-3, rows
    # the front end's own tracks move the camera further than the exact ones do
    assert np.abs(rows["tracks"][:2]).max() > 5 * np.abs(rows["exact"][:2]).max(), rows
    variants = {"written", "tracks", "exact", "exact, true poses", "pieces 3"}
    assert set(json.loads(out.read_text())["mean_abs"]) == variants
    assert "| exact |" in capsys.readouterr().out


def test_pieces_cut_every_track_and_keep_every_view(monkeypatch):
    from runtime import calibration

    tracks = [[(n, np.array([n, 0.0])) for n in range(7)], [(n, np.array([0.0, n])) for n in range(2, 4)]]
    xn = [np.arange(14.0).reshape(7, 2), np.zeros((2, 2))]
    monkeypatch.setattr(calibration, "tracks_from_features", lambda *a: (tracks, xn))
    cut_t, cut_x = in_pieces(3)(None, [], np.zeros(0), 2)
    assert [[n for n, _ in t] for t in cut_t] == [[0, 1, 2], [3, 4, 5], [2, 3]]  # the 1-view tail is dropped
    assert [x.shape[0] for x in cut_x] == [3, 3, 2] and np.array_equal(cut_x[1], xn[0][3:6])


def test_a_folder_that_is_no_rendered_sequence_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="not a dit-sim euroc sequence"):
        main(["--sequences", str(tmp_path)])
