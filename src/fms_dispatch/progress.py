"""Output that never ends the work: progress lines, and standard streams whose reader may leave.

Progress lines of long work (a search's best so far, an experiment's steps) go to standard error, so that standard
output carries only results (``fms solve ... | head -1`` reads the result line). A closed pipe on either stream
(``| head``, ``2>&1 | head``) must not end a command half-way: it ended a solve before its ``--out`` file was written,
with exit code 0. :func:`say` writes a progress line; :func:`surviving_streams` makes every write of a command
survive its reader (``fms`` runs each command inside it).
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, Iterator, TextIO

__all__ = ["say", "surviving_streams", "send_nowhere"]


def send_nowhere(stream: Any) -> None:
    """Send ``stream``'s file descriptor to the null device (each later write, and Python's flush at exit, would
    fail the same way)."""
    with contextlib.suppress(OSError, ValueError, AttributeError):  # (a stream without a file descriptor)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, stream.fileno())
        os.close(devnull)


def say(line: str) -> None:
    """Print ``line`` to standard error at once. If its reader has left, standard error goes nowhere from then on."""
    try:
        print(line, file=sys.stderr, flush=True)
    except BrokenPipeError:
        send_nowhere(sys.stderr)


class _Surviving:
    """A text stream whose writes survive a reader that left: the stream goes nowhere from then on."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            send_nowhere(self._stream)
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            send_nowhere(self._stream)
            with contextlib.suppress(BrokenPipeError, OSError, ValueError):
                self._stream.flush()  # (what was buffered now goes to the null device)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


@contextlib.contextmanager
def surviving_streams() -> Iterator[None]:
    """While entered, ``sys.stdout`` and ``sys.stderr`` survive a reader that leaves (see the module docstring)."""
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _Surviving(out), _Surviving(err)  # type: ignore[assignment]
    try:
        yield
    finally:
        with contextlib.suppress(BrokenPipeError, OSError, ValueError):
            sys.stdout.flush()
        sys.stdout, sys.stderr = out, err
