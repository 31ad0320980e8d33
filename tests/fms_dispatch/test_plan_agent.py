"""Plan execution by the agent's logic: a plan made at the first state, then answered state by state."""

import os
import time

import pytest

from fms_dispatch.agent_logic import AgentLogic, UnavailableSolver, make_decider, needs_full_net
from fms_dispatch.solvers import solve
from fms_msgs_json import decode, encode, make_order
from fms_sim.benchmarks import builtin
from fms_sim.shop_service import ShopService
from fms_sim.validate import validate


def drive(inst, solver, *, decisions="full", idle_stops=True, orders=None, replan=0.0, replans=None, settle=True,
          delta=False):
    """Run a ShopService against AgentLogic in-process; returns (service, errors published by the agent).
    ``replans`` (a list) collects the agent's re-plan messages; with ``settle`` a re-plan under way is waited
    for before the next state (deterministic tests), else the run goes on meanwhile. ``delta``: the shop sends
    history deltas (``history_delta``); the agent must follow them without asking for the whole history."""
    svc = ShopService(inst, run_id="r", decisions=decisions, history=True, idle_stops=idle_stops, features=False,
                      history_delta=delta)
    agent = AgentLogic(solver, instance=inst, replan=replan)
    svc.start()
    errors = []
    steps = 0
    while not svc.done:
        if orders and steps in orders:
            res = svc.handle_order(encode(orders[steps]))
            assert not [o for o in res if o.topic == "fms/errors"], res
        out = agent.on_state(encode(svc.state))
        job = getattr(agent.decide, "_job", None)
        if settle and job is not None:
            assert job.done.wait(30)
        if replans is not None:
            replans += [o.msg for o in out if o.topic == "fms/replans"]
        errors += [o.msg for o in out if o.topic == "fms/errors"]
        assert not [o for o in out if o.topic == "fms/replay_request"], "the twin lost the deltas' thread"
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


def test_a_plan_agent_follows_history_deltas_through_orders():
    """A ``history_delta`` shop (each state carries what was applied since the one before): the plan agent's twin
    follows the deltas, an order included, and the run is the one a shop sending whole histories gets."""
    inst = builtin("ra01")
    order = make_order("o1", [[{"machine": 1, "tool": 1, "duration": 5}, {"machine": 3, "duration": 4}]])
    whole, errors = drive(inst, "plan:list", orders={20: order}, replan=0.5)
    svc, delta_errors = drive(inst, "plan:list", orders={20: order}, replan=0.5, delta=True)
    assert errors == delta_errors == [] and validate(svc.instance, svc.final_schedule) == []
    for key in ("operations", "agv_trips", "tool_trips"):
        assert svc.final_schedule.to_dict()[key] == whole.final_schedule.to_dict()[key], key


def test_orders_hand_over_to_the_fallback_rule_and_say_so():
    inst = builtin("ra01")
    order = make_order("o1", [[{"machine": 1, "tool": 1, "duration": 5}]])
    svc, errors = drive(inst, "plan:list", orders={20: order})
    assert svc.done and validate(svc.instance, svc.final_schedule) == []
    assert len(errors) == 1 and errors[0]["code"] == "internal"
    assert "does not cover" in errors[0]["message"] and "decides from here on" in errors[0]["message"]


@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
def test_an_order_is_replanned_and_the_new_jobs_are_served_by_the_plan(in_process, monkeypatch):
    from fms_dispatch import agent_logic

    if in_process:
        _forking()
    monkeypatch.setattr(agent_logic, "REPLAN_IN_PROCESS", in_process)
    inst = builtin("ra01")
    order = make_order("o1", [[{"machine": 1, "tool": 1, "duration": 5}, {"machine": 3, "duration": 4}]])
    replans = []
    svc, errors = drive(inst, "plan:list", orders={20: order}, replan=0.5, replans=replans)
    assert svc.done and errors == []  # no hand-over to the fallback rule
    s = svc.final_schedule
    assert validate(svc.instance, s) == [] and {r.job for r in s.operations} == set(range(inst.n_jobs + 1))
    (msg,) = [m for m in replans if m["reason"] == "order"]
    assert msg["status"] == "adopted" and msg["before"] is None and msg["after"] >= s.makespan - 50
    assert msg["budget_ms"] == 500 and 0 <= msg["wall_ms"] <= 500 + 1000
    assert decode(encode(msg), expect="replan") == msg


