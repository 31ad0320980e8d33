"""Operations of zero duration at one instant (found by fuzzing random shops): the validator accepts a feasible
order of a tool's tied uses whatever the job numbers, and replay carries out valid schedules whose tied operations
a list order would deadlock. Both made solvers fail on such shops (list, rules, plan:, tabu, ppo)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fms_dispatch.solvers import solve
from fms_sim.instance import Instance
from fms_sim.replay import replay
from fms_sim.schedule import Schedule
from fms_sim.validate import tool_use_orders, validate

DATA = Path(__file__).resolve().parent.parent / "data" / "zero_duration_ties.json"

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
