"""AgentLogic (the agent node's logic, no ROS): rules on state features decide exactly like RulePolicy."""

from __future__ import annotations

import json

import pytest

import fms_msgs_json as m
from fms_msgs_json import decode, encode
from fms_dispatch.agent_logic import (
    FEATURE_JOB_KEYS, AgentLogic, DecisionError, UnavailableSolver, legal_labels, make_decider,
)
from fms_dispatch.rules import JOB_RULES, RulePolicy, all_rule_pairs
from fms_dispatch.solvers import solve
from fms_sim import validate
from fms_sim.benchmarks import builtin
from fms_sim.shop_service import ShopService


def drive(instance_name: str, solver: str, seed: int = 0, check_policy: RulePolicy | None = None) -> ShopService:
    """Run the shop service with the agent logic over encoded messages; optionally compare every decision
    with ``check_policy`` on the live shop."""
    svc = ShopService(builtin(instance_name), run_id="r")
    agent = AgentLogic(solver, seed=seed)
    out = svc.start()
    while not svc.done:
        (state,) = [o.msg for o in out if o.topic == m.TOPIC_STATE]
        (cmd,) = agent.on_state(encode(state))
        assert cmd.topic == m.TOPIC_COMMAND and cmd.msg["agent"] == agent.name
        if check_policy is not None:
            assert svc.shop.action_labels()[check_policy(svc.shop)] == cmd.msg["action"]
        out = svc.handle_command(encode(cmd.msg))
        assert not [o for o in out if o.topic == m.TOPIC_ERRORS]
    assert agent.on_state(encode(svc.state)) == []            # the final state needs no answer
    return svc


@pytest.mark.parametrize("name", ["EX12", "ra01"])
def test_every_rule_pair_matches_the_offline_rule_solver(name: str) -> None:
    for rule in all_rule_pairs(include_nearest=True):
        svc = drive(name, rule, check_policy=RulePolicy(*rule.split(":")[1].split("+")))
        ref = solve(builtin(name), rule)
        assert svc.final_schedule.to_dict()["operations"] == ref.to_dict()["operations"], rule
        assert svc.final_schedule.makespan == ref.makespan
        assert validate(svc.instance, svc.final_schedule) == []


@pytest.mark.parametrize("rule", ["rule:SPTN+nearest", "rule:LWT+least-work", "rule:MTWR+first"])
def test_rules_on_a_large_instance(rule: str) -> None:
    svc = drive("sl00", rule, check_policy=RulePolicy(*rule.split(":")[1].split("+")))
    ref = solve(builtin("sl00"), rule)
    assert svc.final_schedule.to_dict()["operations"] == ref.to_dict()["operations"]
    assert svc.final_schedule.makespan == ref.makespan
    assert validate(svc.instance, svc.final_schedule) == []


def test_every_job_key_equals_the_rule_key_on_live_states() -> None:
    assert set(FEATURE_JOB_KEYS) == set(JOB_RULES)
    svc = ShopService(builtin("sl00"), run_id="r")
    svc.start()
    agent = AgentLogic("rule:LPSR+nearest")
    steps = 0
    while not svc.done:
        cols, shop = svc.state["features"]["jobs"], svc.shop
        if steps % 25 == 0:
            for name, key in JOB_RULES.items():
                for j in range(shop.n_jobs):
                    if shop.next_op(j) < len(shop.instance.jobs[j]):
                        assert FEATURE_JOB_KEYS[name](cols, j) == key(shop, j), (name, j)
        (cmd,) = agent.on_state(encode(svc.state))
        svc.handle_command(encode(cmd.msg))
        steps += 1


def test_first_and_random() -> None:
    svc = drive("ra01", "first")
    assert svc.final_schedule.to_dict()["operations"] == solve(builtin("ra01"), "first").to_dict()["operations"]
    a, b = drive("EX12", "random", seed=3), drive("EX12", "random", seed=3)
    assert a.final_schedule.to_dict()["operations"] == b.final_schedule.to_dict()["operations"]
    assert a.final_schedule.to_dict()["agv_trips"] == b.final_schedule.to_dict()["agv_trips"]
    assert validate(a.instance, a.final_schedule) == []


@pytest.mark.parametrize("solver, needle", [
    ("ppo", "solver 'ppo' is not available without the shop's instance: it replays the shop into a twin"),
    ("ppo:bu", "solver 'ppo:bu' is not available without the shop's instance"),
    ("lookahead", "solver 'lookahead' is not available without the shop's instance"),
    ("ppo+lookahead", "solver 'ppo+lookahead' is not available without the shop's instance"),
    ("ppo:+lookahead", "solver 'ppo:+lookahead' names no model"),
    ("ppo:", "solver 'ppo:' names no model"),
    ("cpsat", "plans a whole schedule offline"),
    ("sos", "plans a whole schedule offline"),
    ("magic", "unknown solver 'magic'; the agent node accepts first, random, rule:<JOB>[+"),
    ("rule:XYZ", "unknown job rule 'XYZ'"),
    ("rule:FIFO+fastest", "unknown vehicle rule 'fastest'"),
    ("  ", "a solver must be named"),
])
def test_unavailable_solvers(solver: str, needle: str) -> None:
    with pytest.raises(UnavailableSolver) as info:
        AgentLogic(solver)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_names_are_canonical() -> None:
    assert make_decider("rule:mtwr+NEAREST")[1] == "rule:MTWR+nearest"
    assert make_decider("rule:SPT")[1] == "rule:SPT+first"
    assert make_decider("FIRST")[1] == "first"


def test_each_state_is_answered_once() -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    agent = AgentLogic("first")
    s0 = encode(svc.state)
    assert agent.waiting_for() is None
    (cmd,) = agent.on_state(s0)
    assert cmd.msg == m.make_command("r", 0, "job:0", agent="first")
    assert agent.waiting_for() == ("r", 0)
    assert agent.on_state(s0) == []                           # a latched state delivered again
    svc.handle_command(encode(cmd.msg))
    s1 = encode(svc.state)
    assert len(agent.on_state(s1)) == 1 and agent.on_state(s0) == []   # an older state is ignored
    assert agent.waiting_for() == ("r", 1)
    other = ShopService(builtin("EX12"), run_id="r2")          # a new run starts from seq 0 again
    other.start()
    assert len(agent.on_state(encode(other.state))) == 1 and agent.decisions == 3
    # an agent of one run (fms up's) leaves other runs on its domain to their own agents: both answered a shop's
    # states, and its schedule was of two solvers, reported as the requested one's
    mine = AgentLogic("first", only_run="r2")
    assert mine.on_state(s0) == [] and mine.decisions == 0
    assert len(mine.on_state(encode(other.state))) == 1 and mine.decisions == 1


def _bare(state: dict) -> dict:
    """A state as a shop that names no incarnation in its states sends it."""
    return {k: v for k, v in state.items() if k != "incarnation"}


