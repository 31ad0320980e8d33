"""The tabu search over a schedule's resource orders (fms_dispatch.tabu): valid, never worse, exact optima on small
shops, every mode (AGVs, AGVs + tools, tools only, plain job shop), reproducible, and its error paths."""

from __future__ import annotations

import time

import pytest

import random

from fms_dispatch.exact import greedy_schedule, simple_lower_bound
from fms_dispatch.tabu import _Graph, _orders, residual_lower_bound, solve_tabu, tabu_plan
from fms_sim.benchmarks import BU_OPTIMAL_MAKESPAN, builtin
from fms_sim.disruptions import Breakdown, Scenario
from fms_sim.full_shop import FullShop
from fms_sim.generate import generate_instances
from fms_sim.snapshot import Snapshot, nominal_copy, snapshot
from fms_sim.validate import validate

from ..conftest import finish_by, run_plan_until


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
    # NaN or 1.5 iterations, and max_stall=-1, ran as no limit or a rounded one, silently
    for name, bad in (("max_iters", float("nan")), ("max_iters", 1.5), ("max_stall", -1), ("max_stall", 2.5)):
        with pytest.raises(ValueError, match=f"{name} must be an integer >= 0"):
            tabu_plan(inst, plan, **{"budget": 0.1, name: bad})
    with pytest.raises(ValueError, match="positive, finite number of seconds, got '1'"):  # was a TypeError
        solve_tabu(inst, time_limit="1")
    shop = FullShop(inst)
    for _ in range(6):
        shop.act(shop.legal_actions()[0])
    from fms_sim.snapshot import snapshot

    snap = snapshot(shop)
    residual = greedy_schedule(inst, origin=snap)
    with pytest.raises(ValueError, match="residual"):
        tabu_plan(inst, residual, budget=0.1)
    with pytest.raises(ValueError, match="does not start from the snapshot"):
        tabu_plan(inst, plan, budget=0.1, origin=snap)  # a whole schedule is not a plan from this state
    with pytest.raises(ValueError, match="does not start from the snapshot"):
        tabu_plan(inst, greedy_schedule(inst, origin=Snapshot.initial(inst)), budget=0.1, origin=snap)
    with pytest.raises(ValueError, match="jobs"):
        tabu_plan(builtin("EX11"), residual, budget=0.1, origin=snap)


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


# ---------------------------------------------------------------------------------------------- residual plans
def test_from_the_initial_state_the_residual_search_is_the_whole_one():
    for name in ("EX74", "ra05"):
        inst = builtin(name)
        start = Snapshot.initial(inst)
        whole = tabu_plan(inst, greedy_schedule(inst), budget=None, max_iters=100)
        residual = tabu_plan(inst, greedy_schedule(inst, origin=start), budget=None, max_iters=100, origin=start)
        assert validate(inst, whole) == []
        assert residual.meta["residual"] == 0 and residual.makespan == whole.makespan < greedy_schedule(inst).makespan
        assert (residual.operations, residual.agv_trips, residual.tool_trips) == (
            whole.operations, whole.agv_trips, whole.tool_trips)


@pytest.mark.parametrize("name", ["EX74", "ra05", "ra05/no-agvs", "tools"])
def test_residual_plans_from_running_shops_are_searched_and_run_to_a_valid_end(name):
    # from states of nominal and disrupted runs (parts on their way, tools reserved and carried, machines down):
    # only what has not started is planned, from the state; never later than the list schedule's residual plan
    # nor below the bound; and the shop runs to a valid end by it (a nominal copy, and the disrupted shop itself)
    inst = _tool_shop() if name == "tools" else builtin(name[:4])
    if name.endswith("no-agvs"):
        inst = inst.without_agvs()
    plan = greedy_schedule(inst, rule="ect")
    rng = random.Random(2)
    gains = reserved = 0
    for cut in sorted(rng.sample(range(1, 4 * inst.n_operations), 6)):
        for sc in (None, Scenario(breakdowns=(Breakdown(1, 5, 30),), noise=0.3, seed=cut)):
            shop, st = run_plan_until(inst, plan, cut, sc)
            if st.kind == "done":
                continue
            snap = snapshot(shop)
            reserved += bool(snap.tool_reserved)
            listed = greedy_schedule(inst, origin=snap)
            bound = residual_lower_bound(snap)
            better = tabu_plan(inst, listed, budget=None, max_iters=150, bound=bound, origin=snap)
            assert better.meta["residual"] == snap.now
            assert {(r.job, r.op) for r in better.operations} == {
                (j, k) for j, job in enumerate(inst.jobs) for k in range(snap.next_op[j], len(job))}
            assert all(r.start >= snap.now for r in better.operations)
            assert bound <= better.makespan <= listed.makespan
            assert better.makespan == max([r.end for r in better.operations] + [snap.makespan])
            gains += better.makespan < listed.makespan
            out = finish_by(nominal_copy(shop) if sc is None else shop, better)
            assert validate(inst, out) == [], (name, cut, sc)
    assert gains > 0  # the search improves residual plans
    if inst.has_tools and inst.has_agvs:
        assert reserved > 0  # states with a tool reserved for an operation were searched from


