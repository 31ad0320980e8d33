"""Snapshots of a running full-decision shop, and residual plans made from them."""

import random

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.disruptions import Breakdown, Scenario
from fms_sim.full_shop import FullShop
from fms_sim.generate import generate_instances
from fms_sim.snapshot import Snapshot, nominal_copy, snapshot
from fms_sim.stepping import Stepper
from fms_sim.validate import validate
from fms_dispatch.exact import greedy_schedule

from ..conftest import finish_by, run_plan_until


def _small_tools():
    return generate_instances(8, 5, 4, 1, n_agvs=2, n_tool_transporters=2, name_prefix="snap")[0]


def test_the_snapshot_of_a_fresh_shop_is_the_initial_state_with_its_idle_vehicles_held():
    # the vehicles stand idle: a residual plan resumed there cannot pre-position them (PlanPolicy.resume drops their
    # empty legs), whereas a whole plan from the initial state moves them at their first idle stop
    from dataclasses import replace

    for name in ("EX12", "ra03"):
        inst = builtin(name)
        shop = FullShop(inst)
        Stepper(shop, idle_stops=True).advance()
        held = {("agv", v) for v in range(inst.n_agvs)} | {("tt", r) for r in range(inst.n_tool_transporters)}
        assert snapshot(shop) == replace(Snapshot.initial(inst), held=frozenset(held))
        assert Snapshot.initial(inst).held == frozenset()


def test_a_list_schedule_from_the_initial_snapshot_is_the_plain_one():
    for name in ("EX74", "ra05", "sl00"):
        inst = builtin(name)
        a = greedy_schedule(inst, rule="est")
        b = greedy_schedule(inst, rule="est", origin=Snapshot.initial(inst))
        assert b.operations == a.operations and b.agv_trips == a.agv_trips and b.tool_trips == a.tool_trips
        assert b.makespan == a.makespan and b.meta["residual"] == 0


@pytest.mark.parametrize("name", ["EX74", "ra05", "small-tools"])
def test_residual_plans_from_any_state_run_to_a_valid_end(name):
    inst = _small_tools() if name == "small-tools" else builtin(name)
    plan = greedy_schedule(inst, rule="ect")
    rng = random.Random(1)
    checked = 0
    for cut in sorted(rng.sample(range(1, 4 * inst.n_operations), 12)):
        shop, st = run_plan_until(inst, plan, cut)
        if st.kind == "done":
            continue
        checked += 1
        snap = snapshot(shop)
        assert snap.now == shop.now and snap.remaining == sum(len(j) for j in inst.jobs) - sum(shop.started)
        for rule in ("est", "ect"):
            sim = nominal_copy(shop)
            residual = greedy_schedule(inst, rule=rule, origin=snap)
            # only what has not started is planned, none of it before now
            assert {(r.job, r.op) for r in residual.operations} == {
                (j, k) for j, job in enumerate(inst.jobs) for k in range(snap.next_op[j], len(job))}
            assert all(r.start >= snap.now for r in residual.operations)
            out = finish_by(sim, residual)  # never stuck: the residual plan fits the state
            assert validate(inst, out) == [], (name, cut, rule)
    assert checked >= 6  # most cuts fall inside the run (a run ending early would make this test check nothing)


def test_a_snapshot_is_refused_while_a_vehicle_choice_is_pending():
    inst = builtin("EX12")
    shop = FullShop(inst)
    shop.net.advance()
    shop.fire_action(shop.action_index("job:0"))  # an AGV must be chosen now
    with pytest.raises(ValueError, match="pending"):
        snapshot(shop)


def test_the_nominal_copy_forgets_noise_and_future_breakdowns_but_not_the_present():
    inst = builtin("ra05")
    plan = greedy_schedule(inst)
    sc = Scenario(breakdowns=(Breakdown(1, 1, 6), Breakdown(2, plan.makespan, 9)), noise=0.3, seed=4)
    shop, st = run_plan_until(inst, plan, 2 * inst.n_operations, scenario=sc)
    assert shop.now > 1
    sim = nominal_copy(shop)
    assert sim.scenario is not None and sim.scenario.noise == 0
    assert [b.machine for b in sim.scenario.breakdowns] == [1]  # the one that has begun
    assert not any(c[0] == "down" for _, c in sim.net.sojourning(sim.p_disrupt))
    snap = snapshot(shop)
    assert any(i >= 0 for i in sim._running_rec)
    for m, i in enumerate(sim._running_rec):
        if i >= 0:
            r = sim.rec.ops[i]
            # a running operation ends at its nominal estimate in the copy and in the snapshot alike
            assert r.end == snap.machine_free[m] == max(r.start + inst.jobs[r.job][r.op].duration
                                                        + (6 if m == 1 and r.start < 1 < r.end else 0), shop.now + 1)
    # the real shop is untouched
    assert shop.scenario is sc


