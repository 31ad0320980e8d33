"""Independent schedule validator.

It checks a :class:`~fms_sim.schedule.Schedule` against its :class:`~fms_sim.instance.Instance` by the
project's semantic contract, without using the Petri net, and reports *every* violation it finds:

* times, indices and counts are integers (a record of another type is reported and nothing else is judged);
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
  while out of service. The realised times are recomputed from the scenario's seed, not read from the run;
* jobs of live orders (``meta["arrivals"]``: ``[job, time]`` pairs, recorded by the shop the order joined): none
  of the job's operations, and no trip for it (its part's carries, its tools' carries), starts before it arrived.
"""

from __future__ import annotations

import numbers
from collections import defaultdict
from operator import attrgetter
from typing import Any, Iterable

import numpy as np

from .disruptions import Scenario, ScenarioError
from .instance import Instance, require_instance
from .schedule import AgvTrip, OperationRecord, Schedule, ToolTrip, require_schedule
from .ties import settle, tool_order, tool_use_orders, trips_by_op, uses_by_tool

__all__ = ["validate", "check", "ScheduleInvalid", "tool_use_orders", "recorded_scenario", "recorded_arrivals"]


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


def recorded_scenario(schedule: Schedule) -> Scenario | None:
    """The scenario ``schedule`` records in ``meta["scenario"]`` (None: none); raises :class:`ScenarioError` saying
    it is malformed (a value that is no object was silently ignored)."""
    recorded = schedule.meta.get("scenario")
    if recorded is None:
        return None
    try:
        if not isinstance(recorded, dict):
            raise ScenarioError(f"meta.scenario must be an object, got {type(recorded).__name__}")
        return Scenario.from_dict(recorded)
    except ScenarioError as exc:
        raise ScenarioError(f"the schedule's recorded scenario is malformed: {exc}") from None


def recorded_arrivals(schedule: Schedule, instance: Instance) -> dict[int, int]:
    """When each job of a live order arrived, as ``schedule`` records it in ``meta["arrivals"]`` (``[job, time]``
    pairs; none: ``{}``); raises ValueError saying how the record is malformed."""
    recorded = schedule.meta.get("arrivals")
    if recorded is None:
        return {}
    if not isinstance(recorded, list):
        raise ValueError(f"meta.arrivals must be a list of [job, time] pairs, got {type(recorded).__name__}")
    out: dict[int, int] = {}
    for i, pair in enumerate(recorded):
        if (not isinstance(pair, (list, tuple)) or len(pair) != 2
                or not all(_is_int(v) for v in pair)):
            raise ValueError(f"meta.arrivals[{i}] must be a [job, time] pair of integers, got {pair!r}")
        job, time = int(pair[0]), int(pair[1])
        if not 0 <= job < instance.n_jobs:
            raise ValueError(f"meta.arrivals[{i}]: job {job} does not exist (0..{instance.n_jobs - 1})")
        if time < 0:
            raise ValueError(f"meta.arrivals[{i}]: job {job} arrives at {time}, before the run began")
        if job in out:
            raise ValueError(f"meta.arrivals[{i}]: job {job} arrives twice")
        out[job] = time
    return out


def _check_arrivals(schedule: Schedule, arrivals: dict[int, int], errs: list[str]) -> None:
    """No operation of a job of a live order, and no trip for it, starts before the job arrived."""
    for r in schedule.operations:
        t = arrivals.get(r.job)
        if t is not None and r.start < t:
            errs.append(f"op ({r.job},{r.op}) starts at {r.start}, before its job arrived (a live order) at {t}")
    for what, trips in (("AGV", schedule.agv_trips), ("tool transporter", schedule.tool_trips)):
        for trip in trips:
            t = arrivals.get(trip.job) if trip.job is not None else None
            if t is not None and trip.start < t:
                errs.append(f"{what} trip {trip.from_}->{trip.to} for op ({trip.job},{trip.op}) starts at "
                            f"{trip.start}, before its job arrived (a live order) at {t}")


