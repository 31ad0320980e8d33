"""Re-planning: keep what has started, re-optimise the rest from the shop's state, within a time budget.

A plan (a schedule from ``cpsat``, ``sos``, ...) is executed through the full-decision net by
:class:`fms_sim.replay.PlanPolicy`. When the shop departs from it, :class:`Replanner` re-plans:

* **triggers** — a live order (jobs the plan does not cover), a breakdown or an outage that begins, an
  operation that starts later than planned by more than ``drift`` times the plan's makespan, or a plan that
  cannot go on (its orders are stuck; rare, after an adopted plan met decisions taken meanwhile);
* **the state** — a :class:`fms_sim.snapshot.Snapshot`: running operations, committed moves and tool
  reservations stay as they are;
* **the optimisation** (:func:`replan`) — within ``budget`` seconds: the current plan's order continued from
  the state (the prediction *before*), earliest-start and earliest-completion list schedules from the state, a
  CP-SAT model of the remaining work (machines, tools, job precedences with their loaded trips; vehicles are
  left to the list scheduler) *hinted with the remaining plan* whose start times then guide a list schedule,
  randomised list-scheduling restarts around the best plan, then a tabu search over its resource orders
  (:func:`fms_dispatch.tabu.tabu_plan` from the state) until the budget is spent; optionally
  (``rules``) the continuations of full-net rules, each run to the end on a nominal copy. The best predicted
  makespan (*after*) wins; if it is no better than *before*, the current plan stays in force (an order always
  needs a new plan: the old one does not cover its jobs);
* **the new plan** is a residual plan: the remaining operations and new trips, executed from the shop's state
  by :meth:`fms_sim.replay.PlanPolicy.resume`.

Each re-plan is an event ``{reason, time, wall_time, budget, before, after, status}`` (status ``adopted``,
``kept`` or ``failed``; the agent node also reports ``timeout``). Offline (:func:`solve_with_replanning`, solvers
``plan:...`` with ``replan``) the simulated shop waits for the re-plan; the agent node re-plans in a forked process
(or a thread) and answers from the current plan (or its fallback rule) meanwhile
(:class:`fms_dispatch.agent_logic.PlanDecider`).
"""

from __future__ import annotations

import copy
import math
import numbers
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

from ortools.sat.python import cp_model

from fms_msgs_json import REPLAN_REASONS  # why a re-plan happens (the values of fms/replan/v1's "reason")

from fms_sim.disruptions import Scenario
from fms_sim.full_shop import FullShop
from fms_sim.instance import Instance, require_instance
from fms_sim.replay import PlanPolicy, ReplayError, execute
from fms_sim.schedule import Schedule
from fms_sim.snapshot import Snapshot, can_snapshot, nominal_copy, snapshot
from fms_sim.stepping import Stepper
from fms_sim.validate import validate

from .exact import _improve_by_priorities, cp_seed, greedy_schedule, run_solver
from .full_rules import parse_full_rule
from .tabu import residual_lower_bound, tabu_plan

__all__ = ["ReplanResult", "replan", "simulate", "Replanner", "retime_from", "solve_with_replanning",
           "REPLAN_REASONS", "DEFAULT_DRIFT", "REPLAN_TABU"]

DEFAULT_DRIFT = 0.05
"""Re-plan when an operation starts later than planned by more than this fraction of the plan's makespan."""

REPLAN_TABU = 0.0025
"""Seconds of tabu search per operation left to plan, after the restarts (at most half of what the budget has left
then): the guided models' plan search's share (:data:`fms_dispatch.rl.guide.DEFAULT_EFFORT`)."""


@dataclass
class ReplanResult:
    """What :func:`replan` found: the best residual plan, the predicted makespans of keeping the current plan
    (``before``; None when it does not cover the remaining work) and of the new one (``after``), the method that
    made it and the wall time in seconds."""

    plan: Schedule
    before: int | None
    after: int
    method: str
    wall_time: float
    n_jobs: int = 0  # the jobs the plan covers (the snapshot's)

    @property
    def better(self) -> bool:
        """Whether the new plan should replace the current one."""
        return self.before is None or self.after < self.before