@pytest.mark.parametrize("named", [True, False], ids=["incarnation", "no-incarnation"])
def test_a_shop_restarted_with_the_same_run_id_is_answered_again(named: bool) -> None:
    """A shop respawned with fixed parameters (its run_id too) publishes state 0 again; the agent took it for an old
    state and re-sent its command for the old run's later state, which the shop refused as never published: neither
    moved for ever. Its states name the shop's incarnation, so the agent begins the run again at once; from a shop
    whose states name none, the shop sends its current state with that refusal, and the same older state twice
    begins the run again."""
    plain = (lambda s: s) if named else _bare
    first = ShopService(builtin("EX12"), run_id="r")
    out = first.start()
    agent = AgentLogic("first")
    for _ in range(5):  # the first run goes some way, then its shop dies
        (state,) = [o.msg for o in out if o.topic == m.TOPIC_STATE]
        (cmd,) = agent.on_state(encode(plain(state)))
        out = first.handle_command(encode(cmd.msg))
    stale = cmd
    again = ShopService(builtin("EX12"), run_id="r")  # respawned: the same run id, from state 0
    out = again.start()
    (state0,) = [o.msg for o in out if o.topic == m.TOPIC_STATE]
    if named:
        (cmd,) = agent.on_state(encode(state0))  # another start of the run: a new run
        assert cmd.msg["state_seq"] == 0
        out = again.handle_command(encode(cmd.msg))
    else:
        assert agent.on_state(encode(_bare(state0))) == []  # taken for an old state once
        out = again.handle_command(encode(stale.msg))  # the agent's re-sent command: refused, state 0 published anew
        assert [o.msg["code"] for o in out if o.topic == m.TOPIC_ERRORS] == ["stale_state"]
    (state,) = [o.msg for o in out if o.topic == m.TOPIC_STATE]
    while not again.done:
        (cmd,) = agent.on_state(encode(plain(state)))
        out = again.handle_command(encode(cmd.msg))
        assert not [o for o in out if o.topic == m.TOPIC_ERRORS]
        state = again.state
    inst = builtin("EX12")
    assert validate(inst, again.shop.schedule()) == []
    assert again.shop.schedule().makespan == solve(inst, "first").makespan


def test_a_late_state_of_a_restarted_shops_earlier_start_is_not_answered() -> None:
    """After a shop restarted with the same run_id (another incarnation), a state of its earlier start still on its
    way was taken for yet another restart: the agent answered the dead shop's state as a new run, then the live
    shop's next state as a restart again, rebuilding its twin each time. A start the run has begun again from is
    never answered."""
    inst = builtin("EX12")
    first = ShopService(inst, run_id="r")
    first.start()
    agent = AgentLogic("first")
    for _ in range(4):
        (cmd,) = agent.on_state(encode(first.state))
        first.handle_command(encode(cmd.msg))
    late = encode(first.state)  # published by the first start just before it died, delivered after the restart
    again = ShopService(inst, run_id="r")
    again.start()
    (cmd,) = agent.on_state(encode(again.state))
    assert cmd.msg["state_seq"] == 0
    again.handle_command(encode(cmd.msg))
    assert agent.on_state(late) == []
    while not again.done:
        (cmd,) = agent.on_state(encode(again.state))
        assert cmd.msg["state_seq"] == again.state_seq
        assert not [o for o in again.handle_command(encode(cmd.msg)) if o.topic == m.TOPIC_ERRORS]
        assert agent.on_state(late) == []
    assert validate(inst, again.shop.schedule()) == []


@pytest.mark.parametrize("solver", ["first", "plan:list"])
def test_an_old_state_delivered_twice_is_not_taken_for_a_restart(solver: str) -> None:
    """An old state that comes twice (reordered and duplicated on its way) was taken for a shop restarted with the
    same run_id: the agent answered it as a new run (a plan agent rebuilt its twin and started a re-plan from it) and
    its command was refused stale. The states name the shop's incarnation: an older state of the same one is never
    answered."""
    inst = builtin("EX12")
    net = dict(decisions="full", history=True, idle_stops=True, features=False) if solver.startswith("plan:") else {}
    svc = ShopService(inst, run_id="r", **net)
    svc.start()
    agent = AgentLogic(solver, instance=inst)
    states = []
    for _ in range(6):
        states.append(encode(svc.state))
        (cmd,) = [o for o in agent.on_state(states[-1]) if o.topic == m.TOPIC_COMMAND]
        assert not m.decode(encode(cmd.msg), expect="command")["state_seq"] < svc.state_seq
        svc.handle_command(encode(cmd.msg))
    rebuilds = getattr(agent.decide, "rebuilds", None)
    assert agent.on_state(states[2]) == [] and agent.on_state(states[2]) == [] and agent.on_state(states[2]) == []
    assert agent.decisions == 6 and getattr(agent.decide, "rebuilds", None) == rebuilds
    assert len([o for o in agent.on_state(encode(svc.state)) if o.topic == m.TOPIC_COMMAND]) == 1


def test_undecidable_states_give_errors() -> None:
    svc = ShopService(builtin("EX12"), run_id="r", features=False)
    svc.start()
    agent = AgentLogic("rule:SPT+first")
    (err,) = agent.on_state(encode(svc.state))
    assert err.topic == m.TOPIC_ERRORS and err.msg["code"] == "bad_schema"
    assert "state 0 has no 'features'; rule:SPT+first needs them" in err.msg["message"]
    assert err.msg["run_id"] == "r" and agent.waiting_for() is None
    assert len(AgentLogic("first").on_state(encode(svc.state))) == 1   # 'first' needs no features
    state = json.loads(encode(svc.state))
    state["mask"] = [False] * len(state["mask"])
    (err,) = AgentLogic("first").on_state(json.dumps(state))
    assert "state 0 enables no action" in err.msg["message"]
    (err,) = agent.on_state("not json")
    assert err.msg["code"] == "malformed_json" and err.msg["source"] == "fms_agent"
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    state = json.loads(encode(svc.state))
    for col in state["features"]["jobs"].values():
        col.pop()                                              # features cover 4 jobs, 5 are offered
    (err,) = AgentLogic("rule:SPT+first").on_state(json.dumps(state))
    assert "features and actions disagree" in err.msg["message"]


def test_legal_labels() -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    assert legal_labels(decode(encode(svc.state))) == ["job:0", "job:1", "job:2", "job:3", "job:4"]
    bad = json.loads(encode(svc.state))
    bad["actions"][0] = "crane:0"
    with pytest.raises(DecisionError, match="'crane:0'"):
        legal_labels(bad)


