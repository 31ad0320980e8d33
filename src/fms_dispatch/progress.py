"""Progress lines of long work (a search's best so far, an experiment's steps).

They go to standard error, so that standard output carries only results (``fms solve ... | head -1`` reads the
result line), and they are never fatal: when their reader has left (a closed pipe), the work goes on silently
instead of ending without its result.
"""

from __future__ import annotations

import contextlib
import os
import sys

__all__ = ["say"]


def say(line: str) -> None:
    """Print ``line`` to standard error at once. If its reader has left, standard error goes nowhere from then on
    (each later line, and Python's flush at exit, would fail the same way)."""
    try:
        print(line, file=sys.stderr, flush=True)
    except BrokenPipeError:
        with contextlib.suppress(OSError, ValueError):  # (a stream without a file descriptor: nothing to redirect)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stderr.fileno())
            os.close(devnull)
