"""The instance data model refuses what breaks it, with a message that names the field."""

from __future__ import annotations

import json
import re
from typing import Any

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.instance import Instance, InstanceError, Operation

Z3 = [[0, 1, 2], [1, 0, 1], [2, 1, 0]]  # L/U + 2 machines
Z4 = [[0, 1, 2, 3], [1, 0, 1, 2], [2, 1, 0, 1], [3, 2, 1, 0]]  # L/U + 3 machines


def _inst(**kw: Any) -> Instance:
    base: dict[str, Any] = dict(name="x", jobs=[[{"machine": 1, "tool": 1, "duration": 3}]])
    base.update(kw)
    return Instance(**base)


@pytest.mark.parametrize("kw, match", [
    (dict(jobs=[]), "instance has no jobs"),
    (dict(jobs=[[]]), "job 0 has no operations"),
    (dict(jobs=[[{"machine": 0, "duration": 3}]]), "job 0 operation 0: machine must be an integer from 1 to 1000"),
    (dict(jobs=[[{"machine": 1, "duration": -1}]]), "duration must be a non-negative integer"),
    (dict(jobs=[[{"machine": 1}]]), "missing field 'duration'"),
    (dict(jobs=[[{"machine": 1, "duration": 3, "tol": 1}]]), "job 0 operation 0: unknown field 'tol'"),
    # a tool above the declared count, as a machine above the machine count
    (dict(tool_travel=Z3, n_tool_transporters=1, jobs=[[{"machine": 1, "tool": 2, "duration": 3}]], n_tools=1),
     "an operation uses tool 2 but the instance has only 1 tools"),
    (dict(agv_travel=Z3, n_agvs=1, jobs=[[{"machine": 3, "duration": 3}]]),
     r"uses machine 3 but the instance has only 2 machines \(from the 3 rows of agv_travel"),
    (dict(agv_travel=Z4, n_agvs=1, tool_travel=Z3, n_tool_transporters=1),
     r"agv_travel has 4 rows and tool_travel 3: both must be \(m\+1\)x\(m\+1\)"),
    (dict(agv_travel=Z4, n_agvs=1, tool_travel=Z3, n_tool_transporters=1, n_machines=3),
     "tool_travel must be a 4x4 matrix"),
    (dict(agv_travel=[[0, 1, 2], [1, 1, 1], [2, 1, 0]], n_agvs=1), r"agv_travel\[1\]\[1\] must be 0"),
    (dict(agv_travel=[[0, -1, 2], [1, 0, 1], [2, 1, 0]], n_agvs=1), r"agv_travel\[0\]\[1\] is negative"),
    (dict(agv_travel=Z3), "AGV travel matrix but no AGVs"),
    (dict(tool_travel=Z3), "tool travel matrix but no tool transporters"),
    (dict(), "operations need tools but tool_travel is null: give a tool travel matrix, or operations without "
             "tools$"),
    # the constructor set these to 0 without a word (Instance.from_dict refused them)
    (dict(jobs=[[(1, None, 2)]], n_agvs=3), "n_agvs is 3 but agv_travel is missing"),
    (dict(jobs=[[(1, None, 2)]], agv_travel=Z3, n_agvs=1, n_tool_transporters=2),
     "n_tool_transporters is 2 but tool_travel is missing"),
    # tools without their matrix were kept: a "plain job shop" of 3 tools (an env padded its observations by them)
    (dict(jobs=[[(1, None, 2)]], n_tools=3), r"n_tools is 3 but tool_travel is missing: tools need a tool travel "
                                             r"matrix and transporters \(give tool_travel and n_tool_transporters, "
                                             r"or leave n_tools out for a shop without tools\)"),
    (dict(jobs=[[(1, None, 2)]], agv_travel=Z3, n_agvs=1, n_tools=1), "n_tools is 1 but tool_travel is missing"),
])
def test_refused(kw: dict, match: str) -> None:
    with pytest.raises(InstanceError, match=match):
        _inst(**kw)


def test_counts_derived_or_given() -> None:
    a = _inst(tool_travel=Z3, n_tool_transporters=1)
    assert (a.n_machines, a.n_tools) == (2, 1)  # machines from the matrix, tools from the operations
    b = _inst(tool_travel=Z3, n_tool_transporters=1, n_tools=4)
    assert b.n_tools == 4  # more tools than the operations use is fine (an idle tool)


@pytest.mark.parametrize("change, match", [
    (lambda d: d.update(n_agv=5), "unknown instance field 'n_agv'"),
    (lambda d: d["jobs"][0][0].update(tol=1), "unknown field 'tol'"),
    (lambda d: d.pop("jobs"), "missing the field 'jobs'"),
])
def test_json_refuses_misspelt_fields(change: Any, match: str) -> None:
    data = builtin("EX12").to_dict()
    change(data)
    with pytest.raises(InstanceError, match=match):
        Instance.from_json(json.dumps(data))


def test_json_round_trip() -> None:
    for name in ("EX12", "ra01", "sl00"):
        inst = builtin(name)
        assert Instance.from_json(inst.to_json()) == inst


