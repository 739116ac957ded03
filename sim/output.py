"""The output folder of a ``dit-sim`` job (``euroc``, its bags, ``nyu``, ``imu``): one owner, never half-written.

Every job writes through :func:`sim_output`:

* earlier ``dit-sim`` output in the folder is replaced, anything else is refused (:func:`prepare_output`);
* ``sim_info.json`` says ``"complete": false`` while the job runs and is replaced by the full summary (which has
  no ``complete`` key) as the last step (:func:`write_info`), so a run killed outright (SIGKILL, power loss)
  leaves a folder marked partial, which the next run replaces;
* an interrupted or failed run (Ctrl-C, SIGTERM, an exception) removes its own partial output before the
  exception goes on: a rerun into the same folder starts clean.

Single files (images, h5 frames, ``sim_info.json``) are written under a temporary name and renamed
(:func:`runtime.outputs.atomic_write`), so no file is ever present half-written under its final name.

>>> import tempfile
>>> d = Path(tempfile.mkdtemp())
>>> with sim_output(d, ("data",), "demo") as out:
...     _ = (out / "data").mkdir()
...     earlier(out)
'partial'
>>> _ = write_info(d, {"generator": GENERATOR, "job": "demo"})
>>> earlier(d)
'complete'
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from runtime.outputs import atomic_text

__all__ = ["GENERATOR", "earlier", "prepare_output", "remove_output", "sim_output", "write_info"]

GENERATOR = "dit-sim"
INFO = "sim_info.json"


def _read_info(out: Path) -> dict | None:
    try:
        info = json.loads((out / INFO).read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) and info.get("generator") == GENERATOR else None


def earlier(out: str | Path) -> str | None:
    """What a dit-sim job left in ``out``: ``"partial"`` (a run that did not finish), ``"complete"``, or None."""
    info = _read_info(Path(out))
    if info is None:
        return None
    return "partial" if info.get("complete", True) is False else "complete"


def prepare_output(out: Path, parts: tuple[str, ...]) -> None:
    """Create ``out``; remove earlier dit-sim output (``parts`` below ``out``) but never anything else.

    Raises:
        FileExistsError: ``out`` holds one of ``parts`` that dit-sim did not write (no ``sim_info.json``).
    """
    out.mkdir(parents=True, exist_ok=True)
    existing = [out / p for p in parts if (out / p).exists()]
    if not existing:
        return
    if _read_info(out) is None:
        raise FileExistsError(
            f"{existing[0]} exists and was not written by {GENERATOR} (no {out / INFO}); choose another output folder"
        )
    remove_output(out, parts)


def remove_output(out: Path, parts: tuple[str, ...]) -> None:
    """Remove ``parts`` below ``out`` and ``sim_info.json`` (what one dit-sim job owns there)."""
    for p in (*(out / q for q in parts), out / INFO):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def write_info(out: Path, info: dict) -> Path:
    """Write the final ``sim_info.json`` (atomically): the job's output is complete from here on."""
    return atomic_text(out / INFO, json.dumps(info, indent=2) + "\n")


@contextmanager
def sim_output(out: Path, parts: tuple[str, ...], job: str, **meta) -> Iterator[Path]:
    """Own ``parts`` of ``out`` for one run of ``job``: prepared, marked partial, removed if the run stops.

    Args:
        out: the output folder (created).
        parts: the files and folders the job writes below ``out`` (besides ``sim_info.json``).
        job: the job's name, recorded in the partial ``sim_info.json``.
        meta: further keys of the partial ``sim_info.json`` (e.g. preset, seed).

    Yields:
        ``out``. The body writes ``parts`` and ends with :func:`write_info`; any exception leaving the body
        (``KeyboardInterrupt`` included) removes ``parts`` and ``sim_info.json`` and is raised again.

    Raises:
        FileExistsError: ``out`` holds output that dit-sim did not write.
    """
    prepare_output(out, parts)
    partial = {"generator": GENERATOR, "job": job, "complete": False, **meta}
    write_info(out, partial)
    try:
        yield out
    except BaseException:  # interrupted or failed: remove this run's partial output
        remove_output(out, parts)
        raise
