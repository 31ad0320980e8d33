"""A shop that keeps to a clock: the simulated shop publishes each state no earlier than its shop time allows.

Simulated as fast as the agent answers, a shop of a hundred jobs runs in seconds, so what a live dispatcher does
meanwhile — a re-plan beside its decisions, an operator's order sent with ``fms send`` — lands at a point of the
run that a real shop would reach much later (docs/benchmarks.md §8: an unpaced shop running on under the old plan
ends later than one that waits). With a time scale ``s`` (wall seconds per unit of shop time) the shop node holds
the messages of a step until ``s × (the state's time − the previous state's)`` after the command that led to it
arrived, as a shop running at that speed would show them: between two decisions the agent has the time the shop
gives it. While the shop waits for an answer its clock stands (a simulated decision is made at its state's time),
so an agent slower than the scale slows the run down rather than compressing what follows.

:class:`Pacer` is the queue (no ROS: the shop node feeds it each step's messages and publishes what it releases,
on a timer); messages keep their order, and those that come with no state (a replay) wait behind held ones; a
step of errors only (a refused order or disruption: nothing changed) goes out at once (held behind a paced step, an
operator's refusal reached ``fms send`` after its timeout).
"""

from __future__ import annotations

import time
from collections import deque
from typing import Callable, Sequence

from fms_msgs_json import TOPIC_ERRORS, TOPIC_STATE

from .shop_service import Outgoing

__all__ = ["Pacer"]


class Pacer:
    """Holds each step's messages until ``scale`` (seconds per time unit) × the shop time since the previous state
    has passed on the wall clock, from when the step came (or, if the previous step is still held, from its
    release); ``scale`` 0 releases everything at once."""

    def __init__(self, scale: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not scale >= 0 or scale == float("inf"):
            raise ValueError(f"the time scale must be a finite number of seconds per time unit >= 0, got {scale!r}")
        self.scale = float(scale)
        self._clock = clock
        self._last: tuple[float, int] | None = None  # (release time, shop time) of the last state queued
        self._held: deque[tuple[float, list[Outgoing]]] = deque()
        self.last_delay = 0.0  # how long the step pushed last waits (seconds from its push)

    def due_at(self, out: Sequence[Outgoing]) -> float:
        """The wall time at which ``out`` (a step's messages, coming now) may be published: after the shop time
        from the previous state to its last state (none: at once, behind what is held)."""
        times = [o.msg["time"] for o in out if o.topic == TOPIC_STATE]
        if not times or not self.scale:
            return float("-inf")
        now, t = self._clock(), times[-1]
        if self._last is None:
            due = now
        else:
            released, before = self._last
            due = max(now, released) + self.scale * max(0, t - before)
        self._last = (due, t)
        return due

    def push(self, out: Sequence[Outgoing]) -> list[Outgoing]:
        """Queue a step's messages; returns those due now (in order; an earlier held step keeps its place). Errors
        alone are due at once: they change nothing that a held step shows."""
        if out and all(o.topic == TOPIC_ERRORS for o in out):
            self.last_delay = 0.0
            return self.release() + list(out)
        due = self.due_at(out)
        self.last_delay = max(0.0, due - self._clock())
        self._held.append((due, list(out)))
        return self.release()

    def release(self) -> list[Outgoing]:
        """The held messages that are due now, in order (the node calls this on a timer)."""
        now = self._clock()
        out: list[Outgoing] = []
        while self._held and self._held[0][0] <= now:
            out += self._held.popleft()[1]
        return out

    @property
    def holding(self) -> bool:
        """Whether messages wait for their time."""
        return bool(self._held)
