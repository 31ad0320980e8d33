"""ShopService (the shop node's logic, no ROS): states, commands, events, orders, replays and every rejection."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from typing import Any

import pytest

import fms_msgs_json as m
from fms_msgs_json import MessageError, decode, encode
from fms_sim import Instance, Operation, validate
from fms_sim.benchmarks import builtin
from fms_sim.schedule import AgvTrip, OperationRecord, Schedule, ToolTrip
from fms_sim.shop import Shop
from fms_sim.shop_service import Outgoing, ShopService, new_run_id, shop_features

T3 = [[0, 2, 6], [5, 0, 3], [4, 7, 0]]
TT3 = [[0, 1, 2], [1, 0, 1], [2, 1, 0]]


def by_topic(out: list[Outgoing], topic: str) -> list[dict[str, Any]]:
    return [o.msg for o in out if o.topic == topic]


def state_of(out: list[Outgoing]) -> dict[str, Any]:
    (state,) = by_topic(out, m.TOPIC_STATE)
    return state


def first_label(state: dict[str, Any]) -> str:
    return next(a for a, ok in zip(state["actions"], state["mask"]) if ok)


def command(svc: ShopService, label: str | None = None, seq: int | None = None, run_id: str | None = None) -> str:
    assert svc.state is not None
    return encode(m.make_command(run_id or svc.run_id, svc.state_seq if seq is None else seq,
                                 label or first_label(svc.state), agent="test"))


def run_to_end(svc: ShopService) -> list[Outgoing]:
    out: list[Outgoing] = []
    while not svc.done:
        step = svc.handle_command(command(svc))
        assert not by_topic(step, m.TOPIC_ERRORS), step
        out += step
    return out


def rebuild(events: list[dict[str, Any]], instance: str, n_agvs: int, n_tts: int) -> Schedule:
    """A schedule from *_end events alone (the recorder's rule), to compare with the published one."""
    ops, agv, tt = [], [], []
    for e in events:
        d = e["data"]
        if e["kind"] == "op_end":
            ops.append(OperationRecord(d["job"], d["op"], d["machine"], d["tool"], d["start"], e["time"]))
        elif e["kind"] == "agv_trip_end":
            agv.append(AgvTrip(d["agv"], d["job"], d["op"], d["from"], d["to"], d["start"], e["time"], d["loaded"]))
        elif e["kind"] == "tool_trip_end":
            tt.append(ToolTrip(d["transporter"], d["tool"], d["job"], d["op"], d["from"], d["to"], d["start"],
                               e["time"], d["loaded"]))
    return Schedule(instance, max(o.end for o in ops), n_agvs, n_tts, ops, agv, tt)


# ------------------------------------------------------------------------------------------------ a full run
@pytest.mark.parametrize("name", ["EX12", "ra01", "ta01"])
def test_full_run_states_events_and_schedule(name: str) -> None:
    inst = builtin(name)
    svc = ShopService(inst, run_id="run-1")
    out = svc.start()
    events = by_topic(out, m.TOPIC_EVENTS)
    assert events[0] == {"schema": "fms/event/v1", "run_id": "run-1", "seq": 0, "time": 0, "kind": "run_start",
                         "data": {"instance": name, "incarnation": svc.incarnation, "machines": inst.n_machines},
                         "incarnation": svc.incarnation}
    # a shop started again with the same run id (a respawn with fixed parameters) starts another incarnation: its
    # events name it, so the recorder tells the two runs apart
    again = ShopService(inst, run_id="run-1")
    assert re.fullmatch("[0-9a-f]{12}", svc.incarnation) and again.incarnation != svc.incarnation
    assert decode(encode(events[0]))["data"]["incarnation"] == svc.incarnation
    s0 = state_of(out)
    assert (s0["seq"], s0["done"], s0["instance"], s0["makespan"]) == (0, False, name, None)
    assert s0["actions"] == Shop(inst).action_labels() and s0["mask"] == Shop(inst).action_mask()
    out += run_to_end(svc)
    states = by_topic(out, m.TOPIC_STATE)
    assert [s["seq"] for s in states] == list(range(len(states)))
    assert len(states) == svc.decisions + 1
    final = states[-1]
    assert final["done"] and final["makespan"] == svc.shop.makespan and not any(final["mask"])
    assert "features" not in final
    (smsg,) = by_topic(out, m.TOPIC_SCHEDULE)
    sched = Schedule.from_dict(decode(encode(smsg))["schedule"])
    assert validate(inst, sched) == []
    assert sched.makespan == final["makespan"]
    assert sched.meta["run_id"] == "run-1" and sched.meta["decisions"] == svc.decisions
    assert sched.meta["solver"] == "test" and sched.meta["orders"] == {}
    # events: numbered 0.., in time order, every end after its start, and they rebuild the schedule exactly
    events = by_topic(out, m.TOPIC_EVENTS)
    assert events == svc.events
    assert [e["seq"] for e in events] == list(range(len(events)))
    assert [e["time"] for e in events] == sorted(e["time"] for e in events)
    assert events[-1]["kind"] == "run_end" and events[-1]["data"] == {"makespan": sched.makespan}
    n_ops = sum(len(j) for j in inst.jobs)
    kinds = [e["kind"] for e in events]
    assert kinds.count("op_start") == kinds.count("op_end") == n_ops
    assert kinds.count("agv_trip_start") == kinds.count("agv_trip_end") == len(sched.agv_trips)
    assert kinds.count("tool_trip_start") == kinds.count("tool_trip_end") == len(sched.tool_trips)
    rebuilt = rebuild(events, name, sched.n_agvs, sched.n_tool_transporters)
    assert rebuilt.to_dict()["operations"] == sched.to_dict()["operations"]
    assert rebuilt.to_dict()["agv_trips"] == sched.to_dict()["agv_trips"]
    assert rebuilt.to_dict()["tool_trips"] == sched.to_dict()["tool_trips"]
    for e in events:
        decode(encode(e))


def test_events_are_published_when_the_clock_reaches_them() -> None:
    # one AGV, J0: M1(4). State 0 at t=0: choose job 0 then AGV 0: loaded trip [0,2], op [2,6]
    inst = Instance("agv", [[(1, 4)]], agv_travel=T3, n_agvs=1)
    svc = ShopService(inst, run_id="r")
    svc.start()
    out = svc.handle_command(command(svc, "job:0"))
    assert by_topic(out, m.TOPIC_EVENTS) == []          # nothing happened yet: the AGV decision is due at t=0
    assert state_of(out)["mask"] == [False, True]
    out = svc.handle_command(command(svc, "agv:0"))     # the run then completes: every event, in order
    kinds = [(e["time"], e["kind"]) for e in by_topic(out, m.TOPIC_EVENTS)]
    assert kinds == [(0, "agv_trip_start"), (2, "agv_trip_end"), (2, "op_start"), (6, "op_end"), (6, "run_end")]
    trip_end = by_topic(out, m.TOPIC_EVENTS)[1]
    assert trip_end["data"] == {"agv": 0, "job": 0, "op": 0, "from": 0, "to": 1, "loaded": True, "start": 0}


def test_zero_length_operation_ends_after_it_starts() -> None:
    inst = Instance("zero", [[(1, 0), (2, 3)], [(1, 2)]])
    svc = ShopService(inst, run_id="r")
    svc.start()
    run_to_end(svc)
    order = [(e["kind"], e["data"].get("job"), e["data"].get("op")) for e in svc.events]
    assert order.index(("op_start", 0, 0)) < order.index(("op_end", 0, 0))
    assert validate(inst, svc.final_schedule) == []


def test_features_match_the_shop() -> None:
    inst = Instance("both", [[(1, 1, 3), (2, None, 2)], [(2, 2, 4)]], agv_travel=T3, tool_travel=TT3, n_agvs=2,
                    n_tool_transporters=1)
    svc = ShopService(inst, run_id="r")
    f = state_of(svc.start())["features"]
    assert f["jobs"] == {"entry": [0, 1], "n_ops": [2, 1], "next_op": [0, 0], "next_duration": [3, 4],
                         "remaining_work": [5, 4], "total_work": [5, 4], "ready_since": [0, 0]}
    assert f["agvs"] == {"loc": [0, 0], "free_at": [0, 0], "work": [0, 0]}
    assert f["transporters"] == {"loc": [0], "free_at": [0], "work": [0]}
    assert f["agv_request"] is None and f["tt_request"] is None
    f = state_of(svc.handle_command(command(svc, "job:0")))["features"]
    assert f["jobs"]["next_op"] == [1, 0] and f["jobs"]["next_duration"] == [2, 4]
    assert f["jobs"]["remaining_work"] == [2, 4]
    assert f["agv_request"] == {"job": 0, "op": 0, "pickup": 0, "to": 1, "empty_travel": [0, 0]}
    # the shop itself agrees at every decision of a whole run
    svc = ShopService(builtin("ra01"), run_id="r")
    svc.start()
    while not svc.done:
        f, shop = svc.state["features"], svc.shop
        assert f == shop_features(shop)
        for j in range(shop.n_jobs):
            k = shop.next_op(j)
            ops = shop.instance.jobs[j]
            assert f["jobs"]["remaining_work"][j] == sum(o.duration for o in ops[k:])
            assert f["jobs"]["next_duration"][j] == (ops[k].duration if k < len(ops) else 0)
        if f["tt_request"] is not None:
            tool, tloc, *_ = shop.awaiting_transporter()
            assert (f["tt_request"]["tool"], f["tt_request"]["pickup"]) == (tool, tloc)
            assert f["tt_request"]["empty_travel"] == [shop.instance.tool_travel[loc][tloc] for loc in shop.tt_loc]
        svc.handle_command(command(svc))


def test_features_can_be_switched_off() -> None:
    svc = ShopService(builtin("EX12"), run_id="r", features=False)
    assert "features" not in state_of(svc.start())


def test_features_schema_is_strict() -> None:
    svc = ShopService(builtin("ra01"), run_id="r")
    state = state_of(svc.start())
    decode(encode(state))
    bad = json.loads(encode(state))
    bad["features"]["jobs"]["entry"].pop()
    with pytest.raises(MessageError, match="'features.jobs.n_ops' has 5 entries but 'features.jobs.entry' has 4"):
        decode(json.dumps(bad))
    bad = json.loads(encode(state))
    bad["features"]["agvs"]["work"] = [0, True]
    with pytest.raises(MessageError, match=r"features.agvs.work\[1\]"):
        decode(json.dumps(bad))
    bad = json.loads(encode(state))
    bad["features"]["agv_request"] = {"job": 0, "op": 0, "pickup": 0, "to": 1, "empty_travel": [0]}
    with pytest.raises(MessageError, match="agv_request.empty_travel' has 1 entries but there are 2 agvs"):
        decode(json.dumps(bad))
    bad = json.loads(encode(state))
    del bad["features"]["transporters"]
    with pytest.raises(MessageError, match="missing required field 'features.transporters'"):
        decode(json.dumps(bad))
    bad = json.loads(encode(state))
    bad["features"] = None                                   # optional: null is fine
    decode(json.dumps(bad))


# ------------------------------------------------------------------------------------------------ bad commands
def snapshot(svc: ShopService) -> tuple:
    return (svc.state_seq, svc.shop.now, svc.shop.net.marking(), len(svc.events), svc.decisions, svc.state)


@pytest.mark.parametrize("text, code, needle", [
    ("{not json", "malformed_json", "malformed JSON"),
    ('{"schema": "fms/command/v2", "run_id": "r", "state_seq": 0, "action": "job:0"}', "bad_schema",
     "unsupported schema version"),
    ('{"schema": "fms/state/v1", "run_id": "r"}', "bad_schema", "expected"),
    ('{"schema": "fms/command/v1", "run_id": "r", "state_seq": 0, "action": 0}', "bad_schema", "'action'"),
    ('{"schema": "fms/command/v1", "run_id": "r", "state_seq": -1, "action": "job:0"}', "bad_schema", "state_seq"),
    ('{"schema": "fms/command/v1", "run_id": "other", "state_seq": 0, "action": "job:0"}', "unknown_run",
     "names run 'other'"),
    ('{"schema": "fms/command/v1", "run_id": "r", "state_seq": 7, "action": "job:0"}', "stale_state",
     "state 7, which was never published"),
    ('{"schema": "fms/command/v1", "run_id": "r", "state_seq": 0, "action": "job:99"}', "forbidden_action",
     "'job:99' is not an action of state 0"),
    ('{"schema": "fms/command/v1", "run_id": "r", "state_seq": 0, "action": "agv:0"}', "forbidden_action",
     "'agv:0' is not enabled in state 0 (enabled: job:0, job:1, job:2, job:3, job:4)"),
])
def test_bad_command_is_answered_and_changes_nothing(text: str, code: str, needle: str) -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    before = snapshot(svc)
    out = svc.handle_command(text)
    (err,) = by_topic(out, m.TOPIC_ERRORS)
    # a command for a state never published gets the current state again too (an agent of the run before a restart
    # with the same run_id re-sent it for ever, ignoring state 0 as an old one)
    resent = by_topic(out, m.TOPIC_STATE) if "never published" in needle else []
    assert len(out) == 1 + len(resent) and resent in ([], [svc.state])
    assert err["code"] == code and needle in err["message"] and err["source"] == "fms_shop"
    assert err["run_id"] == "r" and err["received"] == text[:1000]
    decode(encode(err))
    assert snapshot(svc) == before
    out = svc.handle_command(command(svc))              # the shop keeps working
    assert state_of(out)["seq"] == 1


def test_stale_and_late_commands() -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    first = command(svc, "job:0")
    svc.handle_command(first)
    again = svc.handle_command(first)
    (err,) = by_topic(again, m.TOPIC_ERRORS)   # the same command again: stale
    assert err["code"] == "stale_state" and "answers state 0 but the current state is 1" in err["message"]
    # and the current state is published again: an agent that lost it re-sent its old command for ever
    assert by_topic(again, m.TOPIC_STATE) == [svc.state] and svc.state["seq"] == 1
    run_to_end(svc)
    (err,) = by_topic(svc.handle_command(command(svc, "job:0")), m.TOPIC_ERRORS)
    assert err["code"] == "stale_state" and "the run is complete" in err["message"]


# ------------------------------------------------------------------------------------------------ orders
def order(oid: str, jobs: list, run_id: str | None = None) -> str:
    return encode(m.make_order(oid, jobs, run_id=run_id))


def test_order_joins_the_running_net() -> None:
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="r")
    svc.start()
    for _ in range(5):
        svc.handle_command(command(svc))
    now, seq, n_actions = svc.shop.now, svc.state_seq, len(svc.state["actions"])
    out = svc.handle_order(order("o-1", [[(1, None, 3), (4, None, 2)], [(2, None, 5)]], run_id="r"))
    assert not by_topic(out, m.TOPIC_ERRORS)
    (ev,) = by_topic(out, m.TOPIC_EVENTS)
    assert ev["kind"] == "order_accepted" and ev["data"] == {"order_id": "o-1", "jobs": [5, 6]}
    assert ev["time"] == now
    st = state_of(out)
    assert st["seq"] == seq + 1 and len(st["actions"]) == n_actions + 2 and "job:6" in st["actions"]
    assert st["features"]["jobs"]["entry"][5:] == [5, 6] and st["features"]["jobs"]["ready_since"][5:] == [now, now]
    run_to_end(svc)
    sched = svc.final_schedule
    assert sched.meta["orders"] == {"o-1": [5, 6]}
    assert svc.instance.n_jobs == 7 and svc.instance.jobs[5] == (Operation(1, None, 3), Operation(4, None, 2))
    assert validate(svc.instance, sched) == []
    new_ops = {(o.job, o.op): o for o in sched.operations if o.job >= 5}
    assert set(new_ops) == {(5, 0), (5, 1), (6, 0)} and all(o.start >= now for o in new_ops.values())


