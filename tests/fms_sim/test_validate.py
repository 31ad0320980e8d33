"""The independent validator accepts feasible schedules and rejects deliberately broken ones."""

import json
from dataclasses import replace

import pytest

from fms_sim import Instance, Schedule, ScheduleError, ScheduleInvalid, check, validate
from fms_sim.disruptions import Breakdown, Outage, Scenario

from .conftest import run_first

T = [[0, 2, 3], [2, 0, 2], [3, 4, 0]]
TT = [[0, 1, 2], [1, 0, 3], [2, 3, 0]]
INST = Instance("both", [[(1, 1, 3), (2, 1, 2)], [(2, 2, 2)]], agv_travel=T, tool_travel=TT,
                n_agvs=1, n_tool_transporters=1)


@pytest.fixture
def good():
    s = run_first(INST)
    assert validate(INST, s) == []
    return s


def op_index(s, j, k):
    return next(i for i, o in enumerate(s.operations) if (o.job, o.op) == (j, k))


def shifted_op(s, j, k, delta):
    s = Schedule.from_dict(s.to_dict())
    i = op_index(s, j, k)
    o = s.operations[i]
    s.operations[i] = replace(o, start=o.start + delta, end=o.end + delta)
    s.makespan = max(x.end for x in s.operations)
    return s


def test_machine_overlap_rejected(good):
    # put (1,0) on M2 right on top of (0,1)
    s = Schedule.from_dict(good.to_dict())
    a = s.operations[op_index(s, 0, 1)]
    i = op_index(s, 1, 0)
    s.operations[i] = replace(s.operations[i], start=a.start, end=a.start + 2)
    v = validate(INST, s)
    assert any("machine 2" in x and "overlaps" in x for x in v)


def test_missing_agv_trip_rejected(good):
    s = Schedule.from_dict(good.to_dict())
    s.agv_trips = [t for t in s.agv_trips if not (t.loaded and t.job == 1)]
    v = validate(INST, s)
    assert any("no AGV trip brings the part" in x for x in v)


def test_wrong_durations_rejected(good):
    s = Schedule.from_dict(good.to_dict())
    i = op_index(s, 0, 0)
    s.operations[i] = replace(s.operations[i], end=s.operations[i].end + 1)
    s.agv_trips[0] = replace(s.agv_trips[0], end=s.agv_trips[0].end + 1)
    v = validate(INST, s)
    assert any("lasts 4, its duration is 3" in x for x in v)
    assert any("travel time is" in x for x in v)


def test_tool_in_two_places_rejected(good):
    # (0,0) and (0,1) both use tool 1: run (0,1) on M2 while (0,0) still holds the tool on M1
    s = Schedule.from_dict(good.to_dict())
    a = s.operations[op_index(s, 0, 0)]
    i = op_index(s, 0, 1)
    s.operations[i] = replace(s.operations[i], start=a.start + 1, end=a.start + 3)
    s.makespan = max(o.end for o in s.operations)
    v = validate(INST, s)
    assert "tool 1 is used by op (0,1) from 3 while busy until 5 (two places at once)" in v
    assert any("before its part is ready" in x or "before its part arrives" in x for x in v)


def test_missing_tool_trip_rejected(good):
    s = Schedule.from_dict(good.to_dict())
    s.tool_trips = [t for t in s.tool_trips if t.tool != 2]
    v = validate(INST, s)
    assert any("tool 2 is at location 0" in x for x in v)


def test_vehicle_teleport_rejected(good):
    s = Schedule.from_dict(good.to_dict())
    s.agv_trips = [t for t in s.agv_trips if t.loaded]  # drop the empty (deadheading) legs
    v = validate(INST, s)
    assert any("but the vehicle is at" in x for x in v)


def test_op_before_part_arrives_and_makespan_mismatch(good):
    s = shifted_op(good, 1, 0, -1)
    v = validate(INST, s)
    assert any("before its part arrives" in x or "overlaps" in x for x in v)
    s2 = Schedule.from_dict(good.to_dict())
    s2.makespan += 1
    assert any("makespan is" in x for x in validate(INST, s2))


