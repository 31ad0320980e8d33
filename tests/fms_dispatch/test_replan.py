"""Re-planning from the shop's state: triggers, budget, events, and valid realised schedules."""

import time
from dataclasses import replace

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.disruptions import Breakdown, Scenario
from fms_sim.full_shop import FullShop
from fms_sim.instance import Operation
from fms_sim.schedule import Schedule
from fms_sim.snapshot import nominal_copy, snapshot
from fms_sim.stepping import Stepper
from fms_sim.validate import validate
from fms_dispatch.exact import greedy_schedule
from fms_dispatch.full_rules import parse_full_rule
from fms_dispatch.replan import REPLAN_REASONS, Replanner, replan, solve_with_replanning
from fms_dispatch.solvers import solve

from ..conftest import finish_by, run_plan_until

EVENT_KEYS = {"reason", "time", "budget", "wall_time", "status", "before", "after"}


def _check_events(events):
    for e in events:
        assert EVENT_KEYS <= set(e) and e["reason"] in REPLAN_REASONS
        assert e["status"] in ("adopted", "kept", "failed")
        if e["status"] == "kept":
            assert e["after"] >= e["before"]  # a new plan replaces the current one only when predicted better
        if e["status"] == "adopted" and e["reason"] not in ("order", "stuck"):
            assert e["after"] < e["before"]


@pytest.mark.parametrize("name", ["EX74", "ra05", "sl00"])
def test_replanning_under_breakdowns_and_noise_gives_valid_schedules(name):
    inst = builtin(name)
    plan = greedy_schedule(inst)
    sc = Scenario.draw(inst, noise=0.2, breakdowns=3, horizon=plan.makespan, seed=5)
    out = solve_with_replanning(inst, plan, budget=0.3, scenario=sc)
    assert validate(inst, out) == []  # against the realised times and the down windows in meta["scenario"]
    events = out.meta["replans"]
    assert any(e["reason"] == "breakdown" for e in events)
    _check_events(events)