#: A run of a plan through the net (:func:`simulate`) costs up to this many list schedules of the same work
#: (``greedy_schedule`` from the same snapshot; ``bench/sim_cost.py`` measured 9 on sl70 to 25 on sl00, with a
#: margin for the first, slower calls of a process).
SIM_COST = 30


def _remaining_starts(snap: Snapshot, plan: Schedule | None) -> dict[tuple[int, int], int] | None:
    """The current plan's start time of every operation that has not started; None if it misses one."""
    if plan is None:
        return None
    starts = {(r.job, r.op): r.start for r in plan.operations}
    out = {}
    for j, job in enumerate(snap.instance.jobs):
        for k in range(snap.next_op[j], len(job)):
            if (j, k) not in starts:
                return None
            out[j, k] = starts[j, k]
    return out


def _relaxed_starts(snap: Snapshot, ub: int, hint: dict[tuple[int, int], int] | None, time_limit: float,
                    workers: int, seed: int) -> dict[tuple[int, int], int] | None:
    """Start times of CP-SAT's best schedule of the remaining work with machines, tools and job precedences
    (loaded trips as lags; vehicles relaxed), from the snapshot's release times, hinted with ``hint``."""
    inst = snap.instance
    jobs = inst.jobs
    atr, ttr = inst.agv_travel, inst.tool_travel
    m = cp_model.CpModel()
    s: dict[tuple[int, int], Any] = {}
    by_res: dict[tuple[str, int], list[Any]] = {}
    horizon = max(ub, snap.now) + 1
    mk = m.new_int_var(snap.makespan, horizon, "makespan")
    for j, job in enumerate(jobs):
        k0 = snap.next_op[j]
        for k in range(k0, len(job)):
            op = job[k]
            lo = snap.machine_free[op.machine]
            if k == k0:
                if j in snap.arrival:
                    lo = max(lo, snap.arrival[j])
                else:
                    pick = job[k - 1].machine if k else 0
                    lo = max(lo, snap.ready[j] + (atr[pick][op.machine] if atr is not None else 0))
            t = op.tool if inst.has_tools else None
            if t is not None:
                res = snap.tool_reserved.get(t)
                if res is not None and res[:2] == (j, k):
                    lo = max(lo, res[2])
                elif res is None:
                    here = snap.tool_loc[t]
                    lo = max(lo, snap.tool_free[t] + (ttr[here][op.machine] if ttr is not None else 0))
            v = m.new_int_var(lo, max(lo, horizon), f"s{j}_{k}")
            s[j, k] = v
            iv = m.new_fixed_size_interval_var(v, op.duration, f"i{j}_{k}")
            by_res.setdefault(("m", op.machine), []).append(iv)
            if t is not None:
                by_res.setdefault(("t", t), []).append(iv)
            if k > k0:
                prev = job[k - 1]
                lag = atr[prev.machine][op.machine] if atr is not None else 0
                m.add(v >= s[j, k - 1] + prev.duration + lag)
        if k0 < len(job):
            m.add(mk >= s[j, len(job) - 1] + job[-1].duration)
    for t, res in snap.tool_reserved.items():  # a reserved tool serves its reservation first
        first = s.get(res[:2])
        if first is None:
            continue
        d = jobs[res[0]][res[1]].duration
        for j, job in enumerate(jobs):
            for k in range(snap.next_op[j], len(job)):
                if (j, k) != res[:2] and inst.has_tools and job[k].tool == t:
                    m.add(s[j, k] >= first + d)
    for ivs in by_res.values():
        if len(ivs) > 1:
            m.add_no_overlap(ivs)
    m.minimize(mk)
    if hint:
        for key, v in s.items():
            if key in hint:
                m.add_hint(v, hint[key])
    solver = cp_model.CpSolver()
    p = solver.parameters
    p.max_time_in_seconds = max(0.01, time_limit)
    p.num_workers = max(1, workers)
    p.random_seed = cp_seed(seed)
    p.catch_sigint_signal = False  # the caller (a node) keeps its own SIGINT handler
    status = run_solver(solver, m)
    if status not in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        return None
    return {key: solver.value(v) for key, v in s.items()}


