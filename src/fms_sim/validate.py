"""Independent schedule validator.

It checks a :class:`~fms_sim.schedule.Schedule` against its :class:`~fms_sim.instance.Instance` by the
project's semantic contract, without using the Petri net, and reports *every* violation it finds:

* every operation appears once, on its machine, with its tool and its exact duration;
* a machine runs one operation at a time;
* without AGVs, operation (j,k) starts after (j,k-1) ends (and at >= 0);
* with AGVs, operation (j,k) is preceded by one loaded trip of job j from its pickup location (L/U for k = 0,
  else the machine of (j,k-1)) to its machine, starting no earlier than the part is ready and ending no later
  than the operation starts (omitted only if pickup == machine: the part then waits in place);
* every AGV starts at L/U at time 0, carries one load at a time, and its trips form a continuous route whose
  legs last exactly ``agv_travel[from][to]`` (empty trips for deadheading);
* every tool starts in the magazine, is at the machine of each operation that uses it from start to end,
  moves only on loaded tool-transporter trips that start after its previous use ended, and each transporter
  route is continuous with exact ``tool_travel`` legs;
* operations and trips of zero length at one instant are recorded in orders that agree with one another (a part's
  operations and trips, a tool's uses and carries, each vehicle's legs): some one sequence follows them all;
* ``makespan`` equals the latest operation end;
* with disruptions (a :class:`~fms_sim.disruptions.Scenario`, given or recorded in ``meta["scenario"]``): each
  operation lasts its realised duration (noise) plus every breakdown of its machine that began while it ran,
  none starts while its machine is down, each trip lasts its realised travel time, and no vehicle starts a trip
  while out of service. The realised times are recomputed from the scenario's seed, not read from the run.
"""

from __future__ import annotations

from collections import defaultdict
from itertools import groupby
from typing import Iterable

from .disruptions import Scenario, ScenarioError
from .instance import Instance, require_instance
from .schedule import Schedule

__all__ = ["validate", "check", "ScheduleInvalid", "tool_use_orders"]


class ScheduleInvalid(ValueError):
    """Raised by :func:`check` when a schedule breaks the contract; ``violations`` lists every problem."""

    def __init__(self, violations: list[str]):
        self.violations = violations
        head = "; ".join(violations[:5])
        more = f" (+{len(violations) - 5} more)" if len(violations) > 5 else ""
        super().__init__(f"{len(violations)} violation(s): {head}{more}")


def check(instance: Instance, schedule: Schedule, scenario: Scenario | None = None) -> None:
    """Raise :class:`ScheduleInvalid` unless ``schedule`` is feasible for ``instance``."""
    v = validate(instance, schedule, scenario)
    if v:
        raise ScheduleInvalid(v)