def test_decisions_keep_flowing_while_a_replan_runs(monkeypatch):
    import time

    from fms_dispatch import replan as replan_module

    slow = replan_module.Replanner.compute

    def compute(self, *args):
        time.sleep(0.6)  # a long re-plan: the shop must not wait for it
        return slow(self, *args)

    monkeypatch.setattr(replan_module.Replanner, "compute", compute)
    inst = builtin("sl00")
    order = make_order("o1", [[{"machine": 2, "tool": 3, "duration": 50}]])
    svc = ShopService(inst, run_id="r", decisions="full", history=True, idle_stops=True, features=False)
    agent = AgentLogic("plan:list", instance=inst, replan=1.0)
    svc.start()
    replans, slowest, steps, during = [], 0.0, 0, 0
    while not svc.done:
        if steps == 30:
            svc.handle_order(encode(order))
        t0 = time.monotonic()
        out = agent.on_state(encode(svc.state))
        job = agent.decide._job
        if job is not None and not job.done.is_set():  # answered while the re-plan runs
            during += 1
            slowest = max(slowest, time.monotonic() - t0)
        replans += [o.msg for o in out if o.topic == "fms/replans"]
        (cmd,) = [o.msg for o in out if o.topic == "fms/command"] or [out]
        svc.handle_command(encode(cmd))
        steps += 1
        if not replans:  # until the re-plan reports, a shop slower than the agent's loop: the run outlasts it
            time.sleep(0.005)
    assert during >= 3 and slowest < 0.4  # states were answered, at once, while the re-plan ran
    assert [m["reason"] for m in replans][:1] == ["order"] and replans[0]["status"] == "adopted"
    assert validate(svc.instance, svc.final_schedule) == []


def _order_run(monkeypatch, compute=None, grace=None, pace=0.002, name="ra01", at=20, replan_wait=False):
    """``name`` with an order at state ``at`` and re-planning on (0.5 s), the shop taking at least ``pace`` s per
    state; ``compute(self, *args)`` replaces the re-plan's computation, and ``grace`` the grace past its budget.
    Returns (service, agent, re-plan messages, the re-plan jobs, states answered while a re-plan ran)."""
    from fms_dispatch import agent_logic
    from fms_dispatch import replan as replan_module

    if compute is not None:
        monkeypatch.setattr(replan_module.Replanner, "compute", compute)
    if grace is not None:
        monkeypatch.setattr(agent_logic, "REPLAN_GRACE_S", grace)
    inst = builtin(name)
    order = make_order("o1", [[{"machine": 1, "tool": 1 if inst.has_tools else None, "duration": 5},
                               {"machine": 3, "duration": 4}]])
    svc = ShopService(inst, run_id="r", decisions="full", history=True, idle_stops=True, features=False)
    agent = AgentLogic("plan:list", instance=inst, replan=0.5, replan_wait=replan_wait)
    svc.start()
    replans, jobs, steps, during = [], [], 0, 0
    while not svc.done:
        if steps == at:
            svc.handle_order(encode(order))
        out = agent.on_state(encode(svc.state))
        job = agent.decide._job
        if job is not None and job not in jobs:
            jobs.append(job)
        during += job is not None
        replans += [o.msg for o in out if o.topic == "fms/replans"]
        (cmd,) = [o.msg for o in out if o.topic == "fms/command"]
        svc.handle_command(encode(cmd))
        steps += 1
        time.sleep(pace)  # a shop slower than the agent's loop: the run outlasts the re-plan
    assert validate(svc.instance, svc.final_schedule) == []
    return svc, agent, replans, jobs, during


