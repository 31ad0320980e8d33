"""Operations of zero duration at one instant (found by fuzzing random shops): the validator accepts a feasible
order of a tool's tied uses whatever the job numbers, and replay carries out valid schedules whose tied operations
a list order would deadlock. Both made solvers fail on such shops (list, rules, plan:, tabu, ppo). The validator
refuses tied events recorded in orders that contradict one another (no sequence follows every resource), and
CP-SAT, whose precedences allow such ties, records its tied trips in an order their tools and parts follow."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fms_dispatch.solvers import solve
from fms_sim.instance import Instance
from fms_sim.replay import ReplayError, replay
from fms_sim.schedule import Schedule
from fms_sim.validate import tool_use_orders, validate

DATA = Path(__file__).resolve().parent.parent / "data" / "zero_duration_ties.json"
#: fuzzed shops (zero tool travel): "recorded", a CP-SAT schedule whose tied tool trips contradict the tool's
#: order; "unrepairable_ties", a shop where CP-SAT's solutions tie trips in orders no re-sequencing repairs;
#: "job_against_tool", one where they order a tool's uses at t=0 against a job's operations
CONTRADICTION = Path(__file__).resolve().parent.parent / "data" / "tie_contradiction.json"

#: tool 2 is carried 0->5 for job 1's use, then 5->2 for job 0's, all at t=0 over zero travel times
INST = Instance.from_dict({
    "name": "tied", "tool_travel": [[0] * 6 for _ in range(6)], "n_tool_transporters": 1,
    "jobs": [[{"machine": 2, "tool": 2, "duration": 0}],
             [{"machine": 5, "tool": 2, "duration": 0}, {"machine": 1, "tool": None, "duration": 1}]]})
TIED = {"instance": "tied", "makespan": 1, "n_agvs": 0, "n_tool_transporters": 1, "agv_trips": [], "meta": {},
        "operations": [{"job": 0, "op": 0, "machine": 2, "tool": 2, "start": 0, "end": 0},
                       {"job": 1, "op": 0, "machine": 5, "tool": 2, "start": 0, "end": 0},
                       {"job": 1, "op": 1, "machine": 1, "tool": None, "start": 0, "end": 1}],
        "tool_trips": [{"transporter": 0, "tool": 2, "job": 1, "op": 0, "from": 0, "to": 5, "start": 0, "end": 0,
                        "loaded": True},
                       {"transporter": 0, "tool": 2, "job": 0, "op": 0, "from": 5, "to": 2, "start": 0, "end": 0,
                        "loaded": True}]}


def test_tied_uses_are_checked_in_an_order_the_tool_can_follow():
    sched = Schedule.from_dict(TIED)
    assert validate(INST, sched) == []  # it named the tool in two wrong places (job 0's use checked first)
    assert tool_use_orders(INST, sched) == {2: [(1, 0), (0, 0)]}
    # no order fits when the trips do not chain: still refused, naming the tool's places
    bad = json.loads(json.dumps(TIED))
    bad["tool_trips"][1]["from"] = 3
    assert any("but the tool is at" in e for e in validate(INST, Schedule.from_dict(bad)))


@pytest.mark.parametrize("name", ["list", "list:ect", "rules", "plan:list", "tabu"])
def test_solvers_that_replay_a_plan_solve_the_tied_shop(name):
    s = solve(INST, name, **({"time_limit": 0.2} if name in ("rules", "tabu") else {}))
    assert validate(INST, s) == [] and s.makespan == 1


@pytest.mark.parametrize("case", sorted(json.loads(DATA.read_text())))
def test_valid_schedules_with_tied_operations_replay(case):
    inst_doc, sched_doc = json.loads(DATA.read_text())[case]
    inst, sched = Instance.from_dict(inst_doc), Schedule.from_dict(sched_doc)
    assert validate(inst, sched) == []
    out = replay(inst, sched)  # it was "stuck: no planned order can be carried out and nothing is in flight"
    assert validate(inst, out) == [] and out.makespan <= sched.makespan


def _contradiction() -> tuple[Instance, dict]:
    doc = json.loads(CONTRADICTION.read_text())["recorded"]
    return Instance.from_dict(doc["instance"]), doc["schedule"]


def test_tied_trips_recorded_against_their_tools_order_are_refused():
    """At t=26 transporter 0 records carrying tool 1 2->1 for op (1,2), then 1->2 for op (2,1), while the tool is
    on machine 1 until op (2,1) has used it on machine 2: each resource's own order holds (the route chains, the
    tool has an order of its own), no order holds them all. CP-SAT made it; replay got stuck on it."""
    inst, doc = _contradiction()
    errs = validate(inst, Schedule.from_dict(doc))
    assert len(errs) == 1 and errs[0].startswith("at time 26 no order of the events follows every resource: ")
    assert "tool 1 for op (1,2)" in errs[0] and "tool 1 for op (2,1)" in errs[0] and "-> op (2,1) ->" in errs[0]
    with pytest.raises(ReplayError, match="not valid"):
        replay(inst, Schedule.from_dict(doc))
    # the same times in the order the tool follows (the transporter first goes back empty to machine 1): valid
    trips = doc["tool_trips"]
    late = [t for t in trips if t["start"] == 26]
    assert [(t["job"], t["op"]) for t in late] == [(1, 2), (2, 1)]
    back = {"transporter": 0, "tool": None, "job": None, "op": None, "from": 2, "to": 1, "start": 7, "end": 7,
            "loaded": False}
    doc["tool_trips"] = [t for t in trips if t["start"] < 26] + [back, late[1], late[0]]
    sched = Schedule.from_dict(doc)
    assert validate(inst, sched) == []
    out = replay(inst, sched)
    assert validate(inst, out) == [] and out.makespan <= sched.makespan


def test_a_part_carried_on_before_it_arrives_is_refused():
    """Zero travel and durations: an AGV records carrying job 0's part 2->1 for op (0,2) before carrying it 1->2
    for op (0,1). The route chains (0->1, 1->2 empty, 2->1, 1->2) and each trip fits its operation's times."""
    inst = Instance.from_dict({"name": "hop", "agv_travel": [[0] * 3 for _ in range(3)], "n_agvs": 1,
                               "jobs": [[{"machine": 1, "duration": 0}, {"machine": 2, "duration": 0},
                                         {"machine": 1, "duration": 0}]]})

    def sched(trips: list[tuple]) -> Schedule:
        return Schedule.from_dict({
            "instance": "hop", "makespan": 0, "n_agvs": 1, "n_tool_transporters": 0, "tool_trips": [],
            "operations": [{"job": 0, "op": k, "machine": m, "tool": None, "start": 0, "end": 0}
                           for k, m in enumerate((1, 2, 1))],
            "agv_trips": [{"agv": 0, "job": None if k is None else 0, "op": k, "from": a, "to": b, "start": 0,
                           "end": 0, "loaded": k is not None} for k, a, b in trips]})

    wrong = sched([(0, 0, 1), (None, 1, 2), (2, 2, 1), (1, 1, 2)])
    errs = validate(inst, wrong)
    assert len(errs) == 1 and errs[0].startswith("at time 0 no order of the events follows every resource: ")
    assert "AGV 0's trip 2->1 with op (0,2)'s part" in errs[0] and "AGV 0's trip 1->2 with op (0,1)'s part" in errs[0]
    right = sched([(0, 0, 1), (1, 1, 2), (2, 2, 1)])
    assert validate(inst, right) == []
    assert validate(inst, replay(inst, right)) == []


