"""A plan's orders read from any state of the full net: the guide of a policy's observation, and its follower.

:class:`fms_sim.replay.PlanPolicy` executes a schedule by consuming, resource by resource, the orders it
fixes (each machine's operations, each tool's uses, each vehicle's carries). A policy cannot learn from that
directly: which order comes next is a fact of the plan, not of the state (a policy cloned from exact replays of
CP-SAT plans without it ended 88 % above them, docs/benchmarks.md §9). :class:`PlanGuide` makes it a fact of the
state: for any state of a :class:`~fms_sim.full_shop.FullShop` it computes the *head* of every resource's order
(its first order not yet carried out, read from what the shop has started, dispatched and reserved), without
memory of how the state was reached, so the lookahead's twins and a drifting live shop read it as well.

* :meth:`PlanGuide.features` — per job, tool, AGV and transporter, whether its planned next order can be carried
  out now (:data:`GUIDE_JOB_FEATURES` etc.), plus the job's rank and lateness in the plan: what
  ``FastShopEnv(..., guide="list")`` appends to the observation (:mod:`fms_dispatch.rl.envs`);
* :class:`GuideFollower` — the policy that does what the heads say (dispatch, tool take-up, start, the planned
  vehicles) and holds otherwise; on the plan's own run it is the replay but for the replay's empty
  pre-positioning trips, so it reaches the list schedule's makespan or comes within about 1 % of it
  (``bench/guide_follower.py``). It is the expert a guided model is cloned from
  (``warm_start.expert = "guide"``), and it labels any state the policy reaches (DAgger).

The guide's plan (:func:`guide_plan`) is the better of the earliest-start and earliest-completion list schedules
(:func:`fms_dispatch.exact.greedy_schedule`, 0.7 s for both on a 100-job shop), searched further as a
:class:`PlanEffort` says: the 36 rule pairs' schedules (without tools), randomised restarts, a tabu search over
the plan's resource orders (:mod:`fms_dispatch.tabu`) and, on shops small enough for CP-SAT's full model, a CP-SAT
polish, within a time budget (:data:`DEFAULT_EFFORT` when solving; none in training, where the plan is the plain
list schedule). It is planned
when a run starts, or from the shop's state (residual plans) when a shop is first seen after it started or after
its jobs changed (a live order), or on demand (:meth:`fms_dispatch.rl.envs.FastShopEnv.replan_guide`: when a
machine breaks down or the plan runs :data:`REPLAN_DRIFT` late in a disrupted run, solving and the agent node
re-plan, :class:`fms_dispatch.rl.agent.GuideReplanner`); a new plan
replaces the one in force only if it ends :data:`REPLAN_MARGIN` earlier than that one's order continued from the
state (:func:`retimed_plan`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import numbers
import time
from typing import Any, Callable

import numpy as np

from fms_sim.full_shop import FullShop
from fms_sim.instance import Instance
from fms_sim.schedule import Schedule

from ..full_rules import FullRulePolicy

__all__ = ["GUIDE_JOB_FEATURES", "GUIDE_TOOL_FEATURES", "GUIDE_AGV_FEATURES", "GUIDE_TT_FEATURES", "PlanGuide",
           "GuideFollower", "GuideMoves", "guide_plan", "retimed_plan", "replan_search", "PlanEffort", "DEFAULT_EFFORT",
           "effort_from", "REPLAN_MARGIN", "REPLAN_DRIFT", "REPLAN_BUDGET", "GuideReplan"]

#: per job: buffered part heads its machine's order; its next carry heads its planned AGV's route, and that AGV
#: is idle; its pending request heads the chosen tool's order; rank of its next operation's planned start
#: among the unfinished jobs (0 first, 1 finished); tanh of (planned start - now) / mean operation duration
GUIDE_JOB_FEATURES = ("start_head", "dispatch_head", "carrier_idle", "use_head", "rank", "due")
#: per tool: its next use in the plan can be taken up now as the plan does it (replay's condition)
GUIDE_TOOL_FEATURES = ("take_up",)
#: per AGV / transporter: it is the planned carrier of the part / tool awaiting a vehicle now
GUIDE_AGV_FEATURES = ("planned",)
GUIDE_TT_FEATURES = ("planned",)


@dataclasses.dataclass(frozen=True)
class PlanEffort:
    """How hard the guide's plan is searched: the better list schedule; with ``rules``, for a run at its start on
    a shop without tools, the schedules of the 36 paper-net rule pairs (:func:`fms_dispatch.rules.all_rule_pairs`)
    if better (with tools the rules are far behind the list schedules, docs/benchmarks.md §7); then up to
    ``restarts`` randomised restarts of the best (:func:`fms_dispatch.exact.restart_list_plan`, seeded with
    ``seed``; they search around its start times too), the restarts preceded by the two list schedules that send
    each carry to the nearest vehicle (:func:`fms_dispatch.exact.greedy_schedule`'s ``vehicle="nearest"``) if
    better. The rules stop when the next would end after half of ``budget`` seconds, the nearest-vehicle schedules
    and the restarts after all of it (None: no time limit). Then, with ``tabu`` seconds per operation to plan (all of
    the shop's at a run's start; from a state, those not started), a tabu search over the plan's resource orders
    (:func:`fms_dispatch.tabu.tabu_plan`); for a run at its start, with ``exact`` seconds, on a shop small enough for
    CP-SAT's full model
    (:data:`fms_dispatch.exact.FULL_MODEL_MAX_TASKS` transport tasks), a CP-SAT polish of the best plan
    (:func:`fms_dispatch.exact.polish_plan`). The restarts leave both their time, but keep at least half of what the
    budget has left after the polish's; each gets no more than what the budget has left. ``PlanEffort()`` is the
    plain list schedule, the plan the guided models were trained with; a better plan needs no retraining, since the
    guide's features only say what heads its orders. Results are reproducible while ``budget`` does not cut the
    search short and neither a tabu search (its time limit) nor a CP-SAT polish (its parallel search) runs."""

    restarts: int = 0
    budget: float | None = None
    seed: int = 0
    rules: bool = False
    exact: float = 0.0
    tabu: float = 0.0

    def __post_init__(self) -> None:
        def whole(v: Any) -> bool:  # (numpy's integers too: they are made Python's below)
            return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))

        def seconds(v: Any) -> bool:  # a string was a TypeError at the first comparison; inf never ended
            return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and 0 <= float(v) < math.inf

        if not whole(self.restarts) or self.restarts < 0:
            raise ValueError(f"plan restarts must be an integer >= 0, got {self.restarts!r}")
        if self.budget is not None and not seconds(self.budget):
            raise ValueError(f"plan budget must be a finite number of seconds >= 0 (or None), got {self.budget!r}")
        if not whole(self.seed):
            raise ValueError(f"plan seed must be an integer, got {self.seed!r}")
        if not isinstance(self.rules, (bool, np.bool_)):
            raise ValueError(f"plan rules must be True or False, got {self.rules!r}")
        object.__setattr__(self, "rules", bool(self.rules))  # (np.bool_)
        if not seconds(self.exact):
            raise ValueError(f"plan polish (exact) must be a finite number of seconds >= 0, got {self.exact!r}")
        if not seconds(self.tabu):
            raise ValueError(f"plan tabu search must be a finite number of seconds >= 0 per operation, got "
                             f"{self.tabu!r}")
        for name in ("restarts", "seed", "exact", "tabu", "budget"):
            value = getattr(self, name)
            if isinstance(value, np.generic):  # numpy's numbers as Python's (in meta, configs, JSON)
                object.__setattr__(self, name, value.item())

    def as_dict(self) -> dict[str, Any]:
        return {"restarts": self.restarts, "budget": self.budget, "seed": self.seed, "rules": self.rules,
                "exact": self.exact, "tabu": self.tabu}


#: what a guided model's solver plans with unless told otherwise (``fms solve --guide-restarts/--guide-budget/
#: --[no-]guide-rules/--guide-tabu/--guide-exact``), chosen on validation shops (docs/benchmarks.md §9): 64
#: restarts, then 2.5 ms of tabu search per operation (0.05 s on a 20-operation shop), within 1 s; on larger shops
#: the budget cuts both, the restarts keeping at least half of it
DEFAULT_EFFORT = PlanEffort(restarts=64, budget=1.0, rules=False, exact=0.0, tabu=0.0025)


def effort_from(restarts: int | None = None, budget: float | None = None, rules: bool | None = None,
                exact: float | None = None, tabu: float | None = None, seed: int | None = None) -> PlanEffort:
    """:data:`DEFAULT_EFFORT` with the given settings replaced (the command-line options): ``budget=0`` means no
    time limit, ``exact=0`` no CP-SAT polish, ``tabu=0`` no tabu search, ``seed`` the restarts' seed. Raises
    ValueError for a negative count, budget, polish, tabu search or seed."""
    changes: dict[str, Any] = {}
    if seed is not None:
        if isinstance(seed, numbers.Integral) and not isinstance(seed, bool) and seed < 0:
            raise ValueError(f"plan seed must be an integer >= 0, got {seed!r}")
        changes["seed"] = seed
    if tabu is not None:
        changes["tabu"] = tabu
    if exact is not None:
        changes["exact"] = exact
    if restarts is not None:
        changes["restarts"] = restarts
    if budget is not None:  # 0: no limit (False was taken as 0: refused as PlanEffort refuses True)
        changes["budget"] = None if budget == 0 and not isinstance(budget, bool) else budget
    if rules is not None:
        changes["rules"] = rules
    return dataclasses.replace(DEFAULT_EFFORT, **changes)


#: a guide re-planned from a disrupted state (a breakdown) is adopted only if its plan ends at least this fraction
#: earlier than the plan in force continued from the same state (:func:`retimed_plan`); otherwise the plan in force
#: stays. Chosen on the validation shops in disrupted runs (docs/benchmarks.md §9): the forecasts are nominal and
#: the noise still to come decides, so a new plan that promises only a little loses about as often as it gains
REPLAN_MARGIN = 0.02

#: a guided model also re-plans when an operation starts later than its plan in force says by more than this fraction
#: of that plan's makespan (None: only at breakdowns); plan re-planning's ``DEFAULT_DRIFT``, confirmed on the
#: validation shops (docs/benchmarks.md §9)
REPLAN_DRIFT: float | None = 0.05

#: seconds a re-plan from a state may search (None: the plan search's own budget, 1 s by default; 0.1 s lost half the
#: gain on the validation shops)
REPLAN_BUDGET: float | None = None


@dataclasses.dataclass(frozen=True)
class GuideReplan:
    """What re-planning a guide found: the predicted makespans of the plan in force continued from the state
    (``before``; None where it cannot be continued) and of the new plan (``after``), whether the new plan was
    adopted, the wall time and the search's budget in seconds (None: no limit)."""

    adopted: bool
    before: int | None
    after: int
    wall_time: float
    budget: float | None

    def event(self, reason: str, time: int) -> dict[str, Any]:
        """The re-plan as a run's event (``meta["replans"]``, as :mod:`fms_dispatch.replan` records them)."""
        return {"reason": reason, "time": time, "wall_time": round(self.wall_time, 4), "budget": self.budget,
                "before": self.before, "after": self.after, "status": "adopted" if self.adopted else "kept",
                "method": "guide"}


def guide_plan(shop: FullShop, effort: PlanEffort = PlanEffort()) -> Schedule:
    """The guide's plan for ``shop``: the better of the earliest-start and earliest-completion list schedules
    (the project's ``list`` reference; earliest start on ties), searched further as ``effort`` says (rule pairs,
    restarts, tabu search, polish), from scratch when the run has not started and nothing is down
    (:func:`plans_from_scratch`), else from its state (residual plans: no rule pairs and no polish). A
    state with a vehicle or tool-use choice pending cannot be snapshot; the plans then start from a copy that
    answers those choices (first offered) and stops at the next state that can. It is :func:`first_plan` and then
    :func:`search_from` it (which :mod:`fms_dispatch.rl.beside` runs on another core while a run goes on with the
    first plan)."""
    return search_from(shop.instance, first_plan(shop), effort)


@dataclasses.dataclass(frozen=True)
class FirstPlan:
    """Where the guide's plan search of a shop begins (:func:`first_plan`): the earliest-start list schedule
    (``plan``), the state it plans from (``origin``, a snapshot; None: from scratch), when the search began
    (``t0``, ``time.monotonic()``: its budget counts from there) and what the list schedule took (``seconds``)."""

    plan: Schedule
    origin: Any
    t0: float
    seconds: float


def first_plan(shop: FullShop) -> FirstPlan:
    """The first plan of :func:`guide_plan`'s search for ``shop``: the earliest-start list schedule, from scratch or
    from the shop's state as :func:`guide_plan` says. On large shops it is the plan the search returns: the
    earliest-completion schedule ends 30-50 % later on the large benchmark's 100-job shops, and neither the restarts
    nor the tabu search improve it within the 1 s budget on 5 of its 10 with tools (docs/benchmarks.md §9)."""
    from ..exact import greedy_schedule

    t0 = time.monotonic()
    origin = None if plans_from_scratch(shop) else _state(shop)
    t1 = time.monotonic()
    plan = greedy_schedule(shop.instance, rule="est", origin=origin)
    return FirstPlan(plan, origin, t0, time.monotonic() - t1)


def search_from(inst: Instance, first: FirstPlan, effort: PlanEffort = PlanEffort()) -> Schedule:
    """The rest of :func:`guide_plan`'s search of ``inst`` after its first plan (``first``, :func:`first_plan` of a
    shop of ``inst``): the earliest-completion list schedule, then what ``effort`` adds, within ``effort.budget``
    counted from ``first.t0``. Returns ``first.plan`` itself (the same object) where nothing ends earlier."""
    from ..exact import fits_full_model, greedy_schedule, polish_plan, restart_list_plan, simple_lower_bound
    from ..tabu import residual_lower_bound, tabu_plan

    t0, origin = first.t0, first.origin
    t1 = time.monotonic()
    ect = greedy_schedule(inst, rule="ect", origin=origin)
    one_list = (first.seconds + time.monotonic() - t1) / 2  # what a restart costs
    best = min((first.plan, ect), key=lambda p: p.makespan)  # (the earliest start on ties)
    plans = [first.plan, ect]
    deadline = None if effort.budget is None else t0 + effort.budget
    if effort.rules and origin is None and not inst.has_tools:
        from fms_sim.shop import run_policy

        from ..rules import all_rule_pairs, parse_rule_name

        # a rule run costs 1-8 list schedules (8 on small shops); then about what the last run cost. The rules get
        # half the budget, the restarts the rest
        run_s = 8 * one_list
        half = None if deadline is None else t0 + effort.budget / 2
        names = all_rule_pairs(True)
        for name in sorted(names, key=lambda n: not n.endswith("+nearest")):  # the nearest vehicle first
            t1 = time.monotonic()
            if half is not None and t1 + run_s > half:
                break
            plans.append(run_policy(inst, parse_rule_name(name)))
            run_s = time.monotonic() - t1
            if plans[-1].makespan < best.makespan:
                best = plans[-1]
    # the tabu search (its time grows with the operations to plan: all of them at the run's start, those not started
    # from a state), then, at the run's start, CP-SAT's polish on shops within its full model
    tabu_s = effort.tabu * (inst.n_operations if origin is None else origin.remaining)
    polish = effort.exact if origin is None and fits_full_model(inst) else 0.0
    if effort.restarts:
        # the same two list schedules with the nearest vehicle for each carry, where they end within the budget
        for rule in ("est", "ect"):
            if deadline is not None and time.monotonic() + one_list > deadline - polish:
                break
            cand = greedy_schedule(inst, rule=rule, origin=origin, vehicle="nearest")
            if cand.makespan < best.makespan:
                best = cand
        left = None
        if deadline is not None:
            now = time.monotonic()
            # the restarts leave the polish its time and the tabu search its time, but keep at least half of what is
            # left (on large shops the tabu search's time would take it all; restarts do better there with tools)
            left = deadline - now - polish - min(tabu_s, (deadline - now - polish) / 2)
        if left is None or left >= one_list:  # the first restart would end within the budget
            best = restart_list_plan(inst, best, tries=effort.restarts, budget=left, seed=effort.seed, origin=origin)
    if tabu_s:
        # the bound first: its time (tens of ms on a 100-job shop) counts against the budget too
        bound = simple_lower_bound(inst) if origin is None else residual_lower_bound(origin)
        left = tabu_s if deadline is None else min(tabu_s, deadline - time.monotonic() - polish)
        if left > 0:
            best = tabu_plan(inst, best, budget=left, seed=effort.seed, bound=bound, origin=origin)
    if polish:
        left = polish if deadline is None else min(polish, deadline - time.monotonic())
        if left > 0:
            best = polish_plan(inst, best, time_limit=left, seed=effort.seed)
    return best


def _state(shop: FullShop) -> Any:
    """The snapshot residual plans start from: of ``shop`` now, or, when a vehicle or tool-use choice is pending
    (no snapshot), of a copy that answers those choices (first offered) up to the next state that has one."""
    from fms_sim.snapshot import can_snapshot, snapshot

    if not can_snapshot(shop):
        shop = copy.deepcopy(shop)
        while not can_snapshot(shop) and not shop.done:
            shop.act(shop.legal_actions()[0])
    return snapshot(shop)


def retimed_plan(shop: FullShop, plan: Schedule) -> Schedule:
    """``plan``'s order continued from ``shop``'s state: a residual list schedule that takes the unfinished
    operations in the order of their planned starts (:func:`fms_dispatch.exact.greedy_schedule` with
    ``rule="guided"``), so its makespan is what keeping the plan's order now promises."""
    from ..exact import greedy_schedule

    priority = {(r.job, r.op): float(r.start) for r in plan.operations}
    return greedy_schedule(shop.instance, rule="guided", priority=priority, origin=_state(shop))


def replan_search(shop: FullShop, old: Schedule, effort: PlanEffort) -> tuple[Schedule, int | None]:
    """A re-plan of a guide from ``shop``'s state: the new plan (:func:`guide_plan` with ``effort``) and the makespan
    of ``old``, the plan in force, continued from the state (:func:`retimed_plan`; None where it cannot go on: it
    does not cover the shop's work). It reads ``shop`` and changes nothing, so it can run on a forked copy of the
    shop beside the run (the agent node's re-plans)."""
    plan = guide_plan(shop, effort)
    try:
        before: int | None = retimed_plan(shop, old).makespan
    except (KeyError, ValueError):
        before = None
    return plan, before


def plans_from_scratch(shop: FullShop) -> bool:
    """Whether the guide plans ``shop`` from scratch, as the nominal shop at time 0 (rule pairs and the polish
    allowed, :func:`guide_plan`): its run has not started (:func:`at_start`) and no machine is broken down and no
    vehicle out of service now. A breakdown or outage from time 0 is in the shop's state only: a plan from scratch
    ignored it (EX12 with AGV 0 out for its first 80: the re-plan at time 0 promised the nominal 82, it was adopted
    and the run took 148, 108 with the outage one time unit later)."""
    return at_start(shop) and not any(any(flags) for flags in down_now(shop)[:3])


def down_now(shop: FullShop) -> tuple:
    """What is down in ``shop`` now, with the disruptions it knows: which machines are broken down, which AGVs and
    transporters out of service, and its scenario. At time 0 the state, and so the plan from it, depends on nothing
    else: a guide planned from it serves a run (a twin of it too) with the same, not another run's."""
    out = getattr(shop, "out", {})
    return (tuple(getattr(shop, "m_down", ())), tuple(out.get("agv", ())), tuple(out.get("tt", ())),
            getattr(shop, "scenario", None))


def at_start(shop: FullShop) -> bool:
    """Whether ``shop``'s run has not started: time 0, no operation started and, with AGVs, no part dispatched (a
    shop without AGVs has its first parts at their machines from time 0, without a decision)."""
    if shop.now > 0 or any(shop.started):
        return False
    return not (shop.instance.has_agvs and any(shop.job_started_ops))



class _Orders:
    """Resource orders concatenated: ``J[i], K[i]`` the i-th order, segment ``s`` is ``lo[s]:hi[s]``."""

    def __init__(self, queues: dict[int, list[tuple[int, int]]], ids: range):
        self.ids = list(ids)
        J: list[int] = []
        K: list[int] = []
        lo, hi = [], []
        self.index: dict[tuple[int, int], int] = {}
        for s in self.ids:
            lo.append(len(J))
            for j, k in queues.get(s, ()):
                self.index[j, k] = len(J)
                J.append(j)
                K.append(k)
            hi.append(len(J))
        self.J = np.asarray(J, dtype=np.int64)
        self.K = np.asarray(K, dtype=np.int64)
        self.lo = np.asarray(lo, dtype=np.int64)
        self.hi = np.asarray(hi, dtype=np.int64)

    def heads(self, done: np.ndarray) -> dict[int, tuple[int, int]]:
        """Resource id -> its first order not done."""
        undone = np.flatnonzero(~done)
        if not undone.size:
            return {}
        pos = np.searchsorted(undone, self.lo)
        first = undone[np.minimum(pos, undone.size - 1)]
        ok = (pos < undone.size) & (first < self.hi)
        seg = np.flatnonzero(ok)
        at = first[seg]
        ids = self.ids
        return {ids[s]: jk for s, jk in zip(seg.tolist(), zip(self.J[at].tolist(), self.K[at].tolist()))}


class PlanGuide:
    """The orders of ``plan`` (a schedule of ``instance``, or a residual plan) read from shop states; see the
    module docstring."""

    def __init__(self, instance: Instance, plan: Schedule, effort: PlanEffort | None = None):
        self.instance = instance
        self.plan = plan
        #: the search that made the plan (:meth:`for_shop`); None for a plan given from elsewhere
        self.effort = effort
        #: the time a residual plan starts from (a run's state); None for a plan from scratch
        self.origin: int | None = plan.meta.get("residual")
        #: a plan from the state at its run's start (something down then): :func:`down_now` of that state
        self.down: tuple | None = None
        inst = instance
        L = max(len(ops) for ops in inst.jobs)
        self.start = np.full((inst.n_jobs, L + 1), np.inf)
        mq: dict[int, list[tuple[int, int]]] = {}
        tq: dict[int, list[tuple[int, int]]] = {}
        for r in sorted(plan.operations, key=lambda r: (r.start, r.end)):
            self.start[r.job, r.op] = r.start
            mq.setdefault(r.machine, []).append((r.job, r.op))
            tool = inst.jobs[r.job][r.op].tool if inst.has_tools else None
            if tool is not None:
                tq.setdefault(tool, []).append((r.job, r.op))
        #: where each planned carry starts ((kind, job, op) -> location): the end of the vehicle's empty trip
        self.carry_start: dict[tuple[str, int, int], int] = {}
        aq, self.part_carrier = self._routes("agv", [(t.agv, t) for t in plan.agv_trips])
        rq, self.tool_carrier = self._routes("tt", [(t.transporter, t) for t in plan.tool_trips])
        self.machines = _Orders(mq, range(1, inst.n_machines + 1))
        self.tools = _Orders(tq, range(1, (inst.n_tools if inst.has_tools else 0) + 1))
        self.agvs = _Orders(aq, range(inst.n_agvs if inst.has_agvs else 0))
        self.tts = _Orders(rq, range(inst.n_tool_transporters if inst.has_tools else 0))
        ops = sum(len(o) for o in inst.jobs)
        self.mean_duration = max(1.0, sum(op.duration for o in inst.jobs for op in o) / max(1, ops))
        # the last value of each order's heads and of the plan ranks, with the state they were read from: most
        # decisions change none of what they read (an operation starts at about one decision in seven)
        self._memo: dict[str, tuple[Any, Any]] = {}

    def _cached(self, name: str, key: Any, compute: Any) -> Any:
        """``compute()``, or its last value if it was computed for the same ``key`` (the state it reads). The value
        is shared between the calls that get it: callers read it, never change it."""
        hit = self._memo.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        value = compute()
        self._memo[name] = (key, value)
        return value

    def _routes(self, kind: str, trips: list[tuple[int, Any]]
                ) -> tuple[dict[int, list[tuple[int, int]]], dict[tuple[int, int], int]]:
        """Each vehicle's planned carries in time order and each carry's vehicle, from ``(vehicle, trip)``
        pairs; records where each carry starts in :attr:`carry_start`. Empty trips and legs from a place to
        itself carry nothing."""
        routes: dict[int, list[tuple[int, int]]] = {}
        carrier: dict[tuple[int, int], int] = {}
        for v, t in sorted(trips, key=lambda vt: (vt[1].start, vt[1].end)):
            if t.loaded and t.from_ != t.to:
                routes.setdefault(v, []).append((t.job, t.op))
                carrier[t.job, t.op] = v
                self.carry_start[kind, t.job, t.op] = t.from_
        return routes, carrier

    @classmethod
    def for_shop(cls, shop: FullShop, effort: PlanEffort = PlanEffort()) -> "PlanGuide":
        """The guide of :func:`guide_plan` for ``shop``."""
        guide = cls(shop.instance, guide_plan(shop, effort), effort)
        guide.mark(shop)
        return guide

    def mark(self, shop: Any) -> None:
        """Record what is down in ``shop`` (:attr:`down`) if this is a plan from its state at its start (the state
        at time 0, or, where that cannot be snapshot, the first one after it that can: ``origin`` then later)."""
        self.down = down_now(shop) if self.origin is not None and at_start(shop) else None

    def fits_start(self, shop: Any) -> bool:
        """Whether this guide serves ``shop`` at its start (:func:`at_start`): planned from scratch for the
        nominal start, or from its state at its start with the same things down (:func:`down_now`)."""
        if plans_from_scratch(shop):
            return self.origin is None
        return self.down is not None and self.down == down_now(shop)

    # ------------------------------------------------------------------ the heads of a state
    @staticmethod
    def _served(shop: FullShop, orders: _Orders, started: np.ndarray) -> np.ndarray:
        """Tool orders carried out: the operation started, or its tool reserved for it (use fired)."""
        done = started[orders.J] > orders.K if orders.J.size else np.zeros(0, dtype=bool)
        for t in range(1, len(shop.tool_user)):
            for op in (shop.tool_user[t], shop.tool_next[t]):
                i = orders.index.get(op) if op is not None else None
                if i is not None:
                    done[i] = True
        return done

    def agv_heads(self, shop: FullShop) -> dict[int, tuple[int, int]]:
        """Each AGV's next planned carry not yet dispatched (a dict shared with later calls: read it only)."""
        sent = shop.job_started_ops
        return self._cached("agvs", tuple(sent), lambda: self.agvs.heads(
            np.asarray(sent, dtype=np.int64)[self.agvs.J] > self.agvs.K))

    def tt_heads(self, shop: FullShop, started: np.ndarray, state: tuple | None = None) -> dict[int, tuple[int, int]]:
        """Each transporter's next planned carry whose tool use is not yet served (``started``: the shop's
        next operation to start per job, as an array; ``state``: :meth:`_tool_state` of the shop if the caller has
        it; a dict shared with later calls: read it only)."""
        return self._cached("tts", self._tool_state(shop) if state is None else state,
                            lambda: self.tts.heads(self._served(shop, self.tts, started)))

    @staticmethod
    def _tool_state(shop: FullShop, started: tuple | None = None) -> tuple:
        """What the tool and transporter heads read: the operations started (``started``: ``tuple(shop.started)``
        if the caller has it) and the tools' reservations."""
        return (tuple(shop.started) if started is None else started), tuple(shop.tool_user), tuple(shop.tool_next)

    def view(self, shop: FullShop, tools: bool = True) -> dict[str, Any]:
        """The heads of every order in ``shop``'s state and what follows for each job (see the module
        docstring); the input of :meth:`features` and :class:`GuideFollower`. ``tools=False`` skips the tools'
        and transporters' orders (a state with no tool decision open does not need them)."""
        inst = self.instance
        n = inst.n_jobs
        started = np.asarray(shop.started, dtype=np.int64)
        key = tuple(shop.started)  # (the memo key of what reads the operations started)
        m_heads = self._cached("machines", key, lambda: self.machines.heads(started[self.machines.J] > self.machines.K))
        start_head = np.zeros(n, dtype=bool)
        # a job's buffered part heads its machine's order (read from the buffered parts, a few dozen, rather than
        # asking the buffer for each machine's head: FullShop.buffered_op; the buffer is keyed by job)
        for bucket in shop.p_buffer.buckets.values():
            if bucket:
                j, k, m = bucket[0].colour[:3]
                if m_heads.get(m) == (j, k):
                    start_head[j] = True
        dispatch_head = np.zeros(n, dtype=bool)
        carrier_idle = np.zeros(n, dtype=bool)
        if inst.has_agvs:
            idle_agvs = {v for v, _ in shop.idle_agvs()}
            for v, (j, k) in self.agv_heads(shop).items():
                if shop.next_op(j) == k:
                    dispatch_head[j] = True
                    carrier_idle[j] = v in idle_agvs
        t_heads: dict[int, tuple[int, int]] = {}
        r_heads: dict[int, tuple[int, int]] = {}
        idle_tts: set[int] = set()
        if inst.has_tools and tools:
            state = self._tool_state(shop, key)
            t_heads = self._cached("tools", state, lambda: self.tools.heads(self._served(shop, self.tools, started)))
            r_heads = self.tt_heads(shop, started, state)
            idle_tts = {u for u, _ in shop.idle_transporters()}
        return dict(shop=shop, started=started, started_key=key, start_head=start_head, dispatch_head=dispatch_head,
                    carrier_idle=carrier_idle, t_heads=t_heads, r_heads=r_heads, idle_tts=idle_tts)

    def planned_assignment(self, shop: FullShop, kind: str, legal: list[int]) -> int | None:
        """The plan's answer to an assignment choice of ``kind`` (``agv``/``tt``: the planned carrier,
        :meth:`planned_vehicle`; ``use``: the request the tool serves next, :meth:`planned_use`) if it is among
        ``legal``, else None."""
        if kind == "use":
            job = self.planned_use(shop)
            a = shop.action_index(f"use:{job}") if job is not None else None
        else:
            v = self.planned_vehicle(shop, kind)
            a = shop.action_index(f"{kind}:{v}") if v is not None else None
        return a if a in legal else None

    def planned_use(self, shop: FullShop) -> int | None:
        """:meth:`use_head` of ``shop`` without the rest of its :meth:`view`: the job whose request the chosen tool
        serves next in the plan, from the tools' order heads alone (the same heads, memo and key as the view's)."""
        t = shop.tool_choice
        if t is None:
            return None
        state = self._tool_state(shop)
        heads = self._cached("tools", state, lambda: self.tools.heads(
            self._served(shop, self.tools, np.asarray(shop.started, dtype=np.int64))))
        head = heads.get(t)
        if head is None or shop.request_of(t, head[0]) != head[1]:
            return None
        return head[0]

    def use_head(self, v: dict[str, Any]) -> int | None:
        """The job whose request the chosen tool serves next in the plan (None: no choice open, or the plan's
        next use of the tool is not a pending request now)."""
        shop = v["shop"]
        t = shop.tool_choice
        head = v["t_heads"].get(t) if t is not None else None
        if head is None or shop.request_of(t, head[0]) != head[1]:
            return None
        return head[0]

    def take_up(self, v: dict[str, Any], t: int) -> bool:
        """Tool ``t`` may take up its next planned use now as the replay does: the request is pending and may be
        served, and the tool is at the machine or its planned transporter is idle with this carry next."""
        shop = v["shop"]
        head = v["t_heads"].get(t)
        if head is None:
            return False
        j, k = head
        if shop.request_of(t, j) != k or not shop._servable(t):
            return False
        r = self.tool_carrier.get((j, k))
        if r is not None:
            if v["r_heads"].get(r) != (j, k) or r not in v["idle_tts"]:
                return False
        elif shop.tool_loc[t] != self.instance.jobs[j][k].machine:
            return False
        return shop._candidate(t, j)

    def planned_vehicle(self, shop: FullShop, kind: str) -> int | None:
        """The planned carrier of the part (``kind="agv"``) or tool (``"tt"``) awaiting a vehicle now."""
        if kind == "agv":
            req = shop.awaiting_agv()
            return self.part_carrier.get((req[0], req[1])) if req is not None else None
        req = shop.awaiting_transporter()
        return self.tool_carrier.get((req[2], req[3])) if req is not None else None

    def empty_trips(self, shop: FullShop, idle: list[tuple[str, int, int]]) -> list[tuple[str, int, int]]:
        """The plan's empty trips for the idle vehicles ``(kind, vehicle, location)``: each to where its next
        planned carry starts, when that is elsewhere, as ``(kind, vehicle, destination)``."""
        inst = self.instance
        heads = {"agv": self.agv_heads(shop) if inst.has_agvs else {},
                 "tt": self.tt_heads(shop, np.asarray(shop.started, dtype=np.int64)) if inst.has_tools else {}}
        out = []
        for kind, v, here in idle:
            head = heads[kind].get(v)
            to = self.carry_start.get((kind,) + head) if head is not None else None
            if to is not None and to != here:
                out.append((kind, v, to))
        return out

    @staticmethod
    def vehicle_target(shop: FullShop, kind: str) -> int:
        """Where the awaiting part (``"agv"``) or tool (``"tt"``) is picked up."""
        return shop.awaiting_agv()[2] if kind == "agv" else shop.awaiting_transporter()[1]

    # ------------------------------------------------------------------ features
    def _ranks(self, started: np.ndarray, now: int) -> np.ndarray:
        """Per job, the rank of its next operation's planned start among the jobs' (over the jobs; 1 for none
        planned) and how far ahead of ``now`` that start is (tanh, in mean durations; 0 for none)."""
        n = self.instance.n_jobs
        rows = np.arange(n)
        nops = self.start.shape[1] - 1
        k = np.minimum(started, nops)
        ps = self.start[rows, k]
        fin = np.isfinite(ps)
        order = np.lexsort((rows, np.where(fin, ps, np.inf)))
        rank = np.empty(n, dtype=np.float64)
        rank[order] = np.arange(n)
        out = np.empty((n, 2), dtype=np.float64)
        out[:, 0] = np.where(fin, rank / n, 1.0)
        out[:, 1] = np.where(fin, np.tanh((np.where(fin, ps, 0.0) - now) / self.mean_duration), 0.0)
        return out

    def features(self, shop: FullShop, legal_tools: list[int], max_jobs: int, max_tools: int, max_agvs: int,
                 max_tts: int) -> list[np.ndarray]:
        """The guide's rows (jobs, tools, AGVs, transporters; padded), for the observation."""
        inst = self.instance
        n = inst.n_jobs
        v = self.view(shop, tools=bool(legal_tools) or shop.tool_choice is not None)
        started = v["started"]
        J = np.zeros((max_jobs, len(GUIDE_JOB_FEATURES)), dtype=np.float32)
        J[:n, 0] = v["start_head"]
        J[:n, 1] = v["dispatch_head"]
        J[:n, 2] = v["carrier_idle"]
        u = self.use_head(v)
        if u is not None:
            J[u, 3] = 1.0
        J[:n, 4:6] = self._cached("ranks", (v["started_key"], shop.now), lambda: self._ranks(started, shop.now))
        T = np.zeros((max_tools, len(GUIDE_TOOL_FEATURES)), dtype=np.float32)
        for t in legal_tools:
            T[t - 1, 0] = self.take_up(v, t)
        A = np.zeros((max_agvs, len(GUIDE_AGV_FEATURES)), dtype=np.float32)
        R = np.zeros((max_tts, len(GUIDE_TT_FEATURES)), dtype=np.float32)
        if inst.has_agvs:
            a = self.planned_vehicle(shop, "agv")
            if a is not None:
                A[a, 0] = 1.0
        if inst.has_tools:
            r = self.planned_vehicle(shop, "tt")
            if r is not None:
                R[r, 0] = 1.0
        return [J, T, A, R]


#: the kinds of a choice that only assigns (the net offers such a choice alone): which vehicle carries the part
#: (``agv``) or tool (``tt``) awaiting one, which pending request the chosen tool serves next (``use``)
ASSIGNMENT_KINDS = ("agv", "tt", "use")

_NEAREST = FullRulePolicy("FIFO", "nearest", "earliest-start")  # its vehicle choice only


class GuideFollower:
    """Does what the guide's heads say (``policy(shop) -> net action``): the planned carrier (else the nearest
    vehicle), the planned next use of the chosen tool (else the earliest planned request), then a dispatch, a
    tool take-up or a start that heads its orders, and ``hold`` when none does. When nothing planned is possible
    and the net may not hold (a run that left the plan), the legal action of the earliest planned operation.

    ``guide`` is fixed, or made per shop by :meth:`PlanGuide.for_shop` with ``effort`` (``guide=None``)."""

    def __init__(self, guide: PlanGuide | None = None, effort: PlanEffort = PlanEffort()):
        self.guide = guide
        self.effort = effort
        self._made: dict[int, PlanGuide] = {}

    @property
    def name(self) -> str:
        return "guide:list"

    def _guide(self, shop: FullShop) -> PlanGuide:
        if self.guide is not None:
            return self.guide
        g = self._made.get(id(shop))
        if g is None or g.instance is not shop.instance:
            g = self._made[id(shop)] = PlanGuide.for_shop(shop, self.effort)
        return g

    def __call__(self, shop: FullShop) -> int:
        legal = shop.legal_actions()
        if len(legal) == 1:
            return legal[0]
        g = self._guide(shop)
        kind = shop.action_kind(legal[0])[0]
        if kind in ASSIGNMENT_KINDS:  # the planned carrier or use, else the nearest vehicle or earliest planned request
            a = g.planned_assignment(shop, kind, legal)
            if a is not None:
                return a
            if kind != "use":
                return _NEAREST._vehicle(shop, kind, legal, g.vehicle_target(shop, kind))
            t = shop.tool_choice
            jobs = [shop.action_kind(x)[1] for x in legal]
            return shop.action_index(f"use:{min(jobs, key=lambda j: (g.start[j, shop.request_of(t, j)], j))}")
        view = g.view(shop, tools=any(shop.action_kind(a)[0] == "tool" for a in legal))
        by_kind: dict[str, list[int]] = {}
        for a in legal:
            k, num = shop.action_kind(a)
            by_kind.setdefault(k, []).append(num)
        for j in by_kind.get("job", []):
            if view["dispatch_head"][j] and view["carrier_idle"][j]:
                return shop.action_index(f"job:{j}")
        for t in by_kind.get("tool", []):
            if g.take_up(view, t):
                return shop.action_index(f"tool:{t}")
        for j in by_kind.get("start", []):
            if view["start_head"][j]:
                return shop.action_index(f"start:{j}")
        if shop.hold_action in legal:
            return shop.hold_action
        started = view["started"]

        def planned(a: int) -> tuple[float, int]:
            k, num = shop.action_kind(a)
            if k in ("job", "start"):
                op = shop.next_op(num) if k == "job" else started[num]
                return (float(g.start[num, min(op, g.start.shape[1] - 1)]), a)
            return (float("inf"), a)

        return min(legal, key=planned)


class GuideMoves:
    """Answers a :class:`~fms_sim.stepping.Stepper`'s idle stops with the guide's empty trips
    (:meth:`PlanGuide.empty_trips`): the pre-positioning of a guided model (``+lookahead-guide``). A policy's
    plain run has no idle stops, so its vehicles wait where they are until dispatched; the plan's replay sends
    them ahead, and a run that follows the plan with these trips ends no later than the plan
    (``bench/guide_follower.py``: the guide follower reaches the plan on sl00-sl70; a model that departs from it may
    end later: the default model on sl60 with tools, 4828 against its searched plan's 4822). The moves are not
    verified by trial runs (the lookahead's verification costs a full run per idle stop, minutes on 100 jobs), so a
    run that departs from its plan is not guaranteed to gain by them.

    ``guide_of(shop)`` gives the shop's guide (:meth:`fms_dispatch.rl.agent.Agent.guide_of`). The counters match
    :class:`~fms_dispatch.rl.lookahead.LookaheadPlanner`'s (nothing is verified: :attr:`verifies` is False, and
    progress lines say so instead of counting)."""

    verifies = False

    def __init__(self, guide_of: Callable[[FullShop], PlanGuide]):
        self.guide_of = guide_of
        self.verified = self.accepted = self.rejoined = self.skipped = 0

    @classmethod
    def for_agent(cls, agent: Any) -> "GuideMoves":
        """The empty trips of ``agent``'s guide (:class:`fms_dispatch.rl.agent.Agent`); ValueError for a model
        without a guide."""
        if agent.guide is None:
            raise ValueError(f"model {agent.name} has no plan guide: +lookahead-guide needs a guided model "
                             "(e.g. guided)")
        return cls(agent.guide_of)

    def reset(self) -> None:
        """Nothing to forget: the moves are read from each state."""

    def plan(self, stepper: Any) -> list[Any]:
        from fms_sim.stepping import Move

        shop = stepper.shop
        return [Move(k, v, to) for k, v, to in self.guide_of(shop).empty_trips(shop, stepper.idle)]
