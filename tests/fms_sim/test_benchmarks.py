"""Built-in instances: Bilge-Ulusoy (EX), Raj with tools (ra), the LCG benchmark (sl) and ta01."""

from __future__ import annotations

import json
from importlib import resources

import pytest

from fms_sim.benchmarks import BU_OPTIMAL_MAKESPAN, SL_GROUPS, builtin, builtin_names, is_builtin_name
from fms_sim.generate import AGV_SEED, ROUTE_SEED, TIME_SEED, TaillardRNG, taillard_routing, taillard_times
from fms_sim.instance import InstanceError, Operation

LAYOUT2 = ((0, 4, 6, 8, 6), (6, 0, 2, 4, 2), (8, 12, 0, 2, 4), (6, 10, 12, 0, 2), (4, 8, 10, 12, 0))
TOOLS_LAYOUT2 = ((0, 3, 4, 6, 4), (4, 0, 1, 3, 1), (6, 8, 0, 1, 3), (4, 7, 8, 0, 1), (3, 6, 7, 8, 0))


def _data(name: str) -> dict:
    return json.loads(resources.files("fms_sim").joinpath("data").joinpath(name).read_text())


def test_builtin_names() -> None:
    names = builtin_names()
    assert len(names) == 40 + 20 + 80 + 1 == len(set(names))
    assert names[:5] == ["EX11", "EX12", "EX13", "EX14", "EX21"]
    assert "EX104" in names and "ra20" in names and "sl79" in names and names[-1] == "ta01"
    assert all(is_builtin_name(n) for n in names)
    assert not is_builtin_name("foo.txt")


@pytest.mark.parametrize("name", builtin_names())
def test_every_builtin_loads(name: str) -> None:
    inst = builtin(name)
    assert inst.name == name
    assert builtin(name.upper()).name == name  # case-insensitive


def test_ex12() -> None:
    inst = builtin("EX12")
    assert (inst.n_jobs, inst.n_operations, inst.n_machines, inst.n_agvs) == (5, 13, 4, 2)
    assert inst.agv_travel == LAYOUT2
    assert inst.tool_travel is None and inst.n_tool_transporters == 0 and inst.n_tools == 0
    assert inst.jobs[0] == (Operation(1, None, 8), Operation(2, None, 16), Operation(4, None, 12))
    assert inst.meta["optimal_makespan"] == 82 == BU_OPTIMAL_MAKESPAN[(1, 2)]


def test_ex_layout_is_last_digit() -> None:
    ex101 = builtin("ex101")
    assert ex101.name == "EX101" and ex101.n_jobs == 6 and ex101.n_operations == 21
    assert ex101.agv_travel == tuple(map(tuple, _data("bu_layouts.json")["layouts"]["1"]))
    assert builtin("EX104").meta["optimal_makespan"] == 157
    assert builtin("EX12", layout=2).name == "EX12"
    with pytest.raises(InstanceError, match=r"EX12 already names layout 2; layout 3 conflicts \(use EX13\)"):
        builtin("EX12", layout=3)


def test_set3_job3_correction_and_ra03_typo() -> None:
    for lay in range(1, 5):
        assert builtin(f"EX3{lay}").jobs[2] == (Operation(1, None, 20), Operation(2, None, 10))
    assert _data("bu_jobsets.json")["jobsets"]["set3"]["jobs"][2][0] == [1, 20]
    # ra03 keeps the authors' typo (M1 = 10), as documented.
    assert builtin("ra03").jobs[2][0] == Operation(1, 3, 10)


def test_ra01_default_layout() -> None:
    inst = builtin("ra01")
    assert inst.name == "ra01" and inst.mode == "agvs+tools"
    assert (inst.n_agvs, inst.n_tool_transporters, inst.n_tools, inst.n_machines) == (2, 1, 4, 4)
    assert inst.agv_travel == LAYOUT2 and inst.tool_travel == TOOLS_LAYOUT2
    assert inst.jobs[0] == (Operation(1, 3, 8), Operation(2, 4, 16), Operation(4, 1, 12))
    # Same machines/times as BU set 1.
    ex = builtin("EX12")
    assert [[(o.machine, o.duration) for o in ops] for ops in inst.jobs] == [
        [(o.machine, o.duration) for o in ops] for ops in ex.jobs
    ]


def test_ra_layouts() -> None:
    l3 = builtin("ra01", layout=3)
    assert l3.name == "ra01L3" and builtin("RA01l3") == l3
    raw = _data("raj_bu_tools.json")
    assert l3.agv_travel == tuple(map(tuple, _data("bu_layouts.json")["layouts"]["3"]))
    assert l3.tool_travel == tuple(map(tuple, raw["tool_transport"]["3"]))
    assert builtin("ra05L2").name == "ra05"
    assert builtin("ra05", layout=2).name == "ra05"
    assert builtin("ra12L4").name == "ra12L4"
    with pytest.raises(InstanceError, match=r"ra01L3 already names layout 3; layout 1 conflicts \(use ra01L1\)"):
        builtin("ra01L3", layout=1)
    with pytest.raises(InstanceError, match="layout"):
        builtin("ra01", layout=5)
    with pytest.raises(InstanceError, match="layouts are 1-4"):
        builtin("ra01L7")