@pytest.mark.parametrize("seed", [0, 1])
def test_cpsat_records_tied_trips_in_an_order_their_tools_follow(seed):
    """The shop of the contradiction above: every CP-SAT solution routed the transporter through the tied trips
    in the recorded, impossible order (10 seeds of 10) before its routes' ties were put in each tool's order."""
    inst, _ = _contradiction()
    s = solve(inst, "cpsat", time_limit=1.0, seed=seed)
    assert validate(inst, s) == []
    out = replay(inst, s)
    assert validate(inst, out) == [] and out.makespan <= s.makespan


def test_tools_at_one_instant_are_ordered_together_with_the_jobs():
    """At t=4 job 1 uses tool 1, then tool 2 (carried in); job 0 uses tool 2, then tool 1, all on machine 1. Tool
    2's order is forced (its carry comes first); tool 1's two uses are both where it is, and taken alone the first
    by job number (job 0) closes a cycle with the jobs: the orders are searched together, job 1's use first."""
    inst = Instance.from_dict({
        "name": "crossed", "tool_travel": [[0] * 4 for _ in range(4)], "n_tool_transporters": 1, "n_machines": 3,
        "jobs": [[{"machine": 2, "tool": None, "duration": 4}, {"machine": 1, "tool": 2, "duration": 0},
                  {"machine": 1, "tool": 1, "duration": 0}],
                 [{"machine": 3, "tool": None, "duration": 4}, {"machine": 1, "tool": 1, "duration": 0},
                  {"machine": 1, "tool": 2, "duration": 0}],
                 [{"machine": 1, "tool": 1, "duration": 2}]]})

    def op(j: int, k: int, m: int, tool: int | None, s: int, e: int) -> dict:
        return {"job": j, "op": k, "machine": m, "tool": tool, "start": s, "end": e}

    def trip(tool: int | None, j: int | None, k: int | None, a: int, b: int, s: int) -> dict:
        return {"transporter": 0, "tool": tool, "job": j, "op": k, "from": a, "to": b, "start": s, "end": s,
                "loaded": tool is not None}

    sched = Schedule.from_dict({
        "instance": "crossed", "makespan": 4, "n_agvs": 0, "n_tool_transporters": 1, "agv_trips": [], "meta": {},
        "operations": [op(2, 0, 1, 1, 0, 2), op(0, 0, 2, None, 0, 4), op(1, 0, 3, None, 0, 4), op(1, 1, 1, 1, 4, 4),
                       op(1, 2, 1, 2, 4, 4), op(0, 1, 1, 2, 4, 4), op(0, 2, 1, 1, 4, 4)],
        "tool_trips": [trip(1, 2, 0, 0, 1, 0), trip(None, None, None, 1, 0, 0), trip(2, 1, 2, 0, 1, 4)]})
    assert validate(inst, sched) == []  # it named the cycle op (0,1) -> op (0,2) -> op (1,1) -> op (1,2)
    assert tool_use_orders(inst, sched) == {1: [(2, 0), (1, 1), (0, 2)], 2: [(1, 2), (0, 1)]}
    out = replay(inst, sched)
    assert validate(inst, out) == [] and out.makespan == 4
    for name in ("list", "cpsat", "plan:list", "tabu"):
        s = solve(inst, name, **({"time_limit": 0.5} if name in ("cpsat", "tabu") else {}))
        assert validate(inst, s) == [] and s.makespan == 4, name