def _forking():
    """Skip where re-plans do not run in a forked process."""
    from fms_dispatch import agent_logic

    if not agent_logic.REPLAN_IN_PROCESS:
        pytest.skip("re-plans run in a forked process on Linux only")


@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
@pytest.mark.parametrize("name,at", [("ra01", 20), ("EX42", 10)])
def test_with_replan_wait_the_shop_waits_and_the_run_ends_as_predicted(name, at, in_process, monkeypatch):
    """The state of the order is answered once the re-plan is in force: no state is answered meanwhile, and in a
    nominal shop the run ends at the re-plan's prediction (a simulation from that very state). Without waiting, the
    run goes on under the old plan meanwhile (on these small shops it even ends before the re-plan is back)."""
    from fms_dispatch import agent_logic

    if in_process:
        _forking()
    monkeypatch.setattr(agent_logic, "REPLAN_IN_PROCESS", in_process)
    spans = {}
    for wait in (True, False):
        svc, _, replans, _, during = _order_run(monkeypatch, pace=0, name=name, at=at, replan_wait=wait)
        s = svc.final_schedule
        assert {r.job for r in s.operations} == set(range(builtin(name).n_jobs + 1))  # the order's job served too
        spans[wait] = s.makespan
        if wait:
            assert during == 0 and [(m["reason"], m["status"]) for m in replans] == [("order", "adopted")]
            assert s.makespan == replans[0]["after"]
        else:
            assert during > 0
    assert spans[True] < spans[False]


def test_a_replan_in_a_process_reports_its_error_and_the_plan_stays(monkeypatch):
    def compute(self, *args):
        raise RuntimeError("no plan fits\nsecond line")

    _forking()
    _, _, replans, [job, *_], _ = _order_run(monkeypatch, compute)
    assert job.process is not None and job.process.pid != os.getpid()  # computed in another process
    assert replans[0]["reason"] == "order" and replans[0]["status"] == "failed"
    assert replans[0]["message"] == "no plan fits"


def test_a_replan_process_that_dies_is_a_failed_replan(monkeypatch):
    def compute(self, *args):
        os._exit(3)  # killed, out of memory...: no result comes back

    _forking()
    _, _, replans, _, _ = _order_run(monkeypatch, compute)
    assert replans[0]["status"] == "failed" and "ended without a result (exit code 3)" in replans[0]["message"]


def test_a_replan_runs_in_a_thread_when_no_process_can_be_forked(monkeypatch):
    import multiprocessing.context

    def start(self):
        raise OSError(12, "Cannot allocate memory")

    _forking()
    monkeypatch.setattr(multiprocessing.context.ForkProcess, "start", start)
    _, _, replans, [job, *_], _ = _order_run(monkeypatch)
    assert job.process is None and replans[0]["status"] == "adopted"


def test_a_replan_still_running_when_the_run_ends_is_reported_and_stopped(monkeypatch):
    def compute(self, *args):
        time.sleep(60)

    _forking()
    svc, agent, replans, [job, *_], _ = _order_run(monkeypatch, compute)
    assert replans == [] and svc.state["done"]  # the run outlasts no re-plan here
    out = agent.on_state(encode(svc.state))  # the final state: no command, the re-plan's report
    (msg,) = [o.msg for o in out]
    assert msg["schema"] == "fms/replan/v1" and msg["reason"] == "order" and msg["status"] == "timeout"
    assert "the run ended" in msg["message"] and "dropped" in msg["message"]
    assert job.done.wait(10) and job.process.exitcode is not None  # ended (and reaped by the job), not left to run
    assert agent.decide.finish(svc.state) == []  # said once


def test_a_replan_process_past_its_time_is_stopped(monkeypatch):
    def compute(self, *args):
        time.sleep(60)

    _forking()
    _, _, replans, [job, *_], _ = _order_run(monkeypatch, compute, grace=0.2, pace=0.02)
    assert replans[0]["status"] == "timeout"
    assert job.done.wait(10) and job.process.exitcode is not None  # terminated, not left to run for a minute


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


