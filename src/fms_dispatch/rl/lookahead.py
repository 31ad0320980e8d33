"""Running a policy on the shop, optionally with the digital-twin lookahead (pre-positioning idle vehicles).

Without lookahead, :func:`run_agent` is the plain loop ``while not shop.done: shop.act(policy(shop))``.

With lookahead, the shop is run by a :class:`~fms_sim.stepping.Stepper` with idle stops, so that the moments
when a vehicle stands idle with nothing assigned become visible: no decision is due, yet an AGV (or tool
transporter) is idle and has not been looked at since the last decision. At each such stop, for each idle
vehicle offered, a twin of the shop is rolled forward with the same policy until a task lands on that vehicle
(the policy picks it for a request); the request's pickup (the part's location, or the tool's location for a
transporter) is read at that moment. Twins are trial runs on the shop itself
(:meth:`Shop.trial <fms_sim.shop.Shop.trial>` saves its state and puts it back), not deep copies, and the
planner reads the next tasks from its cached plain completion (:class:`Trajectory`) instead of rolling out
again at every stop. If it differs from where the vehicle
is, the real vehicle is sent there empty now (:meth:`Stepper.move <fms_sim.stepping.Stepper.move>`) instead of
waiting for the request. Repositioning is a net transition like any other, so every schedule stays feasible by
construction (tests validate it); it can cost time when another request arrives while the vehicle is on its way,
which the benchmarks measure. The same :class:`LookaheadPlanner` answers the shop node's idle states in the
agent node (``ppo+lookahead``), so over ROS topics the run is the same as offline.

In a **disrupted** shop (a :class:`~fms_sim.full_shop.FullShop` with a scenario: noise, breakdowns, outages)
a trial run on the shop itself would see its realised future, which no dispatcher knows. There the twins are
made by a ``twin`` function instead (:func:`nominal_twin`, built on :func:`fms_sim.snapshot.nominal_copy`):
a copy whose future is the nominal one (no noise on what is still to come, no breakdown or outage that has not
begun). Each idle stop then predicts and verifies from a fresh nominal copy of the current state (the real run
leaves the predicted trajectory as soon as a time differs, so nothing is cached), and "never worse than the
plain policy" holds for the predictions, not for the realised run. :func:`nominal_twin` makes no twin for an
undisrupted shop (it returns None), so the same planner keeps the cached trial runs there; the offline solver,
the disruptions experiment and the agent node (whose twin mirrors the shop's scenario) all use it.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Any, Callable, Iterable, Iterator

from fms_sim.schedule import Schedule
from fms_sim.shop import Shop
from fms_sim.snapshot import nominal_copy
from fms_sim.stepping import Move, Stepper

__all__ = ["run_agent", "run_with_lookahead", "predict_task", "predict_tasks", "LookaheadPlanner", "Trajectory",
           "finish", "plain_trajectory", "TwinMaker", "nominal_twin"]

Choose = Callable[[Shop], int]
#: makes a twin of a shop for the lookahead's predictions, or None: trial runs on the shop itself will do
TwinMaker = Callable[[Shop], "Shop | None"]


def nominal_twin(shop: Shop) -> Shop | None:
    """A nominal copy (:func:`fms_sim.snapshot.nominal_copy`) of a disrupted shop; None for one without a
    scenario, whose trial runs know nothing a dispatcher does not."""
    if getattr(shop, "scenario", None) is None:
        return None
    return nominal_copy(shop)  # type: ignore[arg-type]  # (only a FullShop has a scenario)

#: at most this many decisions are simulated in the twin per idle vehicle
DEFAULT_HORIZON = 200


def run_agent(shop: Shop, choose: Choose, lookahead: bool = False, horizon: int = DEFAULT_HORIZON,
              verify: bool = True, progress: Callable[[str], None] | None = None, retry: bool = True,
              twin: TwinMaker | None = None, planner: Any = None, every_s: float = 2.0) -> Schedule:
    """Run ``shop`` to completion with ``choose(shop) -> net action``; pre-position idle vehicles if asked
    (``retry``, ``twin``, ``planner``: see :func:`run_with_lookahead`). ``progress`` (e.g. ``print``) receives a
    one-line report at most every ``every_s`` seconds, with or without the lookahead: a 100-job shop takes the plain
    policy about 10 s (docs/benchmarks.md §9)."""
    if lookahead:
        return run_with_lookahead(shop, choose, horizon, verify, progress, every_s, retry=retry, twin=twin,
                                  planner=planner)
    t0 = last = time.perf_counter()
    while not shop.done:
        shop.act(choose(shop))
        if progress is not None and time.perf_counter() - last >= every_s:
            last = time.perf_counter()
            progress(progress_line(shop, last - t0))
    return shop.schedule()


def progress_line(shop: Shop, seconds: float, more: str = "") -> str:
    """A plain run's progress report: the operations done, the shop's time and the run's ``seconds`` so far (then
    ``more``)."""
    return (f"  policy: {sum(shop.job_done_ops)}/{shop.instance.n_operations} operations done, time {shop.now}, "
            f"{seconds:.1f} s{more}")


def predict_task(shop: Shop, choose: Choose, kind: str, vehicle: int, horizon: int = DEFAULT_HORIZON) -> int | None:
    """Where the next task of ``vehicle`` (``kind`` "agv" or "tt") starts, by rolling ``choose`` forward in a
    trial run (``shop`` is put back as it was).

    Returns the pickup location (AGV: the part's location; transporter: the tool's location), or None if no
    task lands on the vehicle within ``horizon`` decisions or before the run ends.
    """
    return predict_tasks(shop, choose, [(kind, vehicle)], horizon)[(kind, vehicle)]


def predict_tasks(shop: Shop, choose: Choose, vehicles: list[tuple[str, int]],
                  horizon: int = DEFAULT_HORIZON, copies: bool = False) -> dict[tuple[str, int], int | None]:
    """:func:`predict_task` for several vehicles with one twin: the plain policy's trajectory from here is
    the same whichever vehicle is watched, so one rollout (until every vehicle has a task, the horizon or
    the end) gives each vehicle's first pickup (None if none). ``shop`` is left as it was (``copies``: the twin
    is a deep copy instead of a trial run; slower, the reference)."""
    with _twin(shop, copies) as twin:
        twin.net.advance()
        return _first_pickups(_rollout(twin, choose, horizon), _targets(twin, vehicles), vehicles)


def _rollout(shop: Shop, choose: Choose, horizon: int) -> Iterator[tuple[int, int | None]]:
    """Up to ``horizon`` decisions of ``choose`` on ``shop`` as ``(action, pickup)``, made as they are consumed."""
    for _ in range(horizon):
        if shop.done:
            return
        a = choose(shop)
        yield a, _pickup(shop, a)
        shop.act(a)


def _first_pickups(steps: Iterable[tuple[int, int | None]], targets: dict[int, tuple[str, int]],
                   vehicles: list[tuple[str, int]]) -> dict[tuple[str, int], int | None]:
    """Each watched vehicle's first pickup among ``steps`` (None if it gets no task there); stops reading
    ``steps`` once every vehicle has one."""
    found: dict[tuple[str, int], int | None] = {}
    if targets:
        for a, pickup in steps:
            key = targets.get(a)
            if key is not None and key not in found:
                found[key] = pickup
                if len(found) == len(targets):
                    break
    return {key: found.get(key) for key in vehicles}


@contextmanager
def _twin(obj: Any, copies: bool) -> Iterator[Any]:
    """A twin of a :class:`Shop` or :class:`Stepper`: a trial run on ``obj`` itself, or a deep copy."""
    if copies:
        yield obj.copy()
    else:
        with obj.trial():
            yield obj


def _targets(shop: Shop, vehicles: list[tuple[str, int]]) -> dict[int, tuple[str, int]]:
    """Net action -> (kind, vehicle) for the watched vehicles."""
    return {(shop.n_jobs if kind == "agv" else shop.n_jobs + shop.n_agvs) + v: (kind, v) for kind, v in vehicles}


def _pickup(shop: Shop, action: int) -> int | None:
    """Where the task that vehicle ``action`` is chosen for now starts (None for a job choice)."""
    if action < shop.n_jobs:
        return None
    if action < shop.n_jobs + shop.n_agvs:
        req = shop.awaiting_agv()
        return None if req is None else req[2]
    treq = shop.awaiting_transporter()
    return None if treq is None else treq[1]


class Trajectory:
    """The plain policy's decisions from one state to the end: ``steps[i]`` is the ``start + i``-th decision of
    the run (counted by the net, :attr:`Net.acted <fms_sim.petri.Net.acted>`) as ``(action, pickup)``, the
    pickup being where a chosen vehicle's task starts. As long as the real run follows the plain policy from
    that state, its decisions are exactly these, so every idle vehicle's next task is read here instead of
    being simulated again at every idle stop.

    ``keys[i]`` (when recorded) are the shop's quick and full :meth:`state keys <fms_sim.shop.Shop.state_key>`
    before decision ``i``: a verifying rollout that reaches one of these states has rejoined this run, and its
    makespan is known without running on. ``rejoined`` marks such a rollout (its steps stop there).
    """

    def __init__(self, start: int, steps: list[tuple[int, int | None]], makespan: int,
                 keys: list[tuple[int, int]] | None = None, rejoined: bool = False):
        self.start, self.steps, self.makespan = start, steps, makespan
        self.keys, self.rejoined = keys, rejoined

    def next_pickups(self, shop: Shop, vehicles: list[tuple[str, int]],
                     horizon: int = DEFAULT_HORIZON) -> dict[tuple[str, int], int | None]:
        """What :func:`predict_tasks` returns for ``shop`` (which must be on this trajectory, between decisions)."""
        i = shop.net.acted - self.start
        if not 0 <= i <= len(self.steps):
            raise ValueError(f"the shop (decision {shop.net.acted}) is not on this trajectory "
                             f"(decisions {self.start}..{self.start + len(self.steps)})")
        return _first_pickups(self.steps[i:i + horizon], _targets(shop, vehicles), vehicles)


def _complete(shop: Shop, choose: Choose, keys: bool = False, rejoin: Trajectory | None = None) -> Trajectory:
    """Run ``shop`` (between decisions or at one) to the end with ``choose``, recording the trajectory (with
    the state keys if ``keys``). With ``rejoin`` (a trajectory with keys), stop as soon as the run reaches
    one of its states: from there it is that run, so its makespan is ``rejoin``'s."""
    start = shop.net.acted
    shop.net.advance()
    steps: list[tuple[int, int | None]] = []
    marks: list[tuple[int, int]] | None = [] if keys else None
    ref = rejoin.keys if rejoin is not None else None
    while not shop.done:
        if marks is not None:
            marks.append((shop.state_key(quick=True), shop.state_key()))
        if ref is not None:
            i = shop.net.acted - rejoin.start
            if 0 <= i < len(ref) and ref[i][0] == shop.state_key(quick=True) and ref[i][1] == shop.state_key():
                return Trajectory(start, steps, rejoin.makespan, rejoined=True)
        a = choose(shop)
        steps.append((a, _pickup(shop, a)))
        shop.act(a)
    return Trajectory(start, steps, shop.makespan, marks)


