"""dit-slam's outputs: checked before any work, never mixed with an earlier run, unique default names,
interruption writes what was processed, and one-line errors (exit status 2) for the expected failures."""

import json
import os
import signal

import pytest

from apps.slam import main as slam_main
from runtime.calibration import IntrinsicsConfig
from runtime.io.euroc import read_euroc
from runtime.run import run_sequence
from runtime.slam import SlamConfig


def _fails(capsys, args):
    with pytest.raises(SystemExit) as e:
        slam_main([*args, "progress=false"])
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


@pytest.mark.parametrize(
    "arg, message",
    [
        ("viz=foo", "viz='foo': expected none or rerun"),
        ("max_frames=-1", "max_frames=-1: expected a positive number of frames"),
        ("start_s=-1", "start_s=-1: expected seconds >= 0"),
        ("start_s=100", "start_s=100: leaves 0 of the sequence's 80 frames"),
        ("runtime.backend.window_size=0", "setting runtime.backend.window_size=0 is out of range: must be >= 2"),
        ("runtime.features.max_features=0", "setting runtime.features.max_features=0 is out of range: must be >= 1"),
        ("out=/proc/x", "out=/proc/x is not writable"),
    ],
)
def test_bad_arguments_fail_in_one_line_before_any_work(tiny_seq, capsys, arg, message):
    assert message in _fails(capsys, [f"sequence={tiny_seq}", arg])


def test_out_that_is_a_file_fails_in_one_line(tiny_seq, tmp_path, capsys):
    f = tmp_path / "f"
    f.write_text("x")
    assert f"out={f} is a file, not a folder" in _fails(capsys, [f"sequence={tiny_seq}", f"out={f}"])
    assert f.read_text() == "x"


def test_debug_shows_the_traceback(tiny_seq, capsys):
    with pytest.raises(SystemExit) as e:
        slam_main([f"sequence={tiny_seq}", "viz=foo", "--debug"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" in err and err.strip().endswith("expected none or rerun")


def test_a_new_run_removes_the_earlier_runs_outputs_and_says_so(tiny_seq, tmp_path, capsys):
    out = tmp_path / "o"
    (out / "keyframe_depth").mkdir(parents=True)
    (out / "dense_map.ply").write_text("old dense map")
    (out / "dense_map.png").write_text("old picture")
    (out / "keyframe_depth.png").write_text("old depth picture")
    (out / "dense_mesh.ply").write_text("old mesh")
    (out / "notes.txt").write_text("not ours")
    slam_main([f"sequence={tiny_seq}", f"out={out}", "progress=false", "dense=false"])  # a sparse run writes none
    text = capsys.readouterr().out
    assert "removed the outputs of the earlier run" in text
    assert "dense_map.ply, dense_map.png, keyframe_depth.png, dense_mesh.ply, keyframe_depth" in text
    old = ("dense_map.ply", "dense_map.png", "keyframe_depth.png", "dense_mesh.ply", "keyframe_depth")
    assert not any((out / n).exists() for n in old)
    assert (out / "notes.txt").read_text() == "not ours"
    m = json.loads((out / "metrics.json").read_text())
    assert m["complete"] is True and m["run_id"] and m["frames_processed"] == m["frames"] == 80
    assert m["frames_with_pose"] > 0


def test_a_run_started_later_poses_only_the_frames_from_its_start(tiny_seq, tmp_path, capsys):
    from runtime.io.euroc import read_euroc
    from runtime.io.tum import read_tum

    out = tmp_path / "o"
    slam_main([f"sequence={tiny_seq}", f"out={out}", "progress=false", "dense=false", "start_s=1.0"])
    assert "(60 frames, from 1 s (frame 20)" in capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert m["start_s"] == 1.0 and m["frames"] == m["frames_processed"] == 60
    assert m["fps_frame_loop"] >= m["fps"] > 0  # the frame loop alone: the intrinsics' first pass left out
    ts, _ = read_tum(out / "trajectory.txt")
    first = int(read_euroc(tiny_seq).frame_ts[20])
    assert ts.size > 0 and int(ts.min()) >= first


def test_default_outputs_differ_for_two_sequences_with_the_same_folder_name(tmp_path):
    from apps.slam import default_out

    a, b = default_out(tmp_path / "x" / "seq"), default_out(tmp_path / "y" / "seq")
    assert a != b and a.name.startswith("seq-") and b.name.startswith("seq-")
    assert default_out(tmp_path / "x" / "seq") == a


def test_sigint_stops_and_writes_what_was_processed(tiny_seq, tmp_path):
    seq = read_euroc(tiny_seq)
    read = seq.image

    def image(i):  # Ctrl-C arrives while frame 30 is read (the prefetch runs 3 frames ahead)
        if i == 30:
            os.kill(os.getpid(), signal.SIGINT)
        return read(i)

    seq.image = image
    out = tmp_path / "o"
    cfg = SlamConfig(intrinsics=IntrinsicsConfig(refine=False))  # the signal comes in the main pass
    m = run_sequence(seq, out, cfg, progress=False, plot=False)
    assert m["complete"] is False and m["interrupted_by"] == "SIGINT"
    assert 26 <= m["frames_processed"] <= 31 < m["frames"] == len(seq)
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["complete"] is False and on_disk["frames_processed"] == m["frames_processed"]
    assert (out / "trajectory.txt").is_file() and (out / "sparse_map.ply").is_file()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


def test_sigint_in_the_intrinsics_pass_stops_the_run(tiny_seq, tmp_path):
    seq = read_euroc(tiny_seq)
    read = seq.image

    def image(i):  # Ctrl-C during the first (intrinsics) pass: no main pass, the written camera kept
        if i == 10:
            os.kill(os.getpid(), signal.SIGINT)
        return read(i)

    seq.image = image
    m = run_sequence(seq, tmp_path / "o", progress=False, plot=False)
    assert m["complete"] is False and m["interrupted_by"] == "SIGINT" and m["frames_processed"] == 0
    assert m["intrinsics"] == {"refined": False, "reason": "interrupted by SIGINT"}
    assert json.loads((tmp_path / "o" / "metrics.json").read_text())["complete"] is False


def test_a_killed_run_leaves_a_metrics_stub_marked_incomplete(tmp_path):
    from runtime.outputs import prepare_run_dir

    out = tmp_path / "o"
    run_id, removed, previous = prepare_run_dir(out)
    m = json.loads((out / "metrics.json").read_text())
    assert m == {"run_id": run_id, "complete": False, "status": "running", "started_utc": run_id.split("-")[0]}
    assert removed == [] and previous is None
    run2, removed, previous = prepare_run_dir(out)
    assert removed == ["metrics.json"] and previous == run_id != run2


def test_atomic_write_never_leaves_a_truncated_file(tmp_path):
    from runtime.outputs import atomic_text, atomic_write

    p = atomic_text(tmp_path / "t.txt", "old, whole")

    def half(tmp):
        tmp.write_text("new, but ha")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(p, half)
    assert p.read_text() == "old, whole" and [x.name for x in tmp_path.iterdir()] == ["t.txt"]