def test_missing_and_duplicate_ops_and_unknown_vehicle(good):
    s = Schedule.from_dict(good.to_dict())
    s.operations = s.operations[1:] + s.operations[-1:]
    v = validate(INST, s)
    assert any("missing from the schedule" in x for x in v)
    assert "op (0,1) is scheduled more than once" in v
    s2 = Schedule.from_dict(good.to_dict())
    s2.agv_trips[0] = replace(s2.agv_trips[0], agv=3)
    assert any("AGV 3 does not exist" in x for x in validate(INST, s2))
    # a vehicle beyond the fleet is named once, with its trips counted (one line per trip filled replay's ten)
    s3 = Schedule.from_dict(good.to_dict())
    s3.agv_trips = [replace(t, agv=4) for t in s3.agv_trips]
    absent = [x for x in validate(INST, s3) if "does not exist" in x]
    assert absent == [f"AGV 4 does not exist (fleet of {INST.n_agvs}): {len(s3.agv_trips)} trips from 0"]


def _edit(rows: str, i: int, **kw):
    """A mutation of the good schedule's dict: row ``i`` of ``rows`` updated with ``kw``."""
    return lambda d: d[rows][i].update({k.rstrip("_"): v for k, v in kw.items()})


def _append(rows: str, i: int, **kw):
    """A mutation of the good schedule's dict: a copy of row ``i`` of ``rows``, updated with ``kw``, appended."""
    return lambda d: d[rows].append({**d[rows][i], **{k.rstrip("_"): v for k, v in kw.items()}})


# One mutation per rule of the validator, each on the good schedule of INST (run_first):
#   ops    (0,0) M1 tool 1 [2,5)   (1,0) M2 tool 2 [7,9)   (0,1) M2 tool 1 [13,15)
#   AGV 0  (0,0) 0->1 [0,2), 1->0 [2,4), (1,0) 0->2 [4,7), 2->1 [7,11), (0,1) 1->2 [11,13)
#   TT 0   tool 1 (0,0) 0->1 [0,1), 1->0 [2,3), tool 2 (1,0) 0->2 [3,5), 2->1 [7,10), tool 1 (0,1) 1->2 [10,13)
# ``only``: the mutation breaks that rule alone, so the message must be the only violation.
RULES = [
    ("duplicate op", _append("operations", 1), "op (1,0) is scheduled more than once", False),
    ("wrong machine", _edit("operations", 1, machine=1), "op (1,0) runs on machine 1, needs machine 2", True),
    ("wrong tool", _edit("operations", 1, tool=1), "op (1,0) uses tool 1, needs tool 2", True),
    ("op before time 0", _edit("operations", 0, start=-1, end=2), "op (0,0) starts before time 0", False),
    ("op that does not exist", _append("operations", 1, op=5), "op (1,5) does not exist in the instance", False),
    ("trip for an op that does not exist", _append("agv_trips", 2, op=5), "loaded AGV trip for nonexistent op (1,5)",
     False),
    ("part moved twice", _append("agv_trips", 2), "op (1,0): the part is moved 2 times (one loaded trip expected)",
     False),
    ("loaded trip names no op", _edit("agv_trips", 2, job=None, op=None),
     "loaded AGV trip of AGV 0 at 4 names no operation", False),
    ("empty trip names an op", _edit("agv_trips", 1, job=1, op=0), "empty AGV trip of AGV 0 at 2 names an operation",
     True),
    ("part taken too early", _edit("operations", 0, start=9, end=12),
     "op (0,1): loaded trip starts at 11 before the part is ready at 12", False),
    ("part travels wrong", _edit("agv_trips", 2, to=1), "op (1,0): the part travels 0->1, must go 0->2", False),
    ("vehicle trips overlap", _edit("agv_trips", 3, start=6, end=10),
     "AGV 0: trip 2->1 at 6 starts before its previous trip ends at 7", True),
    # a vehicle's first trip before time 0 was said to start "before its previous trip ends at 0": it has none
    ("vehicle's first trip before time 0", _edit("agv_trips", 0, start=-3, end=-1),
     "AGV 0: trip 0->1 at -3 starts before time 0", False),
    ("unknown location", _edit("agv_trips", 1, to=7), "AGV 0: trip 1->7 at 2 names an unknown location", False),
    ("tool moved, no use", _edit("tool_trips", 0, tool=3), "tool 3 is moved but no operation uses it", False),
    ("tool carried for another op", _edit("tool_trips", 2, tool=1),
     "tool 1 is carried for op (1,0), which does not use it", False),
    ("tool carried twice", _append("tool_trips", 4), "tool 1 is carried 2 times for op (0,1)", False),
    ("tool taken from the wrong place", _edit("tool_trips", 4, from_=0),
     "tool 1 for op (0,1): trip starts at 0 but the tool is at 1", False),
    ("tool taken to the wrong machine", _edit("tool_trips", 4, to=1),
     "tool 1 for op (0,1): trip goes to 1, the op is on machine 2", False),
    ("tool moved while in use", _edit("tool_trips", 4, start=4, end=7),
     "tool 1 for op (0,1): moved at 4 while busy until 5", False),
    ("tool trip names no tool", _edit("tool_trips", 2, tool=None),
     "loaded trip of transporter 0 at 3 names no tool/operation", False),
    ("empty tool trip names a tool", _edit("tool_trips", 1, tool=2),
     "empty trip of transporter 0 at 2 names a tool or operation", True),
    # an operation alone (no tool, no job) passed, where the AGVs' check refused it
    ("empty tool trip names an op", _edit("tool_trips", 1, op=0),
     "empty trip of transporter 0 at 2 names a tool or operation", True),
]