@pytest.mark.parametrize("shop, seed", [("unrepairable_ties", 0), ("unrepairable_ties", 2),
                                        ("job_against_tool", 0), ("job_against_tool", 1)])
def test_cpsat_never_returns_ties_no_shop_can_follow(shop, seed):
    """CP-SAT's solutions of this shop tie a transporter's zero-length carries of two tools at t=35 in an order that
    contradicts one tool's, and no re-sequencing of the route reaches every pickup in time: such a solution is no
    schedule. CP-SAT returned it (6 seeds of 12, status OPTIMAL); now a list schedule following its start times
    stands in where it is better than the best schedule so far, and OPTIMAL is claimed only at the bound. In the
    other shop CP-SAT's tool sequence at t=0 put job 0's second use of tool 1 before its first (both of zero
    length: the job's precedence holds as an equality), and the schedule was refused by the tool check."""
    inst = Instance.from_dict(json.loads(CONTRADICTION.read_text())[shop]["instance"])
    s = solve(inst, "cpsat", time_limit=0.5, seed=seed)
    assert validate(inst, s) == []
    assert s.meta["lower_bound"] <= s.makespan
    assert (s.meta["status"] == "OPTIMAL") == (s.makespan == s.meta["lower_bound"])
    out = replay(inst, s)
    assert validate(inst, out) == [] and out.makespan <= s.makespan


