"""Work in a forked process: its result, its error, its death and its cancellation reach the parent."""

from __future__ import annotations

import os
import time

import pytest

from fms_dispatch.forked import FORK_AVAILABLE, Forked

pytestmark = pytest.mark.skipif(not FORK_AVAILABLE, reason="forked work runs on Linux only")


def _fails() -> None:
    raise ValueError("bad input\nsecond line")


def test_the_result_comes_from_another_process():
    job = Forked(os.getpid, ())
    assert job.result() != os.getpid() and job.ready() and job.result() == job.result()


def test_an_error_or_a_death_in_the_child_is_a_runtime_error():
    with pytest.raises(RuntimeError, match="^bad input$"):
        Forked(_fails, ()).result()
    with pytest.raises(RuntimeError, match="ended without a result"):
        Forked(os._exit, (3,)).result()


def test_cancel_ends_the_child():
    job = Forked(time.sleep, (60,))
    assert not job.ready()
    job.cancel()
    assert not job.process.is_alive() and job.process.exitcode is not None
    with pytest.raises(RuntimeError, match="cancelled"):
        job.result()
