"""One synthetic sequence as an ASL folder, a ROS1 bag and a ROS2 bag gives byte-identical trajectories."""

import pytest

pytest.importorskip("rosbags")
sim_euroc = pytest.importorskip("sim.euroc")

from apps.slam import main as slam_main  # noqa: E402
from runtime.io.sequence import open_sequence  # noqa: E402
from runtime.run import run_sequence  # noqa: E402
from sim.bag import write_bag  # noqa: E402


@pytest.mark.slow
def test_asl_ros1_and_ros2_give_byte_identical_trajectories(tmp_path):
    asl = sim_euroc.write_euroc_sequence(
        tmp_path / "asl", "textured", duration=4.5, seed=3, imu_noise=True, progress=False, scale=0.5, realism=False
    )
    inputs = {
        "asl": (asl, None),
        "ros1": (write_bag(asl, tmp_path / "seq.bag", "bag", calib_dir=tmp_path / "calib"), tmp_path / "calib"),
        "ros2": (write_bag(asl, tmp_path / "seq_ros2", "ros2"), tmp_path / "calib"),
    }
    traj = {}
    for name, (path, calib) in inputs.items():
        m = run_sequence(open_sequence(path, calib), tmp_path / f"out_{name}", progress=False, plot=False)
        assert m["frames"] == 90 and m["frames_with_pose"] > 20, (name, m.get("error"))
        traj[name] = (tmp_path / f"out_{name}" / "trajectory.txt").read_bytes()
    assert traj["ros1"] == traj["asl"]
    assert traj["ros2"] == traj["asl"]
    # the command line: dit-slam sequence=FILE.bag calib=DIR, the sparse system as above (it refines the intrinsics
    # first; the dense one does not)
    bag, calib = inputs["ros1"]
    slam_main([f"sequence={bag}", f"calib={calib}", f"out={tmp_path / 'cli'}", "progress=false", "dense=false"])
    assert (tmp_path / "cli" / "trajectory.txt").read_bytes() == traj["asl"]
