"""Errors of the ASL (EuRoC) layout readers, shared by the sequence and the sensor.yaml readers."""

from __future__ import annotations

from pathlib import Path


class EurocFormatError(ValueError):
    """A file of an EuRoC-layout sequence is missing or malformed; the message names file and problem."""


class EurocWarning(UserWarning):
    """Recoverable oddity in an EuRoC-layout sequence (e.g. a ``data.csv`` row whose image is missing)."""


def read_text(path: Path) -> str:
    """The text of a sequence file; a missing or unreadable file raises naming it."""
    if not path.is_file():
        raise EurocFormatError(f"{path}: missing file")
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise EurocFormatError(f"{path}: cannot read ({e})") from e