def finish(shop: Shop, choose: Choose) -> int:
    """Makespan of completing ``shop`` (possibly between decisions) with ``choose``, in a trial run (``shop``
    is put back as it was)."""
    return plain_trajectory(shop, choose).makespan


def plain_trajectory(shop: Shop, choose: Choose, copies: bool = False, keys: bool = False) -> Trajectory:
    """The :class:`Trajectory` of completing ``shop`` with ``choose``, in a twin (see :func:`predict_tasks`);
    ``keys`` records the state keys too."""
    with _twin(shop, copies) as twin:
        return _complete(twin, choose, keys)


def _trajectory_after_moves(stepper: Stepper, choose: Choose, moves: list[Move], copies: bool,
                            rejoin: Trajectory | None = None) -> Trajectory:
    with _twin(stepper, copies) as twin:
        twin.idle_stops = False  # the plain policy from here on: no further moves
        twin.move(moves)
        return _complete(twin.shop, choose, rejoin=rejoin)


class LookaheadPlanner:
    """Answers the idle stops of a :class:`~fms_sim.stepping.Stepper` (see the module docstring).

    :meth:`plan` returns the moves for the vehicles offered at an idle stop. With ``verify`` (default) a
    proposed set of moves is checked in a trial run: the run is completed with the moves and compared with
    the completion without them (the plain policy from here); the moves are kept only if the completed
    makespan is strictly smaller. The plain completion is cached as a :class:`Trajectory`: it stays exact
    while the real run follows the plain policy, and becomes the completion with the moves once they are
    made, so it also gives every idle vehicle's next task without another rollout. Each idle stop therefore
    costs one rollout only when it proposes moves, and that rollout stops early if it reaches a state of the
    plain completion (same :meth:`state key <fms_sim.shop.Shop.state_key>` at the same decision): the moves
    then change nothing, and are rejected. Call :meth:`reset` when the run changes in a way the
    planner did not see (new jobs, a fresh twin, other answers than the planner's).

    ``reference=True`` plans as the first implementation did, for benchmarks and tests: twins are deep copies,
    every idle stop rolls the policy out again to predict the next tasks and verifying rollouts always run to
    the end. Its moves are the same. ``verified``, ``accepted`` and ``rejoined`` count the verifying rollouts,
    those whose moves were kept, and those stopped early.

    ``twin`` (:func:`nominal_twin` for disrupted shops; see the module docstring): where ``twin(shop)`` makes a
    twin, every twin is ``twin(shop)`` and every idle stop predicts and verifies afresh from the current state
    (with :func:`fms_sim.snapshot.nominal_copy` on an undisrupted shop, the moves are the reference's); where it
    returns None, the planner runs trials on the shop itself as without it.

    ``retry=False`` is the *fast* lookahead for very large instances: a move (vehicle, location) that a
    verification rejected is not proposed again until some moves are accepted (which changes the planned
    completion); the other vehicles' moves at a stop are still proposed. By default (``retry=True``) the
    same move is verified again at each idle stop, because a move that did not pay at one moment can pay a
    little later. Without retries there are far fewer verifying rollouts (on sl70 with tools about a third per
    operation; sl70 and sl71 with tools ran 8.2 and 6.4 times faster). Every kept move is still verified, so the makespan is
    still never worse than the plain policy's, but the schedules differ from the default's (better or
    worse). ``skipped`` counts the moves not proposed again.
    """

    verifies = True  #: its moves are checked in trial runs (progress lines count them)

    def __init__(self, choose: Choose, horizon: int = DEFAULT_HORIZON, verify: bool = True,
                 reference: bool = False, retry: bool = True, twin: TwinMaker | None = None) -> None:
        self.choose = choose
        self.twin = twin
        if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 0:  # -1 sliced nearly to the end
            raise ValueError(f"the lookahead horizon must be an integer >= 0 (decisions), got {horizon!r}")
        self.horizon = horizon
        self.verify = verify
        self.reference = reference
        self.retry = retry
        self.trajectory: Trajectory | None = None  # the plain completion from the current state
        self.verified = self.accepted = self.rejoined = self.skipped = 0
        self._rejected: set[Move] = set()  # without retries: moves rejected since the last accepted ones

    def reset(self) -> None:
        self.trajectory = None
        self._rejected.clear()

    def plan(self, stepper: Stepper) -> list[Move]:
        shop, choose = stepper.shop, self.choose
        vehicles = [(m.kind, m.vehicle) for m in stepper.idle]
        ref = self.reference
        first = self.twin(shop) if self.twin is not None else None
        if first is not None:
            return self._plan_on_twins(stepper, vehicles, first)
        if self.verify and not ref:
            if self.trajectory is None:
                self.trajectory = plain_trajectory(shop, choose, keys=True)
            dests = self.trajectory.next_pickups(shop, vehicles, self.horizon)
        else:
            dests = predict_tasks(shop, choose, vehicles, self.horizon, copies=ref)
        moves = self._proposed(stepper, dests)
        if moves and self.verify:
            if self.trajectory is None or (self.trajectory.keys is None and not ref):
                # after accepted moves the cache is their rollout, recorded without keys: record them now
                self.trajectory = plain_trajectory(shop, choose, copies=ref, keys=not ref)
            with_moves = _trajectory_after_moves(stepper, choose, moves, ref, None if ref else self.trajectory)
            self.rejoined += with_moves.rejoined
            if self._verdict(moves, with_moves.makespan, self.trajectory.makespan):
                self.trajectory = with_moves
            else:
                moves = []
        return moves

    def _made(self, shop: Shop) -> Shop:
        twin = self.twin(shop) if self.twin is not None else None
        assert twin is not None  # (the shop was disrupted at this stop, so it still is)
        return twin

    def _proposed(self, stepper: Stepper, dests: dict[tuple[str, int], int | None]) -> list[Move]:
        """The moves of the idle vehicles to their next pickups (``dests``), less those not to be retried."""
        moves = [Move(kind, v, dest) for kind, v, loc in stepper.idle
                 if (dest := dests[(kind, v)]) is not None and dest != loc]
        if moves and self.verify and not self.retry:
            kept = [m for m in moves if m not in self._rejected]
            self.skipped += len(moves) - len(kept)
            moves = kept
        return moves

    def _verdict(self, moves: list[Move], made: int, plain: int) -> bool:
        """Whether verified ``moves`` are kept (their completion ``made`` beats the ``plain`` one); counts."""
        self.verified += 1
        if made < plain:
            self.accepted += 1
            self._rejected.clear()
            return True
        if not self.retry:
            self._rejected.update(moves)
        return False

    def _plan_on_twins(self, stepper: Stepper, vehicles: list[tuple[str, int]], twin_shop: Shop) -> list[Move]:
        """:meth:`plan` with every twin made by ``self.twin`` from the current state (``twin_shop`` the first;
        nothing cached)."""
        assert self.twin is not None
        shop, choose = stepper.shop, self.choose
        # the next tasks from a short rollout (it stops once every idle vehicle has one); the plain completion
        # is run to the end only when there are moves to verify
        twin_shop.net.advance()
        dests = _first_pickups(_rollout(twin_shop, choose, self.horizon), _targets(twin_shop, vehicles), vehicles)
        moves = self._proposed(stepper, dests)
        if moves and self.verify:
            plain = _complete(self._made(shop), choose)
            twin = Stepper(self._made(shop), idle_stops=False)
            twin.idle_first, twin.looked, twin.kind, twin.idle = (stepper.idle_first, set(stepper.looked), "idle",
                                                                  list(stepper.idle))
            twin.move(moves)
            if not self._verdict(moves, _complete(twin.shop, choose).makespan, plain.makespan):
                moves = []
        return moves