def validate(instance: Instance, schedule: Schedule, scenario: Scenario | None = None) -> list[str]:
    """Every violation of the contract, as human-readable lines; an empty list means feasible. ``scenario``
    (default: the one the schedule records in ``meta["scenario"]``, if any) gives the disruptions of the run."""
    require_instance(instance, "validate")
    if not isinstance(schedule, Schedule):
        raise TypeError(f"validate takes a Schedule (Schedule.from_dict or Schedule.load reads one), got "
                        f"{type(schedule).__name__}")
    errs: list[str] = []
    recorded = schedule.meta.get("scenario")
    if scenario is None and recorded is not None and not isinstance(recorded, dict):  # it was silently ignored
        return [f"the schedule's recorded scenario is malformed: meta.scenario must be an object, got "
                f"{type(recorded).__name__}"]
    if scenario is None and isinstance(recorded, dict):
        try:
            scenario = Scenario.from_dict(schedule.meta["scenario"])
        except ScenarioError as exc:
            return [f"the schedule's recorded scenario is malformed: {exc}"]
    if scenario is not None:
        try:
            scenario.check(instance)
        except ScenarioError as exc:
            return [f"the scenario does not fit the instance: {exc}"]
        if scenario.empty:
            scenario = None
    ops = _check_operations(instance, schedule, errs, scenario)
    if ops is None:
        return errs
    _check_machines(schedule, errs)
    if instance.has_agvs:
        _check_parts_with_agvs(instance, schedule, ops, errs)
        _check_routes("AGV", "agv", instance.agv_travel, schedule.n_agvs, instance.n_agvs,
                      [(t.agv, t.from_, t.to, t.start, t.end) for t in schedule.agv_trips], errs, scenario)
    else:
        if schedule.agv_trips:
            errs.append("schedule has AGV trips but the instance has no AGVs")
        for j, job in enumerate(instance.jobs):
            for k in range(len(job)):
                prev_end = ops[j, k - 1][1] if k else 0
                if ops[j, k][0] < prev_end:
                    errs.append(f"op ({j},{k}) starts at {ops[j, k][0]} before its part is ready at {prev_end}")
    if instance.has_tools:
        _check_tools(instance, schedule, ops, errs)
        _check_routes("tool transporter", "transporter", instance.tool_travel, schedule.n_tool_transporters,
                      instance.n_tool_transporters,
                      [(t.transporter, t.from_, t.to, t.start, t.end) for t in schedule.tool_trips], errs, scenario)
    elif schedule.tool_trips:
        errs.append("schedule has tool trips but the instance has no tools")
    if not errs:  # every resource's own order holds; now they must hold together where events tie in time
        _check_ties(instance, schedule, ops, errs)
    ends = [e for (_, e) in ops.values()]
    true_ms = max(ends) if ends else 0
    if schedule.makespan != true_ms:
        errs.append(f"makespan is {schedule.makespan} but the latest operation ends at {true_ms}")
    return errs


def _check_operations(instance: Instance, schedule: Schedule, errs: list[str],
                      scenario: Scenario | None = None) -> dict[tuple[int, int], tuple[int, int]] | None:
    ops: dict[tuple[int, int], tuple[int, int]] = {}
    for r in schedule.operations:
        key = (r.job, r.op)
        if not (0 <= r.job < instance.n_jobs and 0 <= r.op < len(instance.jobs[r.job])):
            errs.append(f"op ({r.job},{r.op}) does not exist in the instance")
            continue
        if key in ops:
            errs.append(f"op ({r.job},{r.op}) is scheduled more than once")
            continue
        spec = instance.jobs[r.job][r.op]
        if r.machine != spec.machine:
            errs.append(f"op ({r.job},{r.op}) runs on machine {r.machine}, needs machine {spec.machine}")
        want_tool = spec.tool if instance.has_tools else None
        if instance.has_tools and r.tool != want_tool:
            errs.append(f"op ({r.job},{r.op}) uses tool {r.tool}, needs tool {want_tool}")
        if scenario is None:
            if r.end - r.start != spec.duration:
                errs.append(f"op ({r.job},{r.op}) lasts {r.end - r.start}, its duration is {spec.duration}")
        else:
            real = scenario.op_duration(r.job, r.op, spec.duration)
            want = scenario.op_end(spec.machine, r.start, real)
            if r.end != want:
                errs.append(f"op ({r.job},{r.op}) ends at {r.end}; with its realised duration {real} and the "
                            f"breakdowns of machine {spec.machine} it ends at {want}")
            for b in scenario.windows(spec.machine):
                if b.start < r.start < b.end:
                    errs.append(f"op ({r.job},{r.op}) starts at {r.start} while machine {spec.machine} is down "
                                f"[{b.start}, {b.end})")
        if r.start < 0:
            errs.append(f"op ({r.job},{r.op}) starts before time 0")
        ops[key] = (r.start, r.end)
    missing = [(j, k) for j, job in enumerate(instance.jobs) for k in range(len(job)) if (j, k) not in ops]
    for j, k in missing:
        errs.append(f"op ({j},{k}) is missing from the schedule")
    return None if missing else ops


def _check_machines(schedule: Schedule, errs: list[str]) -> None:
    by_machine: dict[int, list] = defaultdict(list)
    for r in schedule.operations:
        by_machine[r.machine].append(r)
    for m, rs in by_machine.items():
        rs.sort(key=lambda r: (r.start, r.end))
        for a, b in zip(rs, rs[1:]):
            if b.start < a.end:
                errs.append(f"machine {m}: op ({a.job},{a.op}) [{a.start},{a.end}) overlaps op ({b.job},{b.op}) "
                            f"[{b.start},{b.end})")


