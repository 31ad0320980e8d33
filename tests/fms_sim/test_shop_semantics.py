"""Each semantic rule of the shop net, on a hand-built instance whose schedule is checked to the time unit."""

import pytest

from fms_sim import AgvTrip, Instance, ToolTrip, validate
from fms_sim.instance import InstanceError
from fms_sim.petri import InvalidAction
from fms_sim.shop import Shop

from .conftest import run_first


def ops(s):
    return {(o.job, o.op): (o.machine, o.start, o.end) for o in s.operations}


def test_plain_job_shop_non_delay_dispatch():
    # J0: M1(3) M2(2); J1: M2(4) M1(1). Both start at 0; at 4 M2 frees: J0 -> M2 [4,6], J1 -> M1 [4,5].
    inst = Instance("js", [[(1, 3), (2, 2)], [(2, 4), (1, 1)]])
    s = run_first(inst)
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (1, 0, 3), (1, 0): (2, 0, 4), (0, 1): (2, 4, 6), (1, 1): (1, 4, 5)}
    assert s.makespan == 6 and s.agv_trips == [] and s.tool_trips == []


def test_job_selectable_only_when_machine_free_without_agvs():
    inst = Instance("js", [[(1, 3)], [(1, 2)]])
    shop = Shop(inst)
    assert shop.legal_actions() == [0, 1]
    shop.act(1)                              # J1 takes M1 at 0
    assert shop.now == 2 and shop.legal_actions() == [0]   # J0 waits until M1 frees
    shop.act(0)
    s = shop.schedule()
    assert ops(s) == {(1, 0): (1, 0, 2), (0, 0): (1, 2, 5)} and validate(inst, s) == []


T3 = [[0, 2, 6], [5, 0, 3], [4, 7, 0]]     # asymmetric: T[from][to]


def test_agv_loaded_trips_and_deadheading():
    # J0: M1(4); J1: M2(1); one AGV at L/U.
    # t=0 J0: AGV 0->1 loaded [0,2], op [2,6]. AGV idle at M1 from 2.
    # t=2 J1: AGV empty 1->0 [2,7] (T[1][0]=5), loaded 0->2 [7,13] (T[0][2]=6), op [13,14].
    inst = Instance("agv", [[(1, 4)], [(2, 1)]], agv_travel=T3, n_agvs=1)
    s = run_first(inst)
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (1, 2, 6), (1, 0): (2, 13, 14)}
    assert sorted(s.agv_trips, key=lambda t: t.start) == [
        AgvTrip(0, 0, 0, 0, 1, 0, 2, True),
        AgvTrip(0, None, None, 1, 0, 2, 7, False),
        AgvTrip(0, 1, 0, 0, 2, 7, 13, True),
    ]
    assert s.makespan == 14


def test_part_travels_from_previous_machine_after_it_ends():
    # J0: M2(5) then M1(3): loaded 0->2 [0,6], op [6,11]; AGV waits at M2; loaded 2->1 [11,18], op [18,21].
    inst = Instance("agv", [[(2, 5), (1, 3)]], agv_travel=T3, n_agvs=1)
    s = run_first(inst)
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (2, 6, 11), (0, 1): (1, 18, 21)}
    assert [(t.from_, t.to, t.start, t.end, t.loaded) for t in s.agv_trips] == [(0, 2, 0, 6, True), (2, 1, 11, 18, True)]


def test_two_agvs_choice_and_machine_one_at_a_time():
    # Both jobs on M1 (dur 4 and 2); two AGVs. t=0: J0 with AGV0 (0->1 [0,2]); J1 with AGV1 (0->1 [0,2]).
    # Both arrive at 2; M1 takes the earlier dispatch (J0) [2,6], then J1 [6,8].
    inst = Instance("agv2", [[(1, 4)], [(1, 2)]], agv_travel=T3, n_agvs=2)
    shop = Shop(inst)
    assert shop.decision_kind() == "job"
    shop.act(shop.action_index("job:0"))
    assert shop.decision_kind() == "agv" and shop.legal_actions() == [2, 3]
    shop.act(shop.action_index("agv:0"))
    shop.act(shop.action_index("job:1"))
    shop.act(shop.action_index("agv:1"))
    s = shop.schedule()
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (1, 2, 6), (1, 0): (1, 6, 8)}
    assert {t.agv for t in s.agv_trips} == {0, 1}


