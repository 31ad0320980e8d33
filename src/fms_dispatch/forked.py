"""Work on another core: a function run in a forked copy of this process, its result sent back on a pipe.

A forked child starts as a copy of its parent in a few milliseconds (nothing is pickled on the way in: it reads
the parent's objects as they were at the fork) and sends back only its result. The agent node's live re-plans
(:mod:`fms_dispatch.agent_logic`) and a guided model's plan search beside its run (:mod:`fms_dispatch.rl.beside`)
run this way on Linux, where ``fork`` is the process start method; elsewhere they fall back to a thread or to
running in line.
"""

from __future__ import annotations

import os
import sys
from typing import Any, Callable

__all__ = ["FORK_AVAILABLE", "child_main", "Forked"]

#: whether work can run in a forked process here (Linux; macOS's fork is unsafe with its system libraries)
FORK_AVAILABLE = sys.platform.startswith("linux")


def child_main(fn: Callable[..., Any], args: tuple, conn: Any, parent: int) -> None:
    """The body of a forked child: ``fn(*args)``, its result (or its error's first line) sent on ``conn`` as
    ``("ok", value)`` or ``("error", text)``. A Ctrl-C meant for the parent is left to the parent (which ends this
    process); a parent gone meanwhile is no error.

    SIGTERM ends it (a ROS node's own handler, inherited through the fork, kept it alive: a node stopping during a
    re-plan waited for it at exit and was reported as not stopping cleanly), and so does its parent's end (a parent
    killed with SIGKILL left it searching on, at full CPU, to the end of its budget). ``parent`` is the parent's pid,
    taken before the fork: read in the child, a parent killed right after the fork was already gone, the child took
    init for its parent and searched on."""
    import signal
    import threading
    import time

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)

    def orphaned() -> None:
        while os.getppid() == parent:
            time.sleep(0.2)
        os._exit(1)

    threading.Thread(target=orphaned, name="fms-forked-parent", daemon=True).start()
    try:
        out: tuple[str, Any] = ("ok", fn(*args))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which decides what a failure means
        out = ("error", str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    try:
        conn.send(out)
    except OSError:  # the parent stopped (or dropped this work) while it ran
        pass
    conn.close()


class Forked:
    """``fn(*args)`` running in a forked daemon process (:func:`child_main`), for a caller that polls for its result
    between its own steps. Raises OSError where no process can be forked now (out of memory or processes); only
    where :data:`FORK_AVAILABLE`."""

    def __init__(self, fn: Callable[..., Any], args: tuple, name: str = "fms-forked") -> None:
        import multiprocessing

        if multiprocessing.current_process().daemon:  # (multiprocessing's own refusal is an AssertionError)
            raise OSError("a daemonic process (a multiprocessing.Pool's worker) may not start a process")
        ctx = multiprocessing.get_context("fork")
        self._receive, send = ctx.Pipe(duplex=False)
        #: the child (``pid``, ``exitcode``; reaped by :meth:`result` or :meth:`cancel`)
        self.process = ctx.Process(target=child_main, args=(fn, args, send, os.getpid()), name=name, daemon=True)
        try:
            self.process.start()
        finally:
            send.close()  # the child holds the sending end: its exit ends a wait on the receiving end
        self._out: tuple[str, Any] | None = None

    def ready(self) -> bool:
        """Whether the result (or the child's end) is there: :meth:`result` would not wait."""
        return self._out is not None or self._receive.poll()

    def result(self) -> Any:
        """``fn(*args)`` as the child computed it, waiting for it; RuntimeError with the child's error, or where the
        child died without a result (killed, out of memory; the message names its exit code)."""
        if self._out is None:
            try:
                out: tuple[str, Any] | None = self._receive.recv()
            except (EOFError, OSError):  # the child died (killed, out of memory) or was terminated
                out = None
            self._receive.close()
            self.process.join()  # (the child ends right after sending)
            self._out = out or ("error", f"the process ended without a result (exit code {self.process.exitcode})")
        kind, value = self._out
        if kind != "ok":
            raise RuntimeError(value if value else "the process failed")
        return value

    def terminate(self) -> None:
        """Signal the child to end if it still runs, for a caller whose other thread waits in :meth:`result` (which
        then reaps it and reports its end)."""
        if self._out is None and self.process.is_alive():
            self.process.terminate()

    def cancel(self) -> None:
        """End the child if it still runs (its result is dropped) and reap it; for a caller that does not wait in
        :meth:`result` meanwhile."""
        if self._out is None:
            self.terminate()
            self.process.join()
            self._receive.close()
            self._out = ("error", "cancelled")