def validate(instance: Instance, schedule: Schedule, scenario: Scenario | None = None) -> list[str]:
    """Every violation of the contract, as human-readable lines; an empty list means feasible. ``scenario``
    (default: the one the schedule records in ``meta["scenario"]``, if any) gives the disruptions of the run."""
    require_instance(instance, "validate")
    require_schedule(schedule, "validate")
    errs = _check_types(schedule)
    if errs:  # times and indices that are no integers: nothing below can be judged (or computed) with them
        return errs
    if scenario is None:
        try:
            scenario = recorded_scenario(schedule)
        except ScenarioError as exc:
            return [str(exc)]
    if scenario is not None:
        if not isinstance(scenario, Scenario):  # (a dict failed with AttributeError: no attribute 'check')
            raise TypeError(f"scenario must be a Scenario (Scenario.from_dict reads one), got {type(scenario).__name__}")
        try:
            scenario.check(instance)
        except ScenarioError as exc:
            return [f"the scenario does not fit the instance: {exc}"]
        if scenario.empty:
            scenario = None
    try:
        arrivals = recorded_arrivals(schedule, instance)
    except ValueError as exc:
        return [str(exc)]
    # the fleet the schedule was made for, first: a schedule of the shop without its AGVs or tools breaks many rules
    # after it, and a reader of the first lines (fms replay shows ten) should see the cause
    # (an instance without AGVs or tools has none: a schedule that declares some was made for another shop)
    if schedule.n_agvs != instance.n_agvs:
        errs.append(f"schedule declares {schedule.n_agvs} AGVs, the instance has {instance.n_agvs or 'none'}")
    if schedule.n_tool_transporters != instance.n_tool_transporters:
        errs.append(f"schedule declares {schedule.n_tool_transporters} tool transporters, the instance has "
                    f"{instance.n_tool_transporters or 'none'}")
    ops = _check_operations(instance, schedule, errs, scenario)
    if ops is None:
        return errs
    _check_machines(schedule, errs)
    if arrivals:
        _check_arrivals(schedule, arrivals, errs)
    if instance.has_agvs:
        _check_parts_with_agvs(instance, schedule, ops, errs)
        _check_routes("AGV", "agv", instance.agv_travel, instance.n_agvs,
                      [(t.agv, t.from_, t.to, t.start, t.end) for t in schedule.agv_trips], errs, scenario)
    else:
        if schedule.agv_trips:
            errs.append("schedule has AGV trips but the instance has no AGVs")
        for j, job in enumerate(instance.jobs):
            for k in range(len(job)):
                prev_end = ops[j, k - 1][1] if k else 0
                if ops[j, k][0] < prev_end:
                    errs.append(f"op ({j},{k}) starts at {ops[j, k][0]} before its part is ready at {prev_end}")
    orders: dict[int, list[tuple]] = {}
    if instance.has_tools:
        orders = _check_tools(instance, schedule, ops, errs)
        _check_routes("tool transporter", "transporter", instance.tool_travel, instance.n_tool_transporters,
                      [(t.transporter, t.from_, t.to, t.start, t.end) for t in schedule.tool_trips], errs, scenario)
    elif schedule.tool_trips:
        errs.append("schedule has tool trips but the instance has no tools")
    if not errs:  # every resource's own order holds; now they must hold together where events tie in time
        _, contradiction = settle(instance, schedule, ops, orders)
        if contradiction is not None:
            errs.append(contradiction)
    ends = [e for (_, e) in ops.values()]
    true_ms = max(ends) if ends else 0
    if schedule.makespan != true_ms:
        errs.append(f"makespan is {schedule.makespan} but the latest operation ends at {true_ms}")
    return errs


#: per record type, its integer fields (``None`` allowed in the second group) and what a message calls it
_FIELDS: tuple[tuple[type, str, tuple[str, ...], tuple[str, ...]], ...] = (
    (OperationRecord, "operations", ("job", "op", "machine", "start", "end"), ("tool",)),
    (AgvTrip, "agv_trips", ("agv", "from_", "to", "start", "end"), ("job", "op")),
    (ToolTrip, "tool_trips", ("transporter", "from_", "to", "start", "end"), ("tool", "job", "op")),
)


def _is_int(v: Any) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))


def _check_types(schedule: Schedule) -> list[str]:
    """The schedule's fields that are not of the contract's types (times, indices and counts are integers: a
    schedule built in Python with ``start=2.5`` was judged feasible, one with ``start=None`` crashed the checks);
    each record as ``operations[3].start`` (the index in its list) with the value found."""
    errs = [f"{name} must be an integer, got {v!r}" for name in ("makespan", "n_agvs", "n_tool_transporters")
            if not _is_int(v := getattr(schedule, name))]
    for cls, where, ints, optional in _FIELDS:
        records = getattr(schedule, where)
        if not isinstance(records, (list, tuple)):
            errs.append(f"{where} must be a list of {cls.__name__} records, got {type(records).__name__}")
            continue
        if _plain(records, cls, ints, optional):  # the usual case, a pass per field (sl70: 10,000 records)
            continue
        for i, r in enumerate(records):
            if not isinstance(r, cls):
                errs.append(f"{where}[{i}] must be of type {cls.__name__}, got {type(r).__name__}")
                continue
            errs.extend(f"{where}[{i}].{f.rstrip('_')} must be an integer, got {v!r}"
                        for f in ints if not _is_int(v := getattr(r, f)))
            errs.extend(f"{where}[{i}].{f} must be an integer or None, got {v!r}"
                        for f in optional if (v := getattr(r, f)) is not None and not _is_int(v))
            loaded = getattr(r, "loaded", False)  # (a trip's)
            if not isinstance(loaded, (bool, np.bool_)):
                errs.append(f"{where}[{i}].loaded must be true or false, got {loaded!r}")
    return errs