def test_no_job_selectable_while_all_agvs_busy():
    inst = Instance("agv", [[(1, 4)], [(2, 1)]], agv_travel=T3, n_agvs=1)
    shop = Shop(inst)
    shop.act(0)
    shop.act(shop.action_index("agv:0"))
    assert shop.now == 2                    # time jumped to the AGV's arrival
    assert shop.legal_actions() == [1]


TT3 = [[0, 1, 2], [1, 0, 4], [2, 3, 0]]


def test_tool_moves_between_machines_with_transporter():
    # No AGVs. J0: M1 tool1 (3); J1: M2 tool1 (2); one transporter.
    # t=0 J0 dispatched; tool 1 in magazine -> transporter 0->1 loaded [0,1]; op (0,0) [1,4].
    # J1 dispatched at 0 (M2 idle) but tool 1 is busy; at 4 the transporter (at M1) carries it 1->2 [4,8];
    # op (1,0) [8,10].
    inst = Instance("tools", [[(1, 1, 3)], [(2, 1, 2)]], tool_travel=TT3, n_tool_transporters=1)
    s = run_first(inst)
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (1, 1, 4), (1, 0): (2, 8, 10)}
    assert sorted(s.tool_trips, key=lambda t: t.start) == [
        ToolTrip(0, 1, 0, 0, 0, 1, 0, 1, True), ToolTrip(0, 1, 1, 0, 1, 2, 4, 8, True)]
    assert s.makespan == 10


def test_tool_already_at_machine_needs_no_trip():
    inst = Instance("tools", [[(1, 1, 3)], [(1, 1, 2)]], tool_travel=TT3, n_tool_transporters=1)
    s = run_first(inst)
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (1, 1, 4), (1, 0): (1, 4, 6)}
    assert len(s.tool_trips) == 1


def test_transporter_deadheads_to_the_tool():
    # tools 1 and 2; J0: M1 tool1 (3); J1: M2 tool2 (1). Transporter: 0->1 with tool1 [0,1];
    # then tool 2 is in the magazine: empty 1->0 [1,2], loaded 0->2 [2,4]; op (1,0) [4,5].
    inst = Instance("tools", [[(1, 1, 3)], [(2, 2, 1)]], tool_travel=TT3, n_tool_transporters=1)
    s = run_first(inst)
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (1, 1, 4), (1, 0): (2, 4, 5)}
    assert ToolTrip(0, None, None, None, 1, 0, 1, 2, False) in s.tool_trips


def test_agvs_and_tools_op_waits_for_both():
    # J0: M1 tool1 (3). AGV 0->1 takes 2, transporter 0->1 takes 5: op starts at max(2,5)=5.
    T = [[0, 2], [2, 0]]
    TT = [[0, 5], [5, 0]]
    inst = Instance("both", [[(1, 1, 3)]], agv_travel=T, tool_travel=TT, n_agvs=1, n_tool_transporters=1)
    shop = Shop(inst)
    shop.act(0)
    assert shop.decision_kind() == "agv|tt"
    shop.act(shop.action_index("agv:0"))
    shop.act(shop.action_index("tt:0"))
    s = shop.schedule()
    assert validate(inst, s) == []
    assert ops(s) == {(0, 0): (1, 5, 8)} and s.makespan == 8


def test_invalid_actions_raise_and_leave_state_unchanged():
    inst = Instance("agv", [[(1, 4)], [(2, 1)]], agv_travel=T3, n_agvs=1)
    shop = Shop(inst)
    with pytest.raises(InvalidAction):
        shop.act(shop.action_index("agv:0"))   # no job selected yet
    assert shop.legal_actions() == [0, 1] and shop.now == 0
    with pytest.raises(InvalidAction):
        shop.action_index("robot:1")
    with pytest.raises(InvalidAction):
        shop.action_index("agv:5")


