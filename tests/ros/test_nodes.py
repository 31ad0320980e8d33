"""Multi-process tests with the real nodes: a full run via ``fms up``, live orders, agent and recorder crashes,
and every kind of bad input. Every schedule is validated and compared with the recorder's SQLite log."""

from __future__ import annotations

import json
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

import fms_msgs_json as m  # noqa: E402
from fms_msgs_json import encode  # noqa: E402
from fms_sim import Instance, Operation, validate  # noqa: E402
from fms_sim.benchmarks import builtin  # noqa: E402
from fms_sim.recorder_store import RecorderStore, gantt_path  # noqa: E402
from fms_sim.schedule import Schedule  # noqa: E402

from .conftest import RUN_S, STARTUP_S, NodeProcs, Observer, signal_group, wait_file  # noqa: E402

SHOP, AGENT, RECORDER = "fms_sim.shop_node", "fms_dispatch.agent_node", "fms_sim.recorder_node"


def check_log(db: Path, run_id: str, schedule: Schedule, instance: Instance) -> RecorderStore:
    """The SQLite log holds every event of the run exactly once and agrees with the schedule."""
    store = RecorderStore(db)
    seqs = store.event_seqs(run_id)
    end = store.end_seq(run_id)
    assert end is not None and seqs == list(range(end + 1))
    (rows,) = sqlite3.connect(db).execute("SELECT COUNT(*) FROM events WHERE run_id = ?", (run_id,)).fetchone()
    assert rows == end + 1
    assert store.is_complete(run_id)
    rebuilt, stored = store.schedule_from_events(run_id), store.schedule(run_id)
    for s in (rebuilt, stored):
        assert validate(instance, s) == []
        for key in ("makespan", "operations", "agv_trips", "tool_trips"):
            assert s.to_dict()[key] == schedule.to_dict()[key], key
    return store


def stored_seqs(db: Path, run_id: str) -> list[int]:
    """The event numbers in the database, read-only (the recorder may be writing)."""
    if not db.exists():
        return []
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        return [r[0] for r in con.execute("SELECT seq FROM events WHERE run_id = ? ORDER BY seq", (run_id,))]
    except sqlite3.OperationalError:  # the tables are not there yet
        return []
    finally:
        con.close()


def shop_seen(obs: Observer, run_id: str) -> dict[str, Any]:
    """Wait until the observer has the shop's state (discovery done) before timing-sensitive steps."""
    return obs.wait_for(lambda g: next((x for x in g["state"] if x["run_id"] == run_id), None), STARTUP_S,
                        f"a state of {run_id}")


def schedule_of(obs: Observer, run_id: str) -> Schedule:
    msg = obs.wait_for(lambda g: next((s for s in g["schedule"] if s["run_id"] == run_id), None), RUN_S,
                       f"the schedule of {run_id}")
    return Schedule.from_dict(msg["schedule"])


# ------------------------------------------------------------------------------------------------ fms up
def test_fms_up_runs_ex62_end_to_end(ros_env: dict[str, str], tmp_path: Path) -> None:
    out, db = tmp_path / "out" / "EX62.schedule.json", tmp_path / "out" / "fms.sqlite"
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX62", "--solver", "best", "--out", str(out),
                          "--db", str(db), "--run-id", "up-ex62", "--domain-id", ros_env["ROS_DOMAIN_ID"],
                          "--log-dir", str(tmp_path / "logs")],
                         env=ros_env, capture_output=True, text=True, timeout=120)
    wall = time.perf_counter() - t0
    assert res.returncode == 0, res.stderr + res.stdout
    # the shipped default model (guided-dagger) beats the best rule pair (123) and the list schedule (110) in
    # simulation, so best runs it over the topics, on the full net, and gets what the simulation got
    from fms_dispatch.up import best_solver

    inst = builtin("EX62")
    name, span, reason = best_solver(inst)
    assert name.startswith("ppo:guided") and span < 110 and reason in res.stderr
    assert "list schedule plan:list: 110" in reason
    lines = res.stdout.splitlines()
    assert re.match(rf"EX62: makespan {span} \({re.escape(name)} over ROS 2 topics, \d+ decisions, valid\)",
                    lines[0]), lines[0]
    png = gantt_path(db.parent, "up-ex62")
    assert lines[1:] == [f"schedule: {out}", f"sqlite:   {db} (run up-ex62)", f"gantt:    {png}"]
    sched = Schedule.load(out)
    assert validate(inst, sched) == [] and sched.makespan == span
    assert sched.meta["solver"] == name and sched.meta["decisions"] > 2 * inst.n_operations  # full-net decisions
    check_log(db, "up-ex62", sched, inst)
    assert png.read_bytes()[:4] == b"\x89PNG"
    for name in ("shop", "agent", "recorder"):                  # stopped cleanly, no tracebacks
        assert "Traceback" not in (tmp_path / "logs" / f"{name}.log").read_text()
    print(f"fms up EX62: {wall:.2f} s wall")