def test_many_tied_uses_beside_a_search_are_settled_at_once():
    """The crossed instant of the test above makes the tools' orders be searched together at t=4, where tool 3 may
    leave machine 4 only after job 4's use there (which waits for a carry on the other transporter) and 40 jobs use
    tool 5 on machine 7. The search branched on every use and met its state budget after about 9 s, refusing the
    schedule (a review built it); uses where their tool is are now taken at once, only carries are choices."""
    n = 40
    jobs = [[{"machine": 2, "tool": None, "duration": 4}, {"machine": 1, "tool": 2, "duration": 0},
             {"machine": 1, "tool": 1, "duration": 0}],
            [{"machine": 3, "tool": None, "duration": 4}, {"machine": 1, "tool": 1, "duration": 0},
             {"machine": 1, "tool": 2, "duration": 0}],
            [{"machine": 1, "tool": 1, "duration": 2}], [{"machine": 4, "tool": 3, "duration": 4}],
            [{"machine": 6, "tool": 4, "duration": 0}, {"machine": 4, "tool": 3, "duration": 0}],
            [{"machine": 5, "tool": 3, "duration": 0}]] + [[{"machine": 7, "tool": 5, "duration": 0}]] * (n + 1)
    inst = Instance.from_dict({"name": "settled", "jobs": jobs, "tool_travel": [[0] * 8 for _ in range(8)],
                               "n_tool_transporters": 2, "n_machines": 7})

    def op(j: int, k: int, m: int, tool: int | None, s: int, e: int) -> dict:
        return {"job": j, "op": k, "machine": m, "tool": tool, "start": s, "end": e}

    def trip(r: int, tool: int | None, j: int | None, a: int, b: int, s: int) -> dict:
        k = {2: 0, 3: 0, 5: 0, 6: 0, 1: 2, 4: 0}.get(j) if j is not None else None  # (the carried op of job j)
        return {"transporter": r, "tool": tool, "job": j, "op": k, "from": a, "to": b, "start": s, "end": s,
                "loaded": tool is not None}

    ops = [op(2, 0, 1, 1, 0, 2), op(0, 0, 2, None, 0, 4), op(1, 0, 3, None, 0, 4), op(3, 0, 4, 3, 0, 4),
           op(1, 1, 1, 1, 4, 4), op(1, 2, 1, 2, 4, 4), op(0, 1, 1, 2, 4, 4), op(0, 2, 1, 1, 4, 4),
           op(4, 0, 6, 4, 4, 4), op(4, 1, 4, 3, 4, 4), op(5, 0, 5, 3, 4, 4)] + [op(6 + i, 0, 7, 5, 4, 4)
                                                                                for i in range(n + 1)]
    trips = [trip(0, 1, 2, 0, 1, 0), trip(0, None, None, 1, 0, 0), trip(0, 3, 3, 0, 4, 0), trip(0, 3, 5, 4, 5, 4),
             trip(0, None, None, 5, 0, 4), trip(0, 5, 6, 0, 7, 4), trip(1, 2, 1, 0, 1, 4),
             trip(1, None, None, 1, 0, 4), trip(1, 4, 4, 0, 6, 4)]
    sched = Schedule.from_dict({"instance": "settled", "makespan": 4, "n_agvs": 0, "n_tool_transporters": 2,
                                "agv_trips": [], "meta": {}, "operations": ops, "tool_trips": trips})
    assert validate(inst, sched) == []
    out = replay(inst, sched)
    assert validate(inst, out) == [] and out.makespan == 4