@pytest.mark.parametrize("extra, needle", [
    ({"n_agvs": 3}, "n_agvs is 3 but agv_travel is missing"),
    ({"n_tool_transporters": 2}, "n_tool_transporters is 2 but tool_travel is missing"),
    ({"n_tools": 2}, "n_tools is 2 but tool_travel is missing"),
    ({"n_tools": 2, "tool_travel": None}, "n_tools is 2 but tool_travel is missing"),
    ({"n_machines": False}, "n_machines must be an integer from 0 to 1000 (0: derived), got False"),
    ({"n_machines": []}, "n_machines must be an integer from 0 to 1000 (0: derived), got []"),
    ({"n_machines": 0.0}, "n_machines must be an integer from 0 to 1000 (0: derived), got 0.0"),
    ({"n_tools": ""}, "n_tools must be an integer from 0 to 1000 (0: derived), got ''"),
])
def test_counts_in_json_are_not_dropped_or_coerced(extra, needle):
    # n_agvs without a travel matrix became a plain job shop, and false, [], 0.0 or "" were read as 0
    data = {"name": "t", "jobs": [[{"machine": 1, "tool": None, "duration": 3}]], **extra}
    with pytest.raises(InstanceError, match=re.escape(needle)):
        Instance.from_dict(data)
    assert Instance.from_dict({"name": "t", "jobs": data["jobs"], "n_machines": None}).n_machines == 1


@pytest.mark.parametrize("data, needle", [
    ({"jobs": [[{"machine": 1, "duration": 10**30}]]},
     "duration must be a non-negative integer (at most 1,000,000,000)"),
    ({"jobs": [[{"machine": 1, "duration": 3}]], "n_machines": 10**7}, "n_machines must be an integer from 0 to 1000"),
    ({"jobs": [[{"machine": 1, "tool": 10**9, "duration": 3}]]}, "tool must be null or an integer from 1 to 1000"),
    ({"jobs": [[{"machine": 1, "duration": 3}]], "n_agvs": 10**9, "agv_travel": [[0, 1], [1, 0]]},
     "n_agvs must be an integer from 0 to 1000"),
    ({"jobs": [[{"machine": 1, "duration": 3}]], "n_agvs": 1, "agv_travel": [[0, 2**62], [1, 0]]},
     "travel times must be from 0 to 1,000,000,000"),
])
def test_sizes_and_times_are_bounded(data, needle):
    # a time of 10**30 was "valid" to the list schedulers and crashed cpsat and ppo; 10**9 AGVs ran out of memory
    with pytest.raises(InstanceError, match=re.escape(needle)):
        Instance.from_dict({"name": "t", **data})


def test_numpy_integers_and_arrays_build_an_instance_of_python_ints() -> None:
    # shops generated with numpy were refused: "machine must be an integer ..., got np.int64(1)", a numpy travel
    # matrix "must be an (m+1)x(m+1) matrix"; stored as Python ints, they are written as JSON like any other
    import numpy as np

    from fms_sim.formats import load_instance

    rng = np.random.default_rng(0)
    jobs = [[Operation(np.int64(m), None, np.int32(d)) for m, d in zip(rng.permutation(3) + 1, rng.integers(1, 9, 3))]
            for _ in range(2)]
    travel = np.array([[0, 2, 3, 4], [2, 0, 1, 2], [3, 1, 0, 1], [4, 2, 1, 0]])
    inst = Instance("np", jobs=jobs, agv_travel=travel, n_agvs=np.int64(2))
    plain = Instance("np", jobs=[[Operation(int(o.machine), None, int(o.duration)) for o in job] for job in jobs],
                     agv_travel=travel.tolist(), n_agvs=2)
    assert inst == plain and Instance.from_json(inst.to_json()) == inst
    assert all(type(v) is int for job in inst.jobs for op in job for v in (op.machine, op.duration))
    assert type(inst.n_agvs) is int and all(type(x) is int for row in inst.agv_travel for x in row)
    assert Instance("a", jobs=np.array([[[1, 3]], [[2, 4]]])).jobs == ((Operation(1, None, 3),), (Operation(2, None, 4),))
    assert builtin("EX12").with_fleet(n_agvs=np.int64(1)).n_agvs == 1
    assert load_instance("EX12", agvs=np.int64(3)).n_agvs == 3
    with pytest.raises(InstanceError, match="machine must be an integer"):
        Operation(np.float64(1.0), None, 3)  # type: ignore[arg-type]
    with pytest.raises(InstanceError, match="machine must be an integer"):
        Operation(True, None, 3)


def test_describe_counts_in_words() -> None:
    # "1 jobs x 1 machines"
    one = Instance(name="one", jobs=((Operation(1, None, 5),),), n_machines=1)
    assert one.describe() == "one: 1 job x 1 machine, 1 operation, plain job shop"
    assert builtin("EX12").describe() == "EX12: 5 jobs x 4 machines, 13 operations, 2 AGVs"


def test_a_machine_count_read_from_a_travel_matrix_keeps_the_limit() -> None:
    # 1,201 machines taken from a matrix's rows were accepted, and the file written then refused as n_machines 1201
    from fms_sim.instance import MAX_COUNT, InstanceError

    n = MAX_COUNT + 2
    matrix = [[0 if i == j else 1 for j in range(n)] for i in range(n)]
    with pytest.raises(InstanceError, match=f"agv_travel has {n} rows: L/U \\+ {n - 1} machines, more than "
                                            f"{MAX_COUNT}"):
        Instance(name="wide", jobs=[[Operation(1, None, 5)]], agv_travel=matrix, n_agvs=1)


@pytest.mark.parametrize("name", ["\ud800", "a\nb", "x\x00", "t\u202e", "tab\there"])
def test_a_name_that_cannot_be_printed_is_refused(name: str) -> None:
    # a lone surrogate read from JSON ("\ud800") passed, and `fms solve FILE` failed after the solve when it printed
    # the result (not UTF-8); a line break printed one name as two lines
    text = json.dumps({"name": name, "jobs": [[{"machine": 1, "tool": None, "duration": 3}]]})
    with pytest.raises(InstanceError, match="cannot be printed"):
        Instance.from_json(text)
    assert Instance(name="EX12 copy", jobs=((Operation(1, None, 3),),)).name == "EX12 copy"