def _check_parts_with_agvs(instance: Instance, schedule: Schedule, ops: dict, errs: list[str]) -> None:
    loaded: dict[tuple[int, int], list] = defaultdict(list)
    for t in schedule.agv_trips:
        if t.loaded:
            if t.job is None or t.op is None:
                errs.append(f"loaded AGV trip of AGV {t.agv} at {t.start} names no operation")
                continue
            loaded[t.job, t.op].append(t)
        elif t.job is not None or t.op is not None:
            errs.append(f"empty AGV trip of AGV {t.agv} at {t.start} names an operation")
    for key in loaded:
        if key not in ops:
            errs.append(f"loaded AGV trip for nonexistent op ({key[0]},{key[1]})")
    for j, job in enumerate(instance.jobs):
        for k, spec in enumerate(job):
            ready = ops[j, k - 1][1] if k else 0
            pickup = job[k - 1].machine if k else 0
            trips = loaded.get((j, k), [])
            if len(trips) > 1:
                errs.append(f"op ({j},{k}): the part is moved {len(trips)} times (one loaded trip expected)")
                continue
            if not trips:
                if pickup != spec.machine:
                    errs.append(f"op ({j},{k}): no AGV trip brings the part from {pickup} to machine {spec.machine}")
                elif ops[j, k][0] < ready:
                    errs.append(f"op ({j},{k}) starts at {ops[j, k][0]} before its part is ready at {ready}")
                continue
            t = trips[0]
            if t.from_ != pickup or t.to != spec.machine:
                errs.append(f"op ({j},{k}): the part travels {t.from_}->{t.to}, must go {pickup}->{spec.machine}")
            if t.start < ready:
                errs.append(f"op ({j},{k}): loaded trip starts at {t.start} before the part is ready at {ready}")
            if t.end > ops[j, k][0]:
                errs.append(f"op ({j},{k}) starts at {ops[j, k][0]} before its part arrives at {t.end}")


def _check_routes(what: str, key: str, travel, n_declared: int, n_fleet: int,
                  trips: Iterable[tuple[int, int, int, int, int]], errs: list[str],
                  scenario: Scenario | None = None) -> None:
    if n_declared != n_fleet:
        errs.append(f"schedule declares {n_declared} {what}s, the instance has {n_fleet}")
    size = len(travel)
    routes: dict[int, list] = defaultdict(list)
    for v, a, b, s, e in trips:
        if not (0 <= v < n_fleet):
            errs.append(f"{what} {v} does not exist (fleet of {n_fleet})")
            continue
        if not (0 <= a < size and 0 <= b < size):
            errs.append(f"{what} {v}: trip {a}->{b} at {s} names an unknown location")
            continue
        routes[v].append((s, e, a, b))
    for v, legs in routes.items():
        legs.sort(key=lambda leg: (leg[0], leg[1]))  # stable: zero-length legs keep the schedule's order
        here, free, n = 0, 0, 0
        kind = "agv" if key == "agv" else "tt"
        outs = [o for o in scenario.outages if o.kind == kind and o.vehicle == v] if scenario else []
        for s, e, a, b in legs:
            if s < free:
                errs.append(f"{what} {v}: trip {a}->{b} at {s} starts before its previous trip ends at {free}")
            if a != here:
                errs.append(f"{what} {v}: trip {a}->{b} at {s} starts at {a} but the vehicle is at {here}")
            want = travel[a][b]
            if scenario is not None and a != b:
                want = scenario.trip_time(kind, v, n, want)
                n += 1
            if e - s != want:
                errs.append(f"{what} {v}: trip {a}->{b} at {s} lasts {e - s}, travel time is {want}"
                            + (" (realised)" if scenario is not None else ""))
            for o in outs:
                if o.start < s < o.end and a != b:
                    errs.append(f"{what} {v}: trip {a}->{b} starts at {s} while out of service [{o.start}, {o.end})")
            here, free = b, max(free, e)