# ------------------------------------------------------------------------------------------------ ppo
def ppo_run(inst, solver: str = "ppo", restart_at: int | None = None, order_at: int | None = None,
            idle_stops: bool = False, decisions: str = "paper", delta: bool = False, missed: int | None = None):
    """Drive a history-carrying shop (on the net ``decisions``; ``delta``: a ``history_delta`` shop, whose replay
    requests for the whole history are served) with a PPO agent; optionally replace the agent by a fresh one (a
    restart) before state ``restart_at``, send an order before state ``order_at``, and let another agent answer
    state ``missed`` (the first one never sees it)."""
    svc = ShopService(inst, run_id="p", history=True, idle_stops=idle_stops, decisions=decisions,
                      history_delta=delta)
    agent = AgentLogic(solver, instance=inst)
    agents = [agent]
    out = svc.start()
    while not svc.done:
        if svc.state_seq == order_at:
            out = svc.handle_order(encode(m.make_order("o1", [[(1, None, 3), (2, None, 4)]])))
            assert not [o for o in out if o.topic == m.TOPIC_ERRORS]
        if svc.state_seq == restart_at:
            agent = AgentLogic(solver, instance=inst)
            agents.append(agent)
        who = AgentLogic(solver, instance=inst) if svc.state_seq == missed else agent
        outs = who.on_state(encode(svc.state))
        if delta and [o for o in outs if o.topic == m.TOPIC_REPLAY]:  # the twin cannot follow: the whole history
            (req,) = outs
            assert req.msg["what"] == "state" and who.history_asked() == ("p", svc.state_seq)
            assert who.on_state(encode(svc.state)) == []       # the same delta again: asked already
            (again,) = svc.handle_replay(encode(req.msg))
            assert again.topic == m.TOPIC_STATE and again.msg["seq"] == svc.state_seq
            outs = who.on_state(encode(again.msg))
            assert who.history_asked() is None
        (cmd,) = [o for o in outs if o.topic == m.TOPIC_COMMAND]
        assert cmd.msg["agent"] == who.name
        for rep in (o for o in outs if o is not cmd):  # a re-plan searched beside (an order's) may end meanwhile
            assert rep.topic == m.TOPIC_REPLANS and rep.msg["reason"] == "order", rep.msg
            assert rep.msg["status"] in ("adopted", "kept", "timeout"), rep.msg
        out = svc.handle_command(encode(cmd.msg))
        assert not [o for o in out if o.topic == m.TOPIC_ERRORS]
    return svc, agents


@pytest.mark.parametrize("name, solver, model, net", [("EX12", "ppo:bu", "bu", "paper"),
                                                      ("EX12", "ppo", "guided-dagger", "full"),
                                                      ("ra01", "ppo:large", "large", "paper"),
                                                      ("ra01", "ppo", "guided-dagger", "full")])
def test_ppo_over_messages_equals_the_offline_ppo_solver(name: str, solver: str, model: str, net: str) -> None:
    from fms_dispatch.rl import ppo_solver

    inst = builtin(name)
    ref = ppo_solver(solver)(inst)
    svc, (agent,) = ppo_run(inst, solver=solver, decisions=net)
    assert agent.name == f"ppo:{model}" and svc.final_schedule.meta["solver"] == f"ppo:{model}"
    assert svc.final_schedule.to_dict()["operations"] == ref.to_dict()["operations"]
    assert svc.final_schedule.makespan == ref.makespan
    assert validate(inst, svc.final_schedule) == []
    assert agent.decide.rebuilds == 1                         # one twin, one replayed step per state


def test_ppo_agent_restarted_mid_run_replays_the_history() -> None:
    from fms_dispatch.rl import ppo_solver

    inst = builtin("EX12")
    svc, agents = ppo_run(inst, solver="ppo:bu", restart_at=11)
    assert len(agents) == 2 and agents[1].decide.rebuilds == 1 and agents[1].decisions == svc.decisions - 11
    assert svc.final_schedule.makespan == ppo_solver("ppo:bu")(inst).makespan  # the restarted twin goes on alike
    assert validate(inst, svc.final_schedule) == []


@pytest.mark.parametrize("name, solver, net", [("EX12", "ppo:bu", "paper"), ("ra01", "ppo", "full")])
def test_ppo_agent_follows_history_deltas_and_asks_for_the_whole_history_when_it_cannot(name: str, solver: str,
                                                                                      net: str) -> None:
    """A ``history_delta`` shop's states carry what was applied since the state before: the twin follows them (one
    build, no request); a restarted agent, and one that missed a state, ask once for the whole history (a replay
    request ``what: "state"``) and go on with the same run."""
    from fms_dispatch.rl import ppo_solver

    inst = builtin(name)
    ref = ppo_solver(solver)(inst).to_dict()["operations"]
    svc, (agent,) = ppo_run(inst, solver=solver, decisions=net, delta=True)
    assert svc.final_schedule.to_dict()["operations"] == ref
    assert agent.decide.rebuilds == 1 and agent.history_requests == 0
    svc, agents = ppo_run(inst, solver=solver, decisions=net, delta=True, restart_at=11, missed=20)
    assert svc.final_schedule.to_dict()["operations"] == ref and validate(inst, svc.final_schedule) == []
    assert [a.history_requests for a in agents] == [0, 2]        # at its start (11) and after the state it missed
    assert agents[1].decide.rebuilds == 2


def test_a_twin_that_disagrees_after_a_delta_asks_for_the_whole_history() -> None:
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="p", history=True, history_delta=True)
    agent = AgentLogic("ppo:bu", instance=inst)
    svc.start()
    for _ in range(5):
        (cmd,) = agent.on_state(encode(svc.state))
        svc.handle_command(encode(cmd.msg))
    state = json.loads(encode(svc.state))
    assert state["history"]["actions_from"] > 0 and state["history"]["actions"]
    wrong = dict(state, time=state["time"] + 1)
    (req,) = agent.on_state(json.dumps(wrong))
    assert req.topic == m.TOPIC_REPLAY and req.msg == m.make_replay_request("p", 0, agent.source, what="state")
    assert agent.decide.stepper is None                           # the twin is dropped: the whole history rebuilds it
    (again,) = svc.handle_replay(encode(req.msg))
    assert again.msg["history"]["actions_from"] == 0 and again.msg["history"]["actions"].count(" ") == 4
    (cmd,) = agent.on_state(encode(again.msg))
    assert cmd.topic == m.TOPIC_COMMAND and cmd.msg["state_seq"] == state["seq"] and agent.decide.rebuilds == 2
    assert agent.on_state(encode(again.msg)) == []               # answered: not again


def test_ppo_twin_follows_orders() -> None:
    inst = builtin("EX12")
    svc, (agent,) = ppo_run(inst, solver="ppo:bu", order_at=6)
    assert svc.instance.n_jobs == 6 and agent.decide.twin.instance.n_jobs == 6
    assert agent.decide.rebuilds == 1
    assert validate(svc.instance, svc.final_schedule) == []