def test_twin_copy_is_independent():
    inst = Instance("agv", [[(1, 4), (2, 2)], [(2, 1)]], agv_travel=T3, n_agvs=1)
    shop = Shop(inst)
    shop.act(0)
    twin = shop.copy()
    while not twin.done:
        twin.act(twin.legal_actions()[0])
    assert not shop.done and shop.decision_kind() == "agv"
    while not shop.done:
        shop.act(shop.legal_actions()[0])
    assert validate(inst, shop.schedule()) == [] and shop.schedule().makespan == twin.schedule().makespan


@pytest.mark.parametrize("mode", ["jobshop", "tools", "agvs+tools"])
def test_twin_reads_its_own_state_in_every_mode(mode):
    T = [[0, 2, 3], [2, 0, 2], [3, 2, 0]]
    jobs = [[(1, 1, 3), (2, 2, 2)], [(2, 1, 2), (1, 2, 1)], [(1, 2, 2)]]
    kw = {"tool_travel": T, "n_tool_transporters": 1} if mode != "jobshop" else {}
    if mode == "agvs+tools":
        kw.update(agv_travel=T, n_agvs=1)
    if mode == "jobshop":
        jobs = [[(m, d) for m, _, d in ops] for ops in jobs]
    inst = Instance("twin", jobs, **kw)
    shop = Shop(inst)
    shop.act(shop.legal_actions()[-1])
    twin = shop.copy()
    for s in (twin, shop):
        while not s.done:
            s.act(s.legal_actions()[-1])
    a, b = shop.schedule(), twin.schedule()
    assert validate(inst, a) == [] and validate(inst, b) == []
    assert a.to_dict() == b.to_dict()


def test_reposition_sends_idle_agv_empty_and_keeps_it_busy():
    # J0: M1(4); J1: M2(1). t=0 J0 with AGV (0->1 [0,2]). At t=2 the AGV is idle at M1; pre-position it to
    # L/U: empty 1->0 [2,7]. At 7 J1 is selectable: loaded 0->2 [7,13], op [13,14].
    inst = Instance("agv", [[(1, 4)], [(2, 1)]], agv_travel=T3, n_agvs=1)
    shop = Shop(inst)
    shop.act(0)
    shop.act(shop.action_index("agv:0"))
    assert shop.now == 2 and shop.legal_actions() == [1]
    with pytest.raises(InvalidAction, match="location 9"):
        shop.reposition_agv(0, 9)
    shop.reposition_agv(0, 0)
    assert shop.now == 7 and shop.legal_actions() == [1]
    with pytest.raises(InvalidAction, match="does not exist"):
        shop.reposition_transporter(0, 1)
    shop.act(1)
    shop.act(shop.action_index("agv:0"))   # the last operation: the run completes
    with pytest.raises(InvalidAction, match="complete"):
        shop.reposition_agv(0, 1)
    s = shop.schedule()
    assert validate(inst, s) == []
    assert ops(s)[(1, 0)] == (2, 13, 14)
    assert AgvTrip(0, None, None, 1, 0, 2, 7, False) in s.agv_trips
    assert AgvTrip(0, 1, 0, 0, 2, 7, 13, True) in s.agv_trips


def test_reposition_transporter_to_tool():
    TT = [[0, 1, 2], [1, 0, 4], [2, 3, 0]]
    inst = Instance("tools", [[(1, 1, 3)], [(2, 2, 1)]], tool_travel=TT, n_tool_transporters=1)
    shop = Shop(inst)
    shop.act(0)                       # J0 dispatched, tool 1 must come from the magazine
    shop.act(shop.action_index("tt:0"))
    # t=0, J1 is selectable; transporter busy until 1
    with pytest.raises(InvalidAction, match="not idle"):
        shop.reposition_transporter(0, 2)
    while not shop.done:
        shop.act(shop.legal_actions()[0])
    assert validate(inst, shop.schedule()) == []