@pytest.mark.parametrize("jobs, code, needle", [
    ([[{"machine": 9, "duration": 3}]], "bad_order", "machine 9 does not exist (1..4)"),
    ([[{"machine": 1, "tool": 2, "duration": 3}]], "bad_order", "tool 2 does not exist in this shop"),
    ([[{"machine": 1, "duration": -1}]], "bad_schema", "duration"),
    ([[{"machine": 1, "duration": 1.5}]], "bad_schema", "duration"),
    ([[{"machine": 0, "duration": 1}]], "bad_schema", "machine"),
    ([[]], "bad_schema", "non-empty"),
])
def test_invalid_orders_are_rejected_and_change_nothing(jobs: list, code: str, needle: str) -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    before = snapshot(svc)
    text = json.dumps({"schema": "fms/order/v1", "order_id": "bad", "jobs": jobs})
    (err,) = by_topic(svc.handle_order(text), m.TOPIC_ERRORS)
    assert err["code"] == code and needle in err["message"], err
    assert snapshot(svc) == before and svc.instance.n_jobs == 5 and svc.orders == {}


def test_duplicate_foreign_and_late_orders() -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    assert not by_topic(svc.handle_order(order("o", [[(1, None, 1)]])), m.TOPIC_ERRORS)
    (err,) = by_topic(svc.handle_order(order("o", [[(1, None, 1)]])), m.TOPIC_ERRORS)
    assert err["code"] == "bad_order" and "already accepted (jobs 5)" in err["message"]
    (err,) = by_topic(svc.handle_order(order("p", [[(1, None, 1)]], run_id="other")), m.TOPIC_ERRORS)
    assert err["code"] == "unknown_run"
    (err,) = by_topic(svc.handle_order("[1, 2]"), m.TOPIC_ERRORS)
    assert err["code"] == "bad_schema"
    run_to_end(svc)
    (err,) = by_topic(svc.handle_order(order("q", [[(1, None, 1)]])), m.TOPIC_ERRORS)
    assert err["code"] == "bad_order" and "after run 'r' completed" in err["message"]
    assert svc.instance.n_jobs == 6 and validate(svc.instance, svc.final_schedule) == []