@pytest.mark.parametrize("net", ["paper", "full"])
def test_a_shop_grown_past_the_models_padding_is_handed_over_once(net: str) -> None:
    """Orders that take the shop past the model's padding (it can no longer observe the shop) hand the rest of the
    run over, with one ``internal`` error naming the hand-over: a paper-net model (``bu``, 8 jobs at most) to the
    rule pair MTWR+nearest, deciding as that rule does on the live shop; the guided default (100 jobs at most) to
    the guide follower, the expert it was cloned from. Every job is served and the run is valid."""
    import dataclasses

    from fms_dispatch.rl.guide import GuideFollower, effort_from

    if net == "paper":
        inst, solver, order, at = builtin("EX12"), "ppo:bu", [[(1, None, 3), (2, None, 4)]] * 4, 6  # 5 + 4 jobs
    else:  # 99 one-operation jobs of sl70 (a short run), then 3 more
        sl70 = builtin("sl70")
        inst = dataclasses.replace(sl70, name="sl70-1op", jobs=tuple(job[:1] for job in sl70.jobs[:99]))
        solver, order, at = "ppo", [[(1, 2, 30), (3, 4, 20)]] * 3, 20
    svc = ShopService(inst, run_id="g", history=True, decisions=net, idle_stops=net == "full")
    agent = AgentLogic(solver, instance=inst, guide_effort=effort_from(tabu=0.0) if net == "full" else None)
    rule = RulePolicy("MTWR", "nearest")
    errors, after = [], 0
    svc.start()
    while not svc.done:
        if svc.state_seq == at:
            assert not [o for o in svc.handle_order(encode(m.make_order("o1", order))) if o.topic == m.TOPIC_ERRORS]
        out = agent.on_state(encode(svc.state))
        errors += [o.msg for o in out if o.topic == m.TOPIC_ERRORS]
        (cmd,) = [o.msg for o in out if o.topic == m.TOPIC_COMMAND]
        if errors and net == "paper" and not svc.state.get("idle"):
            assert cmd["action"] == svc.shop.action_labels()[rule(svc.shop)]  # the rule decides
            after += 1
        assert not [o for o in svc.handle_command(encode(cmd)) if o.topic == m.TOPIC_ERRORS]
    (err,) = errors
    assert err["code"] == "internal" and f"has outgrown model {agent.name[4:]}" in err["message"]
    assert ("the rule pair MTWR+nearest" if net == "paper" else "the guide follower") in err["message"]
    if net == "full":
        assert isinstance(agent.decide._handover, GuideFollower)
    else:
        assert after > 10
    s = svc.final_schedule
    assert {r.job for r in s.operations} == set(range(svc.instance.n_jobs)) and svc.instance.n_jobs > inst.n_jobs
    assert validate(svc.instance, s) == []


def test_ppo_without_history_or_with_another_instance_is_an_error() -> None:
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="p")                      # no history
    agent = AgentLogic("ppo:bu", instance=inst)
    svc.start()
    (err,) = agent.on_state(encode(state := svc.state))
    assert err.topic == m.TOPIC_ERRORS and err.msg["code"] == "bad_schema"
    assert "has no 'history'" in err.msg["message"] and "history:=true" in err.msg["message"]
    other = ShopService(builtin("EX11"), run_id="q", history=True)
    other.start()
    (err,) = agent.on_state(encode(other.state))
    assert "is of instance 'EX11' but this agent holds 'EX12'" in err.msg["message"]
    assert state["seq"] == 0


def test_ppo_twin_mismatch_rebuilds_then_falls_back_to_the_first_action() -> None:
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="p", history=True)
    agent = AgentLogic("ppo:bu", instance=inst)
    svc.start()
    for _ in range(4):
        (cmd,) = agent.on_state(encode(svc.state))
        svc.handle_command(encode(cmd.msg))
    assert agent.decide.rebuilds == 1
    state = json.loads(encode(svc.state))
    (cmd,) = agent.on_state(json.dumps(state))
    assert agent.decide.rebuilds == 1
    # a history that cannot lead to this state: an internal error, then the first enabled action
    bad = dict(state, seq=state["seq"] + 1, history={"actions": "", "orders": []})
    err, cmd = agent.on_state(json.dumps(bad))
    assert err.topic == m.TOPIC_ERRORS and err.msg["code"] == "internal"
    assert "the twin of the shop disagrees with the state" in err.msg["message"]
    assert cmd.topic == m.TOPIC_COMMAND and cmd.msg["action"] == legal_labels(bad)[0]
    # the next good state rebuilds the twin and decides with the policy again
    good = dict(state, seq=state["seq"] + 2)
    (cmd,) = agent.on_state(json.dumps(good))
    assert cmd.topic == m.TOPIC_COMMAND and agent.decide.rebuilds == 3
    # a history of the same length that differs in an early label is no continuation: the twin is rebuilt
    first, *rest = state["history"]["actions"].split(" ")
    assert first.startswith("job:")
    changed = "job:4" if first != "job:4" else "job:3"
    forged = dict(state, seq=state["seq"] + 3, history=dict(state["history"], actions=" ".join([changed, *rest])))
    agent.on_state(json.dumps(forged))
    assert agent.decide.rebuilds >= 4


def test_the_twin_replays_only_what_follows_the_history_it_has() -> None:
    from fms_dispatch.agent_logic import _extends

    assert _extends("a b c", "a b") and _extends("a b", "a b") and _extends("a", "") and _extends("", "")
    assert not _extends("a bc", "a b") and not _extends("a", "a b") and not _extends("x b c", "a b")


def test_unknown_ppo_model_and_oversized_instance() -> None:
    with pytest.raises(UnavailableSolver, match="solver 'ppo:nope': no model named 'nope'"):
        AgentLogic("ppo:nope", instance=builtin("EX12"))
    with pytest.raises(UnavailableSolver, match="is larger than model bu allows"):
        AgentLogic("ppo:bu", instance=builtin("sl00"))


# ------------------------------------------------------------------------------ lookahead over idle stops
@pytest.mark.parametrize("name, fast", [("EX12", False), ("EX22", False), ("EX52", False), ("ra01", False),
                                        ("EX22", True), ("ra01", True)])
def test_ppo_lookahead_over_messages_equals_the_offline_solver(name: str, fast: bool) -> None:
    from fms_dispatch.rl import ppo_solver

    inst = builtin(name)
    suffix = "+lookahead-fast" if fast else "+lookahead"
    ref = ppo_solver("ppo")(inst, lookahead="fast" if fast else True)
    # the default model of ra01 (tools) is the guided full-net one: the shop runs the full net for it
    svc, (agent,) = ppo_run(inst, solver="ppo" + suffix, idle_stops=True, decisions=ref.meta["decisions"])
    model = ref.meta["model"]
    assert agent.name == f"ppo:{model}{suffix}" == svc.final_schedule.meta["solver"] == ref.meta["solver"]
    assert agent.decide.planner.retry is not fast
    got = svc.final_schedule.to_dict()
    for key in ("operations", "agv_trips", "tool_trips", "makespan"):
        assert got[key] == ref.to_dict()[key], key
    assert validate(inst, svc.final_schedule) == []
    assert svc.idle_answers > 0 and svc.final_schedule.meta["idle_answers"] == svc.idle_answers
    assert agent.decide.rebuilds == 1