def test_a_residual_plan_from_a_snapshot_ends_when_it_predicts_in_a_nominal_shop():
    # a vehicle committed to a carry was left at its pickup in the snapshot: residual plans moved it from the
    # wrong place and their executions ended later than they predicted, with no disruption at all
    from fms_dispatch.full_rules import parse_full_rule
    from fms_dispatch.replan import simulate
    from fms_sim.snapshot import can_snapshot

    rule = parse_full_rule("rule:SPT+nearest+fifo")
    checked = 0
    for name in ("ra01", "ra02", "EX22"):
        inst = builtin(name)
        for seed in range(6):
            rng = random.Random(seed)
            shop = FullShop(inst)
            st = Stepper(shop, idle_stops=True)
            st.advance()
            stop_at, n = rng.randint(5, 60), 0
            while st.kind != "done":
                if n >= stop_at and can_snapshot(shop):
                    snap = snapshot(shop)
                    for r in ("est", "ect"):
                        plan = greedy_schedule(inst, rule=r, origin=snap)
                        made = simulate(nominal_copy(shop), plan)
                        assert made is not None and made <= plan.makespan, (name, seed, r, made, plan.makespan)
                        checked += 1
                    break
                if st.kind == "idle":
                    st.move([])
                else:
                    st.decide(rule(shop) if rng.random() < 0.8 else rng.choice(shop.legal_actions()))
                n += 1
    assert checked >= 20


def test_a_residual_plan_runs_when_a_reserved_tool_ties_with_another_use_at_its_start():
    # found by fuzzing: at t=1 tool 2 is reserved for job 1's first operation, which the residual plan runs at 1 with
    # job 0's use of the same tool beside it (both of zero duration); the orders of tied uses (ties.plan_orders, by
    # job number) put job 0's first on the machine, which then waited for a use the tool would never serve: every
    # residual plan from that state got stuck (and a re-plan there raised "every new plan got stuck")
    from fms_sim.instance import Instance, Operation

    inst = Instance(name="reserved-tie", jobs=((Operation(1, 2, 0),), (Operation(1, 2, 0), Operation(1, 1, 3))),
                    tool_travel=((0, 1), (7, 0)), n_tool_transporters=1)
    shop, st = run_plan_until(inst, greedy_schedule(inst), 2)
    snap = snapshot(shop)
    assert st.kind != "done" and snap.tool_reserved == {2: (1, 0, snap.now)}  # the state the test is about
    for rule in ("est", "ect"):
        residual = greedy_schedule(inst, rule=rule, origin=snap)
        assert {(r.start, r.end) for r in residual.operations if r.op == 0} == {(snap.now, snap.now)}  # tied
        out = finish_by(nominal_copy(shop), residual)
        assert validate(inst, out) == [] and out.makespan <= residual.makespan


def _stuck_before(case: str):
    """A shop run to a state from which every list schedule's residual plan got stuck (fuzzed), its stepper."""
    from fms_sim.instance import Instance, Operation

    if case == "one job":  # tool 1 has just been carried to machine 2 for (0,0); (0,1) there and (0,2) on machine 1
        inst = Instance(name="tied-from-m2", jobs=((Operation(2, 1, 0), Operation(2, 1, 0), Operation(1, 1, 0)),),
                        tool_travel=((0, 1, 1), (0, 0, 1), (0, 0, 0)), n_tool_transporters=1)
        labels = ("wait", "tool:1", "use:0", "tt:0")
    else:  # tool 1 stands on machine 2, reserved for (0,0); the uses of three jobs tie at 0 and at 1
        travel = ((0, 0, 0), (0, 0, 1), (0, 0, 0))
        inst = Instance(name="tied-three-jobs", jobs=((Operation(2, 1, 0), Operation(1, 1, 0), Operation(2, 1, 0)),
                        (Operation(2, 1, 0),), (Operation(1, 1, 0),)), agv_travel=travel, tool_travel=travel, n_agvs=2,
                        n_tool_transporters=1)
        labels = ("wait", "job:0", "agv:0", "wait", "tool:1", "use:0", "tt:0", "reposition:tt:0:1",
                  "reposition:tt:0:0", "wait")
    shop = FullShop(inst)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    for label in labels:
        st.apply(label)
    return shop, st


