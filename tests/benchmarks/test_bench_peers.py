"""The pure parts of benchmarks/bench_peers.py (run without the peers installed): the settings written from the
EuRoC-layout sensor.yaml files, the scoring and its alignment choice, the home-trained vocabulary's file format."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from benchmarks.bench_peers import aggregate, failure_note, merge_results, ours_command, ratios
from benchmarks.peers import scoring, settings, vocab
from benchmarks.sequences import parse_sequence
from runtime.io.sensor_yaml import load_sensor_yaml

# EuRoC's cam0 T_BS (camera in the body/IMU frame), as in docs and ORB-SLAM3's own EuRoC.yaml IMU.T_b_c1
T_BS = [
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
]
CAM_YAML = """%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [{data}]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375]
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
IMU_YAML = """sensor_type: imu
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: 200
gyroscope_noise_density: 1.6968e-04
gyroscope_random_walk: 1.9393e-05
accelerometer_noise_density: 2.0000e-3
accelerometer_random_walk: 3.0000e-3
"""


@pytest.fixture
def seq(tmp_path: Path) -> Path:
    for name, text in (("cam0", CAM_YAML.format(data=", ".join(str(v) for r in T_BS for v in r))), ("imu0", IMU_YAML)):
        (tmp_path / "mav0" / name).mkdir(parents=True)
        (tmp_path / "mav0" / name / "sensor.yaml").write_text(text)
    return tmp_path


def test_orbslam3_settings_from_sensor_yaml(seq, tmp_path):
    path = settings.write_orbslam3_settings(seq, tmp_path / "out" / "mi.yaml", inertial=True, imu_noise_scale=2.0)
    d = load_sensor_yaml(path)  # the project's reader accepts OpenCV's YAML as ORB-SLAM3 writes it
    assert path.read_text().startswith("%YAML:1.0\n")
    assert d["File.version"] == "1.0" and d["Camera.type"] == "PinHole"
    assert (d["Camera1.fx"], d["Camera1.fy"], d["Camera1.cx"], d["Camera1.cy"]) == (458.654, 457.296, 367.215, 248.375)
    assert (d["Camera1.k1"], d["Camera1.p2"]) == (-0.28340811, 1.76187114e-05)
    assert (d["Camera.width"], d["Camera.height"], d["Camera.fps"]) == (752, 480, 20)
    # IMU.T_b_c1 is the camera in the body frame: EuRoC's T_BS itself (not its inverse)
    T = np.asarray(d["IMU.T_b_c1"]["data"], dtype=float).reshape(4, 4)
    np.testing.assert_allclose(T, T_BS, atol=1e-12)
    assert d["IMU.T_b_c1"]["rows"] == 4 and d["IMU.T_b_c1"]["dt"] == "f"
    # densities in sensor.yaml's units, scaled
    assert d["IMU.NoiseGyro"] == pytest.approx(2 * 1.6968e-4) and d["IMU.NoiseAcc"] == pytest.approx(4.0e-3)
    assert d["IMU.GyroWalk"] == pytest.approx(2 * 1.9393e-5) and d["IMU.AccWalk"] == pytest.approx(6.0e-3)
    assert d["IMU.Frequency"] == 200.0
    mono = load_sensor_yaml(settings.write_orbslam3_settings(seq, tmp_path / "m.yaml", inertial=False))
    assert not any(k.startswith("IMU.") for k in mono) and mono["ORBextractor.nFeatures"] == 1000


def test_imu_mount_is_composed_into_t_b_c(seq, tmp_path):
    # an IMU mounted 1 m along x of the body: the camera in the IMU frame is inv(T_b_imu) @ T_b_c
    text = IMU_YAML.replace("1.0, 0.0, 0.0, 0.0, 0.0, 1.0", "1.0, 0.0, 0.0, 1.0, 0.0, 1.0", 1)
    (seq / "mav0" / "imu0" / "sensor.yaml").write_text(text)
    s = settings.read_setup(seq)
    expect = np.array(T_BS)
    expect[0, 3] -= 1.0
    np.testing.assert_allclose(s.T_b_c, expect, atol=1e-12)
    cam = settings.cuvslam_camera(s)
    assert cam["distortion"] == "brown" and cam["coeffs"][0] == -0.28340811 and cam["width"] == 752


def test_settings_reject_missing_calibration(tmp_path):
    with pytest.raises(FileNotFoundError, match="cam0"):
        settings.read_setup(tmp_path)
    (tmp_path / "mav0" / "cam0").mkdir(parents=True)
    (tmp_path / "mav0" / "cam0" / "sensor.yaml").write_text(CAM_YAML.format(data=", ".join(["0"] * 16)))
    with pytest.raises(ValueError, match="T_BS"):
        settings.read_setup(tmp_path)