@pytest.mark.parametrize("name", ["EX12", "ra01"])
def test_full_net_ppo_lookahead_in_a_disrupted_shop_over_messages_equals_the_offline_solver(name: str) -> None:
    """The agent's twin mirrors the shop's scenario (noise seed, breakdowns), so its lookahead plans on nominal
    copies, as the offline solver does: neither sees the disrupted future, and the runs are the same."""
    from fms_dispatch.rl import ppo_solver
    from fms_sim.disruptions import Breakdown, Scenario

    inst = builtin(name)
    sc = Scenario(breakdowns=(Breakdown(2, 20, 15),), noise=0.2, seed=4)
    ref = ppo_solver("ppo:full")(inst, lookahead=True, scenario=sc)
    svc = ShopService(inst, run_id="d", history=True, idle_stops=True, decisions="full", scenario=sc)
    agent = AgentLogic("ppo:full+lookahead", instance=inst)
    svc.start()
    while not svc.done:
        (cmd,) = agent.on_state(encode(svc.state))
        assert not [o for o in svc.handle_command(encode(cmd.msg)) if o.topic == m.TOPIC_ERRORS]
    got = svc.final_schedule
    for key in ("operations", "agv_trips", "tool_trips", "makespan"):
        assert got.to_dict()[key] == ref.to_dict()[key], key
    assert validate(inst, got) == [] and svc.idle_answers > 0


def test_first_and_random_decide_on_the_full_net_and_rules_refuse_it() -> None:
    inst = builtin("ra01")
    for solver in ("first", "random"):
        svc = ShopService(inst, run_id=solver, decisions="full")
        decide, _ = make_decider(solver, 3, inst)
        svc.start()
        labels = set()
        while not svc.done:
            label = decide(svc.state)
            labels.add(label.split(":")[0])
            out = svc.handle_command(encode(m.make_command(svc.run_id, svc.state_seq, label, agent=solver)))
            assert not [o for o in out if o.topic == m.TOPIC_ERRORS]
        assert validate(inst, svc.final_schedule) == [] and labels & {"start", "use", "tool"}
    rule, _ = make_decider("rule:MTWR+nearest")
    svc = ShopService(inst, run_id="r", decisions="full")
    svc.start()
    with pytest.raises(DecisionError, match="is of the full net; rule:MTWR\\+nearest decides on the paper's net"):
        rule(svc.state)


def test_lookahead_moves_vehicles_over_messages_and_restarts() -> None:
    from fms_dispatch.rl import ppo_solver

    inst = builtin("EX12")  # the lookahead improves bu on EX12 (pre-positioning pays off)
    plain = ppo_solver("ppo:bu")(inst)
    svc, agents = ppo_run(inst, solver="ppo:bu+lookahead", idle_stops=True, restart_at=9)
    assert any(lab.startswith("reposition:") for lab in svc._applied)  # the agent moved a vehicle
    assert len(agents) == 2 and agents[1].decide.rebuilds == 1
    assert svc.final_schedule.makespan < plain.makespan
    assert svc.final_schedule.makespan == ppo_solver("ppo:bu")(inst, lookahead=True).makespan
    assert validate(inst, svc.final_schedule) == []
    # ``lookahead`` alone is the default model with the lookahead: guided-dagger, on the full net
    svc, (agent,) = ppo_run(inst, solver="lookahead", idle_stops=True, decisions="full")
    assert agent.name == "ppo:guided-dagger+lookahead" and validate(inst, svc.final_schedule) == []


def test_lookahead_twin_follows_orders_at_idle_stops() -> None:
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="p", history=True, idle_stops=True)
    agent = AgentLogic("ppo:bu+lookahead", instance=inst)
    svc.start()
    ordered = False
    while not svc.done:
        if not ordered and svc.state["idle"]:  # an order arriving at an idle stop
            out = svc.handle_order(encode(m.make_order("o1", [[(1, None, 3), (2, None, 4)]])))
            assert not [o for o in out if o.topic == m.TOPIC_ERRORS]
            ordered = True
        (cmd,) = agent.on_state(encode(svc.state))
        out = svc.handle_command(encode(cmd.msg))
        assert not [o for o in out if o.topic == m.TOPIC_ERRORS]
    assert ordered and svc.instance.n_jobs == 6 and agent.decide.twin.instance.n_jobs == 6
    assert validate(svc.instance, svc.final_schedule) == []


@pytest.mark.parametrize("solver", ["rule:SPTN+nearest", "ppo:large"])
def test_other_solvers_wait_at_idle_stops(solver: str) -> None:
    inst = builtin("ra01")
    svc, (agent,) = ppo_run(inst, solver=solver, idle_stops=True)
    ref = solve(inst, solver)
    idle_answers = [lab for lab in svc._applied if lab == "wait" or lab.startswith("reposition")]
    assert svc.idle_answers == len(idle_answers) > 0 and set(idle_answers) == {"wait"}
    assert svc.final_schedule.to_dict()["operations"] == ref.to_dict()["operations"]
    assert svc.final_schedule.makespan == ref.makespan


def test_lookahead_needs_a_shop_with_idle_stops() -> None:
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="p", history=True)        # no idle stops
    agent = AgentLogic("ppo:bu+lookahead", instance=inst)
    svc.start()
    (err,) = agent.on_state(encode(svc.state))
    assert err.topic == m.TOPIC_ERRORS and "has no 'idle' field" in err.msg["message"]
    assert "idle_stops:=true" in err.msg["message"]


def test_guided_default_model_follows_orders_and_disruptions_on_the_full_net() -> None:
    """The default model of a tool shop (``guided-dagger``) re-plans its guide from the live state when an order
    arrives, and runs a shop with a breakdown and an outage; both schedules are valid."""
    from fms_dispatch.rl import ppo_solver
    from fms_sim.disruptions import Breakdown, Outage, Scenario

    inst = builtin("ra01")
    svc, (agent,) = ppo_run(inst, order_at=20, decisions="full")
    assert agent.name == "ppo:guided-dagger" and svc.instance.n_jobs == inst.n_jobs + 1
    assert agent.decide.twin.instance.n_jobs == inst.n_jobs + 1
    assert validate(svc.instance, svc.final_schedule) == []
    sc = Scenario((Breakdown(machine=2, start=20, duration=40),),
                  (Outage(kind="agv", vehicle=0, start=10, duration=50),), 0.1, 5)
    s = ppo_solver("ppo")(inst, scenario=sc)
    assert s.meta["model"] == "guided-dagger" and validate(inst, s) == []


def test_lookahead_guide_over_messages_equals_the_offline_solver() -> None:
    from fms_dispatch.rl import ppo_solver

    inst = builtin("ra01")
    ref = ppo_solver("ppo")(inst, lookahead="guide")
    svc, (agent,) = ppo_run(inst, solver="ppo+lookahead-guide", idle_stops=True, decisions="full")
    assert agent.name == "ppo:guided-dagger+lookahead-guide" == svc.final_schedule.meta["solver"]
    assert any(lab.startswith("reposition:") for lab in svc._applied)  # the plan's empty trips were made
    got = svc.final_schedule.to_dict()
    for key in ("operations", "agv_trips", "tool_trips", "makespan"):
        assert got[key] == ref.to_dict()[key], key
    assert validate(inst, svc.final_schedule) == []
    with pytest.raises(UnavailableSolver, match="has no plan guide"):
        AgentLogic("ppo:bu+lookahead-guide", instance=builtin("EX12"))