def simulate(sim: FullShop, plan: Schedule | PlanPolicy) -> int | None:
    """Run ``plan``'s orders to the end on ``sim`` (a :func:`fms_sim.snapshot.nominal_copy`, consumed) and
    return the makespan, or None when its orders get stuck (they do not fit the state). ``plan`` is a plan
    (resumed from the state) or a policy following the run (consumed)."""
    try:
        execute(sim, plan if isinstance(plan, PlanPolicy) else PlanPolicy.resume(sim, plan))
    except ReplayError:
        return None
    return sim.makespan


def _rule_plan(sim: FullShop, rule: Any) -> Schedule:
    """The schedule of completing ``sim`` (a nominal copy, consumed) with full-net ``rule``: a whole plan that
    agrees with the state's past, and its makespan the simulated one."""
    sim.net.advance()
    while not sim.done:
        sim.act(rule(sim))
    return sim.schedule()


def replan(snap: Snapshot, current: Schedule | None, budget: float, *, sim: FullShop | None = None,
           policy: PlanPolicy | None = None, seed: int = 0, workers: int = 1,
           rules: Sequence[tuple[str, Any]] = (), tabu: float = REPLAN_TABU) -> ReplanResult:
    """Re-optimise the work left in ``snap`` within ``budget`` seconds (module docstring), warm-started from
    ``current`` (the plan in force: a whole schedule or a residual plan).

    With ``sim`` (a :func:`fms_sim.snapshot.nominal_copy` of the shop at the snapshot) the predictions are
    simulations through the net: *before* runs the current plan's orders on, *after* the two best new plans
    (one that gets stuck is dropped), so both are what the shop would do under nominal times; ``policy`` (a copy
    of the policy following the run, consumed) continues the current plan exactly. Simulations are used only
    where three of them take at most half the budget (a run through the net costs up to :data:`SIM_COST` list
    schedules of the same work); otherwise, and without ``sim``, the predictions are the list scheduler's own
    (*before*: the current plan's order, each operation as early as the state allows). At least one list
    schedule is always made, so a re-plan of a large shop may take up to a second (100 x 20) beyond a very small
    budget.

    ``rules`` (``(name, full-net rule)`` pairs; with ``sim`` only) are further candidates: each rule completes
    a copy of ``sim``, and the run's schedule is a plan, predicted by simulating its orders like the others
    (following a plan's orders can end earlier than the rule did: vehicles are sent as soon as the orders
    allow). They are tried first, while at least half the budget is left; a rule reacts to the state it meets, so after a breakdown or
    under noise its continuation can beat every list schedule of the remaining work."""
    t0 = time.monotonic()
    deadline = t0 + budget
    inst = snap.instance
    hint = _remaining_starts(snap, current)
    cands: list[tuple[Schedule, str]] = [(greedy_schedule(inst, rule="est", origin=snap), "est")]
    one = time.monotonic() - t0  # one list schedule: what each further step must fit in
    sim_cost = SIM_COST * one
    # simulate only where three runs (the current plan's, the two best new plans') take at most half the budget:
    # on larger shops they would leave the searches no time, or run past the budget
    if sim is not None and deadline - time.monotonic() < 6 * sim_cost:
        sim = None
    ruled: list[tuple[int, int, Schedule, str]] = []  # (simulated makespan, order, plan, method)
    for name, rule in rules if sim is not None else ():
        if time.monotonic() > t0 + budget / 2:
            break
        made = _rule_plan(copy.deepcopy(sim), rule)
        executed = simulate(copy.deepcopy(sim), made)  # the plan's orders, as the shop will follow them
        if executed is not None:
            ruled.append((executed, -1 - len(ruled), made, name))
    before: int | None = None
    reserve = 0.0
    if hint is not None:  # the current plan covers the remaining work: how would it end?
        t1 = time.monotonic()
        if sim is not None:
            before = simulate(copy.deepcopy(sim), policy if policy is not None else current)
            reserve = 2 * (time.monotonic() - t1)  # the final simulations of two new plans
        else:
            before = greedy_schedule(inst, rule="guided", priority=hint, origin=snap).makespan
    elif sim is not None:
        reserve = sim_cost  # the final simulation of the best new plan (after an order: nothing measured it yet)
    if time.monotonic() + one <= deadline - reserve:
        cands.append((greedy_schedule(inst, rule="ect", origin=snap), "ect"))
    best = min(cands, key=lambda c: c[0].makespan)[0]
    left = deadline - reserve - time.monotonic()
    if left > 2 * one + 0.05:
        starts = _relaxed_starts(snap, best.makespan, hint or {(r.job, r.op): r.start for r in best.operations},
                                 0.4 * left - one, workers, seed)
        if starts is not None and time.monotonic() + one <= deadline - reserve:
            cands.append((greedy_schedule(inst, rule="guided", priority=starts, origin=snap), "cpsat"))
    best = min(cands, key=lambda c: c[0].makespan)[0]
    if time.monotonic() + one <= deadline - reserve:
        # the restarts, then the tabu search from the best plan (its time grows with the work left; at most half of
        # what is left)
        tabu_s = min(tabu * snap.remaining, (deadline - reserve - time.monotonic()) / 2)
        improved = _improve_by_priorities(inst, best, None, 0, deadline - reserve - tabu_s, seed, None, t0,
                                          origin=snap)
        if improved.makespan < best.makespan:
            cands.append((improved, "restarts"))
            best = improved
    left = deadline - reserve - time.monotonic()
    if tabu > 0 and left > 0:
        searched = tabu_plan(inst, best, budget=left, seed=seed, bound=residual_lower_bound(snap), origin=snap)
        if searched.makespan < best.makespan:
            cands.append((searched, "tabu"))
    cands.sort(key=lambda c: c[0].makespan)
    if sim is None:
        plan, method = cands[0]
        after = plan.makespan
    else:
        scored = list(ruled)
        for i, (plan, method) in enumerate(cands[:2]):
            if i and time.monotonic() + reserve / 2 > deadline:
                break
            made = simulate(copy.deepcopy(sim), plan)
            if made is not None:
                scored.append((made, i, plan, method))
        if not scored:
            raise RuntimeError("every new plan got stuck in the simulation of the shop")
        after, _, plan, method = min(scored)
    plan.meta.update(solver="replan", method=method)
    return ReplanResult(plan, before, after, method, time.monotonic() - t0, inst.n_jobs)


