"""benchmarks/ablate.py: the paired summary (known answers) and the runs' orchestration, with a stand-in dit-slam
that writes a metrics.json whose ATE its overrides set (no SLAM is run)."""

from __future__ import annotations

import json
import math
import stat
import sys
from pathlib import Path

import pytest

from benchmarks.ablate import family, main, slam_command, summarise


def _row(seq, system, arm, se3, sim3=None, posed=600, cpu=10.0, complete=True):
    return {
        "sequence": seq,
        "system": system,
        "arm": arm,
        "complete": complete,
        "se3_m": se3,
        "sim3_m": se3 if sim3 is None else sim3,
        "frames": 600,
        "frames_with_pose": posed,
        "cpu_s": cpu,
        "first_pass_s": None,
    }


def test_family_of_the_sequence_names():
    assert [family(s) for s in ("flight_s70", "flight-ideal_s0", "mh05", "mh05_s3")] == [
        "flight",
        "flight-ideal",
        "mh05",
        "mh05",
    ]


def test_slam_command_names_the_system_and_appends_the_overrides():
    cmd = slam_command("dit-slam", Path("S"), Path("O"), "sparse", ["a.b=1"])
    assert cmd == ["dit-slam", "sequence=S", "out=O", "progress=false", "dense=false", "a.b=1"]
    assert "dense=true" in slam_command("dit-slam", Path("S"), Path("O"), "dense", [])
    with pytest.raises(ValueError, match="not one of"):
        slam_command("dit-slam", Path("S"), Path("O"), "both", [])


def test_summary_pairs_each_arm_with_the_baseline_known_answers():
    runs = [
        _row("flight_s1", "sparse", "B", 0.010, cpu=10.0),
        _row("flight_s1", "sparse", "F", 0.012, cpu=8.0),
        _row("flight_s2", "sparse", "B", 0.020, cpu=10.0),
        _row("flight_s2", "sparse", "F", 0.016, cpu=9.0),
        _row("mh05_s1", "sparse", "B", 0.040, sim3=0.030, cpu=10.0),
        _row("mh05_s1", "sparse", "F", 0.060, sim3=0.020, posed=590, cpu=7.0),
        _row("mh05_s2", "sparse", "B", 1.5),  # its pair is incomplete: left out
        _row("mh05_s2", "sparse", "F", 0.01, complete=False),
    ]
    s = summarise(runs, "B")["sparse/F"]
    assert s["pairs"] == 3
    # SE(3) differences +2, -4, +20 mm: mean 6, sample sd sqrt(156), standard error sqrt(156 / 3)
    assert s["se3_mm"] == [6.0, round(math.sqrt(156 / 3), 2)] and s["se3_lower"] == 1
    assert s["sim3_mm"][0] == pytest.approx((2 - 4 - 10) / 3, abs=0.01) and s["sim3_lower"] == 2
    assert s["se3_mm_by_family"]["flight"] == {"mean_se": [-1.0, 3.0], "n": 2}
    assert s["se3_mm_by_family"]["mh05"] == {"mean_se": [20.0, None], "n": 1}
    assert s["mh05_at_or_under_0.05m"] == {"baseline": 1, "arm": 0, "pairs": 1}
    assert s["fewer_frames_posed"] == 1 and s["diverged"] == {"baseline": 0, "arm": 0}
    assert s["cpu_ratio_median"] == 0.8 and s["first_pass_ratio_median"] is None


FAKE_SLAM = """
import json, sys
from pathlib import Path
kv = dict(a.split("=", 1) for a in sys.argv[1:])
out = Path(kv["out"])
out.mkdir(parents=True, exist_ok=True)
with open(Path(kv["sequence"]).parent / "calls.txt", "a") as f:
    f.write(" ".join(sys.argv[1:]) + "\\n")
print(f"first pass of {kv['sequence']}", file=sys.stderr)
if kv.get("fake.fail") == "true":
    print("dit-slam: a bad setting", file=sys.stderr)
    sys.exit(2)
seed = int(Path(kv["sequence"]).name.rsplit("_s", 1)[1])
se3 = 0.01 * seed + float(kv.get("fake.offset", "0")) + (0.001 if kv["dense"] == "true" else 0.0)
m = {"complete": kv.get("fake.complete", "true") == "true", "frames": 100, "frames_with_pose": 100,
     "cpu_s": 5.0 + 100 * float(kv.get("fake.offset", "0")), "fps": 20.0,
     "ate_se3_rmse_m": se3, "ate_sim3_rmse_m": se3 / 2, "intrinsics": {"seconds_total": 1.0},
     "initialisation": {"method": "dynamic", "after_s": 0.1 * seed}}
(out / "metrics.json").write_text(json.dumps(m))
"""


@pytest.fixture
def fake(tmp_path):
    """A stand-in dit-slam, two 'rendered' sequences (enough of the layout for ensure_sequence) and a rule."""
    slam = tmp_path / "fake-dit-slam"
    slam.write_text(f"#!{sys.executable}\n{FAKE_SLAM}")
    slam.chmod(slam.stat().st_mode | stat.S_IXUSR)
    data = tmp_path / "seq"
    for name in ("flight_s1", "flight_s2"):
        (data / name / "mav0" / "cam0").mkdir(parents=True)
        (data / name / "mav0" / "cam0" / "data.csv").write_text("#\n")
    rule = tmp_path / "rule.md"
    rule.write_text("Adopt F if its paired SE(3) mean is below 0.\n")
    base = ["--rule", str(rule), "--sequences", "flight_s1", "flight_s2", "--systems", "sparse", "dense"]
    base += ["--data", str(data), "--work", str(tmp_path / "runs"), "--slam", str(slam)]
    return tmp_path, base, data / "calls.txt"