def test_a_guided_agent_searches_its_plan_as_told() -> None:
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import PlanEffort

    inst = builtin("EX44")
    effort = PlanEffort(restarts=8)  # no rules: the list schedule and 8 restarts
    ref = ppo_solver("ppo")(inst, guide_effort=effort)
    assert ref.makespan != ppo_solver("ppo")(inst).makespan  # the default search plans otherwise here
    svc = ShopService(inst, run_id="g", history=True, decisions="full")
    agent = AgentLogic("ppo", instance=inst, guide_effort=effort)
    svc.start()
    while not svc.done:
        (cmd,) = agent.on_state(encode(svc.state))
        assert not [o for o in svc.handle_command(encode(cmd.msg)) if o.topic == m.TOPIC_ERRORS]
    assert svc.final_schedule.to_dict()["operations"] == ref.to_dict()["operations"]
    assert validate(inst, svc.final_schedule) == []
    with pytest.raises(UnavailableSolver, match="applies to ppo solvers only"):
        AgentLogic("first", guide_effort=effort)
    with pytest.raises(UnavailableSolver, match="reads no plan guide"):
        AgentLogic("ppo:bu", instance=builtin("EX12"), guide_effort=effort)


def test_a_guided_agent_re_plans_at_a_breakdown_over_messages_as_the_offline_solver() -> None:
    """The agent's twin learns of the breakdown from the history and re-plans the guide as the offline solver does
    (the same run: with replan_wait the shop waits for the re-plan, as offline), publishing the re-plan on
    fms/replans; with guide_replan off it acts the start's plan out."""
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import effort_from
    from fms_sim.disruptions import Breakdown, Scenario

    inst = builtin("ra01")
    sc = Scenario((Breakdown(machine=2, start=20, duration=40),), (), 0.1, 5)
    effort = effort_from(tabu=0.0)  # a search the clock does not cut: the same plans in both runs
    for replan in (True, False):
        ref = ppo_solver("ppo")(inst, scenario=sc, guide_effort=effort, guide_replan=replan)
        svc = ShopService(inst, run_id="b", history=True, decisions="full", scenario=sc)
        agent = AgentLogic("ppo", instance=inst, guide_effort=effort, guide_replan=replan, replan_wait=True)
        replans = []
        svc.start()
        while not svc.done:
            out = agent.on_state(encode(svc.state))
            replans += [m.decode(encode(o.msg), expect="replan") for o in out if o.topic == m.TOPIC_REPLANS]
            cmd = out[-1]
            assert cmd.topic == m.TOPIC_COMMAND
            assert not [o for o in svc.handle_command(encode(cmd.msg)) if o.topic == m.TOPIC_ERRORS]
        got = svc.final_schedule
        assert got.to_dict()["operations"] == ref.to_dict()["operations"] and got.makespan == ref.makespan
        assert validate(inst, got, sc) == []
        if replan:
            (msg,) = replans
            (ev,) = ref.meta["replans"]
            assert (msg["run_id"], msg["reason"], msg["status"], msg["method"]) == ("b", "breakdown", "adopted", "guide")
            assert (msg["time"], msg["before"], msg["after"]) == (ev["time"], ev["before"], ev["after"])
        else:
            assert replans == [] and "replans" not in ref.meta


def _guided_breakdown_run(monkeypatch, compute=None, grace=None, budget=None, order_at=None, pace=0.005,
                          breakdown=True, wait=False):
    """ra01 with machine 2 down from time 20 (noise 0.1), run by the default guided model over messages, its guide
    re-planned beside the decisions; ``compute(shop, old, effort)`` replaces the re-plan's search (in the forked
    process or the thread), ``grace`` the grace past its budget, ``budget`` the re-plan's budget (s), ``order_at``
    the state (or states) at which an order joins, and the shop takes at least ``pace`` s per state. Returns (service, agent,
    re-plan messages, the offline reference run, states answered while a re-plan ran, the slowest such answer).
    ``breakdown=False``: a nominal shop (no offline reference: None); ``wait``: the agent's replan_wait."""
    import time

    from fms_dispatch import agent_logic
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import effort_from
    from fms_sim.disruptions import Breakdown, Scenario

    if compute is not None:
        monkeypatch.setattr(agent_logic, "_guide_replan", compute)
    if grace is not None:
        monkeypatch.setattr(agent_logic, "REPLAN_GRACE_S", grace)
    inst = builtin("ra01")
    sc = Scenario((Breakdown(machine=2, start=20, duration=40),), (), 0.1, 5) if breakdown else None
    effort = effort_from(tabu=0.0, budget=budget)  # a search the clock does not cut: the offline run's plans
    ref = ppo_solver("ppo")(inst, scenario=sc, guide_effort=effort) if breakdown else None
    svc = ShopService(inst, run_id="g", history=True, decisions="full", scenario=sc)
    agent = AgentLogic("ppo", instance=inst, guide_effort=effort, replan_wait=wait)
    orders_at = {order_at} if isinstance(order_at, int) else set(order_at or ())
    replans, during, slowest, steps = [], 0, 0.0, 0
    svc.start()
    while not svc.done:
        if steps in orders_at:
            svc.handle_order(encode(m.make_order(f"o{steps}", [[{"machine": 1, "tool": 1 if inst.has_tools else None,
                                                                  "duration": 5}]])))
        t0 = time.monotonic()
        out = agent.on_state(encode(svc.state))
        job = agent.decide._job
        if job is not None and not job.done.is_set():
            during += 1
            slowest = max(slowest, time.monotonic() - t0)
        replans += [m.decode(encode(o.msg), expect="replan") for o in out if o.topic == m.TOPIC_REPLANS]
        (cmd,) = [o.msg for o in out if o.topic == m.TOPIC_COMMAND]
        assert not [o for o in svc.handle_command(encode(cmd)) if o.topic == m.TOPIC_ERRORS]
        steps += 1
        time.sleep(pace)
    assert validate(svc.instance, svc.final_schedule, sc) == []
    return svc, agent, replans, ref, during, slowest


