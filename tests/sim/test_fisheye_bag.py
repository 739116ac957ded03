"""``dit-sim euroc camera=fisheye`` (equidistant calibration written and rendered consistently) and
``format=bag|ros2|mcap`` (a bag with its calibration folder that ``open_sequence`` reads)."""

import numpy as np
import pytest

from runtime.geometry import interpolate_poses
from runtime.io.euroc import read_euroc
from runtime.io.sequence import PinholeView, open_sequence
from sim.cli import main as sim_main
from sim.euroc import EUROC_T_B_C0, write_euroc_sequence


@pytest.fixture(scope="module")
def fish(tmp_path_factory):
    out = tmp_path_factory.mktemp("fish") / "seq"
    return write_euroc_sequence(
        out, "textured", duration=3.0, seed=4, progress=False, scale=0.25, ideal=True, camera="fisheye"
    )


def test_fisheye_sequence_depth_reprojects_between_frames(fish):
    """Rendered depth unprojected through the written equidistant camera lands, in a later frame, where that
    frame's depth says the same surface is: the renderer and Camera agree on the lens."""
    seq = read_euroc(fish)
    cam = seq.camera
    assert cam.model == "equidistant" and cam.width == 188
    i, j = 10, 14
    Ti, Tj = (
        interpolate_poses(np.array([seq.frame_ts[k]]), seq.gt.ts, seq.gt.T_w_b)[0][0] @ EUROC_T_B_C0 for k in (i, j)
    )
    di, dj = seq.depth(i), seq.depth(j)
    v, u = np.nonzero(di > 0)
    p = cam.unproject(np.stack([u, v], -1).astype(float), di[v, u].astype(float))
    ok = np.isfinite(p).all(1)
    pj = (np.linalg.inv(Tj) @ Ti @ np.c_[p[ok], np.ones(ok.sum())].T).T[:, :3]
    uv, valid = cam.project(pj)
    inside = valid & cam.in_image(uv)
    ur, vr = np.round(uv[inside]).astype(int).T
    zj, zr = pj[inside, 2], dj[vr, ur]
    agree = np.abs(zj - zr) < 0.02 * zj
    assert inside.sum() > 5000 and agree.mean() > 0.9, (inside.sum(), agree.mean())


def test_pinhole_view_of_a_fisheye_sequence(fish):
    view = open_sequence(fish)
    assert isinstance(view, PinholeView) and not view.camera.has_distortion
    img = view.image(5)
    assert img.shape == (120, 188) and img.dtype == np.uint8 and img.std() > 5
    assert view.depth(5).shape == (120, 188) and len(view) == len(view.seq)


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_dit_sim_writes_bags_that_dit_slam_reads(tmp_path, fmt, capsys):
    out = tmp_path / fmt
    sim_main(
        [
            "euroc",
            f"out={out}",
            f"format={fmt}",
            "duration=3",
            "scale=0.25",
            "progress=false",
            "workers=1",
            "realism=false",
        ]
    )
    assert f"calib={out / 'calib'}" in capsys.readouterr().out
    bag = out / ("sequence.bag" if fmt == "bag" else "sequence")
    seq = open_sequence(bag, out / "calib")
    assert len(seq) == 60 and seq.imu_ts.size == 600 and seq.gt is not None
    assert not (out / "_asl").exists() and (out / "sim_info.json").is_file()
    assert seq.image(3).shape == (120, 188)
