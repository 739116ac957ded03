"""One error style for every command: an expected failure is one line naming the problem and exit status 2.

Libraries raise (``ValueError``, ``OSError`` and their subclasses such as :class:`UsageError`); the entry points
(``dit-slam``, ``dit-eval``, ``dit-export``, ``dit-sim``) catch these with :func:`report` and print
``<command>: <problem>`` on one line. ``--debug`` on the command line or ``HYDRA_FULL_ERROR=1`` in the environment
also prints the traceback. Anything else (a bug) keeps its traceback.

>>> args, debug = split_debug(["out=x", "--debug"])
>>> args, debug
(['out=x'], True)
>>> one_line(ValueError("bad\\n  value"))
'bad value'
"""

from __future__ import annotations

import os
import sys
import traceback

EXIT_USAGE = 2

__all__ = ["EXIT_USAGE", "EXPECTED", "UsageError", "one_line", "report", "split_debug"]


class UsageError(ValueError):
    """An expected failure of a command (bad setting, unreadable or unwritable path): one line, exit status 2."""


#: Exceptions that are expected failures (bad input, missing or unwritable files), not bugs.
EXPECTED: tuple[type[BaseException], ...] = (ValueError, OSError, EOFError)


def split_debug(args: list[str]) -> tuple[list[str], bool]:
    """``args`` without ``--debug``, and whether tracebacks are wanted (``--debug`` or ``HYDRA_FULL_ERROR=1``)."""
    rest = [a for a in args if a != "--debug"]
    return rest, len(rest) != len(args) or os.environ.get("HYDRA_FULL_ERROR") == "1"


def one_line(e: BaseException) -> str:
    """The message of ``e`` on one line (whitespace runs collapsed), or its type name when it has none."""
    text = " ".join(str(e).split())
    return text or type(e).__name__


def report(command: str, e: BaseException, debug: bool = False) -> int:
    """Print ``command: problem`` (with the traceback when ``debug``) to stderr; returns :data:`EXIT_USAGE`."""
    if debug:
        traceback.print_exception(e, file=sys.stderr)
    print(f"{command}: {one_line(e)}", file=sys.stderr)
    return EXIT_USAGE