def _tool_order(us: list[tuple], trips: dict) -> list[tuple]:
    """The uses of one tool (``(start, end, job, op, machine)``) in the order the tool serves them: by time; uses at
    the same instant (zero durations) in an order the tool can follow (:func:`_tied_order`), else, for the errors to
    name, one on the machine where the tool is before one it must be carried to, carried ones by their trip's start.
    (Job numbers decided ties once: a feasible schedule whose trip served job 1 before job 0's use was refused.)"""
    out: list[tuple] = []
    loc, free = 0, 0  # where the tool is, and until when the uses so far hold it
    for _, group in groupby(sorted(us), key=lambda u: u[:2]):
        tied = list(group)
        found = _tied_order(tied, trips, loc, free) if len(tied) > 1 else None
        if found is not None:
            out += found
            loc, free = found[-1][4], max(free, found[0][1])  # the group's uses share their end
            continue
        while tied:  # a group holds more than one use only for zero durations: it is small
            here = [u for u in tied if not trips.get((u[2], u[3])) and u[4] == loc]
            carried = sorted((u for u in tied if trips.get((u[2], u[3]))), key=lambda u: trips[u[2], u[3]][0].start)
            u = (here or carried or tied)[0]
            tied.remove(u)
            out.append(u)
            loc, free = u[4], max(free, u[1])
    return out


#: the most uses at one instant whose orders :func:`_tied_order` tries (zero durations; the search remembers the
#: dead ends, at most 2^n of them)
_MAX_TIED = 16


def _tied_order(tied: list[tuple], trips: dict, loc: int, free: int) -> list[tuple] | None:
    """An order of one tool's uses at one instant that the tool can follow from ``loc``, free from ``free`` on: each
    carried use's trip leaves from where the tool is and once it is free (a trip that left before the instant comes
    first), each other use is where the tool is, a job's operations in their order; the first found, trying
    uncarried uses, then carried ones by trip start and the schedule's order of the trips (its routes'), then
    by job. None if there is none (the checks then name what is wrong) or the group is too large to try."""
    if len(tied) > _MAX_TIED:
        return None

    def source(u: tuple) -> int:  # where the tool must be for the use (a carried one: where its trip leaves from)
        ts = trips.get((u[2], u[3]))
        return ts[0].from_ if ts else u[4]

    pos = {key: i for i, key in enumerate(trips)}  # the trips in the schedule's order (its routes' order)

    def rank(u: tuple) -> tuple:
        ts = trips.get((u[2], u[3]))
        return (1, ts[0].start, pos[u[2], u[3]], u[2], u[3]) if ts else (0, 0, 0, u[2], u[3])

    dead: set[tuple] = set()  # (uses left, where the tool is, free since) known to lead nowhere

    def search(rest: list[tuple], at: int, since: int) -> list[tuple] | None:
        if not rest:
            return []
        state = (frozenset(rest), at, since)
        if state in dead:
            return None
        for i, u in enumerate(rest):
            ts = trips.get((u[2], u[3]))
            if source(u) != at or (ts and ts[0].start < since) or any(v[2] == u[2] and v[3] < u[3] for v in rest):
                continue
            tail = search(rest[:i] + rest[i + 1:], u[4], max(since, u[1]))
            if tail is not None:
                return [u] + tail
        dead.add(state)
        return None

    return search(sorted(tied, key=rank), loc, free)


def tool_use_orders(instance: Instance, schedule: Schedule) -> dict[int, list[tuple[int, int]]]:
    """Per tool, its uses ``(job, op)`` in the order the tool serves them, as the validator checks them (uses at one
    instant in an order the tool can follow): what a replay of ``schedule`` must keep."""
    if not instance.has_tools:
        return {}
    uses = _uses_by_tool(instance, {(r.job, r.op): (r.start, r.end) for r in schedule.operations})
    moves: dict[int, list] = defaultdict(list)
    for t in schedule.tool_trips:
        if t.loaded and t.tool is not None and t.job is not None and t.op is not None:
            moves[t.tool].append(t)
    return {tool: [(u[2], u[3]) for u in _tool_order(us, _by_op(moves.get(tool, [])))] for tool, us in uses.items()}