@pytest.mark.parametrize("mutate, msg, only", [r[1:] for r in RULES], ids=[r[0] for r in RULES])
def test_each_rule_is_checked(good, mutate, msg, only):
    d = good.to_dict()
    mutate(d)
    v = validate(INST, Schedule.from_dict(d))
    assert v == [msg] if only else msg in v, v


@pytest.mark.parametrize("scenario, msg", [
    (Scenario(breakdowns=(Breakdown(2, 6, 2),)), "op (1,0) starts at 7 while machine 2 is down [6, 8)"),
    (Scenario(outages=(Outage("agv", 0, 3, 3),)), "AGV 0: trip 0->2 starts at 4 while out of service [3, 6)"),
    (Scenario(outages=(Outage("tt", 0, 9, 2),)),
     "tool transporter 0: trip 1->2 starts at 10 while out of service [9, 11)"),
])
def test_a_nominal_schedule_breaks_the_windows_of_a_scenario(good, scenario, msg):
    # the schedule unchanged: only the scenario it is checked against puts a start inside a window
    assert validate(INST, good) == []
    assert msg in validate(INST, good, scenario)


@pytest.mark.parametrize("recorded, msg", [
    ("x", "meta.scenario must be an object, got str"),  # it was silently ignored: the schedule called valid
    ({"bogus": 1}, "the schedule's recorded scenario is malformed: "),
])
def test_a_malformed_recorded_scenario_is_reported(good, recorded, msg):
    s = Schedule.from_dict(good.to_dict())
    s.meta["scenario"] = recorded
    (err,) = validate(INST, s)
    assert err.startswith("the schedule's recorded scenario is malformed: ") and msg in err


def test_plain_job_shop_precedence(good):
    inst = Instance("js", [[(1, 3), (2, 2)]])
    s = run_first(inst)
    assert validate(inst, s) == []
    bad = shifted_op(s, 0, 1, -2)
    assert any("before its part is ready" in x for x in validate(inst, bad))


def test_check_raises_with_every_violation(good):
    s = Schedule.from_dict(good.to_dict())
    s.makespan = 0
    s.tool_trips = []
    with pytest.raises(ScheduleInvalid) as exc:
        check(INST, s)
    assert len(exc.value.violations) >= 3


