"""Replay: drive the full-decision net with the orders of a given valid schedule.

A schedule fixes, for every resource, the order in which it serves: the trips of each AGV and each tool
transporter (empty ones included), the operations of each machine, the uses of each tool. :class:`PlanPolicy`
reads those orders and, at every moment the net stops, does the next thing of each resource as soon as the
net's guards allow it: empty trips become pre-positioning orders when the vehicle turns idle, loaded trips
become ``job:J`` + ``agv:V`` or ``tool:T`` + ``use:J`` + ``tt:R``, machine orders become ``start:J``; when
nothing planned is enabled, time passes to the next event (hold).

Every event then happens no later than in the given schedule (each one waits only for its predecessors on
the same resources and in the same job, which happened no later by induction), so the replayed makespan is at
most the given one, and equal on proven optima. :func:`replay` refuses a schedule that is not valid for the
instance with the validator's first errors, and checks the schedule it returns.
"""

from __future__ import annotations

from collections import defaultdict, deque
from dataclasses import replace
from typing import Callable, Deque

from .disruptions import Scenario
from .full_shop import HOLD, FullShop
from .instance import Instance, require_instance
from .petri import InvalidAction
from .schedule import Schedule, require_schedule
from .stepping import Move, Stepper, moves_label, parse_moves
from .ties import plan_orders
from .validate import validate

__all__ = ["replay", "execute", "ReplayError", "PlanPolicy"]


class ReplayError(ValueError):
    """The schedule cannot be replayed: it is not valid for the instance (``violations`` lists the
    validator's findings), or the net refused its orders (a bug: valid schedules always replay)."""

    def __init__(self, message: str, violations: list[str] | None = None):
        super().__init__(message)
        self.violations = violations or []


