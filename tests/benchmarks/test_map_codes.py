"""benchmarks/map_codes.py: the map's code fit on RGB-D frames at their recorded poses (shipped model)."""

import json

import numpy as np
import pytest

from benchmarks.map_codes import evaluate, folder_frames, group_of, main
from runtime.dense.config import DenseConfig, MapCodeConfig
from runtime.network import DepthNetwork, default_model_dir
from tests.train.test_evaluate_protocol import _folder


def _posed(root, n=4):
    """The plane frames of ``_folder`` with camera poses stepping 5 cm sideways."""
    folder = _folder(root, n=n)
    for i in range(n):
        T = np.eye(4)
        T[0, 3] = 0.05 * i
        np.savetxt(folder / f"frame-{i:06d}.pose.txt", T)
    return folder


def test_groups_take_the_nearest_frames_after_then_before():
    assert group_of(0, 20, 2, 5) == [0, 5, 10]
    assert group_of(10, 20, 2, 5) == [10, 15, 5]
    assert group_of(18, 20, 2, 5) == [18, 13, 8]
    assert group_of(1, 3, 4, 1) == [1, 2, 0]  # fewer frames than neighbours asked for
    assert group_of(0, 1, 2, 1) == [0]


def test_no_neighbours_leave_the_prior_and_a_group_moves_it(tmp_path):
    net = DepthNetwork(default_model_dir())
    frames = folder_frames(_posed(tmp_path / "f"), net)
    alone = evaluate(frames, 1, DenseConfig(map_codes=MapCodeConfig(neighbours=0)))
    assert alone["rmse_m"]["map code"] == alone["rmse_m"]["c=0"] and alone["code_norm_median"] == 0.0
    fitted = evaluate(frames, 1)
    assert fitted["rmse_m"]["c=0"] == alone["rmse_m"]["c=0"]
    assert fitted["rmse_m"]["map code"] != fitted["rmse_m"]["c=0"] and fitted["code_norm_median"] > 0
    assert 0.0 <= fitted["frames_better"] <= 1.0 and np.isfinite(fitted["rmse_m"]["interpolation"])


def test_main_writes_its_table_and_refuses_frames_without_poses(tmp_path, capsys):
    out = tmp_path / "o.json"
    doc = main(["--real", str(_posed(tmp_path / "posed", n=3)), "--gap", "1", "--out", str(out)])
    r = doc["folders"]["posed"]
    assert r["frames"] == 3 and set(r["rmse_m"]) == {"c=0", "map code", "interpolation"}
    assert json.loads(out.read_text())["folders"]["posed"]["rmse_m"] == r["rmse_m"]
    assert "map code over c = 0" in capsys.readouterr().out
    with pytest.raises(ValueError, match="no pose"):
        folder_frames(_folder(tmp_path / "bare", n=2), DepthNetwork(default_model_dir()))
    with pytest.raises(SystemExit, match="gap"):
        main(["--real", str(tmp_path), "--gap", "0"])
