"""benchmarks/track_oracle.py: the tracker's pixels replaced by the true projections of their points."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from benchmarks.track_oracle import exact_tracks, main
from runtime.frontend.tracking import FeatureTracker
from runtime.io.euroc import read_euroc

sim_euroc = pytest.importorskip("sim.euroc")


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    """4 s of `textured` with exact sensors (global shutter)."""
    out = tmp_path_factory.mktemp("seq") / "tx"
    return sim_euroc.write_euroc_sequence(out, "textured", duration=4.0, seed=2, progress=False, ideal=True)


def _follow(seq, n: int):
    """A front end alone over the first ``n`` images; the last frame's features."""
    tracker = FeatureTracker(seq.camera, seq.T_b_c)
    for i in range(n):
        ts, image = int(seq.frame_ts[i]), seq.image(i)
        f = tracker.track(ts, image)
        if tracker.n_tracks < 150:
            tracker.replenish(ts, image)
    return tracker, f


def test_exact_tracks_sit_on_the_true_projection_of_their_first_pixel(ideal):
    seq = read_euroc(ideal)
    info = json.loads((ideal / "sim_info.json").read_text())
    klt = FeatureTracker.track
    with exact_tracks(seq, info) as oracle:
        tracker, f = _follow(seq, 40)
    assert oracle.snapped > 1000 and f.ids.size > 50
    # every reported pixel is its point's projection at the image's pose (the rendered camera is the written one)
    T = seq.gt_pose_at(int(f.ts)) @ seq.T_b_c
    X = np.array([oracle.points[t] for t in f.ids.tolist()])
    q, _ = seq.camera.project((X - T[:3, 3]) @ T[:3, :3])
    assert np.abs(f.uv - q).max() < 1e-3 and np.abs(tracker.uv[: f.ids.size] - q).max() < 1e-3  # new corners after
    assert FeatureTracker.track is klt  # the KLT's own again after the block


def test_a_rolling_shutter_sequence_is_refused(ideal, tmp_path):
    seq = read_euroc(ideal)
    seq.camera = replace(seq.camera, line_delay_s=1e-5)
    with pytest.raises(ValueError, match="global shutter"), exact_tracks(seq, {}):
        pass
    with pytest.raises(SystemExit, match="not a dit-sim euroc sequence"):
        main(["--sequences", str(tmp_path), "--work", str(tmp_path / "w")])
    rolling = tmp_path / "rs"
    shutil.copytree(ideal, rolling)
    yaml = rolling / "mav0" / "cam0" / "sensor.yaml"
    yaml.write_text(yaml.read_text() + "line_delay_s: 1.0e-5\n")
    with pytest.raises(SystemExit, match="rolling shutter"):
        main(["--sequences", str(rolling), "--work", str(tmp_path / "w")])
    assert not (tmp_path / "w").exists()  # refused before any run
