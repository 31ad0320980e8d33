"""Running a policy on the shop, optionally with the digital-twin lookahead (pre-positioning idle vehicles).

Without lookahead, :func:`run_agent` is the plain loop ``while not shop.done: shop.act(policy(shop))``.

With lookahead, the shop is run by a :class:`~fms_sim.stepping.Stepper` with idle stops, so that the moments
when a vehicle stands idle with nothing assigned become visible: no decision is due, yet an AGV (or tool
transporter) is idle and has not been looked at since the last decision. At each such stop, for each idle
vehicle offered, a twin of the shop (:meth:`~fms_sim.shop.Shop.copy`) is rolled forward with the same policy
until a task lands on that vehicle (the policy picks it for a request); the request's pickup (the part's
location, or the tool's location for a transporter) is read at that moment. If it differs from where the vehicle
is, the real vehicle is sent there empty now (:meth:`Stepper.move <fms_sim.stepping.Stepper.move>`) instead of
waiting for the request. Repositioning is a net transition like any other, so every schedule stays feasible by
construction (tests validate it); it can cost time when another request arrives while the vehicle is on its way,
which the benchmarks measure. The same :class:`LookaheadPlanner` answers the shop node's idle states in the
agent node (``ppo+lookahead``), so over ROS topics the run is the same as offline.
"""

from __future__ import annotations

import time
from typing import Callable

from fms_sim.schedule import Schedule
from fms_sim.shop import Shop
from fms_sim.stepping import Move, Stepper

__all__ = ["run_agent", "run_with_lookahead", "predict_task", "predict_tasks", "LookaheadPlanner", "finish"]

Choose = Callable[[Shop], int]

#: at most this many decisions are simulated in the twin per idle vehicle
DEFAULT_HORIZON = 200


def run_agent(shop: Shop, choose: Choose, lookahead: bool = False, horizon: int = DEFAULT_HORIZON,
              verify: bool = True, progress: Callable[[str], None] | None = None) -> Schedule:
    """Run ``shop`` to completion with ``choose(shop) -> net action``; pre-position idle vehicles if asked
    (``progress``: see :func:`run_with_lookahead`)."""
    if lookahead:
        return run_with_lookahead(shop, choose, horizon, verify, progress)
    while not shop.done:
        shop.act(choose(shop))
    return shop.schedule()


def predict_task(shop: Shop, choose: Choose, kind: str, vehicle: int, horizon: int = DEFAULT_HORIZON) -> int | None:
    """Where the next task of ``vehicle`` (``kind`` "agv" or "tt") starts, by rolling ``choose`` on a twin.

    Returns the pickup location (AGV: the part's location; transporter: the tool's location), or None if no
    task lands on the vehicle within ``horizon`` decisions or before the run ends.
    """
    return predict_tasks(shop, choose, [(kind, vehicle)], horizon)[(kind, vehicle)]


def predict_tasks(shop: Shop, choose: Choose, vehicles: list[tuple[str, int]],
                  horizon: int = DEFAULT_HORIZON) -> dict[tuple[str, int], int | None]:
    """:func:`predict_task` for several vehicles with one twin: the plain policy's trajectory from here is
    the same whichever vehicle is watched, so one rollout (until every vehicle has a task, the horizon or
    the end) gives each vehicle's first pickup (None if none)."""
    twin = shop.copy()
    twin.net.advance()
    targets = {(twin.n_jobs if kind == "agv" else twin.n_jobs + twin.n_agvs) + v: (kind, v) for kind, v in vehicles}
    found: dict[tuple[str, int], int | None] = {}
    for _ in range(horizon):
        if twin.done or len(found) == len(targets):
            break
        a = choose(twin)
        key = targets.get(a)
        if key is not None and key not in found:
            if key[0] == "agv":
                req = twin.awaiting_agv()
                found[key] = None if req is None else req[2]
            else:
                treq = twin.awaiting_transporter()
                found[key] = None if treq is None else treq[1]
        twin.act(a)
    return {key: found.get(key) for key in vehicles}


def finish(shop: Shop, choose: Choose) -> int:
    """Makespan of running a twin of ``shop`` (possibly between decisions) to the end with ``choose``."""
    twin = shop.copy()
    twin.net.advance()
    while not twin.done:
        twin.act(choose(twin))
    return twin.makespan


def _finish_after_moves(stepper: Stepper, choose: Choose, moves: list[Move]) -> int:
    twin = stepper.copy()
    twin.idle_stops = False  # the plain policy from here on: no further moves
    twin.move(moves)
    shop = twin.shop
    while not shop.done:
        shop.act(choose(shop))
    return shop.makespan


class LookaheadPlanner:
    """Answers the idle stops of a :class:`~fms_sim.stepping.Stepper` (see the module docstring).

    :meth:`plan` returns the moves for the vehicles offered at an idle stop. With ``verify`` (default) a
    proposed set of moves is checked in a twin: the run is completed with the moves and compared with the
    completion without them (the plain policy from here); the moves are kept only if the completed makespan
    is strictly smaller. The plain completion is cached: it stays exact while the real run follows the plain
    policy, and becomes the completion with the moves once they are made. Call :meth:`reset` when the run
    changes in a way the planner did not see (new jobs, a fresh twin).
    """

    def __init__(self, choose: Choose, horizon: int = DEFAULT_HORIZON, verify: bool = True) -> None:
        self.choose = choose
        self.horizon = horizon
        self.verify = verify
        self.expected: int | None = None  # makespan of the plain completion from the current state

    def reset(self) -> None:
        self.expected = None

    def plan(self, stepper: Stepper) -> list[Move]:
        shop, choose = stepper.shop, self.choose
        dests = predict_tasks(shop, choose, [(m.kind, m.vehicle) for m in stepper.idle], self.horizon)
        moves = [Move(kind, v, dest) for kind, v, loc in stepper.idle
                 if (dest := dests[(kind, v)]) is not None and dest != loc]
        if moves and self.verify:
            if self.expected is None:
                self.expected = finish(shop, choose)
            with_moves = _finish_after_moves(stepper, choose, moves)
            if with_moves < self.expected:
                self.expected = with_moves
            else:
                moves = []
        return moves


def run_with_lookahead(shop: Shop, choose: Choose, horizon: int = DEFAULT_HORIZON, verify: bool = True,
                       progress: Callable[[str], None] | None = None, every_s: float = 2.0) -> Schedule:
    """The lookahead loop of :func:`run_agent`: decisions by ``choose``, idle stops by a
    :class:`LookaheadPlanner` (verified by default, so the makespan is never worse than the plain policy's).

    ``progress`` (e.g. ``print``) receives a one-line report at most every ``every_s`` seconds: on large
    instances the lookahead takes minutes (see docs/benchmarks.md)."""
    stepper = Stepper(shop, idle_stops=True)
    planner = LookaheadPlanner(choose, horizon, verify)
    t0 = last = time.perf_counter()
    total = sum(len(ops) for ops in shop.instance.jobs)
    stops = moved = 0
    stop = stepper.advance()
    while stop != "done":
        if stop == "decision":
            stop = stepper.decide(choose(shop))
        else:
            moves = planner.plan(stepper)
            stops += 1
            moved += bool(moves)
            stop = stepper.move(moves)
        if progress is not None and time.perf_counter() - last >= every_s:
            last = time.perf_counter()
            done = sum(shop.job_done_ops)
            progress(f"  lookahead: {done}/{total} operations done, time {shop.now}, {stops} idle stops, "
                     f"{moved} with moves, {last - t0:.1f} s")
    return shop.schedule()