def _uses_by_tool(instance: Instance, ops: dict) -> dict[int, list[tuple]]:
    """Per tool, its uses ``(start, end, job, op, machine)`` by time, for the operations in ``ops`` (``(job, op)``
    -> ``(start, end)``)."""
    uses: dict[int, list[tuple]] = defaultdict(list)
    for j, job in enumerate(instance.jobs):
        for k, spec in enumerate(job):
            if spec.tool is not None and (j, k) in ops:
                uses[spec.tool].append((*ops[j, k], j, k, spec.machine))
    for us in uses.values():
        us.sort()
    return uses


def _by_op(moves: list) -> dict[tuple, list]:
    """One tool's loaded trips by the operation they serve, in the schedule's order (its routes' order)."""
    trips: dict[tuple, list] = {}
    for t in moves:
        trips.setdefault((t.job, t.op), []).append(t)
    return trips


def _check_tools(instance: Instance, schedule: Schedule, ops: dict, errs: list[str]) -> None:
    uses = _uses_by_tool(instance, ops)
    moves: dict[int, list] = defaultdict(list)
    for t in schedule.tool_trips:
        if t.loaded:
            if t.tool is None or t.job is None or t.op is None:
                errs.append(f"loaded trip of transporter {t.transporter} at {t.start} names no tool/operation")
                continue
            moves[t.tool].append(t)
        elif t.tool is not None or t.job is not None:
            errs.append(f"empty trip of transporter {t.transporter} at {t.start} names a tool or operation")
    for tool in set(moves) - set(uses):
        errs.append(f"tool {tool} is moved but no operation uses it")
    for tool, us in uses.items():
        trips = _by_op(moves.get(tool, []))
        used_keys = {(j, k) for (_, _, j, k, _) in us}
        for key in trips:
            if key not in used_keys:
                errs.append(f"tool {tool} is carried for op ({key[0]},{key[1]}), which does not use it")
        loc, free = 0, 0
        for s, e, j, k, machine in _tool_order(us, trips):
            ts = trips.get((j, k), [])
            if len(ts) > 1:
                errs.append(f"tool {tool} is carried {len(ts)} times for op ({j},{k})")
            elif ts:
                t = ts[0]
                if t.from_ != loc:
                    errs.append(f"tool {tool} for op ({j},{k}): trip starts at {t.from_} but the tool is at {loc}")
                if t.to != machine:
                    errs.append(f"tool {tool} for op ({j},{k}): trip goes to {t.to}, the op is on machine {machine}")
                if t.start < free:
                    errs.append(f"tool {tool} for op ({j},{k}): moved at {t.start} while busy until {free}")
                if t.end > s:
                    errs.append(f"op ({j},{k}) starts at {s} before tool {tool} arrives at {t.end}")
                loc = t.to
            elif loc != machine:
                errs.append(f"op ({j},{k}) on machine {machine} at {s}: tool {tool} is at location {loc}")
            if s < free:
                errs.append(f"tool {tool} is used by op ({j},{k}) from {s} while busy until {free} (two places at once)")
            loc, free = machine, max(free, e)


#: the most operations and trips of one cycle :func:`_check_ties` names
_CYCLE_SHOWN = 8