def test_a_breakdown_replan_beats_keeping_the_plan_on_sl00():
    inst = builtin("sl00")
    plan = greedy_schedule(inst)
    sc = Scenario(breakdowns=(Breakdown(3, plan.makespan // 5, plan.makespan // 6),))
    kept = solve(inst, "plan:list", scenario=sc)
    out = solve_with_replanning(inst, plan, budget=1.0, scenario=sc)
    assert validate(inst, out) == []
    (e,) = out.meta["replans"]
    assert e["reason"] == "breakdown" and e["status"] == "adopted" and e["after"] < e["before"]
    # without noise the prediction is the realised run of the adopted plan, and beats the kept plan
    assert out.makespan == e["after"] < kept.makespan


def test_an_order_mid_run_triggers_a_replan_that_covers_the_new_jobs():
    inst = builtin("ra05")
    plan = greedy_schedule(inst)
    shop = FullShop(inst)
    rp = Replanner(inst, plan, budget=0.3)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    fallback = parse_full_rule("rule:MTWR+nearest+fifo")
    new = [[Operation(2, 1, 7), Operation(4, None, 5)], [Operation(1, 2, 6)]]
    n = 0
    while st.kind != "done":
        if n == 40:
            st.add_jobs(new)
        label = rp.step(st, fallback)
        rp.apply(st, label)
        st.apply(label)
        n += 1
    out = shop.schedule()
    assert validate(shop.instance, out) == [] and shop.instance.n_jobs == inst.n_jobs + 2
    orders = [e for e in rp.events if e["reason"] == "order"]
    assert len(orders) == 1 and orders[0]["status"] == "adopted" and orders[0]["before"] is None
    assert {r.job for r in out.operations} >= {inst.n_jobs, inst.n_jobs + 1}
    _check_events(rp.events)


def test_a_replan_keeps_its_budget():
    inst = builtin("sl30")
    plan = greedy_schedule(inst)
    shop = FullShop(inst)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    from fms_sim.replay import PlanPolicy

    pol = PlanPolicy(inst, plan)
    for _ in range(300):
        label = pol.answer(st)
        pol.apply(st, label)
        st.apply(label)
    while not Replanner.can_snapshot(shop):
        label = pol.answer(st)
        pol.apply(st, label)
        st.apply(label)
    for budget in (0.2, 1.0):  # (sl70, the issue's case, is measured by bench/replan.py)
        t0 = time.monotonic()
        res = replan(snapshot(shop), plan, budget, sim=nominal_copy(shop))
        wall = time.monotonic() - t0
        assert wall <= budget + 1.0, wall
        assert res.before is not None and res.after > 0 and res.wall_time <= wall
        done = finish_by(nominal_copy(shop), res.plan)  # the plan it returns runs to a valid end, as predicted
        assert validate(inst, done) == [] and done.makespan == res.after


def test_bad_replanning_options_are_refused():
    inst = builtin("EX12")
    plan = greedy_schedule(inst)
    with pytest.raises(ValueError, match="budget"):
        Replanner(inst, plan, budget=0)
    with pytest.raises(ValueError, match="drift"):
        Replanner(inst, plan, drift=-1)
    with pytest.raises(ValueError, match="tabu"):
        Replanner(inst, plan, tabu=-0.001)
    # an infinite budget ran a search with no deadline (it never ended); a plan that is not valid was followed as far
    # as it went, then silently replaced by a re-plan from scratch
    for kw in ({"budget": float("inf")}, {"budget": float("nan")}, {"drift": float("inf")}, {"tabu": float("inf")},
               {"budget": "2"}):
        with pytest.raises(ValueError, match="must be .* and finite, got"):
            Replanner(inst, plan, **kw)
        with pytest.raises(ValueError, match="must be .* and finite, got"):
            solve_with_replanning(inst, plan, **kw)
    with pytest.raises(ValueError, match="the plan is not valid for EX12: "):
        solve_with_replanning(inst, replace(plan, operations=plan.operations[3:]), budget=0.5)
    with pytest.raises(ValueError, match="the plan is not valid for EX12: "):
        Replanner(inst, Schedule("EX12", 0), budget=0.5)
    with pytest.raises(TypeError, match="the plan must be a Schedule"):
        Replanner(inst, plan.to_dict())
    import numpy as np

    Replanner(inst, plan, budget=np.int64(2), drift=np.float32(0.1), tabu=np.float64(0))  # numpy numbers are numbers
    with pytest.raises(ValueError, match="budget"):
        solve(inst, "plan:list", replan=-1.0)


def test_the_plan_solvers_take_the_replan_option():
    inst = builtin("EX74")
    sc = Scenario(breakdowns=(Breakdown(2, 30, 25),), noise=0.1, seed=3)
    out = solve(inst, "plan:list", scenario=sc, replan=0.3)
    assert validate(inst, out) == [] and out.meta["solver"] == "plan:list"
    assert [e["reason"] for e in out.meta["replans"]][:1] == ["breakdown"]
    plain = solve(inst, "plan:list", scenario=sc)
    assert "replans" not in plain.meta


def test_a_plan_computed_while_the_shop_moved_on_is_retimed_and_runs_to_a_valid_end():
    inst = builtin("sl00")
    plan = greedy_schedule(inst, rule="ect")
    sc = Scenario(breakdowns=(Breakdown(4, 300, 200),))
    shop = FullShop(inst, scenario=sc)
    rp = Replanner(inst, plan, budget=0.3)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    fallback = parse_full_rule("rule:MTWR+nearest+fifo")
    taken = result = None
    n = 0
    while st.kind != "done":
        if taken is None and shop.now >= 300 and rp.can_snapshot(shop):
            taken = rp.take(shop)  # as the agent does: the plan is computed while the run goes on
            result = rp.compute(*taken)
        elif taken is not None and result is not None and n % 50 == 0 and rp.can_snapshot(shop):
            assert rp.moved_on(shop)
            event = rp.adopt(shop, result, "breakdown")
            result = None
            assert event["status"] == "adopted" and event["after"] < event["before"]  # (this case: adopted)
            assert event["retimed"] and rp.plan.meta["retimed"] == shop.now
        label = rp.step(st, fallback)
        rp.apply(st, label)
        st.apply(label)
        n += 1
    assert taken is not None and result is None and validate(inst, shop.schedule()) == []
    assert not any(e["reason"] == "stuck" for e in rp.events)


@pytest.mark.parametrize("name", ["EX74", "sl00"])
def test_rule_continuations_are_weighed_as_plans(name):
    import copy

    from fms_dispatch.replan import _rule_plan, simulate

    inst = builtin(name)
    plan = greedy_schedule(inst)
    sc = Scenario(breakdowns=(Breakdown(2, plan.makespan // 5, plan.makespan // 4),), noise=0.1, seed=2)
    shop = FullShop(inst, scenario=sc)
    stepper = Stepper(shop, idle_stops=True)
    rp = Replanner(inst, plan, budget=2.0)
    stepper.advance()
    while shop.now < plan.makespan // 3:  # past the breakdown's start, by the plan
        label = rp.answer(stepper)
        rp.apply(stepper, label)
        stepper.apply(label)
    names = ["rule:LPSR+nearest+fifo", "rule:MTWR+nearest+fifo"]
    sim = nominal_copy(shop)
    made = {n: _rule_plan(copy.deepcopy(sim), parse_full_rule(n)) for n in names}
    executed = {n: simulate(copy.deepcopy(sim), s) for n, s in made.items()}
    assert all(executed.values())  # a rule's continuation is a plan the shop can follow from here
    res = replan(snapshot(shop), plan, 2.0, sim=copy.deepcopy(sim), rules=[(n, parse_full_rule(n)) for n in names])
    assert res.after <= min(executed.values())
    assert simulate(copy.deepcopy(sim), res.plan) == res.after  # the prediction is the plan's nominal run
    out = solve_with_replanning(inst, plan, budget=0.5, scenario=sc, rules=names)
    assert validate(inst, out) == []
    _check_events(out.meta["replans"])


def test_unknown_replanning_rules_are_refused():
    inst = builtin("EX12")
    with pytest.raises(ValueError):
        Replanner(inst, greedy_schedule(inst), rules=("rule:NOPE",))


def test_a_replan_searches_its_best_plan_further_with_the_tabu_search():
    # on EX74 the list schedules and restarts from a mid-run state leave room that the tabu search over the residual
    # plan's orders takes (159 kept, about 135-140 after); the plan it makes runs from the state to a valid end
    from fms_dispatch.tabu import residual_lower_bound

    inst = builtin("EX74")
    plan = greedy_schedule(inst)
    shop, st = run_plan_until(inst, plan, inst.n_operations)
    assert st.kind != "done"
    snap = snapshot(shop)
    res = replan(snap, plan, 1.0)
    listed = min(greedy_schedule(inst, rule=r, origin=snap).makespan for r in ("est", "ect"))
    assert res.method == "tabu" == res.plan.meta["method"]
    assert residual_lower_bound(snap) <= res.after < listed and res.after < res.before
    assert replan(snap, plan, 0.3, tabu=0.0).method != "tabu"  # tabu=0: the list search alone
    assert validate(inst, finish_by(nominal_copy(shop), res.plan)) == []


def test_a_kept_plan_is_not_re_planned_again_for_the_same_lateness():
    # a plan kept after a "late" re-plan kept its old start times, so every later start was late again: one
    # re-plan (each spending its whole budget) per operation start, 9 on ra01 here
    inst = builtin("ra01")
    s = solve(inst, "plan:list", replan=0.1, scenario=Scenario(noise=0.4, seed=1))
    assert validate(inst, s) == []
    late = [e for e in s.meta["replans"] if e["reason"] == "late"]
    assert 1 <= len(late) <= 3, late


def _est_run(name, budget):
    """A replanner over ``name``'s earliest-start plan and the stepper of its run, at the first stop."""
    inst = builtin(name)
    rp = Replanner(inst, greedy_schedule(inst, rule="est"), budget=budget)
    st = Stepper(FullShop(inst), idle_stops=True)
    st.advance()
    return rp, st


def _follow(rp, st, n):
    """``n`` answers of ``rp``'s plan in force, then on to a stop where a snapshot can be taken (or the end)."""
    k = 0
    while st.kind != "done" and (k < n or not rp.can_snapshot(st.shop)):
        label = rp.answer(st)
        rp.apply(st, label)
        st.apply(label)
        k += 1


def _live_order(name, at, moved):
    """A run of ``name``'s earliest-start plan to ``at`` answers, where an order of two 3-operation jobs arrives;
    its re-plan (here: the earliest-start list schedule from that state, deterministic) is then computed while the
    run goes on by ``moved`` answers of the old plan (the new jobs wait), as the agent node's threaded re-plan
    does. Returns the replanner, the stepper and the new plan as a re-plan's result."""
    from fms_dispatch.replan import ReplanResult

    rp, st = _est_run(name, 0.3)
    shop = st.shop
    _follow(rp, st, at)
    st.add_jobs([[Operation(m, 1, 50) for m in (1, 2, 3)] for _ in range(2)])
    _follow(rp, st, 0)
    assert rp.trigger(shop) == "order"
    rp.take(shop)
    new = greedy_schedule(shop.instance, rule="est", origin=snapshot(shop))
    _follow(rp, st, moved)
    assert rp.moved_on(shop) == (moved > 0)
    return rp, st, ReplanResult(new, None, new.makespan, "est", 0.0, shop.n_jobs)


def test_a_retimed_plan_is_the_better_of_its_order_and_a_list_schedule_from_the_state():
    # the plan's start times guided the re-timing alone: 800 states after a live order on sl70 an 8000 plan was
    # re-timed to 9447 (realised 9219-10368 in bench/replan.py), where a list schedule from the state made 7894
    rp, st, result = _live_order("sl00", 100, 150)
    shop = st.shop
    snap = snapshot(shop)
    starts = {(r.job, r.op): r.start for r in result.plan.operations}
    last = max(starts.values()) + 1
    prio = {(j, k): starts.get((j, k), last + k) for j, job in enumerate(shop.instance.jobs)
            for k in range(snap.next_op[j], len(job))}
    guided = greedy_schedule(shop.instance, rule="guided", priority=prio, origin=snap).makespan
    est = greedy_schedule(shop.instance, rule="est", origin=snap).makespan
    assert est < guided  # this case: the state has left the plan's order behind
    event = rp.adopt(shop, result, "order")
    assert event["status"] == "adopted" and event["retimed"]
    assert rp.plan.meta["retime"] == "est" and rp.plan.makespan == est and rp.plan.meta["retimed"] == shop.now
    assert finish_by(shop, rp.plan).makespan <= est and validate(shop.instance, shop.schedule()) == []


def test_an_order_that_arrives_while_a_re_plan_runs_gets_its_own_re_plan():
    # the re-plan, made before the order, was re-timed from the state with the order's jobs fitted in by the list
    # schedule, and that was all: the order was never re-planned with the search
    from fms_dispatch.replan import ReplanResult

    rp, st = _est_run("sl00", 0.2)
    shop, inst = st.shop, rp.instance
    _follow(rp, st, 100)
    rp.take(shop)  # a re-plan (here: a list schedule of the state) starts, the run goes on
    made = greedy_schedule(inst, rule="ect", origin=snapshot(shop))
    result = ReplanResult(made, made.makespan + 1, made.makespan, "ect", 0.0, inst.n_jobs)
    st.add_jobs([[Operation(m, 1, 50) for m in (1, 2, 3)]])
    _follow(rp, st, 50)
    event = rp.adopt(shop, result, "late")
    assert event["status"] == "adopted" and event["retimed"]
    assert rp.trigger(shop) == "order"
    order = rp.replan_now(shop, "order")
    assert order["reason"] == "order" and order["status"] in ("adopted", "kept")
    assert {r.job for r in rp.plan.operations} >= {inst.n_jobs}
    assert finish_by(shop, rp.plan).makespan <= rp.plan.makespan and validate(shop.instance, shop.schedule()) == []


@pytest.mark.parametrize("outcome", ["adopted", "kept", "timeout"])
def test_a_disruption_begun_while_a_re_plan_runs_gets_its_own_re_plan(outcome):
    # a re-plan computed beside the run answers the state it started from; when it was collected, the state at the
    # end was taken as seen, so a breakdown begun meanwhile never triggered a re-plan (an AGV outage's re-plan ran, a
    # breakdown began during it, and the run went on with a plan that knew nothing of it)
    from fms_dispatch.replan import ReplanResult

    rp, st = _est_run("sl00", 0.2)
    shop, inst = st.shop, rp.instance
    _follow(rp, st, 100)
    assert rp.trigger(shop) is None
    rp.take(shop)  # a re-plan starts, the run goes on
    made = greedy_schedule(inst, rule="ect", origin=snapshot(shop))
    before = made.makespan + 1 if outcome == "adopted" else made.makespan
    result = ReplanResult(made, before, made.makespan, "ect", 0.0, inst.n_jobs)
    shop.add_disruption(Breakdown(3, shop.now, 60))
    _follow(rp, st, 20)
    assert shop.m_down[3]
    if outcome == "timeout":
        rp.dropped(shop)
    else:
        assert rp.adopt(shop, result, "late")["status"] == outcome
    assert rp.trigger(shop) == "breakdown"
    event = rp.replan_now(shop, "breakdown")
    assert event["reason"] == "breakdown" and rp.trigger(shop) is None  # once: answered by its own re-plan
    # the plan in force ends as promised: the new one (adopted), or the old one continued from the state (kept: the
    # search, bound by its budget, found nothing better on a loaded machine)
    promised = rp.plan.makespan if event["status"] == "adopted" else event["before"]
    assert event["status"] in ("adopted", "kept") and finish_by(shop, rp.plan).makespan <= promised
    assert validate(shop.instance, shop.schedule(), shop.scenario) == []


@pytest.mark.parametrize("outcome", ["failed", "timeout"])
def test_an_order_that_arrives_while_a_re_plan_brings_no_plan_gets_its_own_re_plan(outcome):
    # the failed or timed-out re-plan took the state at its end as seen: the order's trigger was used up, and its jobs
    # waited until the plan got stuck
    rp, st = _est_run("sl00", 0.2)
    shop, inst = st.shop, rp.instance
    _follow(rp, st, 100)
    rp.take(shop)
    st.add_jobs([[Operation(m, 1, 50) for m in (1, 2, 3)]])
    _follow(rp, st, 30)
    if outcome == "timeout":
        rp.dropped(shop)
    else:
        assert rp.adopt(shop, None, "late", error="no plan here")["status"] == "failed"
    assert rp.trigger(shop) == "order"
    event = rp.replan_now(shop, "order")
    assert event["status"] == "adopted" and rp.trigger(shop) is None  # once
    assert {r.job for r in rp.plan.operations} >= {inst.n_jobs}
    assert finish_by(shop, rp.plan).makespan <= rp.plan.makespan and validate(shop.instance, shop.schedule()) == []


def test_simulations_are_skipped_where_they_would_take_most_of_the_budget(monkeypatch):
    # a run through the net costs 9-25 list schedules (bench/sim_cost.py), not the 3 once assumed: on sl40 a 1 s re-plan after an order
    # simulated its plan for 0.44 s after the budget (1.46 s in all; 2-3 s while the agent's decisions flowed), and
    # one with a plan to compare spent the budget on simulations instead of searching
    import fms_dispatch.replan as rpmod

    calls = []
    real = rpmod.simulate
    monkeypatch.setattr(rpmod, "simulate", lambda *a, **k: calls.append(1) or real(*a, **k))
    rp, st, _ = _live_order("sl40", 400, 0)
    shop = st.shop
    res = replan(snapshot(shop), rp.plan, 1.0, sim=nominal_copy(shop))
    assert calls == [] and res.before is None and res.after == res.plan.makespan
    small = FullShop(builtin("EX12"))  # a BU-size shop: simulations fit many times over
    Stepper(small, idle_stops=True).advance()
    res = replan(snapshot(small), None, 1.0, sim=nominal_copy(small))
    assert calls and res.plan.meta["method"] == res.method


@pytest.mark.parametrize("kind", ["outage", "breakdown"])
def test_a_window_that_starts_where_the_one_before_ends_is_re_planned_for(kind):
    # the disruptions in force were compared by their flags alone: a second window of the same vehicle starting at
    # the first's end added nothing, the plan waited for the vehicle through it (EX12: makespan 100,082 for 100)
    from fms_sim.disruptions import Outage

    inst = builtin("EX12")
    if kind == "outage":
        first, second = Outage("agv", 1, 36, 10), Outage("agv", 1, 46, 100_000)
        both, alone = Scenario(outages=(first, second)), Scenario(outages=(second,))
    else:
        first, second = Breakdown(2, 20, 10), Breakdown(2, 30, 100_000)
        both, alone = Scenario(breakdowns=(first, second)), Scenario(breakdowns=(second,))
    runs = {}
    for name, sc in (("both", both), ("alone", alone)):
        s = solve(inst, "plan:list", scenario=sc, replan=1.0)
        assert validate(inst, s, sc) == []
        runs[name] = s
    assert (kind, second.start) in [(e["reason"], e["time"]) for e in runs["both"].meta["replans"]]
    if kind == "outage":  # the other AGV takes the parts (a machine has no stand-in: a breakdown is waited out)
        assert runs["both"].makespan < 1000 and runs["alone"].makespan < 1000  # (re-plans search on the clock)


def test_a_residual_plan_retimed_from_a_later_state_starts_from_that_state():
    # retime_from copied the plan's meta over its own: a residual plan of an earlier state kept that state's time as
    # meta["residual"], and the re-timed plan was refused by the search from the state it was re-timed to
    from fms_dispatch.replan import retime_from
    from fms_dispatch.tabu import tabu_plan

    inst = builtin("EX74")
    plan = greedy_schedule(inst)
    earlier = snapshot(run_plan_until(inst, plan, 10)[0])
    shop, _ = run_plan_until(inst, plan, 30)
    later = snapshot(shop)
    assert earlier.now < later.now
    retimed = retime_from(later, greedy_schedule(inst, origin=earlier))
    assert retimed.meta["residual"] == retimed.meta["retimed"] == later.now
    searched = tabu_plan(inst, retimed, budget=None, max_iters=20, origin=later)
    assert searched.meta["residual"] == later.now and searched.makespan <= retimed.makespan
    assert validate(inst, finish_by(nominal_copy(shop), searched)) == []