def _traj(n=200, seed=0):
    rng = np.random.default_rng(seed)
    ts = 10**18 + np.arange(n, dtype=np.int64) * 50_000_000
    T = np.tile(np.eye(4), (n, 1, 1))
    t = np.linspace(0, 4 * np.pi, n)
    T[:, :3, 3] = np.column_stack([np.cos(t), np.sin(2 * t), 0.3 * t]) + 0.001 * rng.standard_normal((n, 3))
    c, s = np.cos(0.3 * t), np.sin(0.3 * t)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    return ts, T


def _sim3(T, s, R, p):
    out = T.copy()
    out[:, :3, :3] = R @ T[:, :3, :3]
    out[:, :3, 3] = s * (T[:, :3, 3] @ R.T) + p
    return out


def test_alignment_choice_by_system():
    assert scoring.alignments("orbslam3-mono") == ("sim3",) and scoring.reference_frame("cuvslam-mono") == "camera"
    assert scoring.alignments("dit-slam-sparse") == ("se3", "sim3")
    assert scoring.reference_frame("orbslam3-mono-inertial") == "body"
    with pytest.raises(KeyError, match="unknown system"):
        scoring.alignments("svo")


def test_monocular_scored_sim3_against_the_camera_frame():
    gt_ts, gt_T = _traj()
    T_b_c = np.array(T_BS)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    est = _sim3(gt_T @ T_b_c, 3.7, R, np.array([1.0, 2.0, 3.0]))  # a camera trajectory in another scale and frame
    r = scoring.score("orbslam3-mono", gt_ts[5:-5], est[5:-5], gt_ts, gt_T, T_b_c)
    assert set(r) == {"sim3"} and r["sim3"]["ate_m"] < 1e-9
    assert r["sim3"]["scale"] == pytest.approx(1 / 3.7) and r["sim3"]["eval_frames"] == 190
    # the same estimate scored against the body frame is off by the lever arm (a wrong reference is visible)
    wrong = scoring.score("dit-slam-sparse", gt_ts, _sim3(gt_T @ T_b_c, 3.7, R, np.zeros(3)), gt_ts, gt_T, T_b_c)
    assert wrong["sim3"]["ate_m"] > 1e-3


def test_inertial_scored_se3_and_sim3_against_the_body():
    gt_ts, gt_T = _traj()
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    rigid = _sim3(gt_T, 1.0, R, np.array([0.5, 0.0, -1.0]))
    r = scoring.score("orbslam3-mono-inertial", gt_ts, rigid, gt_ts, gt_T, np.array(T_BS))
    assert r["se3"]["ate_m"] < 1e-9 and r["sim3"]["ate_m"] < 1e-9 and r["se3"]["scale"] == 1.0
    scaled = _sim3(gt_T, 1.1, R, np.zeros(3))  # a 10 % scale error: SE(3) sees it, Sim(3) removes it
    r = scoring.score("dit-slam-dense", gt_ts, scaled, gt_ts, gt_T, np.array(T_BS))
    assert r["se3"]["ate_m"] > 0.01 and r["sim3"]["ate_m"] < 1e-9


def test_score_of_an_empty_trajectory_is_nan():
    gt_ts, gt_T = _traj()
    r = scoring.score("dit-slam-sparse", np.zeros(0, np.int64), np.zeros((0, 4, 4)), gt_ts, gt_T, np.eye(4))
    assert math.isnan(r["se3"]["ate_m"]) and r["sim3"]["eval_frames"] == 0
    assert scoring.tracked_fraction(0, 600) == 0.0 and scoring.tracked_fraction(537, 600) == pytest.approx(0.895)