@pytest.mark.parametrize("delta", [False, True], ids=["whole", "delta"])
def test_disruptions_at_run_time_reach_the_shop_and_the_plan_agents_twin(delta):
    from fms_msgs_json import make_disruption

    inst = builtin("ra01")
    svc = ShopService(inst, run_id="r", decisions="full", history=True, idle_stops=True, features=False,
                      history_delta=delta)
    agent = AgentLogic("plan:list", instance=inst)
    svc.start()
    sent = {15: make_disruption("m1", "breakdown", 25, machine=1),
            30: make_disruption("v0", "outage", 20, vehicle_kind="agv", vehicle=0, start=60)}
    errors, events = [], []
    steps = 0
    while not svc.done:
        if steps in sent:
            res = svc.handle_disruption(encode(sent[steps]))
            assert not [o for o in res if o.topic == "fms/errors"], res
            events += [o.msg for o in res if o.topic == "fms/events" and o.msg["kind"] == "disruption_accepted"]
        out = agent.on_state(encode(svc.state))
        errors += [o.msg for o in out if o.topic == "fms/errors"]
        (cmd,) = [o.msg for o in out if o.topic == "fms/command"]
        res = svc.handle_command(encode(cmd))
        assert not [o for o in res if o.topic == "fms/errors"], res
        steps += 1
    assert errors == [] and len(events) == 2  # the twin followed the disruptions: no disagreement
    s = svc.final_schedule
    assert validate(inst, s) == [] and len(s.meta["scenario"]["breakdowns"]) == 1
    assert s.meta["scenario"]["outages"] == [{"kind": "agv", "vehicle": 0, "start": 60, "duration": 20}]


def test_bad_disruptions_are_rejected_and_change_nothing():
    from fms_msgs_json import make_disruption

    inst = builtin("ra01")
    svc = ShopService(inst, run_id="r", decisions="full")
    svc.start()
    before = svc.state_seq
    svc.handle_disruption(encode(make_disruption("ok", "breakdown", 10, machine=2, start=50)))
    cases = [(make_disruption("x1", "breakdown", 5, machine=9), "machine 9"),
             (make_disruption("x2", "outage", 5, vehicle_kind="tt", vehicle=7), "tool transporter 7"),
             (make_disruption("x3", "breakdown", 5, machine=2, start=55), "overlap"),
             (make_disruption("ok", "breakdown", 5, machine=3), "already accepted"),
             (make_disruption("x4", "breakdown", 5, machine=3, run_id="other"), "other")]
    seq = svc.state_seq
    for msg, why in cases:
        (err,) = svc.handle_disruption(encode(msg))
        assert err.topic == "fms/errors" and why in err.msg["message"], err.msg
    assert svc.state_seq == seq > before and len(svc.shop.scenario.breakdowns) == 1
    (err,) = svc.handle_disruption('{"schema": "fms/disruption/v1", "disruption_id": "y", "kind": "outage", '
                                   '"duration": 3}')
    assert err.msg["code"] == "bad_schema"
    paper = ShopService(inst, run_id="p")
    paper.start()
    (err,) = paper.handle_disruption(encode(make_disruption("z", "breakdown", 5, machine=1)))
    assert err.msg["code"] == "bad_disruption" and "decisions:=full" in err.msg["message"]


