"""Plan execution by the agent's logic: a plan made at the first state, then answered state by state."""

import pytest

from fms_dispatch.agent_logic import AgentLogic, UnavailableSolver, make_decider, needs_full_net
from fms_dispatch.solvers import solve
from fms_msgs_json import decode, encode, make_order
from fms_sim.benchmarks import builtin
from fms_sim.shop_service import ShopService
from fms_sim.validate import validate


def drive(inst, solver, *, decisions="full", idle_stops=True, orders=None):
    """Run a ShopService against AgentLogic in-process; returns (service, errors published by the agent)."""
    svc = ShopService(inst, run_id="r", decisions=decisions, history=True, idle_stops=idle_stops, features=False)
    agent = AgentLogic(solver, instance=inst)
    svc.start()
    errors = []
    steps = 0
    while not svc.done:
        if orders and steps in orders:
            res = svc.handle_order(encode(orders[steps]))
            assert not [o for o in res if o.topic == "fms/errors"], res
        out = agent.on_state(encode(svc.state))
        errors += [o.msg for o in out if o.topic == "fms/errors"]
        cmds = [o.msg for o in out if o.topic == "fms/command"]
        if not cmds:
            break
        res = svc.handle_command(encode(cmds[0]))
        assert not [o for o in res if o.topic == "fms/errors"], res
        steps += 1
    return svc, errors


@pytest.mark.parametrize("name,solver", [("EX12", "plan:rules"), ("ra01", "plan:list"), ("sl00", "plan:list"),
                                         ("ra03", "plan:rule:MTWR+nearest")])
def test_live_plan_run_is_the_offline_plan_run(name, solver):
    inst = builtin(name)
    svc, errors = drive(inst, solver)
    assert errors == [] and svc.done
    live, offline = svc.final_schedule, solve(inst, solver)
    assert validate(inst, live) == []
    assert live.to_dict()["operations"] == offline.to_dict()["operations"]
    assert live.to_dict()["agv_trips"] == offline.to_dict()["agv_trips"]
    assert live.to_dict()["tool_trips"] == offline.to_dict()["tool_trips"]


def test_live_cpsat_plan_reaches_the_proven_optimum():
    inst = builtin("EX12")
    svc, errors = drive(inst, "plan:cpsat:10")
    assert errors == [] and svc.final_schedule.makespan == 82 == inst.meta["optimal_makespan"]


def test_a_state_answered_twice_gets_the_same_answer():
    inst = builtin("ra01")
    decider, _ = make_decider("plan:list", instance=inst)
    svc = ShopService(inst, run_id="r", decisions="full", history=True, idle_stops=True, features=False)
    svc.start()
    for _ in range(40):
        state = decode(encode(svc.state), expect="state")
        first, again = decider(state), decider(state)
        assert first == again
        svc.handle_command(encode({"schema": "fms/command/v1", "run_id": "r", "state_seq": state["seq"],
                                   "action": first}))


def test_orders_hand_over_to_the_fallback_rule_and_say_so():
    inst = builtin("ra01")
    order = make_order("o1", [[{"machine": 1, "tool": 1, "duration": 5}]])
    svc, errors = drive(inst, "plan:list", orders={20: order})
    assert svc.done and validate(svc.instance, svc.final_schedule) == []
    assert len(errors) == 1 and errors[0]["code"] == "internal"
    assert "does not cover" in errors[0]["message"] and "decides from here on" in errors[0]["message"]


def test_plan_solvers_need_the_full_net_with_idle_stops_and_the_instance():
    inst = builtin("EX12")
    assert needs_full_net("plan:cpsat:10") and not needs_full_net("rule:MTWR+nearest")
    _, errors = drive(inst, "plan:list", decisions="paper")
    assert errors and "decisions:=full" in errors[0]["message"]
    _, errors = drive(inst, "plan:list", idle_stops=False)
    assert errors and "idle_stops:=true" in errors[0]["message"]
    with pytest.raises(UnavailableSolver, match="instance"):
        make_decider("plan:cpsat:5")
    with pytest.raises(UnavailableSolver, match="bad plan solver"):
        make_decider("plan:ppo", instance=inst)
    with pytest.raises(UnavailableSolver, match="plan:cpsat"):
        make_decider("cpsat", instance=inst)
