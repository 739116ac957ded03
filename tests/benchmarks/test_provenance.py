"""benchmarks.common.run_provenance: the machine / date / code lines the notebooks print."""

import re
import subprocess

import pytest

from benchmarks.common import run_provenance


def _git(repo, *args):
    subprocess.run(
        ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args], check=True, capture_output=True
    )


def test_run_provenance_names_the_commit_and_uncommitted_code(tmp_path):
    (tmp_path / "runtime").mkdir()
    (tmp_path / "runtime" / "a.py").write_text("x = 1\n")
    (tmp_path / "notes.txt").write_text("n\n")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "commit", "-q", "-m", "c")
    sha = subprocess.run(
        ["git", "-C", str(tmp_path), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    machine, date, code = run_provenance(tmp_path).splitlines()
    assert machine.startswith("machine    ") and " cores, load (" in machine
    assert re.fullmatch(r"date       \d{4}-\d\d-\d\d \d\d:\d\d UTC", date)
    assert code == f"code       commit {sha}"
    (tmp_path / "runtime" / "a.py").write_text("x = 2\n")
    (tmp_path / "notes.txt").write_text("m\n")  # outside the code paths: not listed
    assert run_provenance(tmp_path).splitlines()[2] == f"code       commit {sha} + uncommitted changes in runtime/a.py"


def test_run_provenance_without_a_repository(tmp_path):
    if subprocess.run(["git", "-C", str(tmp_path), "rev-parse"], capture_output=True).returncode == 0:
        pytest.skip("tmp_path lies inside a git repository")
    assert run_provenance(tmp_path).splitlines()[2] == "code       commit ?"