def test_fms_up_ppo_on_ra01(ros_env: dict[str, str], tmp_path: Path) -> None:
    from fms_dispatch.rl import ppo_solver

    from fms_dispatch.rl.guide import effort_from

    # the default search but no tabu search, whose time limit makes it not reproducible in general: the node's
    # run and the offline solver's must match decision for decision
    out, db = tmp_path / "ra01.json", tmp_path / "fms.sqlite"
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "ra01", "--solver", "ppo", "--guide-tabu", "0",
                          "--out", str(out), "--db", str(db), "--run-id", "up-ppo", "--domain-id",
                          ros_env["ROS_DOMAIN_ID"], "--log-dir", str(tmp_path / "logs")],
                         env=ros_env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr + res.stdout
    inst = builtin("ra01")
    ref = ppo_solver("ppo")(inst, guide_effort=effort_from(tabu=0))
    sched = Schedule.load(out)
    # the default model of a tool shop decides on the full net: fms up runs the shop on it
    assert validate(inst, sched) == [] and sched.meta["solver"] == "ppo:guided-dagger"
    assert sched.to_dict()["operations"] == ref.to_dict()["operations"] and sched.makespan == ref.makespan
    assert res.stdout.startswith(f"ra01: makespan {ref.makespan} (ppo:guided-dagger over ROS 2 topics")
    check_log(db, "up-ppo", sched, inst)
    for name in ("shop", "agent"):
        assert "Traceback" not in (tmp_path / "logs" / f"{name}.log").read_text()


def test_fms_up_passes_the_guide_search_to_the_agent(ros_env: dict[str, str], tmp_path: Path) -> None:
    """``--guide-restarts 0 --no-guide-rules --guide-tabu 0`` reaches the agent node: it acts out the plain list
    schedule, as the offline solver with that search does, not the default search's better plan."""
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import effort_from

    out, db = tmp_path / "EX62.json", tmp_path / "fms.sqlite"
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX62", "--solver", "ppo", "--guide-restarts",
                          "0", "--no-guide-rules", "--guide-tabu", "0", "--out", str(out), "--db", str(db),
                          "--run-id", "up-plain",
                          "--domain-id", ros_env["ROS_DOMAIN_ID"], "--log-dir", str(tmp_path / "logs")],
                         env=ros_env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr + res.stdout
    inst = builtin("EX62")
    plain = ppo_solver("ppo")(inst, guide_effort=effort_from(0, None, False, 0, 0))
    searched = ppo_solver("ppo")(inst)
    sched = Schedule.load(out)
    assert validate(inst, sched) == [] and sched.meta["solver"] == "ppo:guided-dagger"
    assert sched.makespan == plain.makespan > searched.makespan
    assert sched.to_dict()["operations"] == plain.to_dict()["operations"]
    bad = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX62", "--solver", "first", "--guide-restarts",
                          "3", "--out", str(tmp_path / "bad.json"), "--db", str(tmp_path / "bad.sqlite"),
                          "--domain-id", ros_env["ROS_DOMAIN_ID"]], env=ros_env, capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 2 and "applies to ppo solvers only" in bad.stderr


def test_fms_up_guided_agent_re_plans_at_a_breakdown(ros_env: dict[str, str], tmp_path: Path) -> None:
    """In a shop with a breakdown the default (guided) agent node re-plans its guide when the breakdown begins, as
    the offline solver does: by default the simulated shop, which keeps no clock, waits for the re-plan and the run
    is the offline one; with --no-replan-wait the re-plan runs beside the decisions (a forked process) and is the
    offline one's (the same trigger state), the run going on meanwhile. The re-plan is published and recorded;
    --no-guide-replan is refused for a solver that is not ppo."""
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import effort_from
    from fms_sim.disruptions import Scenario

    sc_file = tmp_path / "sc.json"
    sc_file.write_text(json.dumps({"schema": "fms/scenario/v1", "noise": 0.1, "seed": 5,
                                   "breakdowns": [{"machine": 2, "start": 20, "duration": 40}]}))
    inst = builtin("ra01")
    sc = Scenario.load(sc_file)
    ref = ppo_solver("ppo")(inst, scenario=sc, guide_effort=effort_from(tabu=0))
    (ev,) = ref.meta["replans"]
    for wait in (True, False):
        out, db, run = tmp_path / f"ra01-{wait}.json", tmp_path / f"fms-{wait}.sqlite", f"up-bd-{wait}"
        res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "ra01", "--solver", "ppo", "--guide-tabu", "0",
                              *([] if wait else ["--no-replan-wait"]), "--scenario", str(sc_file), "--out", str(out),
                              "--db", str(db), "--run-id", run, "--domain-id", ros_env["ROS_DOMAIN_ID"],
                              "--log-dir", str(tmp_path / "logs")],
                             env=ros_env, capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr + res.stdout
        sched = Schedule.load(out)
        assert validate(inst, sched, sc) == []
        rec, *later = RecorderStore(db).replans(run)
        assert (rec["reason"], rec["method"], rec["time"]) == ("breakdown", "guide", ev["time"])
        if not wait and rec["status"] == "timeout":  # a loaded machine: the run ended before the re-plan was back
            assert "the run ended" in rec["message"] and later == []
            continue
        assert rec["status"] == "adopted" and (rec["before"], rec["after"]) == (ev["before"], ev["after"])
        assert ("the shop waits for each re-plan" in res.stderr) is wait
        if wait:
            assert ", 1 re-plan (1 adopted), valid)" in res.stdout.splitlines()[0]  # counted from the recorder
            assert later == [] and sched.to_dict()["operations"] == ref.to_dict()["operations"]
    bad = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "ra01", "--solver", "first", "--no-guide-replan",
                          "--db", str(tmp_path / "bad.sqlite"), "--domain-id", ros_env["ROS_DOMAIN_ID"]],
                         env=ros_env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--[no-]guide-replan applies to ppo solvers only" in bad.stderr