@pytest.mark.parametrize("case", ["one job", "three jobs"])
def test_a_residual_plan_orders_its_tied_uses_from_where_the_tool_stands(case):
    # found by fuzzing (12-14 of 3196 small shops per planner): ties.plan_orders ordered each tool's uses at one
    # instant as if the tool stood in the magazine, as at the start of a whole schedule; from the machine where it
    # stood, that order was one the tool could not follow (here: (0,2), carried away from machine 2, before (0,0)
    # and (0,1) there; or (1,0) before (0,2), whose carry brings the tool to (1,0)'s machine), the machine and the
    # transporter served the uses in the plan's order, and the replay waited for a use the tool would not serve
    from fms_sim.replay import PlanPolicy, execute
    from fms_sim.snapshot import can_snapshot

    shop, st = _stuck_before(case)
    snap = snapshot(shop)
    assert st.kind != "done" and snap.tool_loc[1] == 2 and snap.tool_reserved[1][:2] == (0, 0)  # the test's state
    for rule in ("est", "ect"):
        residual = greedy_schedule(shop.instance, rule=rule, origin=snap)
        assert sum(r.start == r.end for r in residual.operations) >= 3  # uses of no duration, tied
        out = finish_by(nominal_copy(shop), residual)
        assert validate(shop.instance, out) == [] and out.makespan <= residual.makespan, rule
        # resumed again from a later state of its own run (a plan adopted while the shop went on, or after an
        # answer off the plan): the uses done are left out, the others ordered from where the tool stands then
        twin = nominal_copy(shop)
        run = Stepper(twin, idle_stops=True)
        run.advance()
        pol = PlanPolicy.resume(twin, residual)
        while twin.started == shop.started or not (run.kind == "decision" and can_snapshot(twin)):
            label = pol.answer(run)
            pol.apply(run, label)
            run.apply(label)
        assert run.kind != "done"
        execute(twin, PlanPolicy.resume(twin, residual))
        assert twin.schedule().makespan <= residual.makespan, rule


def test_a_plan_resumed_again_later_orders_only_the_uses_left_from_where_the_tool_stands():
    # PlanPolicy.resume orders the tied uses from where the tools stand now, so the uses done must be left out of
    # that order: here tool 1 stands on machine 1 for (1,1); counted after it, (1,0) (done, on machine 2) put the
    # tool back on machine 2, (1,2) there came before (0,0) at 4, whose carry brings the tool from machine 1, and
    # the replay was stuck (3 of 12840 fuzzed re-resumes of an implementation that kept them)
    from fms_sim.instance import Instance, Operation
    from fms_sim.replay import PlanPolicy, execute
    from fms_sim.snapshot import can_snapshot

    inst = Instance(name="resumed-later", jobs=((Operation(2, 1, 0),), (Operation(2, 1, 1), Operation(1, 1, 1),
                    Operation(2, 1, 0))), tool_travel=((0, 0, 0), (2, 0, 2), (2, 0, 0)), n_tool_transporters=2)
    shop = FullShop(inst)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    plan = greedy_schedule(inst, rule="est", origin=snapshot(shop))
    pol = PlanPolicy.resume(shop, plan)
    while not (shop.now == 1 and st.kind == "decision" and can_snapshot(shop)):
        label = pol.answer(st)
        pol.apply(st, label)
        st.apply(label)
    assert shop.started == [0, 1] and shop.tool_loc[1] == 1 and shop.reserved_op(1) == (1, 1)  # the test's state
    execute(shop, PlanPolicy.resume(shop, plan))
    assert validate(inst, shop.schedule()) == [] and shop.schedule().makespan <= plan.makespan


def test_a_reserved_operation_that_runs_a_while_lets_the_operations_tied_at_its_start_go_first():
    # found by fuzzing: tool 1 is reserved for job 0's operation (3 long) and arrives at its machine at 2, where job 1's
    # operation of no duration is planned at 2 too, before it; resume put the reserved one first on the machine (a rule
    # for uses tied at one instant, all of no duration), job 1 waited for its end, and its last operation ended at 9
    # instead of the 6 that every residual plan predicted
    from fms_dispatch.replan import simulate
    from fms_sim.instance import Instance, Operation

    inst = Instance(name="reserved-runs", jobs=((Operation(1, 1, 3),), (Operation(2, None, 2), Operation(1, None, 0),
                    Operation(2, None, 4))), tool_travel=((0, 2, 2), (2, 0, 2), (2, 2, 0)), n_tool_transporters=1)
    shop = FullShop(inst)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    for label in ("wait", "start:1", "tool:1", "use:0", "tt:0", "wait"):
        st.apply(label)
    snap = snapshot(shop)
    assert st.kind == "decision" and snap.now == 2 and snap.tool_reserved == {1: (0, 0, 2)}  # the state of the test
    for rule in ("est", "ect"):
        residual = greedy_schedule(inst, rule=rule, origin=snap)
        assert (1, 1, 2, 2) in {(r.job, r.op, r.start, r.end) for r in residual.operations}  # tied at the start
        assert simulate(nominal_copy(shop), residual) == residual.makespan == 6, rule
