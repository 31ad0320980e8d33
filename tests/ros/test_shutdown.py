"""spin_until_shutdown: an executor error during the stop is not a crash; any other error still is; a
middleware teardown that stalls ends the process with its stacks in the log.

The race itself (a message taken while the context shuts down) and a stalled DDS teardown cannot be provoked
on demand, so these tests replace rclpy's spin / ok / try_shutdown in the node module by stand-ins that replay
them.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import textwrap
import time
from typing import Any

import pytest

pytest.importorskip("rclpy")

from fms_sim import shop_node  # noqa: E402


class FakeRclpy:
    """``spin`` raises ``exc``; ``ok()`` is True for the first ``ok_calls`` calls, then False."""

    def __init__(self, exc: BaseException, ok_calls: int | None) -> None:
        self.exc = exc
        self.calls = itertools.count()
        self.ok_calls = ok_calls
        self.shutdowns = 0

    def spin(self, node: Any) -> None:
        raise self.exc

    def ok(self) -> bool:
        n = next(self.calls)
        return self.ok_calls is None or n < self.ok_calls

    def try_shutdown(self) -> None:
        self.shutdowns += 1


class FakeNode:
    def __init__(self) -> None:
        self.destroyed = 0

    def destroy_node(self) -> None:
        self.destroyed += 1


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(shop_node, "_ignore_stop_signals", lambda: None)  # keep the test process's handlers
    monkeypatch.setattr(shop_node, "_arm_stop_watchdog", lambda: None)  # it would end the test process
    monkeypatch.setattr(shop_node, "SHUTDOWN_GRACE_S", 0.3)

    def install(exc: BaseException, ok_calls: int | None) -> FakeRclpy:
        f = FakeRclpy(exc, ok_calls)
        monkeypatch.setattr(shop_node, "rclpy", f)
        return f
    return install


@pytest.mark.parametrize("exc", [TypeError("Unable to convert call argument '0' to Python object"),
                                 RuntimeError("Failed to take message")])
def test_executor_error_just_before_the_shutdown_is_a_clean_stop(fake, exc: BaseException) -> None:
    f = fake(exc, ok_calls=3)              # the context reports the shutdown a moment after the error
    closed, node = [], FakeNode()
    assert shop_node.spin_until_shutdown(node, lambda: closed.append(1)) == 0
    assert closed == [1] and node.destroyed == 1 and f.shutdowns == 1


def test_executor_error_while_rclpy_stays_up_is_raised(fake) -> None:
    f = fake(TypeError("a genuine bug"), ok_calls=None)
    closed, node = [], FakeNode()
    with pytest.raises(TypeError, match="a genuine bug"):
        shop_node.spin_until_shutdown(node, lambda: closed.append(1))
    assert closed == [1] and node.destroyed == 1 and f.shutdowns == 1  # still closed (data flushed), shut down


def test_a_stop_while_the_stop_watcher_starts_is_a_clean_stop(fake, monkeypatch: pytest.MonkeyPatch) -> None:
    # the node said it is up, then Ctrl-C came while the watcher thread started (before spin): that ended in a
    # KeyboardInterrupt traceback and exit -2, without close() (tests/ros/test_colcon.py hit it)
    f = fake(AssertionError("spin is not reached"), ok_calls=None)

    def interrupted(node: Any, spinning: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(shop_node, "_watch_busy_stop", interrupted)
    closed, node = [], FakeNode()
    assert shop_node.spin_until_shutdown(node, lambda: closed.append(1)) == 0
    assert closed == [1] and node.destroyed == 1 and f.shutdowns == 1


#: a node process whose stop is replayed: ``close()`` takes argv[1] s, the rclpy shutdown argv[2] s
STALL_SCRIPT = textwrap.dedent('''
    import sys, time
    from fms_sim import shop_node

    class Rclpy:
        def spin(self, node): raise KeyboardInterrupt
        def ok(self): return False
        def try_shutdown(self): time.sleep(float(sys.argv[2]))

    class Node:
        def destroy_node(self): pass

    shop_node.rclpy = Rclpy()
    shop_node.STOP_STALL_S = 1.0
    code = shop_node.spin_until_shutdown(Node(), lambda: time.sleep(float(sys.argv[1])))
    print("saved", flush=True)
    sys.exit(code)
''')


def _stop(close_s: float, shutdown_s: float) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-c", STALL_SCRIPT, str(close_s), str(shutdown_s)],
                         capture_output=True, text=True, timeout=60)
    return res, time.monotonic() - t0


def test_a_stalled_middleware_teardown_ends_with_its_stacks_in_the_log() -> None:
    res, wall = _stop(0.0, 50.0)
    assert res.returncode == 1, res.stderr
    assert wall < 30  # not the 50 s the stalled shutdown would take
    assert "Timeout" in res.stderr and "try_shutdown" in res.stderr  # faulthandler names the blocked call
    assert "saved" not in res.stdout


def test_a_slow_close_is_not_cut_short() -> None:
    # the node's own close (flushing its data) is not bounded: only the teardown after it is
    res, _ = _stop(2.0, 0.0)
    assert res.returncode == 0, res.stderr
    assert "saved" in res.stdout and "Timeout" not in res.stderr


#: a real node whose only callback is busy in native code for about argv[1] s, where a signal cannot interrupt
#: it (as an agent in CP-SAT's search for its first plan: Python raises the KeyboardInterrupt only when the call
#: returns); the stop watchdog fires after 1 s
BUSY_SCRIPT = textwrap.dedent('''
    import hashlib, sys, time
    import rclpy
    from rclpy.node import Node
    from fms_sim import shop_node

    rclpy.init()
    node = Node("busy_for_test")

    def busy():
        print("busy", flush=True)
        t0 = time.monotonic()
        hashlib.pbkdf2_hmac("sha256", b"x", b"y", 100_000)
        rounds = int(float(sys.argv[1]) / max(time.monotonic() - t0, 1e-3) * 100_000)
        hashlib.pbkdf2_hmac("sha256", b"x", b"y", rounds)  # one C call, no signal handled until it returns
        print("callback done", flush=True)

    node.create_timer(0.05, busy)
    shop_node.STOP_STALL_S = 1.0
    code = shop_node.spin_until_shutdown(node, lambda: print("saved", flush=True))
    sys.exit(code)
''')


@pytest.mark.parametrize("busy_s, code", [(60.0, 1), (0.3, 0)])
def test_a_stop_during_a_busy_callback_is_bounded(ros_env: dict[str, str], busy_s: float, code: int) -> None:
    """SIGINT while a callback is busy (an agent planning at the first state: plan:cpsat:60) stopped the node only
    when the callback returned, a minute later; now the stop watchdog ends it after STOP_STALL_S with its stacks
    in the log (exit code 1). A callback that returns in time stops cleanly, its close() unbounded."""
    import signal

    proc = subprocess.Popen([sys.executable, "-c", BUSY_SCRIPT, str(busy_s)], env=ros_env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "busy"
        time.sleep(0.5)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        wall = time.monotonic() - t0
    finally:
        proc.kill()
    assert proc.returncode == code, err
    if code:
        assert wall < 10 and "Timeout" in err and "in busy" in err  # faulthandler names the busy callback
        assert "saved" not in out
    else:
        assert "saved" in out and "Timeout" not in err


def test_a_stopped_node_wakes_its_executor_until_spin_returns(monkeypatch: pytest.MonkeyPatch) -> None:
    """Once in a fresh-clone run a shop node stopped by SIGINT stayed in the executor's wait (the shutdown's own
    wake-up came to nothing) until the stop watchdog ended it with exit 1. The stop watcher now wakes the executor
    again and again once the context is down, until spin returns, and then stops."""
    wakes: list[float] = []
    armed: list[int] = []

    class Executor:
        def wake(self) -> None:
            wakes.append(time.monotonic())

    class Rclpy:
        def get_global_executor(self) -> Executor:
            return Executor()

    class Context:
        def ok(self) -> bool:
            return False  # shut down (SIGINT)

    class Node:
        context = Context()

    monkeypatch.setattr(shop_node, "rclpy", Rclpy())
    monkeypatch.setattr(shop_node, "_arm_stop_watchdog", lambda: armed.append(1))
    spinning = shop_node._Spinning()
    shop_node._watch_busy_stop(Node(), spinning, poll_s=0.01)
    deadline = time.monotonic() + 5
    while len(wakes) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(wakes) >= 3 and armed == [1]  # woken repeatedly, the watchdog armed once
    spinning.release()  # spin returned
    time.sleep(0.1)
    settled = len(wakes)
    time.sleep(0.1)
    assert len(wakes) == settled  # no more wake-ups once spin has returned
