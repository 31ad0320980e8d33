"""The tabu search over a schedule's resource orders (fms_dispatch.tabu): valid, never worse, exact optima on small
shops, every mode (AGVs, AGVs + tools, tools only, plain job shop), reproducible, and its error paths."""

from __future__ import annotations

import time

import pytest

from fms_dispatch.exact import greedy_schedule, simple_lower_bound
from fms_dispatch.tabu import _Graph, _orders, tabu_plan
from fms_sim.benchmarks import BU_OPTIMAL_MAKESPAN, builtin
from fms_sim.full_shop import FullShop
from fms_sim.generate import generate_instances
from fms_sim.validate import validate


def _tool_shop():
    """8 jobs x 5 machines, 4 tools, 2 AGVs and 2 tool transporters."""
    return generate_instances(8, 5, 4, 1, n_agvs=2, n_tool_transporters=2, name_prefix="tabu")[0]


def _shops():
    return [builtin("EX44"), builtin("ra01"), builtin("ra01").without_agvs(), builtin("EX12").without_agvs(),
            _tool_shop()]


def test_the_orders_of_a_plan_give_it_back_or_earlier():
    # the disjunctive graph of a list schedule's orders: no cycle, and its earliest times are never later than the
    # schedule's (every schedule is at least as late as the semi-active one of its orders)
    for inst in _shops():
        for vehicle in ("earliest", "nearest"):
            plan = greedy_schedule(inst, vehicle=vehicle)
            g = _Graph(inst)
            ev = g.evaluate(_orders(g, plan))
            assert ev is not None and ev.makespan <= plan.makespan, inst.name
            planned = {(o.job, o.op): o.start for o in plan.operations}
            assert all(ev.start[i] <= planned[key] for i, key in enumerate(g.key)), inst.name


def test_tabu_search_gives_valid_schedules_never_worse_in_every_mode():
    for inst in _shops():
        plan = greedy_schedule(inst)
        better = tabu_plan(inst, plan, budget=None, max_iters=300, bound=simple_lower_bound(inst))
        assert validate(inst, better) == [], inst.name
        assert better.makespan <= plan.makespan, inst.name
        assert better.makespan >= simple_lower_bound(inst)
        if better is not plan:
            assert better.meta["solver"] == "tabu" and better.meta["improved"] == "greedy"
            assert better.makespan == max(o.end for o in better.operations)


def test_tabu_search_reaches_the_bilge_ulusoy_optima_of_small_instances():
    # from the earliest-start list schedule (EX12: 84, EX11: 132) to the proven optima (82, 96), reproducibly
    for name, (s, lay) in (("EX12", (1, 2)), ("EX11", (1, 1))):
        inst = builtin(name)
        plan = greedy_schedule(inst)
        assert plan.makespan > BU_OPTIMAL_MAKESPAN[s, lay]
        best = tabu_plan(inst, plan, budget=None, max_iters=2000, seed=0)
        assert best.makespan == BU_OPTIMAL_MAKESPAN[s, lay]
        assert validate(inst, best) == []
        again = tabu_plan(inst, plan, budget=None, max_iters=2000, seed=0)
        assert (again.operations, again.agv_trips) == (best.operations, best.agv_trips)


def test_tabu_search_moves_tools_and_transporters():
    # a tools shop: the improved schedule's tool deliveries are its own (the validator checks each tool's path)
    inst = _tool_shop()
    assert inst.has_tools and inst.has_agvs
    plan = greedy_schedule(inst)
    better = tabu_plan(inst, plan, budget=None, max_iters=400)
    assert better.makespan < plan.makespan
    assert validate(inst, better) == []
    assert all(t.loaded == (t.tool is not None) for t in better.tool_trips)


def test_tabu_search_stops_at_its_limits():
    inst = builtin("EX44")
    plan = greedy_schedule(inst)
    assert tabu_plan(inst, plan, budget=0.0) is plan
    assert tabu_plan(inst, plan, budget=None, max_iters=0) is plan
    assert tabu_plan(inst, plan, budget=None, max_iters=50, bound=plan.makespan) is plan  # at the bound already
    seen: list[tuple[int, int, float]] = []
    reported = tabu_plan(inst, plan, budget=None, max_iters=300, progress=lambda *a: seen.append(a))
    assert seen and seen[-1][0] == reported.makespan  # every better schedule, the last one the result
    assert [m for m, _, _ in seen] == sorted((m for m, _, _ in seen), reverse=True)
    stalled = tabu_plan(inst, plan, budget=None, max_iters=10**6, max_stall=20)
    assert stalled.meta["iterations"] < 10**6
    t0 = time.monotonic()
    timed = tabu_plan(inst, plan, budget=0.05)
    assert time.monotonic() - t0 < 1.0 and validate(inst, timed) == [] and timed.makespan <= plan.makespan


def test_tabu_search_refuses_what_it_cannot_do():
    inst = builtin("EX44")
    plan = greedy_schedule(inst)
    with pytest.raises(ValueError, match="budget or an iteration limit"):
        tabu_plan(inst, plan, budget=None)
    with pytest.raises(ValueError, match="budget"):
        tabu_plan(inst, plan, budget=-1.0)
    with pytest.raises(ValueError, match="max_iters"):
        tabu_plan(inst, plan, budget=None, max_iters=-1)
    shop = FullShop(inst)
    for _ in range(6):
        shop.act(shop.legal_actions()[0])
    from fms_sim.snapshot import snapshot

    residual = greedy_schedule(inst, origin=snapshot(shop))
    with pytest.raises(ValueError, match="residual"):
        tabu_plan(inst, residual, budget=0.1)


def test_the_tabu_solver_by_name(capsys):
    from fms_dispatch import solve
    from fms_dispatch.cli import main
    from fms_dispatch.solvers import solver_names

    assert "tabu" in solver_names()
    inst = builtin("EX44")
    s = solve(inst, "tabu", time_limit=0.3)
    assert validate(inst, s) == [] and s.meta["solver"] == "tabu"
    assert s.makespan < min(greedy_schedule(inst, rule=r).makespan for r in ("est", "ect"))
    executed = solve(inst, "plan:tabu:0.3")  # its plan through the full net: never later than the plan
    assert validate(inst, executed) == [] and executed.makespan <= executed.meta["plan_makespan"]
    with pytest.raises(ValueError, match="time_limit"):
        solve(inst, "tabu", time_limit=0)
    assert main(["solve", "ra01", "--solver", "tabu", "--time-limit", "0.2", "-q"]) == 0
    assert "makespan" in capsys.readouterr().out
