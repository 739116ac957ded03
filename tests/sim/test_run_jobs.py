"""The rendering process pool of sim/ (``sim.euroc.run_jobs``): results, errors, and a dying worker."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from sim.euroc import run_jobs

REPO = Path(__file__).resolve().parents[2]

#: A caller's script: run_jobs over two processes, with or without the ``__main__`` guard spawn needs.
SCRIPT = """
import sys
sys.path.insert(0, {repo!r})
from sim.euroc import run_jobs
{guard}
    run_jobs(["ab", "abc"], int, (), len, 2, False, "test", 5)
    print("rendered")
"""


def _script(tmp_path: Path, guarded: bool) -> subprocess.CompletedProcess:
    guard = 'if __name__ == "__main__":' if guarded else "if True:"
    path = tmp_path / "caller.py"
    path.write_text(textwrap.dedent(SCRIPT).format(repo=str(REPO), guard=guard))
    return subprocess.run([sys.executable, str(path)], capture_output=True, text=True, timeout=120, cwd=tmp_path)


def test_a_guarded_script_renders_over_two_processes(tmp_path):
    r = _script(tmp_path, guarded=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "rendered"


def test_a_script_without_the_main_guard_fails_at_once_and_says_why(tmp_path):
    # Each spawned worker imports the script again and dies starting its own pool; multiprocessing.Pool started
    # new workers for ever (the caller hung with no message). Now the caller stops with the remedy.
    r = _script(tmp_path, guarded=False)
    assert r.returncode != 0
    assert "rendered" not in r.stdout
    assert "RuntimeError" in r.stderr and '__name__ == "__main__"' in r.stderr, r.stderr[-2000:]


def test_a_failing_job_raises_its_own_error():
    with pytest.raises(TypeError):
        run_jobs([1, "x"], int, (), abs, 2, False, "test", 2)