def test_a_plan_run_in_a_disrupted_shop_is_the_offline_disrupted_run():
    from fms_sim.disruptions import Breakdown, Outage, Scenario

    inst = builtin("ra02")
    sc = Scenario(breakdowns=(Breakdown(2, 20, 15),), outages=(Outage("tt", 0, 5, 30),), noise=0.15, seed=3)
    svc = ShopService(inst, run_id="r", decisions="full", history=True, idle_stops=True, features=False,
                      scenario=sc)
    agent = AgentLogic("plan:list", instance=inst)
    svc.start()
    while not svc.done:
        out = agent.on_state(encode(svc.state))
        assert not [o for o in out if o.topic == "fms/errors"], out
        (cmd,) = [o.msg for o in out if o.topic == "fms/command"]
        svc.handle_command(encode(cmd))
    live, offline = svc.final_schedule, solve(inst, "plan:list", scenario=sc)
    assert validate(inst, live) == [] and live.meta["scenario"] == sc.to_dict()
    assert live.to_dict()["operations"] == offline.to_dict()["operations"]


def test_a_plan_file_is_executed_live_exactly_as_fms_replay_does(tmp_path):
    from fms_sim.replay import replay

    inst = builtin("EX42")
    plan = solve(inst, "cpsat", time_limit=3)
    path = tmp_path / "plan.json"
    plan.save(path)
    svc, errors = drive(inst, f"plan:file:{path}")
    assert errors == []
    assert svc.final_schedule.to_dict()["operations"] == replay(inst, plan).to_dict()["operations"]
    with pytest.raises(UnavailableSolver, match="not valid for EX43"):
        make_decider(f"plan:file:{path}", instance=builtin("EX43"))
    with pytest.raises(UnavailableSolver, match="cannot read plan"):
        make_decider(f"plan:file:{tmp_path / 'none.json'}", instance=inst)


def test_a_plan_that_cannot_be_made_hands_over_to_the_fallback(monkeypatch):
    import fms_dispatch.solvers as solvers

    def broken(*a, **k):
        raise RuntimeError("cpsat found no feasible schedule")

    monkeypatch.setattr(solvers, "make_plan", broken)
    inst = builtin("EX12")
    svc, errors = drive(inst, "plan:cpsat:1")
    assert svc.done and validate(inst, svc.final_schedule) == []
    assert len(errors) == 1 and "could not plan" in errors[0]["message"]


def _sleep_long() -> None:
    time.sleep(60)


def test_a_replan_process_ends_at_sigterm_even_under_a_nodes_handler(monkeypatch):
    """rclpy's SIGTERM handler, inherited through the fork, kept a re-plan process alive when the node stopping
    terminated it: the node waited for it at exit and was reported as not stopping cleanly."""
    import signal

    from fms_dispatch import agent_logic

    _forking()
    monkeypatch.setattr(agent_logic, "REPLAN_IN_PROCESS", True)
    old = signal.signal(signal.SIGTERM, lambda *a: None)  # a node's handler: SIGTERM asks, it does not end
    try:
        job = agent_logic._ReplanJob(_sleep_long, (), "order", "r", 0, 0)
    finally:
        signal.signal(signal.SIGTERM, old)
    time.sleep(0.5)  # (the child has set its own handlers)
    job.cancel()
    assert job.done.wait(5) and job.process.exitcode == -signal.SIGTERM


def test_a_replan_process_ends_with_its_agent(tmp_path):
    """An agent killed (SIGKILL) during a re-plan left the forked search running to the end of its budget."""
    import signal
    import subprocess
    import sys

    _forking()
    code = ("import os, time, sys\n"
            "from fms_dispatch import agent_logic\n"
            "agent_logic.REPLAN_IN_PROCESS = True\n"
            "job = agent_logic._ReplanJob(time.sleep, (60,), 'order', 'r', 0, 0)\n"
            "print(job.process.pid, flush=True)\n"
            "time.sleep(60)\n")
    agent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert agent.stdout is not None
    child = int(agent.stdout.readline())
    agent.send_signal(signal.SIGKILL)
    agent.wait(10)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and os.path.exists(f"/proc/{child}"):
        with open(f"/proc/{child}/stat") as fh:
            if fh.read().split(")")[-1].split()[0] == "Z":  # ended, not yet reaped by init
                break
        time.sleep(0.1)
    else:
        assert not os.path.exists(f"/proc/{child}"), "the re-plan outlived its agent"