@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
def test_a_guided_agents_re_plan_runs_beside_its_decisions(monkeypatch, in_process: bool) -> None:
    """Without replan_wait the guide's re-plan at the breakdown runs beside the decisions (a forked process, or a
    thread on a copy of the twin): states are answered at once meanwhile, and the re-plan, made from the trigger's
    state, predicts what the offline run's does and is put in force on the same rule (its plan becomes the guide)."""
    import os
    import time

    from fms_dispatch import agent_logic

    if in_process and not agent_logic.REPLAN_IN_PROCESS:
        pytest.skip("re-plans run in a forked process on Linux only")
    monkeypatch.setattr(agent_logic, "REPLAN_IN_PROCESS", in_process)
    real = agent_logic._guide_replan

    def slow(shop, old, effort):
        time.sleep(0.2)  # a long re-plan (ra01's takes about 20 ms): the shop must not wait for it
        plan, before = real(shop, old, effort)
        plan.meta["pid"] = os.getpid()  # where it ran
        return plan, before

    svc, agent, replans, ref, during, slowest = _guided_breakdown_run(monkeypatch, slow)
    assert during >= 3 and slowest < 0.15  # answered at once while the re-plan ran
    (msg,) = replans
    (ev,) = ref.meta["replans"]
    assert (msg["reason"], msg["method"], msg["time"]) == ("breakdown", "guide", ev["time"])
    assert (msg["before"], msg["after"], msg["status"]) == (ev["before"], ev["after"], ev["status"]) == \
        (ev["before"], ev["after"], "adopted")
    assert msg["wall_ms"] >= 200
    # the new plan is the guide in force, re-timed from the state the run had reached when it was put in force
    guide = agent.decide.choose.agent.guide_of(agent.decide.twin)
    assert guide.plan.meta["retimed"] > msg["time"] and guide.plan.meta["retime"] in ("guided", "est")
    assert (guide.plan.meta["pid"] != os.getpid()) == in_process  # searched in a forked process, or here


@pytest.mark.parametrize("wait", [False, True], ids=["beside", "waiting"])
def test_a_live_order_to_a_guided_agent_is_bridged_then_re_planned(monkeypatch, wait: bool) -> None:
    """An order does not hold the agent up for its guide's search: the agent answers at once with a bridge plan (the
    plan in force continued from the state with the new jobs, two list schedules) while the search for the new jobs
    runs beside the decisions, published as an ``order`` re-plan; with replan_wait the state of the order waits for
    that search. Every job is served and the run is valid."""
    import time

    from fms_dispatch import agent_logic

    real = agent_logic._guide_replan

    def slow(shop, old, effort):
        time.sleep(0.3)
        plan, before = real(shop, old, effort)
        plan.meta["jobs"] = shop.n_jobs  # (searched in the forked process: it comes back with the plan)
        return plan, before

    svc, agent, replans, _, during, slowest = _guided_breakdown_run(monkeypatch, slow, order_at=20, breakdown=False,
                                                                    wait=wait)
    (msg,) = replans
    assert (msg["reason"], msg["method"]) == ("order", "guide") and msg["status"] in ("adopted", "kept")
    n = builtin("ra01").n_jobs + 1
    assert msg["wall_ms"] >= 300 and svc.instance.n_jobs == n
    if wait:
        assert during == 0
    else:
        assert during >= 3 and slowest < 0.15  # answered at once, the first of them with the bridge plan
    guide = agent.decide.choose.agent.guide_of(agent.decide.twin)
    assert guide.instance.n_jobs == n and (msg["status"] == "adopted") == (guide.plan.meta.get("jobs") == n)
    assert {r.job for r in svc.final_schedule.operations} == set(range(n))


def test_a_guide_re_plan_running_when_the_shop_outgrows_the_model_is_ended_and_reported(monkeypatch) -> None:
    # the hand-over to the guide follower left it running (a forked process to the end) and unreported until the
    # run's end, where it was said to be "done, its plan dropped there"
    import time

    from fms_dispatch import agent_logic
    from fms_dispatch.rl.guide import effort_from
    from fms_sim.disruptions import Breakdown, Scenario

    real = agent_logic._guide_replan

    def slow(shop, old, effort):
        time.sleep(1.0)
        return real(shop, old, effort)

    monkeypatch.setattr(agent_logic, "_guide_replan", slow)
    monkeypatch.setattr(agent_logic, "REPLAN_GRACE_S", 60)
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="o", history=True, decisions="full", scenario=Scenario((Breakdown(1, 10, 20),)))
    agent = AgentLogic("ppo", instance=inst, guide_effort=effort_from(tabu=0.0))
    big = [[{"machine": 1 + j % 4, "tool": None, "duration": 3}] for j in range(96)]  # 101 jobs: past the padding
    replans, errors, ordered = [], [], False
    svc.start()
    while not svc.done:
        out = agent.on_state(encode(svc.state))
        replans += [m.decode(encode(o.msg), expect="replan") for o in out if o.topic == m.TOPIC_REPLANS]
        errors += [o.msg for o in out if o.topic == m.TOPIC_ERRORS]
        (cmd,) = [o.msg for o in out if o.topic == m.TOPIC_COMMAND]
        assert not [o for o in svc.handle_command(encode(cmd)) if o.topic == m.TOPIC_ERRORS]
        job = agent.decide._job
        if not ordered and job is not None and not job.done.is_set():  # a breakdown's re-plan runs: the order comes
            svc.handle_order(encode(m.make_order("big", big)))
            ordered = True
    assert ordered and [e["code"] for e in errors] == ["internal"] and "has outgrown model" in errors[0]["message"]
    (msg,) = replans  # said at the hand-over, not at the end
    assert (msg["reason"], msg["status"]) == ("breakdown", "failed") and "has outgrown model" in msg["message"]
    assert agent.decide._job is None and agent.on_state(encode(svc.state)) == []
    assert validate(svc.instance, svc.final_schedule) == [] and svc.instance.n_jobs == 101


def test_orders_faster_than_a_guide_re_plan_do_not_starve_re_planning(monkeypatch) -> None:
    """Orders that come faster than a guide re-plan ends: each is bridged at once, and the re-plan running meanwhile
    runs on and comes in (each order ended it, 'failed', and started a re-plan of its own that the next order ended
    too, so no search ever came in while the orders came); the orders' re-plan follows it. The run is valid and
    serves every order."""
    import time

    from fms_dispatch import agent_logic

    real = agent_logic._guide_replan

    def slow(shop, old, effort):
        time.sleep(0.3)
        return real(shop, old, effort)

    orders = range(45, 200, 15)  # one every 15 states from state 45 on: a re-plan spans about 60 states here
    svc, agent, replans, *_ = _guided_breakdown_run(monkeypatch, slow, order_at=orders)
    assert svc.instance.n_jobs > 5 + 3  # several orders came
    assert replans and [m["status"] for m in replans if m["status"] == "failed"] == []
    assert replans[0]["reason"] == "breakdown" and replans[0]["status"] in ("adopted", "kept")
    assert any(m["reason"] == "order" for m in replans) or agent.decide._job.reason == "order"
    assert {r.job for r in svc.final_schedule.operations} == set(range(svc.instance.n_jobs))  # the orders served