def test_order_with_tools_in_a_tool_shop() -> None:
    svc = ShopService(builtin("ra01"), run_id="r")
    svc.start()
    svc.handle_command(command(svc))
    out = svc.handle_order(order("t", [[(2, 3, 4), (1, 1, 2)]]))
    assert not by_topic(out, m.TOPIC_ERRORS)
    run_to_end(svc)
    assert validate(svc.instance, svc.final_schedule) == []


def test_an_order_while_a_tool_user_is_being_chosen_is_offered_only_while_the_choice_is_open() -> None:
    # the new job's use: stayed offered after the choice closed; taking it crashed the shop and stuck the run
    svc = ShopService(builtin("ra01"), decisions="full", run_id="r")
    svc.start()

    def enabled() -> list[str]:
        return [a for a, ok in zip(svc.state["actions"], svc.state["mask"]) if ok]

    while not any(a.startswith("tool:") for a in enabled()):
        svc.handle_command(command(svc, enabled()[0]))
    tool = next(a for a in enabled() if a.startswith("tool:"))
    svc.handle_command(command(svc, tool))
    out = svc.handle_order(order("o1", [[(1, int(tool[5:]), 5)]]))
    assert not by_topic(out, m.TOPIC_ERRORS)
    new = svc.orders["o1"][0]
    assert f"use:{new}" in enabled()  # a candidate while the choice is open
    svc.handle_command(command(svc, next(a for a in enabled() if a.startswith("use:") and a != f"use:{new}")))
    assert f"use:{new}" not in enabled()  # the choice is made
    run_to_end(svc)
    assert validate(svc.instance, svc.final_schedule) == []