def run_with_lookahead(shop: Shop, choose: Choose, horizon: int = DEFAULT_HORIZON, verify: bool = True,
                       progress: Callable[[str], None] | None = None, every_s: float = 2.0,
                       reference: bool = False, decisions: list[tuple[list[int], int]] | None = None,
                       retry: bool = True, twin: TwinMaker | None = None, planner: Any = None) -> Schedule:
    """The lookahead loop of :func:`run_agent`: decisions by ``choose``, idle stops by a
    :class:`LookaheadPlanner` (verified by default, so the makespan is never worse than the plain policy's).

    ``progress`` (e.g. ``print``) receives a one-line report at most every ``every_s`` seconds: on large
    instances the lookahead takes minutes (see docs/benchmarks.md). ``reference``: see
    :class:`LookaheadPlanner`. ``decisions`` (a list, if given) receives ``(legal actions, action)`` for each
    decision of the run itself, not of its twins (the lookahead search mutates them). ``retry=False``: the
    fast lookahead; ``twin``: how twins are made (nominal copies in a disrupted shop; see
    :class:`LookaheadPlanner`). ``planner``: another answer to idle stops (an object with ``plan(stepper)`` and
    the counters, e.g. :class:`fms_dispatch.rl.guide.GuideMoves`) instead of a :class:`LookaheadPlanner`."""
    stepper = Stepper(shop, idle_stops=True)
    if planner is None:
        planner = LookaheadPlanner(choose, horizon, verify, reference, retry, twin)
    t0 = last = time.perf_counter()
    total = sum(len(ops) for ops in shop.instance.jobs)
    stops = moved = 0
    stop = stepper.advance()
    while stop != "done":
        if stop == "decision":
            a = choose(shop)
            if decisions is not None:
                decisions.append((shop.legal_actions(), a))
            stop = stepper.decide(a)
        else:
            moves = planner.plan(stepper)
            stops += 1
            moved += bool(moves)
            stop = stepper.move(moves)
        if progress is not None and time.perf_counter() - last >= every_s:
            last = time.perf_counter()
            done = sum(shop.job_done_ops)
            checks = (f"{planner.verified} verified ({planner.rejoined} stopped early"
                      + ("" if retry else f", {planner.skipped} moves not retried") + ")"
                      if getattr(planner, "verifies", True) else "none verified (the plan's empty trips)")
            progress(f"  lookahead: {done}/{total} operations done, time {shop.now}, {stops} idle stops, "
                     f"{moved} with moves, {checks}, {last - t0:.1f} s")
    return shop.schedule()
