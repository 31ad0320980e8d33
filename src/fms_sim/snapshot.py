"""What a planner knows of a running full-decision shop: a :class:`Snapshot` for re-planning from mid-run.

Re-planning (:mod:`fms_dispatch.replan`) keeps what has started and re-plans the rest. It needs, at the moment
it is asked, when each resource becomes free and where the parts, vehicles and tools are, with everything the
shop has already committed folded in: a part an AGV has been sent for, a tool reserved for an operation (and the
transporter bringing it), an operation running on a machine, a machine that is down, a vehicle out of service.
:func:`snapshot` reads that from a :class:`~fms_sim.full_shop.FullShop` into plain, immutable data, so a plan
can be computed from it in another thread while the shop runs on. :func:`nominal_copy` is the same knowledge
as a runnable shop: a what-if copy in which a plan can be tried to the end (how long it would take, and
whether its orders can all be carried out from here).

Times are what the decider can know: a running operation ends at its start plus its *nominal* duration (plus
the repairs of breakdowns that have begun while it runs), never earlier than one time unit from now; a machine
that is down is free at the end of its known repair; a vehicle out of service is free when its outage ends.
Legs under way end when the shop's record says (travel noise is small against processing; this is the one
realised time a snapshot reads). Breakdowns and outages that have not begun are unknown, as in the shop.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from .disruptions import Scenario
from .full_shop import FullShop
from .instance import Instance

__all__ = ["Snapshot", "snapshot", "can_snapshot", "nominal_copy"]


@dataclass(frozen=True)
class Snapshot:
    """The state a plan continues from (module docstring). Indices: jobs ``0..n-1``, machines ``1..M`` (index 0
    unused), AGVs and transporters from 0, tools ``1..T`` (index 0 unused).

    * ``next_op[j]``: the first operation of job j that has not started (``len(job)`` when all have);
    * ``ready[j]``: when job j's part is free to move on (the end of its running operation, else ``now``);
    * ``arrival[j]``: when the part reaches the machine of ``next_op[j]`` if that move is done or committed (in
      a buffer, carried, or an AGV already sent for it); absent when the plan still has to move it;
    * ``machine_free[m]``, ``agv_loc``/``agv_free``, ``tt_loc``/``tt_free``, ``tool_loc``/``tool_free``: where
      each resource is and when it is free, after its committed work;
    * ``tool_reserved[t] = (job, op, at)``: tool t is reserved for that not-yet-started operation and is at its
      machine at ``at``; no other use of t comes before it;
    * ``makespan``: when the last operation that has started ends (estimated as above);
    * ``held``: the vehicles, as ``("agv", v)`` and ``("tt", r)``, that stand idle now (in service). Their idle
      stop is had (:class:`~fms_sim.stepping.Stepper`: once per idle period, before the decisions of a moment), so
      no empty move can be ordered for them any more: the executor of a residual plan
      (:meth:`fms_sim.replay.PlanPolicy.resume`) drops their leading empty legs, and such a vehicle leaves only when
      its next carry is dispatched, deadheading straight from where it stands. That dispatch is ``job:J`` for a
      part, enabled once the part's previous operation has *started* (or now, when it has), and ``tool:T`` +
      ``use:J`` + ``tt:R`` for a tool, enabled once the tool's previous use has *started* (or now, when the tool is
      free or its use runs). Planners start such a vehicle's first empty trip no earlier than that (a plan that
      sent it off at ``now`` ended later when executed than it predicted). Empty at the start of a run
      (:meth:`initial`), where a whole plan's empty moves are made at the vehicles' first idle stop.
    """

    instance: Instance
    now: int
    next_op: tuple[int, ...]
    ready: tuple[int, ...]
    arrival: dict[int, int]
    machine_free: tuple[int, ...]
    agv_loc: tuple[int, ...]
    agv_free: tuple[int, ...]
    tt_loc: tuple[int, ...]
    tt_free: tuple[int, ...]
    tool_loc: tuple[int, ...]
    tool_free: tuple[int, ...]
    tool_reserved: dict[int, tuple[int, int, int]]
    makespan: int
    held: frozenset[tuple[str, int]] = frozenset()

    @property
    def remaining(self) -> int:
        """How many operations have not started."""
        return sum(len(job) - k for job, k in zip(self.instance.jobs, self.next_op))

    def check_of(self, instance: Instance) -> None:
        """Raise ValueError unless this is a state of ``instance``'s shop: the same jobs (operations, machines,
        tools, durations) and fleets, since a plan from it indexes them (a snapshot of another shop would fail
        deep inside the planner, or plan the wrong jobs)."""
        mine = self.instance
        if mine is instance:
            return
        if mine.jobs != instance.jobs:
            raise ValueError(f"the snapshot is of other jobs than {instance.name}'s")
        fleet = ("n_machines", "n_agvs", "n_tool_transporters", "n_tools")
        if any(getattr(mine, f) != getattr(instance, f) for f in fleet):
            raise ValueError(f"the snapshot is of another shop than {instance.name} (machines, vehicles or tools "
                             f"differ)")
        if mine.agv_travel != instance.agv_travel or mine.tool_travel != instance.tool_travel:  # EX12's for EX11:
            # its vehicles' times were of other travel times, and a residual plan mixed the two layouts
            raise ValueError(f"the snapshot is of another layout than {instance.name}'s (travel times differ)")

    @classmethod
    def initial(cls, instance: Instance) -> "Snapshot":
        """The state at time 0 of a run: everything at the depot (location 0), nothing started."""
        n = instance.n_jobs
        return cls(instance, 0, (0,) * n, (0,) * n, {}, (0,) * (instance.n_machines + 1),
                   (0,) * instance.n_agvs, (0,) * instance.n_agvs, (0,) * instance.n_tool_transporters,
                   (0,) * instance.n_tool_transporters, (0,) * (instance.n_tools + 1), (0,) * (instance.n_tools + 1),
                   {}, 0)


def _running_end(shop: FullShop, m: int, i: int) -> int:
    """The estimated end of the operation recorded at ``shop.rec.ops[i]``, running on machine m."""
    rec, now = shop.rec.ops[i], shop.now
    end = rec.start + shop.instance.jobs[rec.job][rec.op].duration
    sc = shop.scenario
    if sc is not None:
        for b in sc.windows(m):  # repairs of breakdowns that have begun while it runs
            if b.start <= now and rec.start <= b.start < end:
                end += b.duration
    return max(end, now + 1)


def _all(shop: FullShop, place) -> list[tuple]:
    """The colours of the tokens in ``place`` and of those on their way into it (a trip under way)."""
    return place.colours() + [c for _, c in shop.net.sojourning(place)]


def can_snapshot(shop: FullShop) -> bool:
    """Whether ``shop`` stands where a snapshot can be taken: no vehicle or tool-use choice is pending (an idle
    stop, or a decision among the base actions)."""
    return shop.tool_choice is None and not (shop.instance.has_agvs and len(shop.p_awaiting_agv)) and not (
        shop.instance.has_tools and len(shop.p_awaiting_tt))


def snapshot(shop: FullShop) -> Snapshot:
    """The :class:`Snapshot` of ``shop`` now; raises ``ValueError`` unless :func:`can_snapshot`."""
    if not isinstance(shop, FullShop):  # a paper-net Shop failed deep inside (no tool_choice)
        raise TypeError(f"a snapshot is taken of a FullShop (the full-decision net), not a {type(shop).__name__}")
    if not can_snapshot(shop):
        raise ValueError(f"no snapshot at time {shop.now}: a vehicle or tool-use choice is pending")
    inst, now = shop.instance, shop.now
    jobs = inst.jobs
    n, M = inst.n_jobs, inst.n_machines
    sc = shop.scenario
    down_until = [0] * (M + 1)
    out_until: dict[tuple[str, int], int] = {}
    if sc is not None:
        for b in sc.breakdowns:
            if b.start <= now < b.end:
                down_until[b.machine] = b.end
        for o in sc.outages:
            if o.start <= now < o.end:
                out_until[o.kind, o.vehicle] = o.end
    # machines and the operations running on them
    machine_free = [now] * (M + 1)
    op_end: dict[tuple[int, int], int] = {}
    makespan = max((r.end for r in shop.rec.ops if r.end <= now), default=0)
    for m in range(1, M + 1):
        i = shop._running_rec[m]
        if i >= 0:
            r = shop.rec.ops[i]
            machine_free[m] = op_end[r.job, r.op] = _running_end(shop, m, i)
            makespan = max(makespan, machine_free[m])
        machine_free[m] = max(machine_free[m], down_until[m])
    next_op = list(shop.started)
    ready = [op_end.get((j, next_op[j] - 1), now) for j in range(n)]
    # vehicles, with the parts and tools they are committed to
    arrival: dict[int, int] = {}
    agv_loc, agv_free = list(shop.agv_loc), [max(t, now) for t in shop.agv_free_at]
    if inst.has_agvs:
        T = inst.agv_travel
        assert T is not None
        for v, j, k, pickup, m in _all(shop, shop.p_agv_pick):  # on the way to a part, or waiting for it
            start = max(agv_free[v], ready[j], out_until.get(("agv", v), 0))  # an AGV out of service waits
            arrival[j] = agv_free[v] = start + T[pickup][m]
            agv_loc[v] = m  # the committed carry ends at the part's machine (it was left at the pickup)
        for v, j, k, pickup, m in _all(shop, shop.p_agv_drop):  # carrying it
            arrival[j] = agv_free[v]
    for j in range(n):
        k = next_op[j]
        if k >= len(jobs[j]) or j in arrival:
            continue
        if shop.buffered_op(j) is not None:
            arrival[j] = now
        elif not inst.has_agvs or (k > 0 and jobs[j][k - 1].machine == jobs[j][k].machine):
            arrival[j] = ready[j]  # no AGV trip: the part goes to the buffer when it is ready
    tt_loc, tt_free = list(shop.tt_loc), [max(t, now) for t in shop.tt_free_at]
    tool_loc, tool_free = list(shop.tool_loc), [now] * (inst.n_tools + 1)
    reserved: dict[int, tuple[int, int, int]] = {}
    if inst.has_tools:
        TT = inst.tool_travel
        for t in range(1, inst.n_tools + 1):
            user = shop.tool_user[t]
            if shop.tool_running[t] and user is not None:
                tool_free[t] = op_end.get(user, now)
        carried: dict[tuple[int, int], int] = {}
        for r, t, src, j, k, m in _all(shop, shop.p_tt_pick):  # on the way to the tool, or waiting for it
            start = max(tt_free[r], tool_free[t], out_until.get(("tt", r), 0))
            carried[j, k] = tt_free[r] = start + TT[src][m]
            tt_loc[r] = m  # the committed carry ends at the machine
        for r, t, src, j, k, m in _all(shop, shop.p_tt_drop):
            carried[j, k] = tt_free[r]
        for t in range(1, inst.n_tools + 1):
            op = shop.reserved_op(t)
            if op is None:
                continue
            j, k = op
            m = jobs[j][k].machine
            at = carried.get(op)
            if at is None:  # already there, or waiting on its machine for the running use to end
                at = now if op in shop.tool_ready_for else tool_free[t]
            reserved[t] = (j, k, at)
    for (kind, v), end in out_until.items():
        if kind == "agv":
            agv_free[v] = max(agv_free[v], end)
        else:
            tt_free[v] = max(tt_free[v], end)
    # idle vehicles have had their idle stop: they wait for their next carry's dispatch (see Snapshot.held)
    held = frozenset([("agv", v) for v, _ in shop.idle_agvs()] + [("tt", r) for r, _ in shop.idle_transporters()])
    return Snapshot(inst, now, tuple(next_op), tuple(ready), arrival, tuple(machine_free), tuple(agv_loc),
                    tuple(agv_free), tuple(tt_loc), tuple(tt_free), tuple(tool_loc), tuple(tool_free), reserved,
                    makespan, held)


def nominal_copy(shop: FullShop) -> FullShop:
    """A copy of ``shop`` whose future is what a decider can expect: running operations end at the estimate of
    :class:`Snapshot`, everything still to come takes its nominal time (no noise), and breakdowns and outages
    that have not begun do not happen (the ones under way end as known). The copy can be run to the end."""
    if not isinstance(shop, FullShop):
        raise TypeError(f"a nominal copy is made of a FullShop (the full-decision net), not a {type(shop).__name__}")
    sim = shop.copy()
    sc = shop.scenario
    if sc is None:
        return sim
    now = shop.now
    known = Scenario(breakdowns=tuple(b for b in sc.breakdowns if b.start <= now),
                     outages=tuple(o for o in sc.outages if o.start <= now))
    sim.scenario = None if known.empty else known
    sim.net.discard_pending(sim.p_disrupt, lambda c: c[0] in ("down", "out"))  # pending ones have not begun
    for m, i in enumerate(sim._running_rec):
        if i < 0:
            continue
        rec = sim.rec.ops[i]
        delta = _running_end(shop, m, i) - rec.end
        if delta:
            sim.net.postpone(sim.p_busy, m, delta)
            sim.rec.ops[i] = replace(rec, end=rec.end + delta)
            sim.machine_busy_until[m] += delta
    return sim