def test_ablation_runs_every_arm_writes_the_rule_and_summary_and_resumes(fake, capsys):
    tmp, base, calls = fake
    out = tmp / "result.json"
    argv = [*base, "--arm", "B", "", "--arm", "F", "fake.offset=0.002", "--out", str(out)]
    res = main(argv)
    assert len(calls.read_text().splitlines()) == 8  # 2 sequences x 2 systems x 2 arms
    saved = json.loads(out.read_text())
    assert saved["rule"].startswith("Adopt F") and saved["arms"] == {"B": "", "F": "fake.offset=0.002"}
    assert saved["baseline"] == "B" and len(saved["runs"]) == 8 and saved["summary"] == res["summary"]
    assert {(r["sequence"], r["init"], r["init_after_s"]) for r in saved["runs"]} == {
        ("flight_s1", "dynamic", 0.1),
        ("flight_s2", "dynamic", 0.2),
    }
    for system in ("sparse", "dense"):
        s = saved["summary"][f"{system}/F"]
        assert s["pairs"] == 2 and s["se3_mm"][0] == pytest.approx(2.0) and s["sim3_mm"][0] == pytest.approx(1.0)
        assert s["cpu_ratio_median"] == pytest.approx(5.2 / 5.0, abs=1e-3) and s["first_pass_ratio_median"] == 1.0
    assert "sparse/F - B: 2 pairs, SE(3) 2.0" in capsys.readouterr().out
    log = tmp / "runs" / "flight_s2" / "dense" / "F" / "run.log"  # each run keeps its log
    assert log.read_text().startswith("first pass of ") and "flight_s2" in log.read_text()
    # the outcome written by hand is kept, and complete runs of the same command are not made again
    saved["outcome"] = "lost"
    out.write_text(json.dumps(saved))
    again = main(argv)
    assert len(calls.read_text().splitlines()) == 8 and again["outcome"] == "lost"
    assert "0 runs made, 8 kept" in capsys.readouterr().out
    # another command (a changed arm) is run again
    main([*base, "--arm", "B", "", "--arm", "F", "fake.offset=0.003", "--out", str(out)])
    assert len(calls.read_text().splitlines()) == 12
    assert json.loads(out.read_text())["summary"]["dense/F"]["se3_mm"][0] == pytest.approx(3.0)


def test_ablation_runs_an_incomplete_run_again_and_pairs_it_with_nothing(fake):
    tmp, base, calls = fake
    argv = [*base, "--arm", "B", "", "--arm", "I", "fake.complete=false", "--out", str(tmp / "r.json")]
    res = main(argv)
    assert len(calls.read_text().splitlines()) == 8 and res["summary"]["dense/I"]["pairs"] == 0
    main(argv)  # the baseline's complete runs are kept, the interrupted ones are made again
    assert len(calls.read_text().splitlines()) == 12


def test_ablation_reports_a_failed_run_and_leaves_it_out_of_the_pairs(fake, capsys):
    tmp, base, _ = fake
    res = main([*base, "--arm", "B", "", "--arm", "X", "fake.fail=true", "--out", str(tmp / "r.json")])
    failed = [r for r in res["runs"] if r["arm"] == "X"]
    assert len(failed) == 4 and all(r["error"] == "dit-slam: a bad setting" for r in failed)
    assert "dit-slam: a bad setting" in (tmp / "runs" / "flight_s1" / "sparse" / "X" / "run.log").read_text()
    assert res["summary"]["sparse/X"]["pairs"] == 0 and res["summary"]["sparse/X"]["se3_mm"] == [None, None]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--arm", "B", "", "--arm", "B", "x=1"], "each with its own name"),
        (["--arm", "B", ""], "at least two arms"),
        (["--arm", "B", "", "--arm", "F", "", "--sequences", "flight"], "PRESET_sSEED"),
    ],
)
def test_ablation_refuses_bad_arms_and_sequence_names(fake, capsys, extra, message):
    tmp, base, _ = fake
    with pytest.raises(SystemExit) as e:
        main([*base, *extra, "--out", str(tmp / "r.json")])
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_ablation_needs_its_rule_written_first(fake, capsys):
    tmp, base, _ = fake
    base[base.index("--rule") + 1] = str(tmp / "missing.md")
    with pytest.raises(SystemExit):
        main([*base, "--arm", "B", "", "--arm", "F", "", "--out", str(tmp / "r.json")])
    assert "write the rule before the runs" in capsys.readouterr().err


def test_a_run_that_fails_on_rerun_does_not_keep_the_earlier_runs_figures(fake):
    tmp, base, _ = fake
    out = ["--out", str(tmp / "r.json")]
    assert main([*base, "--arm", "B", "", "--arm", "F", "fake.offset=0.002", *out])["summary"]["dense/F"]["pairs"] == 2
    res = main([*base, "--arm", "B", "", "--arm", "F", "fake.offset=0.002 fake.fail=true", *out])
    failed = [r for r in res["runs"] if r["arm"] == "F"]
    assert all(not r["complete"] and r["se3_m"] is None and r["error"] for r in failed)
    assert res["summary"]["dense/F"]["pairs"] == 0
