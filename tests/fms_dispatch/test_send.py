"""``fms send``'s messages and its reading of the shop's answers, without ROS (the exchange with a running shop
node is in ``tests/ros/test_nodes.py``)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import pytest

from fms_dispatch import cli
from fms_dispatch.send import SendError, _add_arguments, answer, build, cmd_send
from fms_msgs_json import decode, encode, make_error, make_event
from fms_sim.benchmarks import builtin
from fms_sim.shop_service import ShopService


def args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    _add_arguments(p)
    return p.parse_args(list(argv))


def test_messages_are_built_and_checked(tmp_path: Path) -> None:
    kind, msg = build(args("order", "--jobs", '[[[1, null, 3], [2, 4]], [{"machine": 3, "duration": 1}]]',
                           "--id", "o1", "--run-id", "r"))
    assert kind == "order" and msg == {"schema": "fms/order/v1", "order_id": "o1", "run_id": "r", "jobs": [
        [{"machine": 1, "tool": None, "duration": 3}, {"machine": 2, "tool": None, "duration": 4}],
        [{"machine": 3, "tool": None, "duration": 1}]]}
    (tmp_path / "order.json").write_text(encode(msg))  # a whole order message in a file: its jobs, id and run (the
    kind, again = build(args("order", "--jobs", f"@{tmp_path / 'order.json'}"))  # id was replaced: a re-sent file
    assert again == msg                                                           # was a new order)
    kind, again = build(args("order", "--jobs", f"@{tmp_path / 'order.json'}", "--id", "o2", "--run-id", "r2"))
    assert (again["order_id"], again["run_id"], again["jobs"]) == ("o2", "r2", msg["jobs"])  # the options win
    (tmp_path / "jobs.json").write_text(json.dumps(msg["jobs"]))  # only jobs: a generated id, the current run
    kind, again = build(args("order", "--jobs", f"@{tmp_path / 'jobs.json'}"))
    assert again["jobs"] == msg["jobs"] and re.fullmatch(r"order-\d{8}T\d{6}-[0-9a-f]{6}", again["order_id"])
    assert "run_id" not in again
    kind, msg = build(args("breakdown", "--machine", "2", "--duration", "7", "--start", "40"))
    assert kind == "disruption" and (msg["kind"], msg["machine"], msg["duration"], msg["start"]) == (
        "breakdown", 2, 7, 40)
    kind, msg = build(args("outage", "--vehicle", "tt:1", "--duration", "5", "--id", "x"))
    assert (msg["kind"], msg["vehicle_kind"], msg["vehicle"], msg["disruption_id"]) == ("outage", "tt", 1, "x")
    assert "start" not in msg  # from now
    for argv, needle in (
        (("order", "--jobs", "[[1, 2"), "--jobs is not JSON"),
        (("order", "--jobs", f"@{tmp_path / 'missing.json'}"), "cannot read"),
        (("order", "--jobs", '[[{"machine": 0, "duration": 3}]]'), "'jobs[0][0].machine' must be an integer >= 1"),
        (("order", "--jobs", "[]"), "jobs"),
        (("outage", "--vehicle", "bus:1", "--duration", "3"), "--vehicle must be agv:V or tt:V"),
        (("outage", "--vehicle", "agv:-1", "--duration", "3"), "--vehicle must be agv:V or tt:V"),
        (("breakdown", "--machine", "1", "--duration", "0"), "duration"),
    ):
        with pytest.raises(SendError, match=re.escape(needle)):
            build(args(*argv))


def test_the_shops_answer_is_recognised() -> None:
    """An acceptance is the event naming the id; a refusal the error quoting (the start of) the text sent."""
    svc = ShopService(builtin("ra01"), run_id="r", decisions="full")
    svc.start()
    kind, msg = build(args("order", "--jobs", "[[[1, null, 3]]]", "--id", "o1"))
    text = encode(msg)
    out = svc.handle_order(text)
    (event,) = [decode(encode(o.msg)) for o in out if o.topic == "fms/events" and o.msg["kind"] == "order_accepted"]
    assert answer(kind, msg, text, "fms/events", event) == (
        True, f"order o1 accepted by run r at time 0: jobs {builtin('ra01').n_jobs}")
    (error,) = [o.msg for o in svc.handle_order(text) if o.topic == "fms/errors"]  # the same id again
    ok, line = answer(kind, msg, text, "fms/errors", error)
    assert not ok and line.startswith("refused by fms_shop: [bad_order]") and "o1" in line
    other = make_event("r", 99, 0, "order_accepted", {"order_id": "o2", "jobs": [11]})
    assert answer(kind, msg, text, "fms/events", other) is None
    assert answer(kind, msg, text, "fms/errors", make_error("fms_agent", "internal", "x", received="{}")) is None
    assert answer(kind, msg, text, "fms/errors", make_error("fms_agent", "internal", "x")) is None
    kind, msg = build(args("breakdown", "--machine", "2", "--duration", "7", "--id", "b1"))
    text = encode(msg)
    (event,) = [o.msg for o in svc.handle_disruption(text) if o.topic == "fms/events"
                and o.msg["kind"] == "disruption_accepted"]
    assert answer(kind, msg, text, "fms/events", event) == (
        True, "breakdown b1 (machine 2, from time 0 for 7) accepted by run r")
    kind, msg = build(args("outage", "--vehicle", "agv:0", "--duration", "4", "--id", "v0", "--start", "30"))
    text = encode(msg)
    (event,) = [o.msg for o in svc.handle_disruption(text) if o.topic == "fms/events"
                and o.msg["kind"] == "disruption_accepted"]
    assert answer(kind, msg, text, "fms/events", event)[1] == "outage v0 (agv 0, from time 30 for 4) accepted by run r"
    long_order = json.dumps(build(args("order", "--jobs", json.dumps([[[9, None, 3]] * 300])))[1])  # no machine 9
    assert len(long_order) > 1000  # a refusal quotes the first 1000 characters: still recognised
    ex12 = ShopService(builtin("EX12"), run_id="q")
    ex12.start()
    (error,) = [o.msg for o in ex12.handle_order(long_order) if o.topic == "fms/errors"]
    assert len(error["received"]) < len(long_order)
    assert answer("order", json.loads(long_order), long_order, "fms/errors", error)[0] is False


def test_bad_input_is_refused_before_anything_is_sent(monkeypatch, capsys) -> None:
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    with pytest.raises(SendError, match="give the shop's ROS domain"):
        cmd_send(args("breakdown", "--machine", "1", "--duration", "3"))
    with pytest.raises(SendError, match="--timeout must be a positive"):
        cmd_send(args("breakdown", "--machine", "1", "--duration", "3", "--timeout", "0", "--domain-id", "3"))
    with pytest.raises(SendError, match="--domain-id must be in 0..232"):
        cmd_send(args("breakdown", "--machine", "1", "--duration", "3", "--domain-id", "300"))
    # the environment's domain is checked as --domain-id is (abc: an RCLError traceback; 300: Fast DDS's colours on
    # stdout; -5: a wait for the whole --timeout)
    for env, msg in (("abc", "ROS_DOMAIN_ID must be an integer, got 'abc'"), ("300", "must be in 0..232, got 300"),
                     ("-5", "must be in 0..232, got -5")):
        monkeypatch.setenv("ROS_DOMAIN_ID", env)
        with pytest.raises(SendError, match=msg):
            cmd_send(args("breakdown", "--machine", "1", "--duration", "3"))
    monkeypatch.delenv("ROS_DOMAIN_ID")
    # message files: a duplicate key kept its last value, another schema was sent as an order, an object without
    # jobs read as the jobs, @ alone was "cannot read : Is a directory", a superscript two failed in int()
    for argv, msg in ((["order", "--jobs", '[[{"machine": 1, "machine": 2, "duration": 5}]]'],
                       "duplicate key 'machine' in an object"),
                      (["order", "--jobs", '{"schema": "fms/order/v2", "jobs": [[[1, null, 5]]]}'],
                       "holds a 'fms/order/v2' message, not an order"),
                      (["order", "--jobs", '{"order_id": "o1"}'], "holds an object without 'jobs'"),
                      (["order", "--jobs", "@"], "--jobs @ names no file"),
                      (["outage", "--vehicle", "agv:\u00b2", "--duration", "3"], "--vehicle must be agv:V or tt:V"),
                      (["outage", "--vehicle", "agv:\u0663", "--duration", "3"], "--vehicle must be agv:V or tt:V")):
        argv = [x.encode().decode("unicode_escape") if x.startswith("agv:") else x for x in argv]
        assert cli.main(["send", *argv, "--domain-id", "3"]) == 2
        assert msg in capsys.readouterr().err
    assert cli.main(["send", "order", "--jobs", "nope", "--domain-id", "3"]) == 2
    assert "fms: error: --jobs is not JSON" in capsys.readouterr().err
    for empty in ("", "  "):  # it was replaced by a generated id without a word
        assert cli.main(["send", "breakdown", "--machine", "1", "--duration", "3", "--id", empty,
                         "--domain-id", "3"]) == 2
        assert "fms: error: --id must be a non-empty name" in capsys.readouterr().err
    # a message file's empty order id, likewise (before any ROS work)
    assert cli.main(["send", "order", "--jobs", '{"order_id": "", "jobs": [[[1, null, 5]]]}', "--domain-id", "3"]) == 2
    assert "field 'order_id' must be a non-empty string, got ''" in capsys.readouterr().err