def test_fms_up_ppo_lookahead_equals_the_offline_solver(ros_env: dict[str, str], tmp_path: Path) -> None:
    from fms_dispatch.rl import ppo_solver

    out, db = tmp_path / "EX12.json", tmp_path / "fms.sqlite"
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX12", "--solver", "ppo:bu+lookahead", "--out",
                          str(out), "--db", str(db), "--run-id", "up-look", "--domain-id", ros_env["ROS_DOMAIN_ID"],
                          "--log-dir", str(tmp_path / "logs")],
                         env=ros_env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr + res.stdout
    inst = builtin("EX12")
    ref = ppo_solver("ppo:bu")(inst, lookahead=True)
    plain = ppo_solver("ppo:bu")(inst)
    sched = Schedule.load(out)
    assert validate(inst, sched) == [] and sched.meta["solver"] == "ppo:bu+lookahead"
    assert sched.makespan == ref.makespan < plain.makespan      # pre-positioning pays off on EX12
    assert sched.to_dict()["agv_trips"] == ref.to_dict()["agv_trips"]
    check_log(db, "up-look", sched, inst)
    for name in ("shop", "agent"):
        assert "Traceback" not in (tmp_path / "logs" / f"{name}.log").read_text()


def test_fms_up_keeps_the_shop_to_a_clock(ros_env: dict[str, str], tmp_path: Path) -> None:
    """--time-scale: the shop publishes each state no earlier than its shop time × the scale from the start, so
    the run takes about makespan × scale on the wall clock; the decisions are the same as unpaced."""
    from fms_dispatch.rl import ppo_solver

    from fms_dispatch.rl.guide import effort_from

    scale = 0.04
    out = tmp_path / "EX12.json"
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX12", "--solver", "ppo", "--guide-tabu", "0",
                          "--time-scale", str(scale), "--out", str(out), "--db", str(tmp_path / "fms.sqlite"),
                          "--domain-id", ros_env["ROS_DOMAIN_ID"], "--log-dir", str(tmp_path / "logs")],
                         env=ros_env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr + res.stdout
    inst = builtin("EX12")
    sched = Schedule.load(out)
    ref = ppo_solver("ppo")(inst, guide_effort=effort_from(tabu=0))
    assert validate(inst, sched) == [] and sched.to_dict()["operations"] == ref.to_dict()["operations"]
    # from the first command (answering state 0, at time 0) to the end, the shop's clock ran at the scale, and
    # stood while the agent decided
    assert sched.makespan * scale <= sched.meta["decision_time"] <= sched.makespan * scale + 3.0, sched.meta
    assert f"{scale:g} s per time unit" in res.stderr
    assert f"{scale:g} s per time unit" in (tmp_path / "logs" / "shop.log").read_text()


def test_fms_up_bad_input_exits_2(ros_env: dict[str, str], tmp_path: Path) -> None:
    for args, needle in ((["EX12", "--solver", "cpsat"], "plans a whole schedule offline"),
                         (["EX12", "--solver", "ppo:nope"], "no model named 'nope'"),
                         (["NOPE"], "no built-in instance or file named 'NOPE'"),
                         (["EX12", "--time-scale", "-1"], "--time-scale must be a finite number >= 0")):
        res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", *args, "--db", str(tmp_path / "x.sqlite")],
                             env=ros_env, capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and res.stderr.startswith("fms up: error: ") and needle in res.stderr


# ------------------------------------------------------------------------------------------------ orders
def test_orders_join_a_running_shop(nodes: NodeProcs, observer: Observer, tmp_path: Path) -> None:
    db = tmp_path / "rec.sqlite"
    nodes.start("recorder", RECORDER, db=db)
    nodes.start("shop", SHOP, instance="EX12", run_id="orders")
    shop_seen(observer, "orders")
    nodes.start("agent", AGENT, solver="rule:SPT+least-work", delay_s=0.05)
    observer.wait_for(lambda g: any(s["seq"] >= 6 for s in g["state"]), STARTUP_S + RUN_S, "state 6")
    bad = [
        ({"schema": "fms/order/v1", "order_id": "b1", "jobs": [[{"machine": 7, "duration": 2}]]}, "bad_order"),
        ({"schema": "fms/order/v1", "order_id": "b2", "jobs": [[{"machine": 1, "duration": -3}]]}, "bad_schema"),
        ({"schema": "fms/order/v1", "order_id": "b3", "jobs": [[{"machine": 1, "tool": 1, "duration": 3}]]},
         "bad_order"),
        ({"schema": "fms/order/v1", "order_id": "b4", "run_id": "another-run",
          "jobs": [[{"machine": 1, "duration": 3}]]}, "unknown_run"),
    ]
    good = m.make_order("o-1", [[(2, None, 4), (3, None, 2)], [(1, None, 5)]], run_id="orders")
    for msg, _ in bad[:2]:
        observer.publish("order", msg)
    observer.publish("order", encode(good))
    for msg, _ in bad[2:]:
        observer.publish("order", msg)
    observer.publish("order", encode(good))                    # a duplicate: rejected, not added twice
    sched = schedule_of(observer, "orders")
    def order_errors(errs: list[dict[str, Any]]) -> list[dict[str, Any]]:
        # a command in flight when an order changed the state is answered stale_state: not an order error
        return [e for e in errs if e["source"] == "fms_shop" and '"fms/order/v1"' in (e.get("received") or "")]

    errors = observer.wait_for(lambda g: order_errors(g["error"]) if len(order_errors(g["error"])) >= 5 else None,
                               10, "5 order errors")
    assert sorted(e["code"] for e in errors) == sorted([c for _, c in bad] + ["bad_order"])
    assert any("already accepted" in e["message"] for e in errors)
    accepted = [e for e in observer.snapshot("event") if e["kind"] == "order_accepted"]
    assert [e["data"] for e in accepted][:1] == [{"order_id": "o-1", "jobs": [5, 6]}]
    inst = builtin("EX12")
    grown = Instance(inst.name, inst.jobs + ((Operation(2, None, 4), Operation(3, None, 2)), (Operation(1, None, 5),)),
                     agv_travel=inst.agv_travel, n_agvs=inst.n_agvs)
    assert validate(grown, sched) == [] and sched.meta["orders"] == {"o-1": [5, 6]}
    assert {(o.job, o.op) for o in sched.operations if o.job >= 5} == {(5, 0), (5, 1), (6, 0)}
    wait_file(gantt_path(tmp_path, "orders"), RUN_S, nodes)
    store = check_log(db, "orders", sched, grown)
    logged = [e["code"] for e in order_errors(store.errors("orders"))]
    assert sorted(logged) == sorted([c for _, c in bad] + ["bad_order"])
    assert "[bad_order]" in nodes.log("shop")                   # and in the node's own log