def test_median_range_and_rows():
    assert scoring.median_range([3.0, float("nan"), 1.0, 2.0]) == (2.0, 1.0, 3.0)
    assert scoring.median_range([4.0, 1.0]) == (2.5, 1.0, 4.0)
    assert all(math.isnan(x) for x in scoring.median_range([None, float("nan")]))
    runs = [
        {
            "frames": 100,
            "loop_wall_s": w,
            "loop_cpu_s": c,
            "child_cpu_s": c + 1,
            "tracked_frac": 0.9,
            "losses": 0,
            "resets": 1,
            "scores": {"sim3": {"ate_m": a, "scale": 2.0}},
        }
        for w, c, a in ((2.0, 1.0, 0.004), (4.0, 3.0, 0.002), (1.0, 2.0, 0.009))
    ]
    (row,) = aggregate("orbslam3-mono", "textured_s0", runs)
    assert (row["ate_m"], row["ate_min_m"], row["ate_max_m"]) == (0.004, 0.002, 0.009)
    assert row["fps"] == 50.0 and row["cpu_ms_per_frame"] == 20.0 and row["runs"] == 3
    assert row["alignment"] == "sim3" and row["reference_frame"] == "camera"
    ours = aggregate(
        "dit-slam-sparse",
        "textured_s0",
        [
            {
                "frames": 100,
                "loop_wall_s": 1.0,
                "loop_cpu_s": 0.5,
                "child_cpu_s": 2.0,
                "tracked_frac": 1.0,
                "scores": {"se3": {"ate_m": 0.003, "scale": 1.0}, "sim3": {"ate_m": 0.002, "scale": 1.0}},
            }
        ],
    )
    assert [r["alignment"] for r in ours] == ["se3", "sim3"]
    (q,) = ratios(ours + [row])
    assert q["alignment"] == "sim3" and q["ate_ratio"] == pytest.approx(0.5) and q["fps_ratio"] == 2.0


def test_parse_sequence_names():
    assert parse_sequence("flight_s2") == {"kind": "sim", "preset": "flight", "seed": 2, "realism": None}
    assert parse_sequence("flight-ideal_s0")["realism"] is False and parse_sequence("mh05") == {"kind": "mh05"}
    assert parse_sequence("mh05_s12") == {"kind": "mh05", "seed": 12}
    for bad in ("flight", "flight_s", "_s3", "mh05_sx"):
        with pytest.raises(ValueError, match="PRESET_sSEED"):
            parse_sequence(bad)


def test_vocabulary_text_round_trip_and_words():
    rng = np.random.default_rng(0)
    # three well separated clusters of 256-bit descriptors (a few bits flipped around three centres)
    centres = rng.integers(0, 2, (3, 256), dtype=np.uint8)
    images = []
    for _ in range(6):
        bits = np.repeat(centres, 20, axis=0)
        flip = rng.random(bits.shape) < 0.03
        images.append(np.packbits(bits ^ flip, axis=1))
    voc = vocab.train_vocabulary(images, k=3, L=2, seed=0)
    assert voc["parent"][0] == 0 and np.all(voc["parent"][:3] == 0)  # the root's three children come first
    assert np.all(np.diff(voc["parent"]) >= 0)  # breadth-first ids: parents never decrease
    path = vocab.write_dbow2_text(voc, Path(pytest.importorskip("tempfile").mkdtemp()) / "voc.txt")
    text = path.read_text()
    assert text.startswith("3 2 0 0\n") and not text.endswith("\n")  # no empty last line for ORB-SLAM3's reader
    back = vocab.read_dbow2_text(path)
    for key in ("parent", "leaf", "desc"):
        np.testing.assert_array_equal(back[key], voc[key])
    np.testing.assert_allclose(back["weight"], voc["weight"], atol=1e-6)
    # a descriptor lands in the subtree of its own cluster: the three clusters get disjoint words
    words = [set(vocab.transform(back, img[20 * c : 20 * c + 20])) for c in range(3) for img in images[:1]]
    assert not (words[0] & words[1]) and not (words[1] & words[2]) and not (words[0] & words[2])
    # every image holds every cluster: the words of the first level are in all images, IDF weight log(6/6) = 0
    assert np.all(back["weight"] >= 0)


def test_per_frame_errors_follow_the_scoring():
    from benchmarks.peers.plot_errors import aligned_errors

    gt_ts, gt_T = _traj()
    T_b_c = np.array(T_BS)
    est = _sim3(gt_T @ T_b_c, 0.5, np.eye(3), np.array([3.0, 0.0, 0.0]))
    est[100:, :3, 3] += np.array([0.0, 0.0, 0.02 * 0.5])  # a 2 cm jump (in the estimate's scale) from frame 100 on
    ts, err = aligned_errors("cuvslam-mono", gt_ts, est, gt_ts, gt_T, T_b_c)
    assert ts.size == 200 and err.max() > 2 * err.min()  # the jump shows in the per-frame curve
    rmse = float(np.sqrt(np.mean(err**2)))
    ref = scoring.score("cuvslam-mono", gt_ts, est, gt_ts, gt_T, T_b_c)["sim3"]["ate_m"]
    assert rmse == pytest.approx(ref, rel=1e-9) and 0.005 < rmse < 0.02


