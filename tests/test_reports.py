"""reports/README.md is what reports/build.py generates from the committed results (it cannot drift)."""

import importlib.util
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _build_module():
    spec = importlib.util.spec_from_file_location("reports_build", REPO / "reports" / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _git(*args: str) -> str | None:
    if shutil.which("git") is None:
        return None
    r = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=False)
    return r.stdout.strip() if r.returncode == 0 else None


def test_committed_report_equals_the_generated_one():
    build = _build_module()
    if _git("rev-parse", "--is-inside-work-tree") != "true":
        pytest.skip("not a git checkout: the report's dates come from git")
    if _git("rev-parse", "--is-shallow-repository") == "true":
        pytest.skip("shallow clone: git cannot date the result files")
    sources = [p.relative_to(REPO).as_posix() for p in build.source_files()]
    dirty = _git("status", "--porcelain", "--", *sources)
    if dirty:
        pytest.skip(f"result files not committed yet ({dirty.splitlines()[0]} ...): commit, then run reports/build.py")
    text = build.build()
    assert "not committed" not in text
    assert (REPO / "reports" / "README.md").read_text() == text, (
        "reports/README.md is out of date: run python reports/build.py and commit it"
    )


def test_committed_peers_page_equals_the_generated_one():
    build = _build_module()
    page = build.peers_page()
    if page is None:
        pytest.skip("no benchmarks/results/peers.json")
    if _git("rev-parse", "--is-inside-work-tree") != "true" or _git("rev-parse", "--is-shallow-repository") == "true":
        pytest.skip("not a full git checkout: the page's date comes from git")
    if _git("status", "--porcelain", "--", "benchmarks/results/peers.json"):
        pytest.skip("peers.json not committed yet: commit, then run reports/build.py")
    assert "not committed" not in page
    assert (REPO / "reports" / "peers.md").read_text() == page, (
        "reports/peers.md is out of date: run python reports/build.py and commit it"
    )
    assert "peers.md" in build.build() and "peers.md" not in dict(build.records())


def test_report_helpers_known_answers():
    build = _build_module()
    assert build._mean_std([0.001, 0.003], 1, 1e3) == "2.0 ± 1.0"
    assert build._mean_std([float("nan"), 0.004], 1, 1e3) == "4.0"
    assert build._mean_std([float("nan")]) == "–"
    assert build._num(float("nan")) == "–" and build._num(0.12345, 2, 100, " %") == "12.35 %"
    assert build._rel_path("/any/where/benchmarks/results/models.json") == "benchmarks/results/models.json"
    assert build._rel_path("/tmp/x") == "/tmp/x"
    cfg = {"presets": ["a", "b"], "set": [], "duration": 60.0, "flag": True, "off": False, "none": None, "n": 3}
    spec = [("presets", "--presets"), ("set", "--set"), ("duration", "--duration"), ("flag", "--flag")]
    spec += [("off", "--off"), ("none", "--none"), ("n", "--n")]
    assert build._flags(cfg, spec) == ["--presets", "a", "b", "--duration", "60", "--flag", "--n", "3"]
    m = {"cpu": "CPU X", "cores": 2, "platform": "Linux", "torch": "2.13.0", "loadavg": [1.25, 1.0, 1.0]}
    assert build._machine(m) == "CPU X, 2 cores, Linux, torch 2.13.0, load 1.2 at the start"
    assert build._machine(None) == "not recorded"
    t = build._table(["a", "b"], [["1", "2"]])
    assert t == "| a | b |\n|---|---|\n| 1 | 2 |"


def test_the_hand_written_records_are_linked():
    build = _build_module()
    names = [name for name, _ in build.records()]
    assert {"ablations.md", "status.md"} <= set(names) and "README.md" not in names
    text = build.build()
    for name, title in build.records():
        assert f"[{title}]({name})" in text