def test_order_published_before_the_shop_starts_is_not_lost(nodes: NodeProcs, observer: Observer) -> None:
    order = m.make_order("early-1", [[(3, None, 4), (1, None, 2)]], run_id="early")
    observer.publish_now("order", encode(order))                # nobody listens yet
    nodes.start("shop", SHOP, instance="EX12", run_id="early")
    observer.wait_for(lambda g: any(e["kind"] == "order_accepted" and e["run_id"] == "early" for e in g["event"]),
                      STARTUP_S, "the early order to be accepted")
    nodes.start("agent", AGENT, solver="rule:FIFO+first")
    sched = schedule_of(observer, "early")
    inst = builtin("EX12")
    grown = Instance(inst.name, inst.jobs + ((Operation(3, None, 4), Operation(1, None, 2)),),
                     agv_travel=inst.agv_travel, n_agvs=inst.n_agvs)
    assert sched.meta["orders"] == {"early-1": [5]} and validate(grown, sched) == []


# ------------------------------------------------------------------------------------------------ crashes
def test_agent_killed_and_restarted(nodes: NodeProcs, observer: Observer, tmp_path: Path) -> None:
    db = tmp_path / "rec.sqlite"
    nodes.start("recorder", RECORDER, db=db)
    nodes.start("shop", SHOP, instance="ra01", run_id="agent-crash")
    shop_seen(observer, "agent-crash")
    first = nodes.start("agent1", AGENT, solver="rule:MTWR+nearest", delay_s=0.1)
    observer.wait_for(lambda g: any(s["seq"] >= 5 for s in g["state"]), STARTUP_S + RUN_S, "state 5")
    nodes.kill(first)
    time.sleep(0.3)                                            # a command already on the wire may still land
    stuck = observer.latest_state()["seq"]
    time.sleep(0.7)
    assert observer.latest_state()["seq"] == stuck and not observer.latest_state()["done"]   # no agent, no progress
    nodes.start("agent2", AGENT, solver="rule:MTWR+nearest")   # gets the latched state and carries on
    sched = schedule_of(observer, "agent-crash")
    inst = builtin("ra01")
    assert validate(inst, sched) == []
    assert sched.meta["decisions"] == observer.latest_state()["seq"]
    wait_file(gantt_path(tmp_path, "agent-crash"), RUN_S, nodes)
    check_log(db, "agent-crash", sched, inst)


def test_agent_stopped_during_its_think_time_stops_cleanly(nodes: NodeProcs, observer: Observer) -> None:
    """The think time (delay_s) was one sleep in the state callback: a SIGTERM during it (rclpy handles it in C,
    no exception interrupts the sleep, as SIGINT's KeyboardInterrupt does) was taken for a stalled callback and
    ended by the stop watchdog 5 s later with the stacks in the log and exit code 1, not exit 0."""
    nodes.start("shop", SHOP, instance="EX12", run_id="think")
    shop_seen(observer, "think")
    agent = nodes.start("agent", AGENT, delay_s=60.0)
    deadline = time.monotonic() + STARTUP_S
    while "deciding with" not in nodes.log("agent") and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(4.0)                    # discovery, then the latched state 0 arrives: the agent thinks for 60 s
    assert observer.latest_state()["seq"] == 0       # (no command yet)
    t0 = time.monotonic()
    signal_group(agent.pid, signal.SIGTERM)
    code = nodes.stop(agent, grace=15.0, interrupt=False)
    assert code == 0 and time.monotonic() - t0 < 4.0, nodes.report({"agent": code})
    assert "Timeout" not in nodes.log("agent")