class PlanPolicy:
    """The orders of ``schedule`` per resource, answered through a :class:`~fms_sim.full_shop.FullShop`.

    :meth:`answer` gives the label for a :class:`~fms_sim.stepping.Stepper`'s stop (moves at an idle stop, the
    planned action or ``hold`` at a decision), so a plan runs offline and, as labels, through the shop node;
    :meth:`step` is the decision part: the action to fire now, or None when nothing planned can be done."""

    def __init__(self, instance: Instance, schedule: Schedule, *, state: FullShop | None = None):
        """``state``: the shop the plan goes on from (:meth:`resume`), whose tools' places and reservations order
        the uses that tie at one instant; None: the start of a run."""
        self.instance = instance
        # a plan of another shop would run into actions the net does not have: refuse it here, by name
        jobs = instance.jobs
        wanted = [("has", r.job, r.op) for r in schedule.operations]
        wanted += [("carries for", t.job, t.op) for t in (*schedule.agv_trips, *schedule.tool_trips)
                   if t.job is not None]
        for what, j, k in wanted:
            if not (0 <= j < len(jobs) and 0 <= k < len(jobs[j])):
                raise ReplayError(f"the plan ({schedule.instance}) {what} operation ({j}, {k}), which "
                                  f"{instance.name} does not have")
        # vehicle routes: ("move", destination) or ("carry", job, op); legs from a place to itself carry nothing
        self.agv: dict[int, Deque[tuple]] = defaultdict(deque)
        for t in sorted(schedule.agv_trips, key=lambda t: (t.start, t.end)):
            if t.from_ != t.to:
                self.agv[t.agv].append(("carry", t.job, t.op) if t.loaded else ("move", t.to))
        self.tt: dict[int, Deque[tuple]] = defaultdict(deque)
        self.tool_carrier: dict[tuple[int, int], int] = {}
        for t in sorted(schedule.tool_trips, key=lambda t: (t.start, t.end)):
            if t.from_ != t.to:
                self.tt[t.transporter].append(("carry", t.job, t.op) if t.loaded else ("move", t.to))
                if t.loaded:
                    self.tool_carrier[t.job, t.op] = t.transporter
        self.part_carrier = {(t.job, t.op): t.agv for t in schedule.agv_trips if t.loaded and t.from_ != t.to}
        # each machine's operations by start (then end), those of zero duration at one instant in an order that
        # every resource's order agrees with (fms_sim.ties.plan_orders: the list's order could close a circular wait
        # with a transporter's carries for them, and the replay of a valid schedule got stuck)
        tools, tied = plan_orders(instance, schedule) if state is None else plan_orders(*_from_state(state, schedule))
        self.machine: dict[int, Deque[tuple[int, int]]] = defaultdict(deque)
        for _, r in sorted(enumerate(schedule.operations),
                           key=lambda ir: (ir[1].start, ir[1].end, tied.get((ir[1].job, ir[1].op), -1), ir[0])):
            self.machine[r.machine].append((r.job, r.op))
        self.tool: dict[int, Deque[tuple[int, int]]] = defaultdict(deque, {t: deque(q) for t, q in tools.items()})

    @classmethod
    def resume(cls, shop: FullShop, plan: Schedule) -> "PlanPolicy":
        """The orders of ``plan`` (a whole schedule, or a residual plan from
        :func:`fms_dispatch.exact.greedy_schedule` with ``origin``) from ``shop``'s state now: operations that
        have started, tool uses already reserved and parts already dispatched are dropped from the orders, so a
        plan made from an earlier state of the same run (re-planning while the shop went on) goes on from here. The
        uses that tie at one instant are ordered from where the tools stand now, a reserved use first
        (:func:`fms_sim.ties.plan_orders` with the state), so a machine's and a transporter's orders agree with
        what its tool can do."""
        pol = cls(shop.instance, plan, state=shop)
        started, dispatched = shop.started, shop.job_started_ops
        for q in pol.machine.values():
            keep = [(j, k) for j, k in q if k >= started[j]]
            q.clear()
            q.extend(keep)
        for t, q in pol.tool.items():
            keep = [(j, k) for j, k in q if k in shop.treq[t].get(j, ())]
            q.clear()
            q.extend(keep)
        jobs = shop.instance.jobs

        def served(j: int, k: int) -> bool:
            tool = jobs[j][k].tool
            return tool is None or k not in shop.treq[tool].get(j, ())

        for plans, done, idle in ((pol.agv, lambda j, k: dispatched[j] > k, shop.idle_agvs()),
                                  (pol.tt, served, shop.idle_transporters())):
            for legs in plans.values():
                # what comes before a vehicle's last carry already done was driven (or is moot) too
                last = max((i for i, leg in enumerate(legs) if leg[0] == "carry" and done(leg[1], leg[2])),
                           default=-1)
                keep = [leg for leg in list(legs)[last + 1:] if leg[0] != "carry" or not done(leg[1], leg[2])]
                legs.clear()
                legs.extend(keep)
            # a vehicle idle now has had its idle stop: its first trip starts from where it stands
            for v, _ in idle:
                legs = plans.get(v)
                while legs and legs[0][0] == "move":
                    legs.popleft()
        return pol

    # ------------------------------------------------------------------ answers at a stepper's stops
    def answer(self, stepper: Stepper) -> str:
        """The label that answers ``stepper``'s current stop: the moves of the offered vehicles whose next leg is
        an empty one (``wait`` if none), or the planned action (``hold`` when nothing planned can be done now).
        Idempotent: the plan moves on only by :meth:`apply`, so a state answered twice gets the same answer."""
        shop = stepper.shop
        assert isinstance(shop, FullShop)
        if stepper.kind == "idle":
            moves = []
            for kind, v, here in stepper.idle:
                leg = self._next_leg(kind, v, here)
                if leg is not None and leg[0] == "move":
                    moves.append(Move(kind, v, leg[1]))
            return moves_label(moves)
        action = self.step(shop)
        if action is None:
            if not shop.hold_allowed():
                raise ReplayError(f"replay of {shop.instance.name} is stuck at time {shop.now}: no planned order "
                                  "can be carried out and nothing is in flight")
            return HOLD
        return shop.action_label(action)

    def apply(self, stepper: Stepper, label: str) -> None:
        """Move the plan on by the answer ``label`` about to be applied at ``stepper``'s current stop (call it
        before the stepper applies it): the legs, uses and starts it carries out are consumed."""
        shop = stepper.shop
        assert isinstance(shop, FullShop)
        if stepper.kind == "idle":
            for kind, v, _ in parse_moves(label):
                plans = self.agv if kind == "agv" else self.tt
                here = next(loc for k, u, loc in stepper.idle if (k, u) == (kind, v))
                self._next_leg(kind, v, here)
                plans[v].popleft()
            return
        if label == HOLD:
            return
        kind, _, num = label.partition(":")
        v = int(num)
        if kind == "agv":
            j, k = shop.awaiting_agv()[:2]
            _consume(self.agv[v], ("carry", j, k))
        elif kind == "tt":
            _, _, j, k, _ = shop.awaiting_transporter()
            _consume(self.tt[v], ("carry", j, k))
        elif kind == "use":
            t = shop.tool_choice
            _consume(self.tool[t], (v, shop.request_of(t, v)))
        elif kind == "start":
            k, m = shop.buffered_op(v)
            _consume(self.machine[m], (v, k))

    def _next_leg(self, kind: str, v: int, here: int | None) -> tuple | None:
        """The vehicle's next leg, dropping empty legs to where it already is (``here``)."""
        plan = (self.agv if kind == "agv" else self.tt).get(v)
        while plan and here is not None and plan[0][0] == "move" and plan[0][1] == here:
            plan.popleft()
        return plan[0] if plan else None

    # ------------------------------------------------------------------ decisions
    def step(self, shop: FullShop) -> int | None:
        """The planned action to fire now (without consuming it), or None when nothing planned can be done."""
        net = shop.net
        first = net.first_offered()
        if first is None:
            return None
        kind, _ = shop.action_kind(first)
        # whether an action is offered is asked of the net action by action (Net.offers): the full list of a tool's
        # candidates costs as much as the jobs waiting for the tool, at every tool choice
        legal = net.offers
        # a choice the plan did not set up (a plan resumed after another decider chose) gets None: not planned
        if kind == "agv":  # the AGV for the job just dispatched
            j, k = shop.awaiting_agv()[:2]
            v = self.part_carrier.get((j, k))
            return _if_legal(shop, f"agv:{v}", legal) if v is not None else None
        if kind == "tt":
            _, _, j, k, _ = shop.awaiting_transporter()
            r = self.tool_carrier.get((j, k))
            return _if_legal(shop, f"tt:{r}", legal) if r is not None else None
        if kind == "use":
            uses = self.tool.get(shop.tool_choice)
            return _if_legal(shop, f"use:{uses[0][0]}", legal) if uses else None
        for choose in (self._dispatch, self._tool, self._start):
            a = choose(shop, legal)
            if a is not None:
                return a
        return None

    def _dispatch(self, shop: FullShop, legal: Callable[[int], bool]) -> int | None:
        for v, here in shop.idle_agvs():
            leg = self._next_leg("agv", v, None)
            if leg is None or leg[0] != "carry":
                continue
            _, j, k = leg
            a = shop.action_index(f"job:{j}")
            if legal(a) and shop.next_op(j) == k:
                return a
        return None

    def _tool(self, shop: FullShop, legal: Callable[[int], bool]) -> int | None:
        idle_tts = dict(shop.idle_transporters())
        for t, uses in self.tool.items():
            if not uses:
                continue
            j, k = uses[0]
            a = shop.action_index(f"tool:{t}")
            if not legal(a) or shop.request_of(t, j) != k or not shop._servable(t):
                continue
            r = self.tool_carrier.get((j, k))
            if r is not None:
                if self._next_leg("tt", r, None) != ("carry", j, k) or r not in idle_tts:
                    continue
            elif shop.tool_loc[t] != shop.instance.jobs[j][k].machine:
                continue
            if shop._candidate(t, j):
                return a
        return None

    def _start(self, shop: FullShop, legal: Callable[[int], bool]) -> int | None:
        for m, queue in self.machine.items():
            if not queue:
                continue
            j, k = queue[0]
            a = shop.action_index(f"start:{j}")
            if legal(a) and shop.buffered_op(j) == (k, m):
                return a
        return None


