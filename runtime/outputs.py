"""The output folder of a run: checked before any work, owned files cleared, every file written atomically.

A run writes ``metrics.json`` first as a stub ``{"run_id": ..., "complete": false}`` and last in full, so a
folder always says which run wrote it and whether that run finished. Files are written to a hidden temporary
name beside their final one and renamed into place (``os.replace`` is atomic within a folder): a reader sees the
old file, the new one, or none, never a truncated one. Folders (``keyframe_depth/``) are filled under a hidden
temporary name and renamed into place the same way (:func:`atomic_folder`).

>>> import tempfile
>>> d = Path(tempfile.mkdtemp())
>>> atomic_text(d / "a.txt", "hello").read_text()
'hello'
>>> sorted(p.name for p in d.iterdir())
['a.txt']
"""

from __future__ import annotations

import json
import os
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from runtime.errors import UsageError

__all__ = [
    "RUN_OUTPUTS",
    "SLAM_OUTPUTS",
    "atomic_folder",
    "atomic_text",
    "atomic_write",
    "check_writable",
    "new_run_id",
    "prepare_run_dir",
]

#: What every ``dit-slam`` run writes into its output folder (``slam.rrd`` with ``viz=rerun``).
RUN_OUTPUTS = (
    "trajectory.txt",
    "frames.csv",
    "keyframes.txt",
    "sparse_map.ply",
    "metrics.json",
    "trajectory_top.png",
    "slam.rrd",
)
#: Everything ``dit-slam`` writes into its output folder (cleared before a new run writes there).
SLAM_OUTPUTS = RUN_OUTPUTS + (
    "dense_map.ply",
    "dense_map.png",
    "keyframe_depth.png",
    "dense_mesh.ply",
    "keyframe_depth",
)


def new_run_id() -> str:
    """A run id: UTC time to the second and 8 random hex digits (sortable, unique)."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + uuid.uuid4().hex[:8]


def _tmp_name(path: Path) -> Path:
    # Keep the suffix: writers such as matplotlib choose the format from it.
    return path.with_name(f".{path.stem}.partial-{os.getpid()}-{uuid.uuid4().hex[:6]}{path.suffix}")


def atomic_write(path: str | Path, writer: Callable[[Path], object]) -> Path:
    """Call ``writer(tmp)`` to write a temporary file beside ``path``, then rename it to ``path``."""
    path = Path(path)
    tmp = _tmp_name(path)
    try:
        writer(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_folder(path: str | Path, writer: Callable[[Path], object]) -> Path:
    """Call ``writer(tmp)`` to fill a temporary folder beside ``path``, then rename it to ``path``.

    An earlier folder at ``path`` is kept until the new one is whole: it is renamed aside (a hidden temporary
    name) just before the new one is renamed into place, and removed after. If ``writer`` fails or is
    interrupted, the temporary folder is removed and ``path`` is left as it was.
    """
    path = Path(path)
    tmp = _tmp_name(path)
    old = None
    try:
        tmp.mkdir()
        writer(tmp)
        if path.is_dir() and not path.is_symlink():
            old = _tmp_name(path)
            os.replace(path, old)
        elif path.exists() or path.is_symlink():
            path.unlink()
        os.replace(tmp, path)
    except BaseException:
        if old is not None and not path.exists():  # interrupted between the two renames: put the old one back
            os.replace(old, path)
            old = None
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    return path


def atomic_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (flushed to disk before the rename)."""

    def write(tmp: Path) -> None:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    return atomic_write(path, write)


def check_writable(out: str | Path, key: str = "out") -> Path:
    """Create folder ``out`` and prove it is writable (a probe file is created and removed).

    Raises:
        UsageError: ``out`` is a file, or cannot be created or written; the message names the key and path.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{key}={out} is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-probe-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise UsageError(f"{key}={out} is not writable: {e.strerror or e}") from e
    return out


def prepare_run_dir(
    out: str | Path, owned: tuple[str, ...] = SLAM_OUTPUTS, key: str = "out"
) -> tuple[str, list, str | None]:
    """Make ``out`` ready for a new run: writable, this command's earlier outputs removed, a stub metrics.json.

    Returns:
        ``(run_id, removed, previous)``: the new run's id, the names of the earlier outputs removed (other files
        in ``out`` are left alone) and the earlier run's id (None when unknown).
    """
    out = check_writable(out, key)
    previous = None
    try:
        previous = json.loads((out / "metrics.json").read_text()).get("run_id")
    except (OSError, ValueError, AttributeError):
        pass
    removed = []
    for name in owned:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
        else:
            continue
        removed.append(name)
    for stale in out.glob(".*.partial-*"):  # temporary files and folders of a killed run
        if stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            stale.unlink(missing_ok=True)
    run_id = new_run_id()
    stub = {"run_id": run_id, "complete": False, "status": "running", "started_utc": run_id.split("-")[0]}
    atomic_text(out / "metrics.json", json.dumps(stub, indent=2))
    return run_id, removed, previous