@pytest.mark.parametrize("delta", [False, True], ids=["whole", "delta"])
def test_ppo_agent_killed_and_restarted_replays_the_history(nodes: NodeProcs, observer: Observer,
                                                            delta: bool) -> None:
    from fms_dispatch.rl import ppo_solver

    nodes.start("shop", SHOP, instance="EX12", run_id="ppo-crash", history=True, history_delta=delta)
    shop_seen(observer, "ppo-crash")
    first = nodes.start("agent1", AGENT, solver="ppo:bu", instance="EX12", delay_s=0.1)
    observer.wait_for(lambda g: any(s["seq"] >= 8 for s in g["state"]), STARTUP_S + RUN_S, "state 8")
    nodes.kill(first)
    time.sleep(0.3)
    # a fresh twin from the latched history; with deltas the latched state has only the last one, so the agent asks
    # for that state again with the whole history
    nodes.start("agent2", AGENT, solver="ppo:bu", instance="EX12")
    sched = schedule_of(observer, "ppo-crash")
    inst = builtin("EX12")
    assert validate(inst, sched) == [] and sched.meta["solver"] == "ppo:bu"
    assert sched.makespan == ppo_solver("ppo:bu")(inst).makespan  # the restarted agent carries the same run on
    assert not [e for e in observer.snapshot("error") if e.get("run_id") == "ppo-crash" and e["code"] == "internal"]
    assert ("asking for it with the whole history" in nodes.log("agent2")) == delta, nodes.log("agent2")


def test_recorder_killed_and_restarted(nodes: NodeProcs, observer: Observer, tmp_path: Path) -> None:
    db = tmp_path / "rec.sqlite"
    first = nodes.start("recorder1", RECORDER, db=db)
    nodes.start("shop", SHOP, instance="EX12", run_id="rec-crash")
    shop_seen(observer, "rec-crash")
    nodes.start("agent", AGENT, solver="first", delay_s=0.08)
    deadline = time.monotonic() + STARTUP_S + RUN_S
    while len(stored_seqs(db, "rec-crash")) < 10:
        assert time.monotonic() < deadline, "the first recorder stored no events"
        time.sleep(0.05)
    nodes.kill(first)
    had = len(stored_seqs(db, "rec-crash"))
    seq = observer.latest_state()["seq"]
    observer.wait_for(lambda g: g["state"][-1]["seq"] >= seq + 4 or g["state"][-1]["done"], RUN_S, "progress")
    nodes.start("recorder2", RECORDER, db=db)
    sched = schedule_of(observer, "rec-crash")
    wait_file(gantt_path(tmp_path, "rec-crash"), RUN_S, nodes)
    inst = builtin("EX12")
    assert validate(inst, sched) == []
    store = check_log(db, "rec-crash", sched, inst)
    events = {e["seq"]: e for e in observer.snapshot("event") if e["run_id"] == "rec-crash"}
    stored = {e["seq"]: e for e in store.events("rec-crash")}
    # check_log proved the store complete (0..run_end, once each). The observer's event subscription is volatile,
    # so it may miss what the shop published before discovery matched it; every event it did see must be stored
    # with the same content, including everything after the first recorder died.
    assert len(stored) > had and set(events) <= set(stored) and max(events) == max(stored)
    assert all((e["time"], e["kind"], e["data"]) == (stored[s]["time"], stored[s]["kind"], stored[s]["data"])
               for s, e in events.items())
    assert "Traceback" not in nodes.log("recorder2")


# ------------------------------------------------------------------------------------------------ bad input
def test_bad_commands_are_rejected_and_the_shop_keeps_running(nodes: NodeProcs, observer: Observer) -> None:
    nodes.start("shop", SHOP, instance="EX12", run_id="bad")
    s0 = observer.wait_for(lambda g: g["state"][0] if g["state"] else None, STARTUP_S, "state 0")
    assert s0["seq"] == 0 and s0["features"]["jobs"]["n_ops"] == [3, 3, 3, 2, 2]

    def cmd(seq: int, action: str, run_id: str = "bad") -> dict[str, Any]:
        return {"schema": "fms/command/v1", "run_id": run_id, "state_seq": seq, "action": action}

    cases = [
        ("{this is not json", "malformed_json"),
        (json.dumps({**cmd(0, "job:0"), "schema": "fms/command/v9"}), "bad_schema"),
        (json.dumps({"schema": "fms/command/v1", "run_id": "bad", "action": "job:0"}), "bad_schema"),
        (json.dumps(cmd(0, "job:0", run_id="someone-else")), "unknown_run"),
        (json.dumps(cmd(3, "job:0")), "stale_state"),            # a state that was never published
        (json.dumps(cmd(0, "agv:1")), "forbidden_action"),       # masked now
        (json.dumps(cmd(0, "job:42")), "forbidden_action"),      # not an action at all
    ]
    for i, (text, code) in enumerate(cases):
        observer.publish("command", text)
        err = observer.wait_for(lambda g: g["error"][i] if len(g["error"]) > i else None, 10, f"error {i}")
        assert (err["code"], err["source"], err["received"]) == (code, "fms_shop", text)
    time.sleep(0.2)
    # nothing changed: state 0, published again with the refusal of the command for a state never published
    assert [s["seq"] for s in observer.snapshot("state")] == [0, 0]
    assert observer.snapshot("state")[1] == s0
    observer.publish("command", json.dumps(cmd(0, "job:1")))
    observer.wait_for(lambda g: g["state"][-1]["seq"] == 1, 10, "state 1")
    observer.publish("command", json.dumps(cmd(0, "job:2")))       # stale now
    err = observer.wait_for(lambda g: g["error"][len(cases)] if len(g["error"]) > len(cases) else None, 10, "stale")
    assert err["code"] == "stale_state" and "answers state 0 but the current state is 1" in err["message"]
    while True:                                                    # the observer finishes the run as agent
        st = observer.latest_state()
        if st["done"]:
            break
        label = next(a for a, ok in zip(st["actions"], st["mask"]) if ok)
        observer.publish("command", encode(m.make_command("bad", st["seq"], label)))
        observer.wait_for(lambda g, s=st["seq"]: g["state"][-1]["seq"] > s, 10, f"state after {st['seq']}")
    sched = schedule_of(observer, "bad")
    assert validate(builtin("EX12"), sched) == []
    log = nodes.log("shop")
    for code in ("malformed_json", "bad_schema", "unknown_run", "stale_state", "forbidden_action"):
        assert f"[{code}]" in log
    code = nodes.stop(nodes.procs[0][1])
    assert code == 0, nodes.report({"shop": code})