def _if_legal(shop: FullShop, label: str, legal: Callable[[int], bool]) -> int | None:
    a = shop.action_index(label)
    return a if legal(a) else None


def _from_state(shop: FullShop, plan: Schedule
                ) -> tuple[Instance, Schedule, dict[int, tuple[int, tuple[int, int] | None]]]:
    """What :func:`fms_sim.ties.plan_orders` orders the rest of ``plan`` from, once ``shop`` has gone as far as it
    has: the instance, the plan without the operations that have started (and without the carries for them), and
    where each tool stands now and the use it is reserved for (its carry made, or under way). The tied uses of a
    residual plan start where its tools stand, not in the magazine as a whole schedule's do; ordered from the
    magazine, they came out in an order the tool cannot follow and the replay got stuck."""
    inst = shop.instance
    started = shop.started
    rest = [r for r in plan.operations if r.op >= started[r.job]]
    trips = [t for t in plan.tool_trips if not t.loaded or t.job is None or t.op is None or t.op >= started[t.job]]
    view = replace(plan, operations=rest, tool_trips=trips)
    origin = {t: (shop.tool_loc[t], shop.reserved_op(t)) for t in range(1, inst.n_tools + 1)} if inst.has_tools else {}
    return inst, view, origin


def _consume(queue: Deque[tuple], item: tuple) -> None:
    """Take ``item`` out of a resource's orders: its head when a plan is followed; wherever it is when the run
    did things in another order (a plan adopted mid-run, a fallback's answer); nothing if it is not there."""
    if queue and queue[0] == item:
        queue.popleft()
    elif item in queue:
        queue.remove(item)