def test_the_residual_lower_bound_holds_what_has_started_and_what_remains():
    inst = builtin("EX74")
    assert residual_lower_bound(Snapshot.initial(inst)) >= max(sum(o.duration for o in job) for job in inst.jobs)
    shop, _ = run_plan_until(inst, greedy_schedule(inst), 20)
    snap = snapshot(shop)
    assert snap.now > 0 and residual_lower_bound(snap) >= snap.makespan
    # every continuation ends at or after it: the list schedule's residual plan, run to its end
    assert finish_by(nominal_copy(shop), greedy_schedule(inst, origin=snap)).makespan >= residual_lower_bound(snap)


def test_another_shops_plan_is_refused():
    """EX12's plan given for EX13 (the same jobs, another layout) came back as EX13's best schedule, infeasible;
    a plan of other jobs failed with a bare KeyError."""
    ex12, ex13, ex22 = builtin("EX12"), builtin("EX13"), builtin("EX22")
    with pytest.raises(ValueError, match="^the plan is not a valid schedule of EX13: "):
        tabu_plan(ex13, greedy_schedule(ex12), budget=0.2)
    with pytest.raises(ValueError, match="^the plan is not a valid schedule of EX12: "):
        tabu_plan(ex12, greedy_schedule(ex22), budget=0.2)


def test_the_tabu_solver_makes_only_the_list_schedules_its_time_limit_allows(monkeypatch):
    # it made all four list schedules before its search whatever the limit: on sl70 a limit of 1 s took 1.9 s
    import fms_dispatch.exact as exact

    made = []
    real = exact.greedy_schedule

    def counted(*args, **kw):
        made.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(exact, "greedy_schedule", counted)
    inst = builtin("sl00")
    s = solve_tabu(inst, time_limit=1e-4)  # less than one list schedule of a 15 x 15 shop
    assert len(made) == 1 and validate(inst, s) == []
    made.clear()
    solve_tabu(builtin("EX11"), time_limit=0.5)  # plenty: all four
    assert len(made) == 4


def test_a_residual_plan_waits_for_a_held_vehicle_to_be_dispatched():
    # found by fuzzing: at the snapshot the transporter stands idle at the magazine after its idle stop, so the
    # executor cannot send it off before its next carry (tool 1 from machine 1 to machine 2, for the job's second
    # operation) is dispatched, once the tool's use on machine 1 has started; the planners sent it off at once, and
    # the executed plan ended a time unit later than every residual plan (list schedules and tabu) predicted
    from fms_dispatch.exact import restart_list_plan
    from fms_dispatch.replan import simulate
    from fms_sim.full_shop import FullShop
    from fms_sim.instance import Instance, Operation
    from fms_sim.snapshot import nominal_copy, snapshot
    from fms_sim.stepping import Stepper

    inst = Instance(name="held", jobs=((Operation(1, 1, 1), Operation(2, 1, 1)),),
                    agv_travel=((0, 2, 3), (1, 0, 3), (4, 4, 0)), tool_travel=((0, 2, 0), (0, 0, 4), (4, 2, 0)),
                    n_agvs=1, n_tool_transporters=1)
    shop = FullShop(inst)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    for label in ("wait", "tool:1", "use:0", "tt:0", "hold", "reposition:tt:0:0", "reposition:tt:0:0", "wait"):
        st.apply(label)
    snap = snapshot(shop)
    assert st.kind == "decision" and shop.idle_transporters() == [(0, 0)]  # the state the test is about
    listed = [greedy_schedule(inst, rule=r, origin=snap) for r in ("est", "ect")]
    plans = listed + [restart_list_plan(inst, listed[0], tries=4, origin=snap),
                      tabu_plan(inst, listed[0], budget=None, max_iters=30, origin=snap)]
    for plan in plans:
        assert simulate(nominal_copy(shop), plan) == plan.makespan, plan.meta
        # the carry's empty leg leaves when the tool's use on machine 1 starts, not at the snapshot
        first = next(t for t in plan.tool_trips if t.transporter == 0)
        assert not first.loaded and first.start == next(r.start for r in plan.operations if r.op == 0) > snap.now
    assert snap.held == {("tt", 0), ("agv", 0)}  # both vehicles stand idle and have had their idle stop