def test_node_startup_errors_exit_2(ros_env: dict[str, str]) -> None:
    for module, args, needle in (
        (AGENT, ["-p", "solver:=lookahead"], "fms-agent: error: solver 'lookahead' is not available without the "
                                             "shop's instance"),
        (SHOP, ["-p", "instance:=EX99"], "fms-shop: error: unknown built-in instance 'EX99'"),
        (SHOP, [], "fms-shop: error: parameter 'instance' is required"),
        (SHOP, ["-p", "instance:=EX12", "-p", "history_delta:=true"], "parameter 'history_delta' needs history:=true"),
        (SHOP, ["-p", "instance:=EX12", "-p", "time_scale:=-0.5"], "parameter 'time_scale': the time scale must be"),
        (RECORDER, ["-p", "retry_s:=0.0"], "fms-recorder: error: parameter 'retry_s' must be positive"),
        # an integer is a number: it reaches the range check (it was refused as "must be a number")
        (RECORDER, ["-p", "retry_s:=0"], "fms-recorder: error: parameter 'retry_s' must be positive"),
        (AGENT, ["-p", "resend_s:=abc"], "fms-agent: error: parameter 'resend_s' must be a finite number"),
        # NaN re-sent every 20 ms, inf crashed the agent at its first state (OverflowError)
        (AGENT, ["-p", "resend_s:=.nan"], "parameter 'resend_s' must be a finite number: got nan"),
        (AGENT, ["-p", "delay_s:=.inf"], "parameter 'delay_s' must be a finite number: got inf"),
        # refused for every solver (a plan: agent refused them, another started with them)
        (AGENT, ["-p", "replan:=-5.0"], "fms-agent: error: parameter 'replan' must be >= 0 (seconds per re-plan; 0: "
                                        "never), got -5"),
        (AGENT, ["-p", "drift:=-1.0"], "parameter 'drift' must be > 0 (a fraction of the plan's makespan), got -1"),
        # Python's generator seeds with abs(seed): seed:=-3 ran as seed:=3 (fms up --seed refuses it too)
        (AGENT, ["-p", "solver:=random", "-p", "seed:=-3"], "fms-agent: error: parameter 'seed' must be an integer "
                                                            ">= 0, got -3"),
        # the message named both parameters, not the one refused nor its value
        (AGENT, ["-p", "resend_s:=0.0"], "fms-agent: error: parameter 'resend_s' must be > 0 (seconds before a "
                                         "command is sent again), got 0"),
        (AGENT, ["-p", "delay_s:=-1.0"], "fms-agent: error: parameter 'delay_s' must be >= 0 (seconds of think "
                                         "time), got -1"),
        (RECORDER, ["-p", "commit_s:=.nan"], "parameter 'commit_s' must be a finite number: got nan"),
        # found at the end, or a traceback: a database folder that cannot be made, outputs inside a file
        (RECORDER, ["-p", "db:=/proc/fms-no-such/db.sqlite"], "its folder cannot be made"),
        (RECORDER, ["-p", "db:=''"], "parameter 'db' names no file (an empty name)"),
        (RECORDER, ["-p", "gantt_dir:=/proc/self/status"], "parameter 'gantt_dir' (/proc/self/status): "
                                                           "/proc/self/status is a file, not a folder"),
        (SHOP, ["-p", "instance:=EX12", "-p", "instance_out:=/proc/self/status/i.json"],
         "parameter 'instance_out' (/proc/self/status/i.json): /proc/self/status is a file, not a folder"),
        (SHOP, ["-p", "instance:=EX12", "-p", "noise_seed:=5"], "parameter 'noise_seed' seeds the noise"),  # ignored
        # the recorder's chart of the run failed (File name too long), as fms up --run-id refuses it
        (SHOP, ["-p", "instance:=EX12", "-p", "run_id:=" + "r" * 201], "fms-shop: error: parameter 'run_id' is too "
                                                                      "long to name the run's files (at most 200"),
        (SHOP, ["-p", "instance:=EX12", "-p", "agvs:=-2"], "got -2 (use no_agvs:=true to drop them)"),  # not a flag
        (SHOP, ["-p", "instance"], "fms-shop: error: bad ROS arguments"),  # malformed: rclpy's RCLError
        # a misspelt parameter is named where the one it was meant to be is missing
        (SHOP, ["-p", "instnace:=EX12"], "parameter 'instance' is required (a built-in name such as EX12, or a "
                                         "file): --ros-args -p instance:=EX12 (unknown parameters, ignored: instnace)"),
    ):
        res = subprocess.run([sys.executable, "-m", module, "--ros-args", *args], env=ros_env, capture_output=True,
                             text=True, timeout=60)
        assert res.returncode == 2 and needle in res.stderr and "Traceback" not in res.stderr, res.stderr
    # a parameter of the wrong type is the node's own, not an unknown one (it was listed as both)
    res = subprocess.run([sys.executable, "-m", SHOP, "--ros-args", "-p", "instance:=5"], env=ros_env,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "parameter 'instance' must be a string" in res.stderr, res.stderr
    assert "unknown parameters" not in res.stderr
    # a refused value stops the setup before later parameters are declared: those were named "unknown, ignored"
    for module, args in ((SHOP, ["instance:=EX12", "time_scale:=.nan", "history:=true"]),
                         (AGENT, ["instance:=EX12", "resend_s:=.inf"]), (RECORDER, ["db:=5", "retry_s:=2.0"])):
        res = subprocess.run([sys.executable, "-m", module, "--ros-args", *[x for a in args for x in ("-p", a)]],
                             env=ros_env, capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and "unknown parameters" not in res.stderr, res.stderr
    # --help describes the node and starts nothing (the recorder would create its database here)
    for module in (AGENT, SHOP, RECORDER):
        res = subprocess.run([sys.executable, "-m", module, "--help"], env=ros_env, capture_output=True, text=True,
                             timeout=60)
        assert res.returncode == 0 and res.stdout.startswith("usage: fms-") and "docs/ros.md" in res.stdout


def test_each_nodes_parameter_list_is_what_it_declares(ros_env, tmp_path: Path) -> None:
    # FmsNode.parameters tells a refused start which parameters are the node's own: it must name every parameter the
    # node declares, and no other
    code = (
        "import rclpy\n"
        "from fms_sim.shop_node import ShopNode\n"
        "from fms_dispatch.agent_node import AgentNode\n"
        "from fms_sim.recorder_node import RecorderNode\n"
        "import sys\n"
        "rclpy.init(args=['x', '--ros-args', '-p', 'instance:=EX12', '-p', 'gantt:=false', '-p', 'db:=' + sys.argv[1]])\n"
        "for cls in (ShopNode, AgentNode, RecorderNode):\n"
        "    obj = cls()\n"
        "    print(cls.__name__, sorted(cls.parameters) == obj.declared_parameters(), len(cls.parameters))\n"
        "    obj.close()\n"
        "    obj.node.destroy_node()\n"
        "rclpy.shutdown()\n")
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "p.sqlite")], env=ros_env, capture_output=True,
                         text=True, timeout=60, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["ShopNode", "True", "18", "AgentNode", "True", "21", "RecorderNode", "True", "5"], \
        res.stdout