@dataclass
class Replanner:
    """Executes ``plan`` on a :class:`~fms_sim.stepping.Stepper` over a :class:`~fms_sim.full_shop.FullShop`
    and re-plans on the triggers of the module docstring (``budget`` seconds each; ``drift`` as a fraction of
    the plan's makespan). Offline use: :meth:`step` at every stop; the agent node drives :meth:`trigger`,
    :meth:`compute` (in a process or a thread) and :meth:`adopt` itself."""

    instance: Instance
    plan: Schedule
    budget: float = 2.0
    drift: float = DEFAULT_DRIFT
    seed: int = 0
    workers: int = 1
    events: list[dict[str, Any]] = field(default_factory=list)
    #: full-net rules (names, e.g. ``rule:LPSR+nearest+fifo``) whose continuations each re-plan also weighs
    rules: Sequence[str] = ()
    #: seconds of tabu search per operation left to plan in each re-plan (0: none; :data:`REPLAN_TABU`)
    tabu: float = REPLAN_TABU

    def __post_init__(self) -> None:
        """Check the arguments (a ValueError naming the first bad one) before anything runs: a budget of inf ran a
        search with no deadline (it never ended), and an invalid plan was followed as far as it went, then dropped
        for a silent re-plan from scratch (replay and ``plan:file:`` refuse one with the validator's errors)."""
        require_instance(self.instance, "Replanner")
        for name, v, least in (("budget", self.budget, "positive"), ("drift", self.drift, "positive"),
                               ("tabu search", self.tabu, ">= 0 seconds per operation")):
            ok = isinstance(v, numbers.Real) and not isinstance(v, bool) and (0 < v if least == "positive" else 0 <= v)
            if not ok or not math.isfinite(v):
                raise ValueError(f"the re-planning {name} must be {least} and finite, got {v!r}")
        if not isinstance(self.plan, Schedule):
            raise TypeError(f"the plan must be a Schedule (Schedule.load reads one), got {type(self.plan).__name__}")
        problems = validate(self.instance, self.plan)
        if problems:
            head = "; ".join(problems[:5]) + (f" (+{len(problems) - 5} more)" if len(problems) > 5 else "")
            raise ValueError(f"the plan is not valid for {self.instance.name}: {head}")
        self._rules = [(name, parse_full_rule(name)) for name in self.rules]
        self.policy: PlanPolicy | None = None
        self._pending: str | None = None
        self._off_plan = False  # the last answer came from the fallback rule: the plan resumes from the state
        self._follow(self.plan, self.instance.n_jobs)

    def _follow(self, plan: Schedule, n_jobs: int, shop: FullShop | None = None) -> None:
        """Make ``plan`` the plan in force (from ``shop``'s state when given)."""
        self.plan = plan
        self.policy = PlanPolicy.resume(shop, plan) if shop is not None else PlanPolicy(self.instance, plan)
        self._planned = {(r.job, r.op): r.start for r in plan.operations}
        self._lag = 0  # the lateness already answered by a re-plan that kept this plan
        self._tol = max(1.0, self.drift * plan.makespan)
        self._n_jobs = n_jobs
        self._seen = len(shop.rec.ops) if shop is not None else 0
        self._active = self._disruptions(shop) if shop is not None else set()

    @staticmethod
    def _disruptions(shop: FullShop) -> set[tuple]:
        """The disruptions in force: each down machine and each vehicle out of service, with the start of its latest
        window begun (a window that starts where the one before ends is a new disruption: by the flags alone it was
        none, and the plan waited for the vehicle through the second window)."""
        sc, now = shop.scenario, shop.now

        def since(windows: Any) -> int | None:
            return max((w.start for w in windows if w.start <= now), default=None)

        down = {("breakdown", m, since(sc.windows(m)) if sc else None) for m, d in enumerate(shop.m_down) if d}
        out = {("outage", kind, v, since(o for o in sc.outages if o.kind == kind and o.vehicle == v) if sc else None)
               for kind, flags in shop.out.items() for v, o in enumerate(flags) if o}
        return down | out

    # ------------------------------------------------------------------ triggers
    def trigger(self, shop: FullShop) -> str | None:
        """Why the plan in force should be revised now (one of :data:`REPLAN_REASONS`), or None. A reason found
        at a stop where no snapshot can be taken is kept until one can (see :func:`fms_sim.snapshot.snapshot`)."""
        reason = self._pending
        if reason is None:
            if shop.n_jobs != self._n_jobs:
                reason = "order"
            else:
                active = self._disruptions(shop)
                new = active - self._active
                self._active = active
                if new:
                    reason = min(d[0] for d in new)  # "breakdown" before "outage"
                else:
                    ops = shop.rec.ops
                    for r in ops[self._seen:]:
                        planned = self._planned.get((r.job, r.op))
                        if planned is not None and r.start - planned - self._lag > self._tol:
                            reason = "late"
                            break
                    self._seen = len(ops)
        if reason is not None and not self.can_snapshot(shop):
            self._pending = reason
            return None
        self._pending = None
        return reason

    can_snapshot = staticmethod(can_snapshot)

    # ------------------------------------------------------------------ re-planning
    def compute(self, snap: Snapshot, sim: FullShop | None = None, policy: PlanPolicy | None = None) -> ReplanResult:
        """The re-plan from ``snap``, ``sim`` (its nominal copy of the shop) and ``policy`` (a copy of the plan's
        policy then), all taken by the caller: this touches nothing of the running shop, so it is safe in another
        thread (see :meth:`take`)."""
        return replan(snap, self.plan, self.budget, sim=sim, policy=policy, seed=self.seed + len(self.events),
                      workers=self.workers, rules=self._rules, tabu=self.tabu)

    def take(self, shop: FullShop) -> tuple[Snapshot, FullShop, PlanPolicy | None]:
        """What :meth:`compute` needs, taken from ``shop`` now (in the thread that runs the shop)."""
        self._taken_at = (shop.now, shop.net.acted, shop.n_jobs)
        self._taken_disruptions: set[tuple] | None = self._disruptions(shop)
        return snapshot(shop), nominal_copy(shop), copy.deepcopy(self.policy)

    def moved_on(self, shop: FullShop) -> bool:
        """Whether ``shop`` has acted since :meth:`take` (a re-plan computed meanwhile must be re-timed)."""
        return getattr(self, "_taken_at", None) != (shop.now, shop.net.acted, shop.n_jobs)

    @staticmethod
    def retime(shop: FullShop, plan: Schedule) -> Schedule:
        """``plan``'s order of the remaining operations, re-timed from ``shop``'s state now (a list schedule
        guided by the plan's start times; jobs the plan does not know come last), or the earliest-start list
        schedule from the state where that ends earlier. A plan made from an earlier state of the run thus fits
        every decision taken since: its orders can all be carried out from here. The plan's order is not kept at
        any price: the decisions taken while it was computed (hundreds on a large shop) can leave its start
        times a poor guide (on sl70, 800 states after a live order the guided re-timing of an 8000 plan ended at
        9447, the list schedule at 7894; ``meta["retime"]`` says which was taken)."""
        return retime_from(snapshot(shop), plan)

    def adopt(self, shop: FullShop, result: ReplanResult | None, reason: str, *, wall_time: float | None = None,
              error: str | None = None) -> dict[str, Any]:
        """Put ``result`` in force if it is better (or the plan no longer covers the shop's jobs) and record the
        event; ``result`` None (the re-plan failed: ``error`` says why) keeps the current plan."""
        event: dict[str, Any] = {"reason": reason, "time": shop.now, "budget": self.budget,
                                 "wall_time": round(wall_time if wall_time is not None
                                                    else (result.wall_time if result else 0.0), 4)}
        if result is None:
            event.update(status="failed", before=None, after=None, error=error or "no plan")
            self.dropped(shop)
        else:
            event.update(before=result.before, after=result.after, method=result.method)
            if result.better or shop.n_jobs != self._n_jobs or reason == "stuck":
                if self.moved_on(shop):  # computed from an earlier state (beside the run): re-time it from here
                    self._follow(self.retime(shop, result.plan), shop.n_jobs, shop)
                    event["retimed"] = True
                    if result.n_jobs and result.n_jobs < shop.n_jobs:
                        self._pending = "order"  # jobs ordered meanwhile were only fitted in: plan them too
                else:
                    self._follow(result.plan, result.n_jobs or shop.n_jobs, shop)
                event["status"] = "adopted"
            else:
                event["status"] = "kept"
                self._follow_state(shop)
        self._answered_at_take()
        self.events.append(event)
        return event

    def dropped(self, shop: FullShop) -> None:
        """A re-plan that brought no plan (it failed, or the agent reports it ``timeout``): the current plan stays, and
        the shop's state is taken as seen, but for the disruptions begun and the jobs ordered since the re-plan started
        (each triggers a re-plan of its own)."""
        self._follow_state(shop)
        self._orders_since_take_stay()
        self._answered_at_take()

    def _orders_since_take_stay(self) -> None:
        """No plan came of a re-plan: jobs ordered since it started (:meth:`take`) were planned by nothing, so they
        stay an order to re-plan for (taking the state as seen used the trigger up, and they waited until the plan
        got stuck)."""
        taken = getattr(self, "_taken_at", None)
        if taken is not None and taken[2] < self._n_jobs:
            self._n_jobs = taken[2]

    def _answered_at_take(self) -> None:
        """A re-plan answers the disruptions of the state it started from (:meth:`take`): those begun while it ran
        (beside the run, as the agent node's re-plans do) stay new, so each triggers a re-plan of its own. Taking the
        state at the end as seen dropped them: a breakdown begun during a re-plan for an outage was never planned
        for."""
        taken = getattr(self, "_taken_disruptions", None)
        if taken is not None:
            self._active &= taken
            self._taken_disruptions = None

    def _follow_state(self, shop: FullShop) -> None:
        """Keep the current plan but take the shop's state as seen, its lateness so far included: one deviation
        triggers once (a kept plan's old start times made every later start 'late' again, one re-plan each)."""
        late = [r.start - self._planned[r.job, r.op] for r in shop.rec.ops if (r.job, r.op) in self._planned]
        self._lag = max([self._lag] + late)
        self._seen = len(shop.rec.ops)
        self._active = self._disruptions(shop)
        self._n_jobs = shop.n_jobs  # new jobs left out wait; a plan that then cannot go on re-plans ("stuck")

    def replan_now(self, shop: FullShop, reason: str) -> dict[str, Any]:
        """Re-plan synchronously from ``shop``'s state (offline: the simulated shop waits)."""
        t0 = time.monotonic()
        try:
            result = self.compute(*self.take(shop))
        except (ValueError, RuntimeError) as exc:
            return self.adopt(shop, None, reason, wall_time=time.monotonic() - t0, error=str(exc).splitlines()[0])
        return self.adopt(shop, result, reason)

    # ------------------------------------------------------------------ answering
    def answer(self, stepper: Stepper) -> str:
        """The plan's answer to ``stepper``'s stop (see :meth:`PlanPolicy.answer`)."""
        assert self.policy is not None
        return self.policy.answer(stepper)

    def apply(self, stepper: Stepper, label: str) -> None:
        """Move the plan on by ``label`` (before the stepper applies it), unless it came from the fallback."""
        assert self.policy is not None
        if not self._off_plan:
            self.policy.apply(stepper, label)

    def step(self, stepper: Stepper, fallback: Any = None) -> str:
        """Offline: re-plan if a trigger fires, then the answer to the stop (moved on by :meth:`apply`). A plan
        that is stuck is re-planned at once; if it still is, ``fallback`` (a full-net rule) answers."""
        shop = stepper.shop
        assert isinstance(shop, FullShop)
        if self._off_plan:  # the fallback acted last time: the plan goes on from what it did
            self.policy = PlanPolicy.resume(shop, self.plan)
            self._off_plan = False
        reason = self.trigger(shop)
        if reason is not None:
            self.replan_now(shop, reason)
        try:
            return self.answer(stepper)
        except ReplayError:
            if self.can_snapshot(shop):
                self.replan_now(shop, "stuck")
                try:
                    return self.answer(stepper)
                except ReplayError:
                    pass
            if fallback is None or stepper.kind == "idle":
                raise
            self._off_plan = True
            return shop.action_label(fallback(shop))