def test_a_guided_agents_re_plan_failing_timing_out_or_outrun_is_reported(monkeypatch) -> None:
    """A re-plan that raises is ``failed`` with its error; one past its budget plus the grace is ``timeout`` (its
    process ended); one whose jobs changed meanwhile (an order) runs on and comes in, the order's own re-plan after
    it; one still running when the run ends is reported at the final state. The guide in force stays each time (but
    where a re-plan comes in) and the runs are valid."""
    import time

    from fms_dispatch import agent_logic

    real = agent_logic._guide_replan

    def broken(shop, old, effort):
        raise ValueError("no plan here\nsecond line")

    _, agent, replans, *_ = _guided_breakdown_run(monkeypatch, broken)
    msg = replans[0]  # (then the plan in force runs late: lateness triggers once per drift, failing as well)
    assert (msg["reason"], msg["status"], msg["message"], msg["before"], msg["after"]) == \
        ("breakdown", "failed", "no plan here", None, None)
    assert {m["status"] for m in replans} == {"failed"} and len(replans) <= 3

    def stuck(shop, old, effort):
        time.sleep(30)

    _, agent, replans, *_ = _guided_breakdown_run(monkeypatch, stuck, grace=0.1, budget=0.2, pace=0.02)
    msg = replans[0]
    assert msg["status"] == "timeout" and msg["budget_ms"] == 200 and "the plan in force stays" in msg["message"]
    assert 300 <= msg["wall_ms"] < 5000  # ended past its budget and grace, not after the search's 30 s

    def slow(shop, old, effort):
        time.sleep(0.3)
        return real(shop, old, effort)

    svc, agent, replans, *_ = _guided_breakdown_run(monkeypatch, slow, order_at=45)  # the trigger: state 39
    # the order came while the breakdown's re-plan ran: it ran on and came in (it was ended, 'failed'), and the
    # order's own re-plan started then (here the run ends before it is in: reported at the final state)
    assert [m["reason"] for m in replans][:1] == ["breakdown"] and replans[0]["status"] in ("adopted", "kept")
    assert agent.decide._job is not None and agent.decide._job.reason == "order"
    assert {r.job for r in svc.final_schedule.operations} == set(range(svc.instance.n_jobs))  # the order served

    svc, agent, replans, *_ = _guided_breakdown_run(monkeypatch, stuck, grace=60, pace=0)
    assert replans == [] and svc.state["done"]
    out = agent.on_state(encode(svc.state))
    (msg,) = [m.decode(encode(o.msg), expect="replan") for o in out]
    assert msg["status"] == "timeout" and "the run ended" in msg["message"] and msg["method"] == "guide"
    assert agent.decide.finish(svc.state) == []  # said once

    def late(shop, old, effort):  # done after the run's last decision: no state came to collect it
        time.sleep(0.5)
        return real(shop, old, effort)

    svc, agent, replans, *_ = _guided_breakdown_run(monkeypatch, late, grace=60, pace=0)
    assert replans == [] and svc.state["done"] and agent.decide._job.done.wait(10)
    (msg,) = [m.decode(encode(o.msg), expect="replan") for o in agent.on_state(encode(svc.state))]
    # it was reported as 'before the re-plan was done', with the time to the final state as its wall time
    assert msg["status"] == "timeout" and "before its plan could be put in force (the re-plan was done after 0." \
        in msg["message"] and 500 <= msg["wall_ms"] < 5000, msg

    def late_failure(shop, old, effort):  # fails after the run's last decision: failed, with its error
        time.sleep(0.5)
        raise ValueError("no plan here")

    svc, agent, replans, *_ = _guided_breakdown_run(monkeypatch, late_failure, grace=60, pace=0)
    assert replans == [] and agent.decide._job.done.wait(10)
    (msg,) = [m.decode(encode(o.msg), expect="replan") for o in agent.on_state(encode(svc.state))]
    assert (msg["status"], msg["message"]) == ("failed", "no plan here") and 500 <= msg["wall_ms"] < 5000, msg


def test_states_the_checks_let_through_are_answered_not_fatal() -> None:
    # each of these took the agent node down: a history disruption without its (optional) start (KeyError), a
    # history scenario that cannot be read (ScenarioError from the twin's rebuild), a label whose number is a
    # digit but no ASCII one ("²": int() failed), a number longer than Python converts, a decider that fails
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="p", history=True, decisions="full")
    svc.start()
    svc.handle_disruption(encode(m.make_disruption("d1", "breakdown", 5, machine=1, run_id="p")))
    state = json.loads(encode(svc.state))
    agent = AgentLogic("ppo", instance=inst)
    (cmd,) = agent.on_state(json.dumps(state))
    good_label = cmd.msg["action"]
    no_start = json.loads(json.dumps(state))
    del no_start["history"]["disruptions"][0]["disruption"]["start"]
    bad_scenario = dict(json.loads(json.dumps(state)), seq=state["seq"] + 2)
    bad_scenario["history"]["scenario"] = {"breakdowns": "x"}
    for bad, said in ((dict(no_start, seq=state["seq"] + 1), "replaying the history failed: KeyError: 'start'"),
                      (bad_scenario, "replaying the history failed: 'breakdowns' and 'outages' must be lists")):
        err, cmd = agent.on_state(json.dumps(bad))
        assert err.msg["code"] == "internal" and said in err.msg["message"], err.msg
        assert cmd.msg["action"] == legal_labels(bad)[0]  # the fallback
    (cmd,) = agent.on_state(json.dumps(dict(state, seq=state["seq"] + 3)))  # a good state: the model again
    assert cmd.msg["action"] == good_label
    odd = dict(state, seq=state["seq"] + 4, actions=["job:\u00b2"] + state["actions"][1:],
               mask=[True] + [False] * (len(state["mask"]) - 1))
    (err,) = AgentLogic("first").on_state(json.dumps(odd))
    assert err.msg["code"] == "bad_schema" and "action label 'job:\u00b2' this agent does not know" in err.msg["message"]
    (err,) = AgentLogic("first").on_state(json.dumps(state).replace('"seq": ', '"seq": 1' + "0" * 5000, 1))
    assert err.msg["code"] == "malformed_json" and "more than 4300 digits" in err.msg["message"]
    failing = AgentLogic("first")

    def broken(state: dict) -> str:
        raise RuntimeError("boom")

    failing.decide = broken  # type: ignore[assignment]
    err, cmd = failing.on_state(json.dumps(state))  # the error, and the safe answer: the shop waits for one
    assert err.msg["code"] == "internal" and err.msg["message"] == f"state {state['seq']}: cannot decide: " \
        f"RuntimeError: boom; sending {legal_labels(state)[0]!r}"
    assert cmd.msg["action"] == legal_labels(state)[0]


def test_a_re_plan_in_a_daemonic_process_runs_in_a_thread(monkeypatch) -> None:
    """A daemonic process (a ``multiprocessing.Pool``'s worker) may not start a process: a re-plan there raised
    multiprocessing's AssertionError ("daemonic processes are not allowed to have children") out of the decision
    instead of running in a thread, as it does where no process can be forked."""
    import multiprocessing
    import os

    from fms_dispatch import agent_logic

    if not agent_logic.REPLAN_IN_PROCESS:
        pytest.skip("re-plans run in a forked process on Linux only")
    monkeypatch.setitem(multiprocessing.current_process()._config, "daemon", True)
    job = agent_logic._ReplanJob(os.getpid, (), "breakdown", "run", 1, 0)
    assert job.done.wait(10)
    assert job.process is None and job.error is None and job.result == os.getpid()  # here, in a thread