def test_node_warns_of_unknown_parameters(nodes: NodeProcs) -> None:
    # ROS ignores a parameter the node does not declare: a misspelt one would run silently with its default
    proc = nodes.start("agent", AGENT, solvr="ppo", seed=3)
    deadline = time.monotonic() + STARTUP_S
    while "unknown parameters" not in nodes.log("agent") and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    log = nodes.log("agent")
    assert "deciding with first" in log, nodes.report({"agent": proc.poll()})  # the default solver runs
    warning = next(line for line in log.splitlines() if "unknown parameters" in line)
    assert "[WARN]" in warning and "ignored: solvr;" in warning
    params = warning.split("this node's parameters are ", 1)[1]
    assert "solver" in params and "seed" in params and "use_sim_time" not in params
    assert nodes.stop(proc) == 0


def test_topic_io_logs_a_message_it_cannot_send_and_sends_the_rest() -> None:
    # a message that cannot be encoded (here a lone surrogate) made publish raise inside the subscription
    # callback, which took the whole shop node down
    from fms_sim.shop_node import TopicIO

    class Pub:
        def __init__(self) -> None:
            self.sent: list[str] = []

        def publish(self, msg: Any) -> None:
            self.sent.append(msg.data)

    class Log:
        def __init__(self) -> None:
            self.errors: list[str] = []

        def error(self, text: str) -> None:
            self.errors.append(text)

    class Node:
        def __init__(self) -> None:
            self.log, self.pub = Log(), Pub()

        def create_publisher(self, *_: Any) -> Pub:
            return self.pub

        def get_logger(self) -> Log:
            return self.log

    node = Node()
    io = TopicIO(node, ["error"])
    bad = m.make_error("fms_shop", "bad_order", "order 'o\ud800' rejected")
    good = m.make_error("fms_shop", "bad_order", "order 'o1' rejected")
    io.publish([(m.TOPIC_ERRORS, bad), (m.TOPIC_ERRORS, good)])
    assert [json.loads(t)["message"] for t in node.pub.sent] == ["order 'o1' rejected"]
    assert any("cannot publish a fms/error/v1 message on fms/errors" in e and "lone surrogate" in e
               for e in node.log.errors)
    # an answer to an older state is a race, logged as a warning: fms up named it as the cause of a stalled run
    node.log.warnings = []
    node.log.warning = node.log.warnings.append
    node.log.errors.clear()
    io.publish([(m.TOPIC_ERRORS, m.make_error("fms_shop", "stale_state", "command answers state 31 but the current "
                                              "state is 32"))])
    assert node.log.errors == [] and node.log.warnings == [
        "[stale_state] command answers state 31 but the current state is 32"]