# ------------------------------------------------------------------------------------------------ replays
def test_replay_republishes_events_and_the_schedule() -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    for _ in range(6):
        svc.handle_command(command(svc))
    replay = svc.handle_replay(encode(m.make_replay_request("*", 3, "rec")))
    assert [o.msg for o in replay] == svc.events[3:] and all(o.topic == m.TOPIC_EVENTS for o in replay)
    assert svc.handle_replay(encode(m.make_replay_request("r", 10**6, "rec"))) == []
    (err,) = by_topic(svc.handle_replay(encode(m.make_replay_request("x", 0, "rec"))), m.TOPIC_ERRORS)
    assert err["code"] == "unknown_run"
    (err,) = by_topic(svc.handle_replay('{"schema": "fms/replay_request/v1"}'), m.TOPIC_ERRORS)
    assert err["code"] == "bad_schema"
    run_to_end(svc)
    replay = svc.handle_replay(encode(m.make_replay_request("r", 0, "rec")))
    assert [o.msg for o in replay[:-1]] == svc.events
    assert replay[-1].topic == m.TOPIC_SCHEDULE and replay[-1].msg["schedule"]["makespan"] == svc.shop.makespan


def test_start_twice_and_run_ids() -> None:
    svc = ShopService(builtin("EX12"))
    assert svc.run_id.startswith("EX12-") and len(svc.run_id) > 20
    assert new_run_id("a b/c") .startswith("a_b_c-") and new_run_id("x") != new_run_id("x")
    svc.start()
    with pytest.raises(RuntimeError, match="already started"):
        svc.start()


