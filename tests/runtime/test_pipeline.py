"""The whole system on small rendered sequences (sim/): accuracy, outputs, CLI, robustness to bad files."""

import json
import shutil

import gtsam
import numpy as np
import pytest

from apps.evaluate import main as eval_main
from apps.slam import main as slam_main
from runtime.backend.imu import ImuStream, integrate, make_bias, preintegration_params
from runtime.geometry import pose_error
from runtime.io.euroc import read_euroc
from runtime.io.ply import read_ply
from runtime.io.tum import read_tum
from runtime.run import ImageCache, run_sequence
from runtime.slam import SlamConfig

sim_euroc = pytest.importorskip("sim.euroc")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """10 s textured sequence at half resolution (376x240), IMU noise on."""
    out = tmp_path_factory.mktemp("seq") / "tiny"
    return sim_euroc.write_euroc_sequence(
        out, "textured", duration=10.0, seed=3, imu_noise=True, progress=False, scale=0.5, realism=False
    )


@pytest.fixture(scope="module")
def tiny_run(tiny, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    m = run_sequence(read_euroc(tiny), out, SlamConfig(), progress=False)
    return out, m


def _copy(src, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(src, dst, symlinks=True)
    return dst


def test_pipeline_on_10s_rendered_sequence_reaches_bounded_ate_and_writes_outputs(tiny_run):
    out, m = tiny_run
    assert m["ate_se3_rmse_m"] < 0.05, m
    assert abs(m["sim3_scale"] - 1.0) < 0.05
    assert m["frames"] == 200 and m["frames_with_pose"] >= 200 - 3.5 * 20  # initialised after the 2.5 s rest
    ts, T = read_tum(out / "trajectory.txt")
    assert len(ts) == m["frames_with_pose"] and np.all(np.diff(ts) > 0)
    # frames.csv: one row per pose, with its status and its seconds on the IMU alone
    rows = [line.split(",") for line in (out / "frames.csv").read_text().splitlines()[1:]]
    assert [int(r[0]) for r in rows] == ts.tolist()
    counts = {st: sum(r[1] == st for r in rows) for st in {r[1] for r in rows}}
    assert counts == m["frame_status"] and sum(counts.values()) == m["frames_with_pose"]
    assert max(float(r[2]) for r in rows) == pytest.approx(m["imu_only_max_s"], abs=1e-3)
    assert all(float(r[2]) == 0 for r in rows if r[1] in ("tracking", "still", "init"))
    kts, _ = read_tum(out / "keyframes.txt")
    assert len(kts) == m["keyframes"] > 5
    xyz, _ = read_ply(out / "sparse_map.ply")
    assert xyz.shape[0] == m["map_points"] > 50
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["ate_se3_rmse_m"] == pytest.approx(m["ate_se3_rmse_m"])
    for k in (
        "fps",
        "timing_ms_per_frame",
        "ate_sim3_rmse_m",
        "rpe_trans_rmse_m",
        "rpe_rot_rmse_deg",
        "events",
    ):
        assert k in saved
    assert (out / "trajectory_top.png").stat().st_size > 1000
    # the sparse run refined the intrinsics over its first 15 s; this sequence's are exact, so the change stays
    # within four of the estimate's standard deviations (about 0.35 % in focal on these 10 s at half size)
    intr = saved["intrinsics"]
    assert intr["refined"] is True and intr["first_pass_frames"] == 200, intr
    for dv, sd in zip(intr["focal_change_rel"], intr["std"]["focal_rel"], strict=True):
        assert 0 < sd < 0.01 and abs(dv) < 4 * sd, intr
    for dv, sd in zip(intr["principal_change_px"], intr["std"]["principal_px"], strict=True):
        assert 0 < sd < 2 and abs(dv) < 4 * sd, intr


def test_zoh_segments_and_gtsam_preintegration_reproduce_noiseless_sim_ground_truth(tmp_path):
    root = sim_euroc.write_euroc_sequence(
        tmp_path / "exact", "textured", duration=5.0, seed=1, imu_noise=False, progress=False, scale=0.25, realism=False
    )
    seq = read_euroc(root)
    imu = ImuStream.from_sequence(seq)
    gt = seq.gt
    pim = gtsam.PreintegratedCombinedMeasurements(preintegration_params(seq.imu), make_bias(np.zeros(6)))
    i, j = 700, 900  # 1 s while moving (rest ends at 2.5 s)
    integrate(pim, *imu.segment(int(gt.ts[i]), int(gt.ts[j])))
    nav = pim.predict(gtsam.NavState(gtsam.Pose3(gt.T_w_b[i]), gt.v_w[i]), make_bias(np.zeros(6)))
    dp, dr = pose_error(nav.pose().matrix(), gt.T_w_b[j])
    assert np.linalg.norm(gt.p_w_b[j] - gt.p_w_b[i]) > 0.1
    assert dp < 1e-3 and np.degrees(dr) < 0.01
    assert np.linalg.norm(nav.velocity() - gt.v_w[j]) < 2e-3


def test_no_ground_truth_still_writes_outputs(tiny, tmp_path):
    root = _copy(tiny, tmp_path)
    shutil.rmtree(root / "mav0" / "state_groundtruth_estimate0")
    m = run_sequence(read_euroc(root), tmp_path / "out", progress=False, max_frames=100)
    assert "ate_se3_rmse_m" not in m and m["frames_with_pose"] > 30
    for name in (
        "trajectory.txt",
        "frames.csv",
        "keyframes.txt",
        "sparse_map.ply",
        "metrics.json",
        "trajectory_top.png",
    ):
        assert (tmp_path / "out" / name).is_file()


def test_corrupt_and_missing_images_are_logged_and_skipped(tiny, tmp_path):
    root = _copy(tiny, tmp_path)
    data = root / "mav0" / "cam0" / "data"
    pngs = sorted(data.iterdir())
    pngs[80].write_bytes(b"not a png at all")
    pngs[81].unlink()
    with pytest.warns(UserWarning, match="do not exist"):
        seq = read_euroc(root)
    m = run_sequence(seq, tmp_path / "out", progress=False, max_frames=120)
    msgs = [msg for _, msg in m["events"]]
    assert any("cannot read image" in msg for msg in msgs)
    assert m["frames"] == 120 and m["frames_with_pose"] > 50
    ts, T = read_tum(tmp_path / "out" / "trajectory.txt")
    assert np.isfinite(T).all()


def test_cli_runs_a_sequence_and_eval_cli_reads_its_output(tiny, tmp_path, capsys):
    out = tmp_path / "cli"
    slam_main(
        [
            f"sequence={tiny}",
            f"out={out}",
            "progress=false",
            "max_frames=120",
            "runtime.backend.window_size=8",
        ]
    )
    text = capsys.readouterr().out
    assert "ATE RMSE" in text and (out / "trajectory.txt").is_file()
    m = json.loads((out / "metrics.json").read_text())
    assert m["config"]["backend"]["window_size"] == 8
    eval_main(["trajectory", f"est={out / 'trajectory.txt'}", f"gt={tiny}", f"out={tmp_path / 'ev'}"])
    text = capsys.readouterr().out
    assert "ate_se3_rmse_m" in text
    ev = json.loads((tmp_path / "ev" / "trajectory_metrics.json").read_text())
    assert ev["ate_se3_rmse_m"] == pytest.approx(m["ate_se3_rmse_m"], rel=1e-6)


def test_cli_errors_are_clear(tiny, tmp_path, capsys):
    root = _copy(tiny, tmp_path)
    csv = root / "mav0" / "imu0" / "data.csv"
    lines = csv.read_text().splitlines()
    lines[5] = lines[5].replace(",", ",x", 1)
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(SystemExit) as e:
        slam_main([f"sequence={root}", f"out={tmp_path / 'o'}", "progress=false"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "imu0/data.csv" in err and "line" in err
    with pytest.raises(SystemExit) as e:
        slam_main([f"sequence={tmp_path / 'nowhere'}", "progress=false"])
    assert e.value.code == 2 and "nowhere" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # dense=true checks its settings first (runs: tests/dense)
        slam_main([f"sequence={tiny}", "dense=true", "dense_settings.n_consis=0"])
    assert e.value.code == 2 and "n_consis" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # Hydra rejects unknown keys itself
        slam_main([f"sequence={tiny}", "runtime.backend.window_sise=3"])
    assert e.value.code != 0 and "window_sise" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # and a forced one is rejected by the typed config
        slam_main([f"sequence={tiny}", "+runtime.backend.window_sise=3"])
    assert e.value.code == 2 and "unknown setting runtime.backend.window_sise" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        eval_main(["trajectory", "est=a.txt"])
    assert "gt=" in capsys.readouterr().err


def test_rerun_recording(tiny, tmp_path):
    pytest.importorskip("rerun")
    m = run_sequence(read_euroc(tiny), tmp_path / "rr", progress=False, max_frames=80, viz="rerun", plot=False)
    assert (tmp_path / "rr" / "slam.rrd").stat().st_size > 10_000 and m["frames"] == 80


def test_the_time_offset_option_moves_the_stamps_by_its_estimate(tiny, tmp_path):
    """``runtime.intrinsics.time_offset``: the camera-IMU offset estimated with the intrinsics, the trajectory on
    the IMU's clock. This sequence renders no camera offset; the IMU factors hold each sample over the next 5 ms,
    half a period behind the instantaneous samples, so the offset the system needs is about +2.5 ms."""
    from apps.slam import _summary
    from runtime.calibration import IntrinsicsConfig

    cfg = SlamConfig(intrinsics=IntrinsicsConfig(time_offset=True))
    m = run_sequence(read_euroc(tiny), tmp_path / "out", cfg, progress=False, plot=False)
    intr = m["intrinsics"]
    d, sd = intr["time_offset_s"], intr["std"]["time_offset_s"]
    assert intr["refined"] and 0 < sd < 2e-3, intr
    assert abs(d - 0.0025) < 4 * sd + 1e-3, intr
    ts, _ = read_tum(tmp_path / "out" / "trajectory.txt")
    frames = read_euroc(tiny).frame_ts
    moved = np.round((ts - int(round(d * 1e9))) / 1e3).astype(np.int64) * 1000  # TUM keeps 9 decimals: ns
    assert np.isin(moved, frames).all() and m["ate_se3_rmse_m"] < 0.05
    assert f"camera-IMU time offset {1e3 * d:+.1f} ms" in _summary(m, tmp_path / "out", False)


class _CountingSequence:
    """Frames of 100 bytes each; counts the decodes; frame 3 is unreadable."""

    def __init__(self):
        self.decoded = []

    def image(self, i):
        self.decoded.append(i)
        if i == 3:
            raise OSError("corrupt")
        return np.full((10, 10), i, np.uint8)


def test_image_cache_gives_the_first_passs_images_to_the_run_once_within_its_bound():
    seq = _CountingSequence()
    cache = ImageCache(max_bytes=400)  # room for 4 frames
    first = [cache.keep(seq, i) for i in range(6)]
    assert len(cache) == 4
    assert [e is None for _, e in first] == [True, True, True, False, True, True]
    again = [cache.take(seq, i) for i in range(8)]
    # frames 0, 1, 2 and 4 come from memory (the same arrays); 3 (unreadable) and 5 (over the bound) are read again
    assert seq.decoded == [0, 1, 2, 3, 4, 5, 3, 5, 6, 7]
    assert all(again[i][0] is first[i][0] for i in (0, 1, 2, 4))
    assert all(int(again[i][0][0, 0]) == i for i in (0, 1, 2, 4, 5, 6, 7))
    assert again[3][0] is None and "corrupt" in again[3][1] and len(cache) == 0
    cache.take(seq, 0)  # taken once: the next read decodes again, and nothing is kept any more
    assert seq.decoded[-1] == 0 and len(cache) == 0


def test_a_refined_run_decodes_each_image_once(tiny, tmp_path, monkeypatch):
    """The first pass covers the whole 10 s here; the run takes its images from memory instead of decoding them
    again (without the cache: 400 decodes of the 200 frames)."""
    from runtime.io.euroc import EurocSequence

    decoded, image = [], EurocSequence.image
    monkeypatch.setattr(EurocSequence, "image", lambda self, i: decoded.append(i) or image(self, i))
    m = run_sequence(read_euroc(tiny), tmp_path / "out", SlamConfig(), progress=False, plot=False)
    assert m["intrinsics"]["first_pass_frames"] == m["frames"] == 200
    assert sorted(decoded) == list(range(200))


def test_the_summary_says_how_the_run_went():
    """The console summary's story line, from metrics.json's fields (known answer); none before a start."""
    from apps.slam import _story

    m = {
        "initialisation": {"method": "hover", "t_s": 101.1, "after_s": 1.1},
        "restarts": [
            {"t_s": 104.1, "why": "after a start turning in place"},
            {"t_s": 109.15, "why": "after a loss with tracks in view"},
        ],
        "frame_status": {"tracking": 400, "imu_backfill": 165, "building": 30, "coasting": 12},
        "from_start": {"left_out_imu_max_s": 8.2},
        "relocalisations": [{"lost_s": 3.0}],
        "segments": [{"segment": 0}, {"segment": 1}],
    }
    assert _story(m) == (
        "  started (hover) 1.10 s in; restarted at 4.10 s (after a start turning in place); restarted at 9.15 s "
        "(after a loss with tracks in view); 165 frames before a (re)start posed by the IMU alone (up to 8.2 s); "
        "30 frames on the IMU before visual tracking was acquired; 12 frames coasting on the IMU; "
        "1 relocalisation(s); 2 segments (reset after a divergence or an IMU gap)"
    )
    assert _story({"initialisation": None}) is None


def test_peak_memory_is_the_runs_own(tiny, tmp_path):
    """``peak_rss_mb`` is the run's peak: 1 GiB held and freed by this process just before the run is not in it
    (Linux resets the high-water mark at the run's start), yet the figure is at least the memory the process held
    when the run began."""
    import resource
    import sys

    if sys.platform != "linux":
        pytest.skip("the run's own peak needs Linux's /proc/self/clear_refs")

    def rss_mb() -> float:
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise AssertionError("no VmRSS in /proc/self/status")

    blob = np.ones(2**30 // 8)  # 1 GiB, touched
    held = rss_mb()
    del blob
    before = rss_mb()
    assert held - before > 900
    m = run_sequence(read_euroc(tiny), tmp_path / "out", progress=False, plot=False, max_frames=60)
    assert m["peak_rss_scope"] == "run"
    assert before - 1 <= m["peak_rss_mb"] < held - 900
    assert m["peak_rss_mb"] <= resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 + 1
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["peak_rss_mb"] == m["peak_rss_mb"]


def test_the_summary_gives_the_peak_memory_and_the_dense_backlog_left_at_the_last_frame(tmp_path):
    """The console summary's memory and later-work lines (known answers); no backlog line when none was left."""
    from apps.slam import _summary

    m = {"frames": 10, "frames_with_pose": 9, "keyframes": 3, "map_points": 40, "fps": 21.04, "peak_rss_mb": 812.4}
    m |= {"dense_later_jobs_at_last_frame": 7, "dense_later_jobs_peak": 12, "dense_later_work_after_last_frame_s": 1.26}
    text = _summary(m, tmp_path, True)
    assert "21.0 frames/s, peak memory 812 MiB" in text
    assert (
        "the network thread was 7 jobs of later work behind at the last frame (map codes, depth metrics, fusion; "
        "at most 12): 1.3 s to finish them, counted in frames/s" in text
    )
    m["dense_later_jobs_at_last_frame"] = 0
    assert "later work" not in _summary(m, tmp_path, True)
    assert "after the intrinsics' first pass" not in text  # no first pass ran
    m |= {"intrinsics": {"first_pass_frames": 301}, "fps_frame_loop": 35.46}
    assert "21.0 frames/s (35.5 after the intrinsics' first pass), peak memory 812 MiB" in _summary(m, tmp_path, True)