@pytest.mark.parametrize("mutate, msg", [
    (lambda d: d.update(makespan="9"), "makespan"),
    (lambda d: d["operations"][0].update(start=1.5), "start"),
    (lambda d: d["agv_trips"][0].update(loaded=1), "loaded"),
    (lambda d: d.pop("operations"), "operations"),
    (lambda d: d["operations"][0].pop("job"), "job"),
])
def test_malformed_schedule_json(good, mutate, msg):
    d = json.loads(good.to_json())
    mutate(d)
    with pytest.raises(ScheduleError, match=msg):
        Schedule.from_dict(d)


def test_json_round_trip(good):
    again = Schedule.from_json(good.to_json())
    assert again.to_dict() == good.to_dict() and validate(INST, again) == []


def test_zero_length_legs_keep_their_order():
    # travel 0 between L/U and M2: the AGV goes 0->2 and 2->0 at the same instant; the route is continuous
    T0 = [[0, 2, 0], [2, 0, 2], [0, 2, 0]]
    inst = Instance("zero", [[(2, 1)], [(1, 1)]], agv_travel=T0, n_agvs=1)
    s = run_first(inst)
    assert validate(inst, s) == []
    d = s.to_dict()
    again = Schedule.from_dict(d)
    assert validate(inst, again) == []


def test_a_schedule_file_that_is_not_a_schedule_is_named(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ScheduleError, match=r"bad\.json: malformed JSON"):
        Schedule.load(bad)
    with pytest.raises(OSError):
        Schedule.load(tmp_path / "missing.json")
    binary = tmp_path / "shot.png"
    binary.write_bytes(b"\xff\xd8\xff")
    with pytest.raises(ScheduleError, match=r"shot\.png: not a text \(UTF-8 JSON\) file"):
        Schedule.load(binary)


def test_zero_duration_uses_of_a_tool_at_one_instant_follow_its_trip():
    # two 0-length operations on machine 1 share tool 1, brought once for job 1: feasible, but uses at one
    # instant were checked in job order (job 0 first, before the tool had arrived) and the schedule refused
    from fms_sim.instance import Instance

    inst = Instance.from_dict({"name": "zt", "n_tool_transporters": 1, "tool_travel": [[0, 3], [3, 0]],
                               "jobs": [[{"machine": 1, "tool": 1, "duration": 0}],
                                        [{"machine": 1, "tool": 1, "duration": 0}]]})
    doc = {"instance": "zt", "makespan": 5, "n_agvs": 0, "n_tool_transporters": 1, "agv_trips": [],
           "operations": [{"job": j, "op": 0, "machine": 1, "tool": 1, "start": 5, "end": 5} for j in (0, 1)],
           "tool_trips": [{"transporter": 0, "tool": 1, "job": 1, "op": 0, "from": 0, "to": 1, "start": 0,
                           "end": 3, "loaded": True}]}
    assert validate(inst, Schedule.from_dict(doc)) == []
    doc["tool_trips"][0].update(start=3, end=6)  # the tool arrives after both uses: still wrong
    assert validate(inst, Schedule.from_dict(doc))


@pytest.mark.parametrize("mutate, msg", [
    # a schedule built in Python with fractional times was judged feasible (a file with them is refused on reading)
    (lambda s: replace(s, operations=[replace(o, start=o.start + 0.5, end=o.end + 0.5) if i == 0 else o
                                      for i, o in enumerate(s.operations)]),
     "operations[0].start must be an integer, got "),
    (lambda s: replace(s, makespan=float(s.makespan)), "makespan must be an integer, got "),
    (lambda s: replace(s, n_agvs=True), "n_agvs must be an integer, got True"),
    # these crashed the checks (TypeError, AttributeError)
    (lambda s: replace(s, operations=[replace(o, start=None) if i == 1 else o for i, o in enumerate(s.operations)]),
     "operations[1].start must be an integer, got None"),
    (lambda s: replace(s, agv_trips=[replace(t, to="2") for t in s.agv_trips[:1]] + s.agv_trips[1:]),
     "agv_trips[0].to must be an integer, got '2'"),
    (lambda s: replace(s, agv_trips=[replace(t, loaded=1) for t in s.agv_trips]),
     "agv_trips[0].loaded must be true or false, got 1"),
    (lambda s: replace(s, tool_trips=[replace(t, tool=1.0) for t in s.tool_trips]),
     "tool_trips[0].tool must be an integer or None, got 1.0"),
    (lambda s: replace(s, tool_trips=[replace(t, loaded="no") for t in s.tool_trips]),
     "tool_trips[0].loaded must be true or false, got 'no'"),
    (lambda s: replace(s, operations=s.operations[:1] + [{"job": 0}] + s.operations[2:]),
     "operations[1] must be of type OperationRecord, got dict"),
    (lambda s: replace(s, tool_trips=None), "tool_trips must be a list of ToolTrip records, got NoneType"),
])
def test_fields_of_the_wrong_type_are_violations(good, mutate, msg):
    errs = validate(INST, mutate(good))
    assert any(e.startswith(msg) for e in errs), errs