def test_sl00_is_ta01_with_fleet() -> None:
    sl00, ta01 = builtin("sl00"), builtin("ta01")
    times = taillard_times(TaillardRNG(TIME_SEED), 15, 15)
    routes = taillard_routing(TaillardRNG(ROUTE_SEED), 15, 15)
    for inst in (sl00, ta01):
        assert [[o.duration for o in ops] for ops in inst.jobs] == times
        assert [[o.machine for o in ops] for ops in inst.jobs] == routes
    assert ta01.mode == "jobshop" and ta01.n_machines == 15 and ta01.meta["optimal_makespan"] == 1231
    assert sl00.mode == "agvs+tools"
    assert (sl00.n_agvs, sl00.n_tool_transporters) == (10, 5)


@pytest.mark.parametrize("g", range(8))
def test_sl_group_sizes(g: int) -> None:
    n, m, t = SL_GROUPS[g]
    for k in (0, 9):
        inst = builtin(f"sl{g}{k}")
        assert (inst.n_jobs, inst.n_machines, inst.n_tools) == (n, m, t)
        assert inst.n_operations == n * m
        assert (inst.n_agvs, inst.n_tool_transporters) == (10, 5)
        for ops in inst.jobs:
            assert sorted(o.machine for o in ops) == list(range(1, m + 1))
            assert sorted(o.tool for o in ops) == list(range(1, t + 1))  # tools: a permutation per job
            assert all(1 <= o.duration <= 99 for o in ops)


def test_sl_groups_table() -> None:
    assert SL_GROUPS == ((15, 15, 15), (20, 15, 15), (20, 20, 20), (30, 15, 15),
                         (30, 20, 20), (50, 15, 15), (50, 20, 20), (100, 20, 20))


def test_sl01_continues_the_streams() -> None:
    t = TaillardRNG(TIME_SEED)
    r = TaillardRNG(ROUTE_SEED)
    taillard_times(t, 15, 15)
    taillard_routing(r, 15, 15)
    sl01 = builtin("sl01")
    assert sl01.jobs[0][0].duration == t.unif(1, 99)
    assert [o.machine for o in sl01.jobs[0]] == taillard_routing(r, 1, 15)[0]
    # sl03 is the 4th instance of the continued streams.
    t = TaillardRNG(TIME_SEED)
    for _ in range(3):
        taillard_times(t, 15, 15)
    assert [[o.duration for o in ops] for ops in builtin("sl03").jobs] == taillard_times(t, 15, 15)
    # Every group restarts at the seeds: sl10 starts like sl00.
    assert builtin("sl10").jobs[0] == builtin("sl00").jobs[0]


def test_sl_travel_matrices() -> None:
    sl00, sl30, sl20 = builtin("sl00"), builtin("sl30"), builtin("sl20")
    agv = sl00.agv_travel
    assert agv is not None and len(agv) == 16
    assert all(agv[i][i] == 0 for i in range(16))
    assert all(1 <= agv[i][j] <= 30 for i in range(16) for j in range(16) if i != j)
    assert sl30.agv_travel == agv and sl30.tool_travel == sl00.tool_travel
    assert sl00.tool_travel != agv
    assert len(sl20.agv_travel) == 21 and sl20.agv_travel != sl00.agv_travel
    # Row-major U[1,30] from the AGV seed, the diagonal drawn and then zeroed.
    rng = TaillardRNG(AGV_SEED)
    draws = [rng.unif(1, 30) for _ in range(16 * 16)]
    assert [list(row) for row in agv] == [[0 if i == j else draws[16 * i + j] for j in range(16)] for i in range(16)]


def test_builtin_returns_independent_meta() -> None:
    a = builtin("sl00")
    a.meta["touched"] = True
    assert "touched" not in builtin("sl00").meta


@pytest.mark.parametrize(
    "name, match",
    [
        ("EX1", "EX12"),
        ("EX111", "sets are 1-10"),
        ("EX15", "layouts 1-4"),
        ("EX01", "sets are 1-10"),
        ("ra21", "ra01..ra20"),
        ("ra1", "ra01..ra20"),
        ("sl80", "groups are 0-7"),
        ("sl123", "sl00..sl79"),
        ("ta02", "ta01"),
        ("nope", "EX11..EX104"),
    ],
)
def test_unknown_names(name: str, match: str) -> None:
    with pytest.raises(InstanceError, match=match):
        builtin(name)


def test_layout_refused_for_fixed_families() -> None:
    for name in ("sl00", "ta01"):
        with pytest.raises(InstanceError, match="layout applies only to ra"):
            builtin(name, layout=2)


def test_a_numpy_layout_is_taken() -> None:
    import numpy as np

    assert builtin("ra01", layout=np.int64(3)) == builtin("ra01", layout=3)  # (refused, as nowhere else)