def _check_ties(instance: Instance, schedule: Schedule, ops: dict, errs: list[str]) -> None:
    """The orders of operations and trips of zero length at one instant must agree with one another.

    Each resource's check above follows its own order of tied events: a vehicle its recorded legs, a part its
    operations, a tool an order of its uses it can follow (:func:`_tool_order`). Every check can pass while
    no sequence of the events follows all of them at once: a transporter that records carrying a tool away from
    a machine before carrying it there, both at one instant. What must precede what (a part's operations and
    trips, a tool's uses and carries, a vehicle's legs) forms a graph over the events (starts and ends of
    operations, departures and arrivals of trips); between events at different times the checks above have
    ordered them, so a cycle joins events at one instant. Every edge between two operations or trips leads from
    one's end to the other's start, so a cycle passes only through operations and trips of zero length: the graph
    is built over those alone (none in most shops) and must have no cycle. Machines add no order (operations of
    zero length may run on one machine in any order). Only run on a schedule that passed every other check."""
    when: dict[tuple, int] = {("op", j, k): s for (j, k), (s, e) in ops.items() if s == e}
    when.update((("agv", i), t.start) for i, t in enumerate(schedule.agv_trips) if t.start == t.end)
    when.update((("tt", i), t.start) for i, t in enumerate(schedule.tool_trips) if t.start == t.end)
    if not when:
        return
    succ: dict[tuple, list[tuple]] = defaultdict(list)

    def before(a: tuple, b: tuple) -> None:  # a ends before b starts; only tied ones of zero length can close a cycle
        t = when.get(a)
        if t is not None and when.get(b) == t:
            succ[a].append(b)

    for kind, trips in (("agv", schedule.agv_trips), ("tt", schedule.tool_trips)):
        legs: dict[int, list] = defaultdict(list)
        for i, t in enumerate(trips):
            legs[t.agv if kind == "agv" else t.transporter].append((t.start, t.end, i))  # type: ignore[union-attr]
        for route in legs.values():
            route.sort(key=lambda leg: leg[:2])  # stable, as the route check orders them
            for a, b in zip(route, route[1:]):
                before((kind, a[2]), (kind, b[2]))
    carry = {(t.job, t.op): i for i, t in enumerate(schedule.agv_trips) if t.loaded}
    for j, job in enumerate(instance.jobs):
        for k in range(len(job)):
            i = carry.get((j, k)) if instance.has_agvs else None
            if i is None:
                if k:
                    before(("op", j, k - 1), ("op", j, k))
                continue
            if k:
                before(("op", j, k - 1), ("agv", i))
            before(("agv", i), ("op", j, k))
    if instance.has_tools:
        moves: dict[int, list] = defaultdict(list)
        where: dict[tuple, int] = {}
        for i, t in enumerate(schedule.tool_trips):
            if t.loaded:
                moves[t.tool].append(t)  # type: ignore[index]
                where[t.tool, t.job, t.op] = i
        for tool, us in _uses_by_tool(instance, ops).items():
            prev = None
            for _, _, j, k, _ in _tool_order(us, _by_op(moves.get(tool, []))):
                i = where.get((tool, j, k))
                if i is not None:
                    if prev is not None:
                        before(("op", *prev), ("tt", i))
                    before(("tt", i), ("op", j, k))
                elif prev is not None:
                    before(("op", *prev), ("op", j, k))
                prev = (j, k)
    cycle = _find_cycle(succ)
    if cycle:
        names = [_event(schedule, e) for e in cycle]
        shown = names[:_CYCLE_SHOWN] + (["..."] if len(names) > _CYCLE_SHOWN else [])
        errs.append(f"at time {when[cycle[0]]} no order of the events follows every resource: "
                    f"{' -> '.join(shown + names[:1])} (each must come before the next; zero-length trips or "
                    "operations recorded in contradicting orders)")


def _find_cycle(succ: dict[tuple, list[tuple]]) -> list[tuple] | None:
    """One cycle of the graph ``succ`` (its nodes in order), or None if it has none."""
    state: dict[tuple, int] = {}  # 1: on the current path, 2: done
    for root in list(succ):
        if root in state:
            continue
        path, stack = [root], [iter(succ[root])]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(succ.get(nxt, ())))
    return None


def _event(schedule: Schedule, e: tuple) -> str:
    """An operation or trip of :func:`_check_ties` in words."""
    if e[0] == "op":
        return f"op ({e[1]},{e[2]})"
    if e[0] == "agv":
        a = schedule.agv_trips[e[1]]
        return f"AGV {a.agv}'s trip {a.from_}->{a.to}" + (f" with op ({a.job},{a.op})'s part" if a.loaded else "")
    t = schedule.tool_trips[e[1]]
    return (f"transporter {t.transporter}'s trip {t.from_}->{t.to}"
            + (f" with tool {t.tool} for op ({t.job},{t.op})" if t.loaded else ""))