def test_numpy_integers_are_integers(good):
    import numpy as np

    s = replace(good, makespan=np.int64(good.makespan),
                operations=[replace(o, start=np.int32(o.start), end=np.int64(o.end)) for o in good.operations])
    assert validate(INST, s) == []


def test_a_schedule_that_declares_vehicles_or_tools_a_plain_shop_lacks_is_refused():
    # only instances with AGVs or tools had their fleet and tools checked: a plain job shop took any declaration
    plain = Instance("p", [[(1, 2), (2, 3)]])
    s = run_first(plain)
    assert validate(plain, s) == []
    assert validate(plain, replace(s, n_agvs=7)) == ["schedule declares 7 AGVs, the instance has none"]
    assert validate(plain, replace(s, n_tool_transporters=3)) == [
        "schedule declares 3 tool transporters, the instance has none"]
    tooled = replace(s, operations=[replace(o, tool=5) if i == 0 else o for i, o in enumerate(s.operations)])
    assert validate(plain, tooled) == ["op (0,0) uses tool 5, needs none"]


def test_to_dict_gives_a_copy_of_the_meta(good):
    s = replace(good, meta={"solver": "first", "scenario": {"noise": 0.1}})
    d = s.to_dict()
    d["meta"]["x"] = 1
    d["meta"]["scenario"]["noise"] = 0.5
    assert s.meta == {"solver": "first", "scenario": {"noise": 0.1}}


# ---------------------------------------------------------------------------------- live orders
def _ordered_run():
    """ra01 (tools, AGVs) run by random choices, with two jobs ordered after 25 decisions: the shop, the order's
    jobs and when they arrived."""
    import random

    from fms_sim.benchmarks import builtin
    from fms_sim.full_shop import FullShop
    from fms_sim.instance import Operation

    rng = random.Random(3)
    shop = FullShop(builtin("ra01"))
    for _ in range(25):
        shop.act(rng.choice(shop.legal_actions()))
    t0 = shop.now
    ids = shop.add_jobs([[Operation(1, 1, 3), Operation(2, 2, 4)], [Operation(3, None, 5)]])
    while not shop.done:
        shop.act(rng.choice(shop.legal_actions()))
    return shop, ids, t0


def test_a_schedule_records_when_the_jobs_of_live_orders_arrived():
    shop, ids, t0 = _ordered_run()
    assert t0 > 0
    sched = shop.schedule()
    assert sched.meta["arrivals"] == [[j, t0] for j in ids]
    assert validate(shop.instance, sched) == []
    back = Schedule.from_json(sched.to_json())  # written and read back, the record still holds
    assert back.meta["arrivals"] == sched.meta["arrivals"] and validate(shop.instance, back) == []
    assert "arrivals" not in run_first(replace(shop.instance, jobs=shop.instance.jobs[:-2])).meta  # no order: none


