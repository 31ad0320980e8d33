"""spin_until_shutdown: an executor error during the stop is not a crash; any other error still is.

The race itself (a message taken while the context shuts down) cannot be provoked on demand, so these tests
replace rclpy's spin / ok / try_shutdown in the node module by stand-ins that replay it.
"""

from __future__ import annotations

import itertools
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


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(shop_node, "_ignore_stop_signals", lambda: None)  # keep the test process's handlers
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
    closed = []
    assert shop_node.spin_until_shutdown(object(), lambda: closed.append(1)) == 0
    assert closed == [1] and f.shutdowns == 1


def test_executor_error_while_rclpy_stays_up_is_raised(fake) -> None:
    f = fake(TypeError("a genuine bug"), ok_calls=None)
    closed = []
    with pytest.raises(TypeError, match="a genuine bug"):
        shop_node.spin_until_shutdown(object(), lambda: closed.append(1))
    assert closed == [1] and f.shutdowns == 1  # still closed (the database is flushed) and shut down