def execute(shop: FullShop, policy: PlanPolicy) -> int:
    """Run ``shop`` to the end with ``policy`` answering every stop of a :class:`~fms_sim.stepping.Stepper`
    (idle stops included); returns the number of answers."""
    if not isinstance(shop, FullShop):
        raise ReplayError(f"a plan is executed through the full-decision net (make_shop(instance, 'full')), not "
                          f"the {shop.decisions!r} one")
    stepper = Stepper(shop, idle_stops=True)
    stepper.advance()
    n = 0
    while stepper.kind != "done":
        label = policy.answer(stepper)
        policy.apply(stepper, label)
        try:
            stepper.apply(label)
        except InvalidAction as exc:  # pragma: no cover - a bug: the policy only gives offered answers
            raise ReplayError(f"replay of {shop.instance.name} failed at time {shop.now}: {exc}") from exc
        n += 1
    return n


def replay(instance: Instance, schedule: Schedule, *, check: bool = True,
           scenario: Scenario | None = None) -> Schedule:
    """Run ``schedule``'s orders through the full-decision net and return the schedule the net makes.

    With a ``scenario`` (breakdowns, outages, noise) the orders are kept and the times shift: the plan executed
    in a disrupted shop without re-planning (its makespan may then exceed the plan's). A schedule of a run with live
    orders (``meta["arrivals"]``) is replayed in ``instance`` as it is, every job there from time 0: the ordered
    jobs may start before their orders came (the output records no arrivals).

    Raises :class:`ReplayError` if ``schedule`` is not valid for ``instance`` (with the validator's first
    errors; nothing is run) or, with ``check``, if the replayed schedule were not valid (never for a valid input;
    the check is the independent validator's)."""
    require_instance(instance, "replay")  # (the validator's own check named validate)
    require_schedule(schedule, "replay")
    problems = validate(instance, schedule)
    if problems:
        head = "; ".join(problems[:5]) + (f" (+{len(problems) - 5} more)" if len(problems) > 5 else "")
        raise ReplayError(f"the schedule is not valid for {instance.name}: {head}", problems)
    shop = FullShop(instance, scenario=scenario)
    execute(shop, PlanPolicy(instance, schedule))
    out = shop.schedule()
    out.meta.update({"solver": "replay", "replayed": schedule.meta.get("solver", "?"),
                     "given_makespan": schedule.makespan})
    if check:
        problems = validate(instance, out)
        if problems:  # pragma: no cover - the net keeps the contract
            raise ReplayError(f"replayed schedule of {instance.name} is invalid: {'; '.join(problems[:5])}", problems)
    return out