def test_nothing_of_an_ordered_job_may_start_before_it_arrived():
    # a schedule of the final instance that starts an ordered job at time 0 was valid: the validator did not know
    # when the order came (it was in the recorder's events only)
    from fms_dispatch.exact import greedy_schedule

    shop, ids, t0 = _ordered_run()
    inst = shop.instance
    # a list schedule of the final instance that takes the ordered jobs first
    early = greedy_schedule(inst, rule="guided", priority={(j, k): k + (0 if j in ids else 100)
                                                           for j, job in enumerate(inst.jobs) for k in range(len(job))})
    assert validate(inst, early) == [] and min(r.start for r in early.operations if r.job in ids) < t0
    early.meta["arrivals"] = shop.schedule().meta["arrivals"]
    errs = validate(inst, early)
    assert any(e.startswith(f"op ({ids[0]},0) starts at ") and e.endswith(f"before its job arrived (a live order) "
                                                                          f"at {t0}") for e in errs), errs
    assert any(e.startswith("AGV trip") and f"for op ({ids[0]},0)" in e for e in errs), errs
    assert any(e.startswith("tool transporter trip") and f"({ids[0]}," in e for e in errs), errs
    # the same schedule with the jobs ordered at time 0 is valid
    early.meta["arrivals"] = [[j, 0] for j in ids]
    assert validate(inst, early) == []


@pytest.mark.parametrize("record, message", [
    ({"5": 3}, "meta.arrivals must be a list of [job, time] pairs, got dict"),
    ([[1]], "meta.arrivals[0] must be a [job, time] pair of integers, got [1]"),
    ([[1, 2.5]], "meta.arrivals[0] must be a [job, time] pair of integers, got [1, 2.5]"),
    ([[1, True]], "meta.arrivals[0] must be a [job, time] pair of integers, got [1, True]"),
    ([[99, 2]], "meta.arrivals[0]: job 99 does not exist (0..2)"),
    ([[1, -1]], "meta.arrivals[0]: job 1 arrives at -1, before the run began"),
    ([[1, 0], [1, 2]], "meta.arrivals[1]: job 1 arrives twice"),
])
def test_a_malformed_arrivals_record_is_reported(record, message):
    from fms_sim.benchmarks import builtin

    inst = builtin("EX11")
    inst = replace(inst, jobs=inst.jobs[:3])
    sched = run_first(inst)
    sched.meta["arrivals"] = record
    assert validate(inst, sched) == [message]


def test_a_schedule_equals_its_json_round_trip_and_another_run_of_it():
    # the JSON form sorts the records and the reader keeps its order, and meta held the wall time: no schedule
    # equalled its own round trip, nor two runs of a deterministic solver each other
    from fms_dispatch.solvers import solve
    from fms_sim.benchmarks import builtin

    inst = builtin("ra01")
    for solver in ("first", "list", "rule:MTWR+nearest"):
        a, b = solve(inst, solver), solve(inst, solver)
        assert a.meta.get("wall_time") is not None
        assert a == Schedule.from_json(a.to_json()) and a == b, solver
    c = solve(inst, "rule:SPT+first")
    assert c.makespan != a.makespan and c != a
    # what changes the meaning is compared: the disruptions, the orders' arrivals, a residual plan's start
    for key, value in (("scenario", Scenario((), (), 0.1, 3).to_dict()), ("arrivals", [[0, 0]]), ("residual", 0)):
        other = Schedule.from_json(a.to_json())
        other.meta[key] = value
        assert other != a and Schedule.from_json(other.to_json()) == other, key
    assert a != a.to_dict() and a.__eq__("x") is NotImplemented


def test_library_inputs_of_other_types_are_taken_or_refused_by_name(tmp_path):
    # JSON bytes were refused as "a bytes-like object is required, not 'str'"; a scenario given as a dict failed
    # with "'dict' object has no attribute 'check'"
    from fms_sim.benchmarks import builtin

    inst = builtin("EX12")
    s = run_first(inst)
    assert Schedule.from_json(s.to_json().encode()) == s
    with pytest.raises(ScheduleError, match="malformed JSON: not UTF-8 text"):
        Schedule.from_json(b"\xff{}")
    with pytest.raises(TypeError, match="JSON text must be a str or bytes, got int"):
        Schedule.from_json(3)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"scenario must be a Scenario \(Scenario.from_dict reads one\), got dict"):
        validate(inst, s, {"breakdowns": []})  # type: ignore[arg-type]