def _plain(records: list | tuple, cls: type, ints: tuple[str, ...], optional: tuple[str, ...]) -> bool:
    """Whether every record is exactly a ``cls`` whose fields are Python ints (and None where ``optional``) and
    bools (``loaded``): one type set per field, built in C; anything else (a numpy integer, a subclass) is then
    checked record by record."""
    if not set(map(type, records)) <= {cls}:
        return False
    if any(not set(map(type, map(attrgetter(f), records))) <= _INT for f in ints):
        return False
    if any(not set(map(type, map(attrgetter(f), records))) <= _INT_OR_NONE for f in optional):
        return False
    return cls is OperationRecord or set(map(type, map(attrgetter("loaded"), records))) <= _BOOL


_INT, _INT_OR_NONE, _BOOL = {int}, {int, type(None)}, {bool}


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
        if r.tool != spec.tool:  # (without tools every operation's is None: a tool there was never checked)
            errs.append(f"op ({r.job},{r.op}) uses tool {r.tool}, needs "
                        + (f"tool {spec.tool}" if spec.tool is not None else "none"))
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


def _check_routes(what: str, key: str, travel, n_fleet: int,
                  trips: Iterable[tuple[int, int, int, int, int]], errs: list[str],
                  scenario: Scenario | None = None) -> None:
    size = len(travel)
    routes: dict[int, list] = defaultdict(list)
    absent: dict[int, list[int]] = {}  # a vehicle beyond the fleet -> its trips' starts (said once per vehicle)
    for v, a, b, s, e in trips:
        if not (0 <= v < n_fleet):
            absent.setdefault(v, []).append(s)
            continue
        if not (0 <= a < size and 0 <= b < size):
            errs.append(f"{what} {v}: trip {a}->{b} at {s} names an unknown location")
            continue
        routes[v].append((s, e, a, b))
    for v, starts in absent.items():
        n = len(starts)
        errs.append(f"{what} {v} does not exist (fleet of {n_fleet}): {n} trip{'s' if n > 1 else ''} from {min(starts)}")
    for v, legs in routes.items():
        legs.sort(key=lambda leg: (leg[0], leg[1]))  # stable: zero-length legs keep the schedule's order
        here, free, n = 0, 0, 0
        kind = "agv" if key == "agv" else "tt"
        outs = [o for o in scenario.outages if o.kind == kind and o.vehicle == v] if scenario else []
        for s, e, a, b in legs:
            if s < 0:  # (the vehicle's first trip: "before its previous trip ends at 0" named a trip it has not)
                errs.append(f"{what} {v}: trip {a}->{b} at {s} starts before time 0")
            elif s < free:
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


def _check_tools(instance: Instance, schedule: Schedule, ops: dict, errs: list[str]) -> dict[int, list[tuple]]:
    """Each tool's route and uses, into ``errs``; returns the order of each tool's uses it checked."""
    uses = uses_by_tool(instance, ops)
    orders: dict[int, list[tuple]] = {}
    moves: dict[int, list] = defaultdict(list)
    for t in schedule.tool_trips:
        if t.loaded:
            if t.tool is None or t.job is None or t.op is None:
                errs.append(f"loaded trip of transporter {t.transporter} at {t.start} names no tool/operation")
                continue
            moves[t.tool].append(t)
        elif t.tool is not None or t.job is not None or t.op is not None:  # (op alone passed; the AGVs' did not)
            errs.append(f"empty trip of transporter {t.transporter} at {t.start} names a tool or operation")
    for tool in set(moves) - set(uses):
        errs.append(f"tool {tool} is moved but no operation uses it")
    for tool, us in uses.items():
        trips = trips_by_op(moves.get(tool, []))
        used_keys = {(j, k) for (_, _, j, k, _) in us}
        for key in trips:
            if key not in used_keys:
                errs.append(f"tool {tool} is carried for op ({key[0]},{key[1]}), which does not use it")
        loc, free = 0, 0
        orders[tool] = tool_order(us, trips)
        for s, e, j, k, machine in orders[tool]:
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
    return orders