def test_add_jobs_mid_run_joins_the_net():
    from fms_sim import Operation
    from fms_sim.benchmarks import builtin

    inst = builtin("ra01")
    shop = Shop(inst)
    for _ in range(10):
        shop.act(shop.legal_actions()[0])
    t_order = shop.now
    ids = shop.add_jobs([[Operation(2, 1, 5), Operation(4, 3, 7)], [Operation(1, None, 3)]])
    assert ids == [inst.n_jobs, inst.n_jobs + 1] and shop.n_jobs == inst.n_jobs + 2
    assert "job:5" in shop.action_labels()
    with pytest.raises(InstanceError, match="machine 9 does not exist"):
        shop.add_jobs([[Operation(9, None, 1)]])
    with pytest.raises(InstanceError, match="tool 7 does not exist"):
        shop.add_jobs([[Operation(1, 7, 1)]])
    while not shop.done:
        shop.act(shop.legal_actions()[-1])
    s = shop.schedule()
    assert validate(shop.instance, s) == []
    first_new = min(o.start for o in s.operations if o.job in ids)
    assert first_new >= t_order
    loaded = [t for t in s.agv_trips if t.loaded and t.job in ids and t.op == 0]
    assert len(loaded) == 2 and min(t.start for t in loaded) >= t_order
    with pytest.raises(InvalidAction, match="complete"):
        shop.add_jobs([[Operation(1, None, 1)]])


@pytest.mark.parametrize("name", ["EX12", "ra01", "ta01"])
def test_incremental_engine_matches_naive_reevaluation(name):
    """Dirty tracking is an optimisation only: the naive engine makes the same decisions and schedule."""
    import random

    from fms_sim.benchmarks import builtin

    inst = builtin(name)
    shops = [Shop(inst), Shop(inst, incremental=False)]
    rng = random.Random(7)
    while not shops[0].done:
        legal = [s.legal_actions() for s in shops]
        assert legal[0] == legal[1] and shops[0].now == shops[1].now
        a = rng.choice(legal[0])
        for s in shops:
            s.act(a)
    assert shops[1].done
    assert shops[0].schedule().to_dict() == shops[1].schedule().to_dict()
    assert validate(inst, shops[0].schedule()) == []


@pytest.mark.parametrize("decisions", ["paper", "full"])
def test_arguments_that_name_no_action_or_vehicle_are_invalid_actions(decisions):
    # reposition("bus", ...) sent a tool transporter on the paper net (KeyError on the full net); a float vehicle was
    # accepted and broke the run later; act(1.0) and act("0") were TypeErrors from list indexing; action_kind(-1)
    # answered through negative indexing, and action_kind(10**6) as a tool transporter
    import numpy as np

    from fms_sim import builtin, make_shop

    shop = make_shop(builtin("ra01"), decisions)
    n = len(shop.action_mask())
    for call, msg in [(lambda: shop.reposition("bus", 0, 3), "unknown vehicle kind 'bus' \\(agv or tt\\)"),
                      (lambda: shop.reposition("agv", 0.0, 3), "the AGV number must be an integer, got 0.0"),
                      (lambda: shop.reposition("tt", 0, 1.5), "the location must be an integer, got 1.5"),
                      (lambda: shop.reposition("agv", None, 1), "the AGV number must be an integer, got None"),
                      (lambda: shop.act(1.0), "action must be an integer, got 1.0"),
                      (lambda: shop.act("0"), "action must be an integer, got '0'"),
                      (lambda: shop.act(True), "action must be an integer, got True"),  # ran action 1
                      (lambda: shop.fire_action(None), "action must be an integer, got None"),
                      (lambda: shop.action_kind(-1), "action -1 is out of range"),
                      (lambda: shop.action_kind(n + 5), f"action {n + 5} is out of range"),
                      (lambda: shop.action_index(None), "action label None"),
                      (lambda: shop.action_index("job: 1"), "action label 'job: 1'")]:
        with pytest.raises(InvalidAction, match=msg):
            call()
    inst = builtin("ra01")  # nothing moved
    assert shop.now == 0 and len(shop.idle_agvs()) == inst.n_agvs
    assert len(shop.idle_transporters()) == inst.n_tool_transporters
    shop.reposition("agv", np.int64(0), np.int64(3))  # numpy integers are integers
    while not shop.done:
        shop.act(np.int64(shop.legal_actions()[0]))
    assert validate(builtin("ra01"), shop.schedule()) == []
    assert shop.schedule().agv_trips[0].to == 3 and type(shop.schedule().agv_trips[0].to) is int