# ------------------------------------------------------------------------------------------------ architecture
def test_core_modules_do_not_import_rclpy() -> None:
    from pathlib import Path

    import fms_sim

    node_modules = {"shop_node.py", "recorder_node.py"}
    for path in Path(fms_sim.__file__).parent.glob("*.py"):
        text = path.read_text()
        if path.name not in node_modules:
            assert "import rclpy" not in text and "from rclpy" not in text, path.name


@pytest.mark.parametrize("module, prog", [("fms_sim.shop_node", "fms-shop"), ("fms_sim.recorder_node", "fms-recorder"),
                                          ("fms_dispatch.agent_node", "fms-agent")])
def test_nodes_without_rclpy_fail_clearly(module: str, prog: str) -> None:
    code = ("import sys\n"
            "class Block:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name.split('.')[0] in ('rclpy', 'std_msgs'):\n"
            "            raise ImportError(f'No module named {name!r}')\n"
            "sys.meta_path.insert(0, Block())\n"
            f"import {module} as mod\n"
            "sys.exit(mod.main(['x']))\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stderr
    assert res.stderr.startswith(f"{prog}: error: ROS 2 (rclpy) is not available")
    assert "pip install 'fms[ros]'" in res.stderr and "Traceback" not in res.stderr


# ------------------------------------------------------------------------------------------------ history
def test_history_is_off_by_default() -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    svc.handle_command(command(svc))
    assert "history" not in svc.state


def test_history_lists_applied_actions_and_orders_and_replays_to_the_same_state() -> None:
    inst = builtin("EX12")
    svc = ShopService(inst, run_id="r", history=True)
    assert state_of(svc.start())["history"] == {"actions": "", "orders": []}
    labels = []
    for _ in range(3):
        labels.append(first_label(svc.state))
        svc.handle_command(command(svc, labels[-1]))
    assert svc.state["history"] == {"actions": " ".join(labels), "orders": []}
    svc.handle_order(order("o-1", [[(1, None, 3), (4, None, 2)]]))
    for _ in range(2):
        labels.append(first_label(svc.state))
        svc.handle_command(command(svc, labels[-1]))
    hist = decode(encode(svc.state))["history"]
    assert hist["actions"] == " ".join(labels) == "job:0 agv:0 job:1 agv:1 job:2"
    assert hist["orders"] == [{"at": 3, "jobs": [[{"machine": 1, "tool": None, "duration": 3},
                                                  {"machine": 4, "tool": None, "duration": 2}]]}]
    # replaying the history on a fresh shop reaches the same state
    twin = Shop(inst)
    for i, label in enumerate(hist["actions"].split(" ")):
        if i == 3:
            twin.add_jobs([[Operation(1, None, 3), Operation(4, None, 2)]])
        twin.act(twin.action_index(label))
    assert (twin.now, twin.action_labels(), twin.action_mask(), twin.net.marking()) == (
        svc.shop.now, svc.state["actions"], svc.state["mask"], svc.state["marking"])
    run_to_end(svc)
    assert svc.state["done"] and "history" not in svc.state
    assert validate(svc.instance, svc.final_schedule) == []


def test_history_schema_is_strict() -> None:
    svc = ShopService(builtin("EX12"), run_id="r", history=True)
    svc.start()
    svc.handle_command(command(svc))
    state = json.loads(encode(svc.state))
    for hist, needle in (
        ({"actions": "job:0  agv:5", "orders": []}, "must separate action labels by single spaces"),
        ({"actions": "job:0 ", "orders": []}, "must separate action labels by single spaces"),
        ({"actions": " job:0", "orders": []}, "must separate action labels by single spaces"),
        ({"actions": "job:0", "orders": [{"at": 2, "jobs": [[{"machine": 1, "duration": 1}]]}]},
         "'history.orders[0].at' is 2 but must be between 0"),
        ({"actions": "job:0", "orders": [{"at": 0, "jobs": []}]}, "history.orders[0].jobs"),
        ({"actions": ["job:0"], "orders": []}, "history.actions"),
        ({"actions": ""}, "missing required field 'history.orders'"),
    ):
        with pytest.raises(MessageError) as info:
            decode(json.dumps(dict(state, history=hist)))
        assert needle in str(info.value), (hist, str(info.value))
    decode(json.dumps(dict(state, history=None)))           # optional: null is fine


def test_a_historys_disruptions_keep_the_rules_of_a_disruption_message() -> None:
    """A state's history took a breakdown without its machine (or an outage without its vehicle), which the
    fms/disruption/v1 message refuses: a twin replaying the history could not apply it. The entries are checked
    by the message's own rules now, naming where they stand; the disruptions a shop publishes still decode."""
    svc = ShopService(builtin("ra01"), run_id="r", history=True, decisions="full")
    svc.start()
    for msg in (m.make_disruption("b", "breakdown", 9, machine=2), m.make_disruption("o", "outage", 5,
                                                                                        vehicle_kind="agv", vehicle=0)):
        assert not by_topic(svc.handle_disruption(encode(msg)), m.TOPIC_ERRORS)
    state = decode(encode(svc.state))
    entries = state["history"]["disruptions"]
    assert [e["disruption"]["kind"] for e in entries] == ["breakdown", "outage"]
    where = "history.disruptions[1].disruption"
    for i, change, needle in (
            (0, {"machine": None}, "a breakdown needs field 'history.disruptions[0].disruption.machine' (1..)"),
            (0, {"vehicle_kind": "agv", "vehicle": 0}, "a breakdown names a machine, not field "
                                                        "'history.disruptions[0].disruption.vehicle_kind'"),
            (1, {"vehicle": None}, f"an outage needs fields '{where}.vehicle_kind' (agv or tt) and '{where}.vehicle'"),
            (1, {"machine": 3}, f"an outage names a vehicle, not field '{where}.machine'"),
            (1, {"kind": "fire"}, f"field '{where}.kind' must be one of 'breakdown', 'outage'"),
            (1, {"duration": 0}, f"field '{where}.duration' must be an integer >= 1")):
        bad = json.loads(json.dumps(state))
        bad["history"]["disruptions"][i]["disruption"].update(change)
        with pytest.raises(MessageError) as info:
            decode(json.dumps(bad))
        assert info.value.code == "bad_schema" and needle in str(info.value), (change, str(info.value))
        assert info.value.field is not None and info.value.field.startswith(f"history.disruptions[{i}].disruption.")


def test_history_deltas_add_up_to_the_whole_history_and_stay_small() -> None:
    """A ``history_delta`` shop sends, in each state, what was applied since the state that the last command
    answered; the deltas, read in order, are the whole history a shop without deltas sends, and the state's size
    stays flat instead of growing with the run. A replay request ``what: "state"`` gets the current state again
    with the whole history (and no events)."""
    from fms_msgs_json import make_disruption

    inst = builtin("ra01")
    whole = ShopService(inst, run_id="r", history=True, decisions="full")
    delta = ShopService(inst, run_id="r", history=True, decisions="full", history_delta=True)
    for svc in (whole, delta):
        svc.start()
    labels: list[str] = []
    orders: list[dict[str, Any]] = []
    disruptions: list[dict[str, Any]] = []
    sizes = []
    step = 0
    while not whole.done:
        if step in (10, 25):  # an order supersedes a state before it was answered: the next delta covers both
            for svc in (whole, delta):
                svc.handle_order(order(f"o{step}", [[(1, None, 3), (2, None, 4)]]))
        if step == 40:
            for svc in (whole, delta):
                assert not by_topic(svc.handle_disruption(encode(make_disruption("b", "breakdown", 9, machine=2))),
                                    m.TOPIC_ERRORS)
        h = decode(encode(delta.state))["history"]
        assert (h["actions_from"], h["orders_from"], h["disruptions_from"]) == (
            len(labels), len(orders), len(disruptions)), step
        labels += h["actions"].split(" ") if h["actions"] else []
        orders += h["orders"]
        disruptions += h.get("disruptions", [])
        full = whole.state["history"]
        assert " ".join(labels) == full["actions"] and orders == full["orders"], step
        assert disruptions == full.get("disruptions", []), step
        sizes.append((len(json.dumps(full)), len(json.dumps(delta.state["history"]))))
        if step == 30:
            (again,) = delta.handle_replay(encode(m.make_replay_request("*", 0, "agent", what="state")))
            assert again.topic == m.TOPIC_STATE and again.msg["seq"] == delta.state_seq
            assert {k: again.msg["history"][k] for k in ("actions", "orders")} == {"actions": full["actions"],
                                                                                  "orders": full["orders"]}
            assert again.msg["history"]["actions_from"] == 0 and delta.state["history"] == h  # the state sent stays
        label = first_label(whole.state)
        for svc in (whole, delta):
            assert not by_topic(svc.handle_command(command(svc, label)), m.TOPIC_ERRORS)
        step += 1
    assert len(orders) == 2 and len(disruptions) == 1
    assert delta.final_schedule.to_dict() == whole.final_schedule.to_dict() | {"meta": delta.final_schedule.meta}
    # the whole history grows with the run (965 bytes at the end here, 120 KB on sl70); a delta is a label or two,
    # or an order's jobs (at most 245 bytes here)
    assert sizes[-1][0] > 900 and max(d for _, d in sizes) < 250
    (final,) = delta.handle_replay(encode(m.make_replay_request("*", 0, "agent", what="state")))
    assert final.msg["done"] and "history" not in final.msg
    with pytest.raises(ValueError, match="history_delta needs history"):
        ShopService(inst, history_delta=True)


def test_replay_request_what_is_checked() -> None:
    assert m.make_replay_request("*", 0, "a", what="state")["what"] == "state"
    assert "what" not in m.make_replay_request("*", 0, "a")
    with pytest.raises(MessageError, match="what"):
        m.make_replay_request("*", 0, "a", what="history")
    with pytest.raises(MessageError, match="actions_from"):
        decode(json.dumps({"schema": "fms/state/v1", "run_id": "r", "seq": 1, "time": 0, "marking": {},
                           "actions": [], "mask": [], "done": False,
                           "history": {"actions": "", "orders": [], "actions_from": -1}}))
    # a delta's orders come after its first action
    with pytest.raises(MessageError, match=r"'history.orders\[0\].at' is 2 but must be between 3"):
        decode(json.dumps({"schema": "fms/state/v1", "run_id": "r", "seq": 1, "time": 0, "marking": {},
                           "actions": [], "mask": [], "done": False,
                           "history": {"actions": "job:0", "actions_from": 3,
                                       "orders": [{"at": 2, "jobs": [[{"machine": 1, "duration": 1}]]}]}}))


# ------------------------------------------------------------------------------------------------ idle stops
def answer(svc: ShopService) -> str:
    """``wait`` at an idle stop, else the first enabled action."""
    return command(svc, "wait") if svc.state["idle"] else command(svc)


def test_idle_stops_are_off_by_default() -> None:
    svc = ShopService(builtin("ra01"), run_id="r")
    svc.start()
    run_to_end(svc)
    assert "idle" not in svc.state and svc.idle_answers == 0 and "idle_answers" not in svc.final_schedule.meta


def test_idle_stops_offer_idle_vehicles_and_waiting_changes_nothing() -> None:
    inst = builtin("ra01")
    plain = ShopService(inst, run_id="a")
    plain.start()
    run_to_end(plain)
    svc = ShopService(inst, run_id="b", history=True, idle_stops=True)
    assert state_of(svc.start())["idle"] == []                   # state 0 is a decision
    seen = set()
    while not svc.done:
        st = decode(encode(svc.state))                           # every state passes the schema
        if st["idle"]:
            assert not any(st["mask"])
            seen |= {d["kind"] for d in st["idle"]}
            idle_now = {("agv", v, loc) for v, loc in svc.shop.idle_agvs()} | {
                ("tt", r, loc) for r, loc in svc.shop.idle_transporters()}
            assert {(d["kind"], d["vehicle"], d["location"]) for d in st["idle"]} <= idle_now
        out = svc.handle_command(answer(svc))
        assert not by_topic(out, m.TOPIC_ERRORS)
    assert seen == {"agv", "tt"} and svc.idle_answers > 0
    assert svc.decisions == plain.decisions
    assert svc.final_schedule.meta["idle_answers"] == svc.idle_answers
    for key in ("operations", "agv_trips", "tool_trips"):
        assert svc.final_schedule.to_dict()[key] == plain.final_schedule.to_dict()[key]


def _to_idle_stop(svc: ShopService) -> None:
    while not svc.state["idle"]:
        svc.handle_command(command(svc))


def test_reposition_command_moves_the_vehicle_and_is_in_the_history() -> None:
    inst = builtin("ra01")
    svc = ShopService(inst, run_id="r", history=True, idle_stops=True)
    svc.start()
    _to_idle_stop(svc)
    v = svc.state["idle"][0]
    dest = (v["location"] + 1) % (inst.n_machines + 1)
    label = f"reposition:{v['kind']}:{v['vehicle']}:{dest}"
    now = svc.shop.now
    out = svc.handle_command(command(svc, label))
    assert not by_topic(out, m.TOPIC_ERRORS)
    assert svc.state["history"]["actions"].split(" ")[-1] == label
    while not svc.done:
        svc.handle_command(answer(svc))
    trips = svc.final_schedule.agv_trips if v["kind"] == "agv" else svc.final_schedule.tool_trips
    vehicle = (lambda t: t.agv) if v["kind"] == "agv" else (lambda t: t.transporter)
    assert any(vehicle(t) == v["vehicle"] and t.start == now and t.to == dest and not t.loaded for t in trips)
    assert validate(inst, svc.final_schedule) == []


@pytest.mark.parametrize("label, needle", [
    ("job:0", "state {seq} is an idle stop: malformed idle answer 'job:0'"),
    ("reposition:agv:7:1", "AGV 7 is not an idle vehicle offered"),
    ("reposition:agv:0:99", "location 99 does not exist"),
    ("reposition:tt:0", "malformed"),
    ("reposition:agv:0:1 ", "plain digits"),  # applied, it broke every later state's history (not encodable)
    ("reposition:agv:0: 1", "plain digits"),
])
def test_bad_answers_to_an_idle_stop_change_nothing(label: str, needle: str) -> None:
    svc = ShopService(builtin("ra01"), run_id="r", idle_stops=True, history=True)
    svc.start()
    _to_idle_stop(svc)
    if "agv:0:99" in label:
        v = svc.state["idle"][0]
        label = f"reposition:{v['kind']}:{v['vehicle']}:99"
    before = snapshot(svc)
    (err,) = by_topic(svc.handle_command(command(svc, label)), m.TOPIC_ERRORS)
    assert err["code"] == "forbidden_action" and needle.format(seq=svc.state_seq) in err["message"]
    assert snapshot(svc) == before and svc.idle_answers == 0
    assert not by_topic(svc.handle_command(command(svc, "wait")), m.TOPIC_ERRORS)
    m.decode(m.encode(svc.state), expect="state")  # the history stays well-formed


def test_idle_answers_at_a_decision_are_refused() -> None:
    svc = ShopService(builtin("ra01"), run_id="r", idle_stops=True)
    svc.start()
    before = snapshot(svc)
    for label in ("wait", "reposition:agv:0:1"):
        (err,) = by_topic(svc.handle_command(command(svc, label)), m.TOPIC_ERRORS)
        assert err["code"] == "forbidden_action" and f"{label!r} is not an action of state 0" in err["message"]
    assert snapshot(svc) == before


def test_idle_schema_is_strict() -> None:
    svc = ShopService(builtin("ra01"), run_id="r", idle_stops=True)
    svc.start()
    _to_idle_stop(svc)
    st = json.loads(encode(svc.state))
    for bad, needle in ((dict(st, idle=[{"kind": "car", "vehicle": 0, "location": 0}]), "kind"),
                        (dict(st, idle=[{"kind": "agv", "vehicle": -1, "location": 0}]), "vehicle"),
                        (dict(st, mask=[True] + st["mask"][1:]), "either a decision or an idle stop")):
        with pytest.raises(MessageError, match=needle):
            decode(json.dumps(bad))


def test_full_net_states_name_their_net_and_idle_stops_offer_no_action() -> None:
    import random

    from fms_msgs_json import make_command

    inst = builtin("ra01")
    paper = ShopService(inst, run_id="p")
    paper.start()
    assert paper.state["decisions"] == "paper"
    svc = ShopService(inst, run_id="f", decisions="full", idle_stops=True, history=True)
    svc.start()
    rng = random.Random(2)
    idle_seen = 0
    while not svc.done:
        st = svc.state
        assert st["decisions"] == "full"
        if st["idle"]:
            idle_seen += 1
            assert not any(st["mask"])
            label = "wait"
        else:
            label = rng.choice([a for a, ok in zip(st["actions"], st["mask"]) if ok])
        out = svc.handle_command(encode(make_command("f", st["seq"], label)))
        assert not [o for o in out if o.topic == "fms/errors"]
    assert idle_seen and validate(svc.instance, svc.final_schedule) == []
    assert {"start:0", "tool:1", "use:0", "hold"} <= set(svc.state["actions"])


@pytest.mark.parametrize("live", [False, True])
def test_an_operation_lengthened_by_a_breakdown_ends_once_at_its_new_end(live: bool) -> None:
    """The end event of an operation was queued when it started: a breakdown of its machine while it ran
    lengthened the operation in the schedule, but its op_end was still published at the old end, so the schedule
    rebuilt from the events (as the recorder rebuilds it) differed from the shop's."""
    from fms_sim.disruptions import Breakdown, Scenario

    inst = builtin("ra01")
    nominal = ShopService(inst, run_id="n", decisions="full")
    nominal.start()
    run_to_end(nominal)
    first = min((o for o in nominal.final_schedule.operations if o.end - o.start >= 2), key=lambda o: o.start)
    bd = Breakdown(first.machine, first.start + 1, 40)  # while it runs (the decisions before are the same)
    svc = ShopService(inst, run_id="r", decisions="full", scenario=None if live else Scenario(breakdowns=(bd,)))
    out = svc.start()
    while not svc.done:
        if live and svc.shop.now >= bd.start and not svc.shop.scenario:
            out += svc.handle_disruption(encode(m.make_disruption("d", "breakdown", bd.duration, machine=bd.machine,
                                                                  run_id="r")))
        out += svc.handle_command(command(svc))
    (smsg,) = by_topic(out, m.TOPIC_SCHEDULE)
    sched = Schedule.from_dict(smsg["schedule"])
    assert validate(inst, sched) == []
    events = by_topic(out, m.TOPIC_EVENTS)
    assert [e["seq"] for e in events] == list(range(len(events)))
    assert [e["time"] for e in events] == sorted(e["time"] for e in events)
    (hit,) = [o for o in sched.operations if (o.job, o.op) == (first.job, first.op)]
    assert (hit.start, hit.end) == (first.start, first.end + bd.duration)  # lengthened
    rebuilt = rebuild(events, inst.name, sched.n_agvs, sched.n_tool_transporters)
    assert sorted(map(repr, rebuilt.operations)) == sorted(map(repr, sched.operations))
    assert [e["kind"] for e in events].count("op_end") == inst.n_operations
