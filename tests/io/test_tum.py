"""TUM trajectory writer/reader: exact ns round trip, quaternion order x,y,z,w, comments, errors."""

from __future__ import annotations

import re

import numpy as np
import pytest

from runtime.geometry import make_T, so3_exp
from runtime.io import TumFormatError, read_tum, write_tum
from runtime.io.tum import ns_to_seconds_str, seconds_str_to_ns

T0 = 1403636579763555584


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([make_T(so3_exp(rng.normal(size=3)), rng.normal(scale=5, size=3)) for _ in range(n)])


def test_round_trip_is_exact_in_time(tmp_path):
    ts = (
        T0 + np.arange(50, dtype=np.int64) * 50_000_001 + 7
    )  # odd nanoseconds a float64 of seconds would lose
    T = _poses(50)
    p = write_tum(tmp_path / "sub" / "traj.txt", ts, T)
    ts2, T2 = read_tum(p)
    assert ts2.dtype == np.int64
    np.testing.assert_array_equal(ts2, ts)
    np.testing.assert_allclose(T2, T, atol=2e-9)


def test_file_layout_and_quaternion_order(tmp_path):
    Rz90 = so3_exp([0, 0, np.pi / 2])
    p = write_tum(tmp_path / "t.txt", np.array([T0]), make_T(Rz90, [1, 2, 3])[None])
    lines = p.read_text().splitlines()
    assert lines[0].startswith("#")
    fields = lines[1].split()
    assert len(fields) == 8
    assert fields[0] == "1403636579.763555584"  # seconds, 9 decimals
    np.testing.assert_allclose(
        [float(x) for x in fields[1:]], [1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-9
    )


def test_reads_comments_commas_and_any_seconds_notation(tmp_path):
    c = np.sqrt(0.5)
    p = tmp_path / "t.txt"
    p.write_text(
        f"# a comment\n\n1.5 0 0 0 0 0 0 1\n  # indented comment\n1.4036365797635556e9,1,2,3,0,0,{c},{c}\n"
        "1403636580 0 0 0 0 0 0 2\n"  # integer seconds; a non-unit quaternion is normalised
    )
    ts, T = read_tum(p)
    np.testing.assert_array_equal(ts, [1_500_000_000, 1_403_636_579_763_555_600, 1_403_636_580_000_000_000])
    np.testing.assert_allclose(T[1][:3, :3], so3_exp([0, 0, np.pi / 2]), atol=1e-15)
    np.testing.assert_array_equal(T[1][:3, 3], [1, 2, 3])
    np.testing.assert_allclose(T[2], np.eye(4), atol=1e-15)


def test_seconds_strings():
    for t in (0, 1, 999_999_999, T0, -1_500_000_000, -5):
        assert seconds_str_to_ns(ns_to_seconds_str(t)) == t
    assert ns_to_seconds_str(1_500_000_000) == "1.500000000"
    assert seconds_str_to_ns("0.0000000015") == 2  # rounds half to even at the ns


def test_evo_reads_our_files(tmp_path):
    """Parity with the evaluator we use: evo's TUM reader sees the same poses."""
    file_interface = pytest.importorskip("evo.tools.file_interface")
    ts = T0 + np.arange(5, dtype=np.int64) * 50_000_000
    T = _poses(5, seed=3)
    traj = file_interface.read_tum_trajectory_file(str(write_tum(tmp_path / "t.txt", ts, T)))
    np.testing.assert_allclose(traj.timestamps, ts / 1e9, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.stack(traj.poses_se3), T, atol=1e-8)


def test_empty_trajectory(tmp_path):
    p = write_tum(tmp_path / "e.txt", np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    ts, T = read_tum(p)
    assert ts.shape == (0,) and T.shape == (0, 4, 4)


@pytest.mark.parametrize(
    "body,fragment",
    [
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", "line 3: expected 8 columns"),
        ("1 0 0 0 0 0 0 1\n2 0 0 x 0 0 0 1\n", "line 3: non-numeric"),
        ("1 0 0 0 0 0 0 1\nabc 0 0 0 0 0 0 1\n", "line 3: timestamp 'abc'"),
        ("1 0 0 0 0 0 0 1\n2 0 0 nan 0 0 0 1\n", "line 3: NaN"),
        ("2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "line 3: timestamps not strictly increasing"),
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 0\n", "line 3: zero quaternion"),
    ],
)
def test_bad_files_name_file_and_line(tmp_path, body, fragment):
    p = tmp_path / "bad.txt"
    p.write_text("# header\n" + body)
    with pytest.raises(TumFormatError, match=re.escape(str(p)) + ".*" + re.escape(fragment)):
        read_tum(p)


def test_missing_file(tmp_path):
    with pytest.raises(TumFormatError, match=re.escape(str(tmp_path / "no.txt")) + ": missing file"):
        read_tum(tmp_path / "no.txt")


def test_writer_checks_inputs(tmp_path):
    T = _poses(2)
    with pytest.raises(ValueError, match="integer"):
        write_tum(tmp_path / "a.txt", np.array([1.0, 2.0]), T)
    with pytest.raises(ValueError, match=r"shape \(3, 4, 4\)"):
        write_tum(tmp_path / "a.txt", np.arange(3), T)
    bad = T.copy()
    bad[1, 0, 0] += 0.1
    with pytest.raises(ValueError, match="pose 1 .*non-orthonormal"):
        write_tum(tmp_path / "a.txt", np.arange(2), bad)
    bad = T.copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="pose 0 .*not finite"):
        write_tum(tmp_path / "a.txt", np.arange(2), bad)