# ------------------------------------------------------------------------------------------------ fms send
def test_fms_send_to_a_run_that_does_not_answer_in_time_says_so(nodes: NodeProcs, observer: Observer,
                                                                 ros_env: dict[str, str]) -> None:
    """With --run-id and a shop of another run on the domain, a named run whose shop did not answer in time (paced:
    its acceptance waits for its next step) was reported as the other shop's refusal ("[unknown_run] ... this shop
    runs 'other'"), as if the named run were not there; now it says that the shop did not answer in time."""
    nodes.start("other", SHOP, instance="EX12", run_id="other")
    shop_seen(observer, "other")
    nodes.start("paced", SHOP, instance="EX12", run_id="paced", time_scale=50.0)
    shop_seen(observer, "paced")
    nodes.start("agent", AGENT, run_id="paced")
    quiet_since, last = time.monotonic(), -1
    deadline = time.monotonic() + STARTUP_S
    # until the agent has answered (its start and discovery take seconds under load) and the paced shop has stood
    # still for a while (50 s per time unit)
    while (last < 1 or time.monotonic() - quiet_since < 1.5) and time.monotonic() < deadline:
        seq = max((x["seq"] for x in observer.snapshot("state") if x["run_id"] == "paced"), default=-1)
        if seq != last:
            quiet_since, last = time.monotonic(), seq
        time.sleep(0.1)
    assert last >= 1, "the agent did not answer the paced shop"
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.send", "order", "--jobs", "[[[1, null, 3]]]",
                          "--run-id", "paced", "--timeout", "6"], env=ros_env, capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 1 and "but the shop did not answer within 6 s" in res.stderr, res.stderr
    assert "shops of other runs refused it" in res.stderr, res.stderr


def test_fms_send_stops_cleanly_on_sigterm(ros_env: dict[str, str]) -> None:
    # rclpy's signal handlers made a SIGTERM a 25-line ExternalShutdownException traceback, exit 1
    import signal

    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.send", "order", "--jobs", "[[[1, null, 5]]]",
                             "--timeout", "30"], env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(3)  # waiting for a shop that does not come
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err


def test_fms_send_delivers_orders_and_disruptions_and_prints_the_shops_answer(nodes: NodeProcs, observer: Observer,
                                                                             ros_env: dict[str, str]) -> None:
    """`fms send` (a separate process, as an operator runs it) waits for the shop, sends, and reports the shop's
    answer: the acceptance with the new job numbers (exit 0) or the shop's refusal (exit 1)."""
    inst = builtin("ra01")
    nodes.start("shop", SHOP, instance="ra01", run_id="send", decisions="full", history=True, idle_stops=True)
    shop_seen(observer, "send")
    nodes.start("agent", AGENT, solver="first", delay_s=0.3)  # slow (about 30 s): the run goes on while orders come

    def send(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "fms_dispatch.send", *args, "--timeout", str(STARTUP_S)],
                              env=ros_env, capture_output=True, text=True, timeout=STARTUP_S + 30)

    res = send("order", "--jobs", '[[[1, null, 3], {"machine": 2, "duration": 4}]]', "--id", "o1")
    assert res.returncode == 0, res.stderr
    assert re.fullmatch(rf"order o1 accepted by run send at time \d+: jobs {inst.n_jobs}\n", res.stdout), res.stdout
    res = send("order", "--jobs", "[[[1, null, 3]]]", "--id", "o1")  # an order id is accepted once
    assert res.returncode == 1 and "fms send: refused by fms_shop: [bad_order]" in res.stderr, res.stderr
    res = send("breakdown", "--machine", "2", "--duration", "7", "--id", "b1")
    assert res.returncode == 0 and re.fullmatch(r"breakdown b1 \(machine 2, from time \d+ for 7\) accepted by run "
                                                r"send\n", res.stdout), (res.stdout, res.stderr)
    res = send("outage", "--vehicle", f"agv:{inst.n_agvs}", "--duration", "3")  # no such AGV
    assert res.returncode == 1 and "[bad_disruption]" in res.stderr, res.stderr
    events = observer.snapshot("event")
    assert [e["data"]["jobs"] for e in events if e["kind"] == "order_accepted"] == [[inst.n_jobs]]
    assert [e["data"]["disruption_id"] for e in events if e["kind"] == "disruption_accepted"] == ["b1"]
    # a second shop on the domain: a message for "the current run" would be taken by both (two fms up runs did)
    nodes.start("shop2", SHOP, instance="EX12", run_id="other")
    shop_seen(observer, "other")
    # without --run-id: refused before sending where both shops are matched by then, else said if both take it; an
    # order taken by one run only (the other matched after fms send had gone) is no harm
    res = send("order", "--jobs", "[[[1, null, 3]]]", "--id", "o2")
    if res.returncode == 0:
        time.sleep(2)
        taken = [e["run_id"] for e in observer.snapshot("event") if e["kind"] == "order_accepted"
                 and e["data"]["order_id"] == "o2"]
        assert len(taken) == 1 and f"accepted by run {taken[0]}" in res.stdout, (taken, res.stdout)
    else:
        assert (res.returncode == 2 and "2 nodes listen on fms/orders" in res.stderr and "--run-id" in res.stderr) or (
            res.returncode == 1 and "was taken by 2 runs" in res.stderr), (res.returncode, res.stdout, res.stderr)
    res = send("order", "--jobs", "[[[1, null, 3]]]", "--id", "o3", "--run-id", "send")  # the other's refusal waits
    assert res.returncode == 0 and "accepted by run send" in res.stdout, res.stderr