def _result(command, rows, runs, vocabulary=None, notes=()):
    return {
        "command": command,
        "machine": {"cpus": 2, "loadavg": [1.0, 1.0, 1.0]},
        "vocabulary": vocabulary,
        "rows": rows,
        "runs": runs,
        "notes": list(notes),
    }


def _row(system, sequence, ate, alignment="sim3"):
    return {
        "system": system,
        "sequence": sequence,
        "alignment": alignment,
        "ate_m": ate,
        "tracked_frac": 1.0,
        "fps": 10.0,
        "cpu_ms_per_frame": 50.0,
    }


def test_merge_keeps_vocabulary_notes_and_other_runs():
    old = _result(
        "bench_peers.py --sequences a b",
        [_row("orbslam3-mono", "a", 0.01), _row("dit-slam-sparse", "a", 0.02), _row("dit-slam-sparse", "b", 0.03)],
        [{"system": "orbslam3-mono", "sequence": "a"}, {"system": "dit-slam-sparse", "sequence": "a", "run": 0}],
        vocabulary="home-trained",
        notes=["a note"],
    )
    new = _result(
        "bench_peers.py --sequences a --systems dit-slam-sparse --merge",
        [_row("dit-slam-sparse", "a", 0.005)],
        [{"system": "dit-slam-sparse", "sequence": "a", "run": 1}],
    )
    m = merge_results(old, new)
    # a rerun of ours alone keeps the peer's vocabulary, the notes and the peer's runs; ours are replaced
    assert m["vocabulary"] == "home-trained" and m["notes"] == ["a note"]
    assert m["runs"] == [
        {"system": "orbslam3-mono", "sequence": "a"},
        {"system": "dit-slam-sparse", "sequence": "a", "run": 1},
    ]
    ates = {(r["system"], r["sequence"]): r["ate_m"] for r in m["rows"]}
    assert ates == {("orbslam3-mono", "a"): 0.01, ("dit-slam-sparse", "a"): 0.005, ("dit-slam-sparse", "b"): 0.03}
    assert m["commands"] == [old["command"], new["command"]] and len(m["machine"]["loadavg_each_run"]) == 2
    (q,) = m["ratios"]  # recomputed from the merged rows
    assert q["sequence"] == "a" and q["ate_ratio"] == pytest.approx(0.5)


def test_ours_command_names_the_mode():
    """``dit-slam`` is dense by default: the sparse row must ask for ``dense=false`` or it measures the dense system."""
    sparse = ours_command("dit-slam-sparse", Path("seq"), Path("out"))
    dense = ours_command("dit-slam-dense", Path("seq"), Path("out"))
    assert "dense=false" in sparse and "dense=true" not in sparse
    assert "dense=true" in dense and "dense=false" not in dense
    assert sparse[1:3] == ["sequence=seq", "out=out"]
    with pytest.raises(ValueError):
        ours_command("orbslam3-mono", Path("seq"), Path("out"))


def test_a_failed_peer_run_is_noted_by_its_cause_not_by_a_warning():
    """ORB-SLAM3 prints its settings warnings last; a crash on an empty map must say so, not quote a warning."""
    out = "There are 1 maps in the atlas\n  Map 0 has 0 KFs\n"
    crashed = subprocess.CompletedProcess([], -11, out, "System.thFarPoints optional parameter does not exist...")
    assert failure_note(crashed) == "failed: killed by SIGSEGV; its map had no keyframe left when saved"
    kept = subprocess.CompletedProcess([], -9, "Map 0 has 0 KFs\nMap 1 has 12 KFs\n", "timed out after 1800 s")
    assert failure_note(kept) == "failed: killed by SIGKILL"
    error = subprocess.CompletedProcess([], 1, "", "Traceback (most recent call last):\nValueError: bad image")
    assert failure_note(error) == "failed: ValueError: bad image"


def test_the_peer_child_imports_without_h5py():
    """The peers' child process reads only sensor.yaml files: it imports in an environment without h5py (a
    separate one for the peers, ``--peers-python``), and the NYU reader imports h5py on first use."""
    import sys

    code = (
        "import sys; sys.modules['h5py'] = None\n"  # any 'import h5py' now raises ImportError
        "import benchmarks.peers.run_peer, runtime.io\n"
        "import tempfile, pathlib\n"
        "from runtime.io.nyu import read_nyu_h5\n"
        "f = pathlib.Path(tempfile.mkdtemp()) / 'frame.h5'\n"
        "f.write_bytes(b'not read')\n"
        "try:\n"
        "    read_nyu_h5(f)\n"
        "except ImportError:\n"
        "    print('h5py needed only here')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=Path(__file__).parents[2])
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "h5py needed only here"