def retime_from(snap: Snapshot, plan: Schedule) -> Schedule:
    """``plan``'s order of the remaining operations re-timed from the state ``snap``, or the earliest-start list
    schedule from it where that ends earlier (see :meth:`Replanner.retime`)."""
    starts = {(r.job, r.op): r.start for r in plan.operations}
    last = max(starts.values(), default=0) + 1
    prio = {(j, k): starts.get((j, k), last + k) for j, job in enumerate(snap.instance.jobs)
            for k in range(snap.next_op[j], len(job))}
    guided = greedy_schedule(snap.instance, rule="guided", priority=prio, origin=snap)
    est = greedy_schedule(snap.instance, rule="est", origin=snap)
    out, how = (est, "est") if est.makespan < guided.makespan else (guided, "guided")  # a tie keeps the order
    out.meta.update(plan.meta)
    out.meta["residual"] = snap.now  # (a residual plan's own, of an earlier state, replaced it: tabu_plan then refused
    out.meta["retimed"] = snap.now   # the re-timed plan with this state's snapshot)
    out.meta["retime"] = how
    return out


def solve_with_replanning(instance: Instance, plan: Schedule, *, budget: float = 2.0, drift: float = DEFAULT_DRIFT,
                          scenario: Scenario | None = None, seed: int = 0,
                          fallback: str = "rule:MTWR+nearest+fifo", rules: Sequence[str] = (),
                          tabu: float = REPLAN_TABU) -> Schedule:
    """Execute ``plan`` through the full-decision net in a shop disrupted by ``scenario``, re-planning on the
    triggers (module docstring; ``rules``, ``tabu``: see :class:`Replanner`); the realised schedule, with
    ``meta["replans"]`` the events."""
    shop = FullShop(instance, scenario=scenario)
    rp = Replanner(instance, plan, budget=budget, drift=drift, seed=seed, rules=tuple(rules), tabu=tabu)
    rule = parse_full_rule(fallback)
    stepper = Stepper(shop, idle_stops=True)
    stepper.advance()
    answers = 0
    while stepper.kind != "done":
        label = rp.step(stepper, rule)
        rp.apply(stepper, label)
        stepper.apply(label)
        answers += 1
    out = shop.schedule()
    out.meta["replans"] = rp.events
    out.meta["answers"] = answers
    return out
