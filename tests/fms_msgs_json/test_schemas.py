"""Tests of fms_msgs_json: builders, strict encode/decode, every rejection path, and the docs' examples."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import fms_msgs_json as m
from fms_msgs_json import MessageError, decode, encode
from fms_sim.instance import Instance, Operation
from fms_sim.schedule import AgvTrip, OperationRecord, Schedule, ToolTrip
from fms_sim.validate import validate as validate_schedule

DOCS = Path(__file__).resolve().parents[2] / "docs" / "ros.md"


# ------------------------------------------------------------------------------------------------ fixtures
def tiny_instance() -> Instance:
    """One machine, two jobs of one operation each; job 0 needs tool 1."""
    return Instance(name="tiny", jobs=((Operation(1, 1, 3),), (Operation(1, None, 2),)),
                    agv_travel=((0, 2), (2, 0)), tool_travel=((0, 1), (1, 0)), n_agvs=1, n_tool_transporters=1)


def tiny_schedule() -> Schedule:
    """A hand-made valid schedule of ``tiny_instance`` with a loaded, an empty and a tool trip."""
    return Schedule(
        instance="tiny", makespan=8, n_agvs=1, n_tool_transporters=1,
        operations=[OperationRecord(0, 0, 1, 1, 2, 5), OperationRecord(1, 0, 1, None, 6, 8)],
        agv_trips=[AgvTrip(0, 0, 0, 0, 1, 0, 2, True), AgvTrip(0, None, None, 1, 0, 2, 4, False),
                   AgvTrip(0, 1, 0, 0, 1, 4, 6, True)],
        tool_trips=[ToolTrip(0, 1, 0, 0, 0, 1, 0, 1, True)],
        meta={"solver": "by hand"},
    )


def examples() -> dict[str, dict[str, Any]]:
    """One valid message per kind, made by the builders."""
    return {
        "state": m.make_state("run-1", 3, 2, {"parts": 1, "agv_idle": 0}, ["job:0", "agv:0"],
                              [True, False], False, instance="tiny"),
        "command": m.make_command("run-1", 3, "job:0", agent="spt"),
        "event": m.make_event("run-1", 7, 2, "agv_trip_end", agv=0, job=0, op=0, from_=0, to=1, loaded=True),
        "schedule": m.make_schedule("run-1", tiny_schedule()),
        "order": m.make_order("order-1", [[(1, None, 3), (2, 1, 4)], [{"machine": 2, "duration": 2}]],
                              run_id="run-1"),
        "error": m.make_error("fms_shop", "stale_state", "command answers state 2, current is 3", run_id="run-1",
                              received='{"x": 1}'),
        "replay_request": m.make_replay_request("*", 0, "fms_recorder"),
    }


def rejected(msg: Any, expect: Any = None) -> MessageError:
    """Encode ``msg`` without validation and return the MessageError that ``decode`` raises."""
    text = msg if isinstance(msg, str) else json.dumps(msg)
    with pytest.raises(MessageError) as info:
        decode(text, expect)
    assert "\n" not in str(info.value)
    return info.value


def changed(kind: str, /, **fields: Any) -> dict[str, Any]:
    msg = examples()[kind]
    msg.update(fields)
    return msg


# ------------------------------------------------------------------------------------------------ constants
def test_constants() -> None:
    assert m.SCHEMA_VERSION == 1
    assert (m.SCHEMA_STATE, m.SCHEMA_COMMAND, m.SCHEMA_EVENT, m.SCHEMA_SCHEDULE, m.SCHEMA_ORDER, m.SCHEMA_ERROR,
            m.SCHEMA_REPLAY_REQUEST) == ("fms/state/v1", "fms/command/v1", "fms/event/v1", "fms/schedule/v1",
                                         "fms/order/v1", "fms/error/v1", "fms/replay_request/v1")
    assert (m.TOPIC_STATE, m.TOPIC_COMMAND, m.TOPIC_EVENTS, m.TOPIC_SCHEDULE, m.TOPIC_ORDERS, m.TOPIC_ERRORS,
            m.TOPIC_REPLAY) == ("fms/state", "fms/command", "fms/events", "fms/schedule", "fms/orders",
                                "fms/errors", "fms/replay_request")
    assert set(m.TOPICS) == set(m.KINDS) == set(m.SCHEMAS)
    assert m.schema_id("order") == "fms/order/v1"
    with pytest.raises(ValueError, match="unknown message kind 'nope'"):
        m.schema_id("nope")
    assert issubclass(MessageError, ValueError)
    assert MessageError("internal", "x").code == "internal"
    with pytest.raises(ValueError, match="unknown error code"):
        MessageError("oops", "x")


def test_package_does_not_use_rclpy() -> None:
    for path in Path(m.__file__).parent.glob("*.py"):
        assert "import rclpy" not in path.read_text() and "from rclpy" not in path.read_text(), path.name


# ------------------------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("kind", sorted(examples()))
def test_round_trip_every_kind(kind: str) -> None:
    msg = examples()[kind]
    assert msg["schema"] == m.SCHEMAS[kind]
    text = encode(msg)
    assert text == json.dumps(msg, separators=(",", ":"), ensure_ascii=False)
    assert json.loads(text) == msg
    assert decode(text) == msg
    assert decode(text, expect=kind) == msg
    assert decode(text, expect=m.SCHEMAS[kind]) == msg
    assert decode(text, expect={kind, "error"}) == msg
    assert m.kind_of(msg) == kind
    assert m.validate(msg) == kind


def test_encode_is_compact_and_exact() -> None:
    text = encode(m.make_command("r", 0, "wait"))
    assert text == '{"schema":"fms/command/v1","run_id":"r","state_seq":0,"action":"wait"}'
    assert encode(m.make_replay_request("r", 4, "rec")) == \
        '{"schema":"fms/replay_request/v1","run_id":"r","from_seq":4,"requester":"rec"}'


def test_builders_fill_exact_fields() -> None:
    ex = examples()
    assert ex["state"] == {"schema": "fms/state/v1", "run_id": "run-1", "instance": "tiny", "seq": 3, "time": 2,
                           "marking": {"parts": 1, "agv_idle": 0}, "actions": ["job:0", "agv:0"],
                           "mask": [True, False], "done": False, "makespan": None}
    assert ex["event"]["data"] == {"agv": 0, "job": 0, "op": 0, "from": 0, "to": 1, "loaded": True}
    assert ex["order"]["jobs"] == [[{"machine": 1, "tool": None, "duration": 3},
                                    {"machine": 2, "tool": 1, "duration": 4}],
                                   [{"machine": 2, "duration": 2, "tool": None}]]
    assert "agent" not in m.make_command("r", 0, "a")
    assert "run_id" not in m.make_order("o", [[(1, 2)]])
    assert m.make_order("o", [[(1, 2)]])["jobs"] == [[{"machine": 1, "tool": None, "duration": 2}]]
    assert m.make_order("o", [[Operation(3, 2, 1)]])["jobs"] == [[{"machine": 3, "tool": 2, "duration": 1}]]
    assert m.make_event("r", 0, 0, "run_start", {"instance": "tiny"})["data"] == {"instance": "tiny"}
    assert m.make_event("r", 1, 9, "run_end", {"makespan": 1}, makespan=9)["data"] == {"makespan": 9}


def test_builders_accept_numpy_and_tuples() -> None:
    msg = m.make_state("r", np.int64(5), np.int32(7), {"p": np.int64(2)}, ("a", "b", "c"),
                       np.array([True, False, True]), np.bool_(True), makespan=np.int64(7))
    assert msg["seq"] == 5 and type(msg["seq"]) is int and type(msg["time"]) is int
    assert msg["mask"] == [True, False, True] and all(type(x) is bool for x in msg["mask"])
    assert msg["actions"] == ["a", "b", "c"] and msg["done"] is True and msg["makespan"] == 7
    assert decode(encode(msg)) == msg


def test_builders_validate_their_output() -> None:
    with pytest.raises(MessageError, match="field 'action' must be a non-empty string") as info:
        m.make_command("r", 0, 3)  # type: ignore[arg-type]
    assert info.value.code == "bad_schema" and info.value.field == "action"
    with pytest.raises(MessageError, match="'mask' has 1 entries but 'actions' has 2"):
        m.make_state("r", 0, 0, {}, ["a", "b"], [True], False)
    with pytest.raises(MessageError, match="field 'kind' must be one of"):
        m.make_event("r", 0, 0, "explosion")
    with pytest.raises(MessageError, match=r"field 'jobs\[0\]\[0\].machine' must be an integer >= 1"):
        m.make_order("o", [[(0, None, 1)]])
    with pytest.raises(MessageError, match="field 'code' must be one of"):
        m.make_error("node", "oops", "x")


def test_make_error_truncates_and_flattens() -> None:
    msg = m.make_error("n", "malformed_json", "line one\nline two", received="x" * 5000)
    assert msg["message"] == "line one line two"
    assert msg["received"] == "x" * m.RECEIVED_MAX_CHARS
    assert m.make_error("n", "internal", "m", received=b"\xffab")["received"] == "\ufffdab"
    assert decode(encode(msg), expect="error") == msg


def test_every_error_field_is_capped_for_a_5_mb_input() -> None:
    """An order with a 5 MB order_id once gave an error whose message was 5 MB (on the topic, in the log and in
    the database): the builders cap every field, so the encoded error stays under ERROR_MAX_BYTES."""
    huge = "\x01\"" * 2_500_000                                # 5 MB of characters JSON escapes (6 and 2 bytes)
    exc = MessageError("bad_order", f"order {huge!r} names machine 7, which this shop does not have")
    for msg in (m.make_error(huge, "bad_order", huge, run_id=huge, received=huge),
                m.error_reply(huge, exc, received=huge.encode(), run_id=huge)):
        for field, most in m.ERROR_MAX_CHARS.items():
            assert len(msg[field]) == most, field
        assert msg["message"].endswith("…") and msg["run_id"].endswith("…") and msg["source"].endswith("…")
        text = encode(msg)
        assert 6 * 1000 < len(text.encode()) <= m.ERROR_MAX_BYTES
        assert decode(text, expect="error") == msg
    assert m.error_reply("n", exc)["message"].startswith("order '\\x01\"\\x01")
    assert m.make_error("n", "internal", "x" * 500)["message"] == "x" * 500          # at the cap: kept whole
    assert m.bounded("abc", 2) == "a…" and m.bounded("ab", 2) == "ab"
    for field in m.ERROR_MAX_CHARS:      # the receiving side: longer fields are bad_schema, not stored whole
        too_long = {"schema": "fms/error/v1", "source": "n", "code": "internal", "message": "m",
                    field: "z" * (m.ERROR_MAX_CHARS[field] + 1)}
        with pytest.raises(MessageError, match=f"field '{field}' must be .* at most"):
            decode(json.dumps(too_long), expect="error")


def test_error_reply() -> None:
    text = '{"schema":"fms/state/v2"}'
    with pytest.raises(MessageError) as info:
        decode(text)
    reply = m.error_reply("fms_shop", info.value, received=text, run_id="r")
    assert reply["code"] == "bad_schema" and reply["received"] == text and reply["run_id"] == "r"
    assert reply["message"] == str(info.value)
    other = m.error_reply("fms_shop", KeyError("boom"))
    assert other["code"] == "internal" and other["message"] == "KeyError: 'boom'"


def test_unknown_extra_fields_are_kept() -> None:
    msg = changed("command", future_field={"nested": [1, 2]})
    assert decode(json.dumps(msg)) == msg
    assert "future_field" in decode(encode(msg))


def test_unknown_extra_fields_inside_a_schedule_message_are_allowed_too() -> None:
    # a schedule file refuses an unknown field by name (Schedule.from_dict); a message keeps the rule above
    msg = m.make_schedule("run-1", tiny_schedule())
    msg["schedule"]["future_field"] = 1
    msg["schedule"]["operations"][0]["label"] = "x"
    assert decode(json.dumps(msg)) == msg
    with pytest.raises(ValueError, match="unknown schedule field 'future_field'"):
        Schedule.from_dict(msg["schedule"])
    assert Schedule.from_dict(msg["schedule"], strict=False).to_dict() == tiny_schedule().to_dict()


def test_optional_fields_may_be_null_or_absent() -> None:
    state = changed("state", instance=None, makespan=None)
    assert decode(json.dumps(state)) == state
    del state["instance"], state["makespan"]
    assert decode(json.dumps(state)) == state
    for msg in (changed("command", agent=None), changed("order", run_id=None),
                changed("error", run_id=None, received=None)):
        assert decode(json.dumps(msg)) == msg


# ------------------------------------------------------------------------------------------------ rejections
@pytest.mark.parametrize("text", ["", "{", "{'schema': 1}", "[1,", "not json", '{"a": 1} trailing'])
def test_malformed_json(text: str) -> None:
    err = rejected(text)
    assert err.code == "malformed_json" and str(err).startswith("malformed JSON")


def test_malformed_json_nan_duplicates_and_non_str() -> None:
    assert rejected('{"schema":"fms/state/v1","time":NaN}').code == "malformed_json"
    err = rejected('{"schema":"fms/command/v1","schema":"fms/state/v1"}')
    assert err.code == "malformed_json" and "duplicate key 'schema'" in str(err)
    with pytest.raises(MessageError, match="expected the message text as a str, got bytes") as info:
        decode(b'{"schema":"fms/command/v1"}')  # type: ignore[arg-type]
    assert info.value.code == "malformed_json"
    # a number longer than Python converts was a plain ValueError ("Exceeds the limit (4300 digits)...")
    err = rejected('{"schema":"fms/command/v1","state_seq":1' + "0" * 5000 + "}")
    assert err.code == "malformed_json" and str(err) == "malformed JSON: a number has more than 4300 digits"
    # 1e400 became infinity in the message (the recorder stored it as Infinity, which is not JSON)
    err = rejected('{"schema":"fms/command/v1","x":1e400}')
    assert err.code == "malformed_json" and str(err) == "malformed JSON: the number 1e400 is too large"


@pytest.mark.parametrize("text", ["[]", "3", '"fms/state/v1"', "null", "true"])
def test_not_an_object(text: str) -> None:
    err = rejected(text)
    assert err.code == "bad_schema" and "a message must be a JSON object" in str(err)


@pytest.mark.parametrize("schema, needle", [
    (None, "must be a string like 'fms/state/v1', got null"),
    (1, "must be a string like 'fms/state/v1', got 1 (integer)"),
    ("state", "unknown schema 'state'"),
    ("fms/state", "unknown schema 'fms/state'"),
    ("fms/state/v1/extra", "unknown schema"),
    ("FMS/STATE/V1", "unknown schema"),
    ("fms/robot/v1", "unknown message kind 'robot'"),
    ("fms/state/v2", "unsupported schema version 'fms/state/v2'; this build reads 'fms/state/v1'"),
    ("fms/command/v0", "unsupported schema version 'fms/command/v0'"),
])
def test_bad_schema_field(schema: Any, needle: str) -> None:
    err = rejected(changed("state", schema=schema))
    assert err.code == "bad_schema" and err.field == "schema" and needle in str(err)


def test_missing_schema() -> None:
    msg = examples()["state"]
    del msg["schema"]
    err = rejected(msg)
    assert err.code == "bad_schema" and str(err) == "message has no 'schema' field (expected e.g. 'fms/state/v1')"
    with pytest.raises(MessageError, match="no 'schema' field"):
        m.kind_of(msg)
    with pytest.raises(MessageError, match="no 'schema' field"):
        encode(msg)


REQUIRED = {
    "state": ["run_id", "seq", "time", "marking", "actions", "mask", "done"],
    "command": ["run_id", "state_seq", "action"],
    "event": ["run_id", "seq", "time", "kind", "data"],
    "schedule": ["run_id", "schedule"],
    "order": ["order_id", "jobs"],
    "error": ["source", "code", "message"],
    "replay_request": ["run_id", "from_seq", "requester"],
}


@pytest.mark.parametrize("kind, key", [(k, f) for k, fs in REQUIRED.items() for f in fs])
def test_missing_required_field(kind: str, key: str) -> None:
    msg = examples()[kind]
    del msg[key]
    err = rejected(msg)
    assert err.code == "bad_schema" and err.field == key
    assert str(err).startswith(f"{m.SCHEMAS[kind]}: missing required field {key!r}")
    with pytest.raises(MessageError):
        encode(msg)


@pytest.mark.parametrize("kind, key, value, needle", [
    ("state", "run_id", "", "field 'run_id' must be a non-empty string, got '' (string)"),
    ("state", "run_id", 5, "field 'run_id' must be a non-empty string, got 5 (integer)"),
    ("state", "seq", -1, "field 'seq' must be an integer >= 0, got -1 (integer)"),
    ("state", "time", 2**63, "field 'time' must be an integer >= 0 of 64 bits (at most 9,223,372,036,854,775,807), "
                             "got 9223372036854775808 (integer)"),
    ("event", "data", {"jobs": [3, 2**64]}, "field 'data.jobs[1]' must be an integer >= 0 of 64 bits"),  # (an array's
    # fast path checked the type and the minimum only)
    ("state", "seq", 1.0, "field 'seq' must be an integer >= 0, got 1.0 (number)"),
    ("state", "seq", "1", "field 'seq' must be an integer >= 0, got '1' (string)"),
    ("state", "time", None, "field 'time' must be an integer >= 0, got null"),
    ("state", "marking", [1], "field 'marking' must be an object, got an array with 1 item"),
    ("state", "marking", {"p": -1}, "field 'marking.p' must be an integer >= 0, got -1"),
    ("state", "marking", {"p": True}, "field 'marking.p' must be an integer >= 0, got true (boolean)"),
    ("state", "actions", "wait", "field 'actions' must be an array, got 'wait' (string)"),
    ("state", "actions", [0, 1], "field 'actions[0]' must be a non-empty string (an action label), got 0"),
    ("state", "actions", ["a", "a"], "field actions[1] repeats 'a' (string); items must be unique"),
    ("state", "mask", [1, 0], "field 'mask[0]' must be a boolean, got 1 (integer)"),
    ("state", "done", 0, "field 'done' must be a boolean, got 0 (integer)"),
    ("state", "instance", 3, "field 'instance' must be null or a string, got 3"),
    ("state", "makespan", -2, "field 'makespan' must be null or an integer >= 0, got -2"),
    ("command", "action", 1, "field 'action' must be a non-empty string (an action label, not an index)"),
    ("command", "state_seq", "3", "field 'state_seq' must be an integer >= 0, got '3' (string)"),
    ("command", "agent", 1, "field 'agent' must be null or a string"),
    ("event", "time", -1, "field 'time' must be an integer >= 0"),
    ("event", "data", [], "field 'data' must be an object, got an array with 0 items"),
    ("event", "data", {"loaded": "yes"}, "field 'data.loaded' must be a boolean, got 'yes' (string)"),
    ("event", "data", {"machine": 0}, "field 'data.machine' must be an integer >= 1, got 0"),
    ("event", "data", {"job": True}, "field 'data.job' must be null or an integer >= 0, got true (boolean)"),
    ("event", "data", {"tool": 0}, "field 'data.tool' must be null or an integer >= 1, got 0"),
    ("event", "data", {"jobs": [0, "1"]}, "field 'data.jobs[1]' must be an integer >= 0, got '1'"),
    ("order", "order_id", "", "field 'order_id' must be a non-empty string"),
    ("order", "run_id", 1, "field 'run_id' must be null or a string"),
    ("error", "source", "", "field 'source' must be a non-empty string of at most 200 characters (the reporting "
                            "node's name)"),
    ("error", "message", "", "field 'message' must be a non-empty string"),
    ("error", "code", "oops", "field 'code' must be one of 'malformed_json', 'bad_schema'"),
    ("error", "received", "x" * 1001, "field 'received' must be null or a string of at most 1000 characters, "
                                      "got 1001 characters"),
    ("replay_request", "from_seq", -1, "field 'from_seq' must be an integer >= 0, got -1"),
    ("replay_request", "run_id", "", 'field \'run_id\' must be a non-empty string (a run id, or "*" for the'),
    ("replay_request", "requester", None, "field 'requester' must be a non-empty string, got null"),
])
def test_wrong_field(kind: str, key: str, value: Any, needle: str) -> None:
    msg = changed(kind, **{key: value})
    err = rejected(msg)
    assert err.code == "bad_schema"
    assert str(err).startswith(m.SCHEMAS[kind] + ": ")
    assert needle in str(err), str(err)
    assert err.field is not None and err.field.split(".")[0].split("[")[0] == key
    with pytest.raises(MessageError):
        encode(msg)


@pytest.mark.parametrize("kind, key", [("state", "seq"), ("state", "time"), ("command", "state_seq"),
                                       ("event", "seq"), ("event", "time"), ("replay_request", "from_seq")])
@pytest.mark.parametrize("value", [True, False])
def test_bool_is_not_an_int(kind: str, key: str, value: bool) -> None:
    err = rejected(changed(kind, **{key: value}))
    assert err.field == key and "got " + ("true" if value else "false") + " (boolean)" in str(err)


def test_mask_length_must_match_actions() -> None:
    err = rejected(changed("state", actions=["a", "b", "c"], mask=[True, False]))
    assert err.field == "mask"
    assert str(err) == ("fms/state/v1: field 'mask' has 2 entries but 'actions' has 3; "
                        "they must have the same length")


@pytest.mark.parametrize("kind", ["", "op_begin", "OP_START", None, 3])
def test_bad_event_kind(kind: Any) -> None:
    err = rejected(changed("event", kind=kind))
    assert err.field == "kind" and "must be one of 'op_start', 'op_end'" in str(err)


def test_every_event_kind_is_accepted() -> None:
    for i, kind in enumerate(m.EVENT_KINDS):
        msg = m.make_event("r", i, i, kind)
        assert decode(encode(msg), expect="event")["kind"] == kind
    assert len(m.EVENT_KINDS) == 10


@pytest.mark.parametrize("incarnation", ["", 7, None])
def test_a_run_starts_incarnation_is_a_non_empty_string(incarnation: Any) -> None:
    ok = m.make_event("r", 0, 0, "run_start", {"instance": "tiny", "incarnation": "3f2a9c01b4de"})
    assert decode(encode(ok), expect="event")["data"]["incarnation"] == "3f2a9c01b4de"
    err = rejected(dict(ok, data={"instance": "tiny", "incarnation": incarnation}))
    assert err.field == "data.incarnation" and "must be a non-empty string" in str(err)


@pytest.mark.parametrize("jobs, field, needle", [
    ([], "jobs", "must be a non-empty array, got an empty one"),
    ({"0": []}, "jobs", "must be a non-empty array, got an object"),
    ([[]], "jobs[0]", "must be a non-empty array, got an empty one"),
    ([[{"machine": 1, "duration": 1}], "op"], "jobs[1]", "must be a non-empty array, got 'op'"),
    ([[[1, None, 2]]], "jobs[0][0]", "must be an operation object {machine, tool, duration}, got an array"),
    ([[{"machine": 0, "duration": 1}]], "jobs[0][0].machine", "must be an integer >= 1, got 0"),
    ([[{"machine": True, "duration": 1}]], "jobs[0][0].machine", "must be an integer >= 1, got true"),
    ([[{"machine": 1, "tool": 0, "duration": 1}]], "jobs[0][0].tool", "must be null or an integer >= 1, got 0"),
    ([[{"machine": 1, "duration": -1}]], "jobs[0][0].duration", "must be an integer >= 0, got -1"),
    ([[{"machine": 1, "duration": 2.5}]], "jobs[0][0].duration", "must be an integer >= 0, got 2.5"),
    ([[{"machine": 1}]], "jobs[0][0].duration", "missing required field 'jobs[0][0].duration'"),
    ([[{"machine": 1, "duration": 1}], [{"duration": 1}]], "jobs[1][0].machine", "missing required field"),
])
def test_bad_order(jobs: Any, field: str, needle: str) -> None:
    err = rejected(changed("order", jobs=jobs))
    assert err.code == "bad_schema" and err.field == field and needle in str(err), str(err)


def test_expect_mismatch() -> None:
    text = encode(examples()["state"])
    err = rejected(text, expect="command")
    assert err.code == "bad_schema" and err.field == "schema"
    assert str(err) == "expected a fms/command/v1 message, got fms/state/v1"
    err = rejected(text, expect={"command", "fms/order/v1"})
    assert str(err) == "expected a fms/command/v1 or fms/order/v1 message, got fms/state/v1"
    # the kind mismatch is reported even when the fields are broken too
    assert "expected a fms/command/v1" in str(rejected(changed("state", seq=-1), expect="command"))
    with pytest.raises(ValueError, match="expect: unknown kind or schema 'fms/state/v2'"):
        decode(text, expect="fms/state/v2")
    with pytest.raises(ValueError, match="empty set"):
        decode(text, expect=set())


def test_kind_of() -> None:
    assert m.kind_of({"schema": "fms/replay_request/v1"}) == "replay_request"
    with pytest.raises(MessageError, match="unsupported schema version"):
        m.kind_of({"schema": "fms/order/v3"})
    with pytest.raises(MessageError, match="must be a JSON object"):
        m.kind_of("fms/state/v1")


def test_encode_rejects_invalid_and_unserialisable() -> None:
    with pytest.raises(MessageError, match="field 'seq'"):
        encode(changed("state", seq=True))
    with pytest.raises(MessageError, match="not JSON-serialisable") as info:
        encode(changed("command", extra=object()))
    assert info.value.code == "bad_schema"
    with pytest.raises(MessageError, match="not JSON-serialisable"):
        encode(changed("command", extra=float("nan")))



def test_encode_refuses_two_keys_that_json_writes_alike() -> None:
    """json.dumps writes the int key 1 as "1": {1: 'a', '1': 'b'} in an extra field became {"1":"a","1":"b"}, a
    message that decode itself refuses (with or without the check, a shop's publisher skips it)."""
    msg = changed("event", data={"agv": 0, "extra": {1: "a", "1": "b"}})
    for check in (True, False):
        with pytest.raises(MessageError, match=r"fms/event/v1: field 'data.extra' has the keys 1 and '1', which JSON "
                                               r"writes alike \('1'\)") as info:
            encode(msg, check=check)
        assert info.value.code == "bad_schema" and info.value.field == "data.extra"
    for a, b in ((True, "true"), (None, "null"), (1.5, "1.5")):  # (inside an array too)
        with pytest.raises(MessageError, match=f"field 'data.extra\\[1\\]' has the keys {a!r} and {b!r}"):
            encode(changed("event", data={"extra": [{}, {a: 1, b: 2}]}))
    msg = changed("command", **{"2": 0})  # the message itself
    msg[2] = 1
    with pytest.raises(MessageError, match="fms/command/v1: the message has the keys 2 and '2'") as info:
        encode(msg)
    assert info.value.field is None
    # keys that differ once written are kept, each once
    fine = changed("event", data={"extra": {7: "a", "2": "b", True: 0, None: 1, 1.5: 2}})
    assert json.loads(encode(fine))["data"]["extra"] == {"7": "a", "2": "b", "true": 0, "null": 1, "1.5": 2}


def test_a_value_nested_too_deeply_is_a_message_error_not_a_recursion_error() -> None:
    """An extra field nested 5,000 deep: encode (and a builder given it) raised a bare RecursionError."""
    deep: dict[str, Any] = {}
    inner = deep
    for _ in range(5000):
        inner["a"] = {}
        inner = inner["a"]
    for check in (True, False):
        with pytest.raises(MessageError, match="fms/command/v1: message is nested too deeply to be written as "
                                               "JSON") as info:
            encode(changed("command", extra=deep), check=check)
        assert info.value.code == "bad_schema"
    with pytest.raises(MessageError, match="nested too deeply to be sent as JSON") as info:
        m.make_event("run-1", 7, 2, "op_start", job=0, op=0, extra=deep)
    assert info.value.code == "bad_schema"
    with pytest.raises(MessageError, match="nested too deeply to be sent as JSON"):
        m.make_event("run-1", 7, 2, "op_start", {"extra": [deep]})


# ------------------------------------------------------------------------------------------------ schedule
def test_schedule_message_carries_a_real_schedule() -> None:
    inst, sched = tiny_instance(), tiny_schedule()
    assert validate_schedule(inst, sched) == []
    msg = decode(encode(m.make_schedule("run-1", sched)), expect="schedule")
    assert msg["schedule"] == sched.to_dict()
    back = Schedule.from_dict(msg["schedule"])
    assert back.to_dict() == sched.to_dict()
    assert validate_schedule(inst, back) == []
    assert m.make_schedule("run-1", sched.to_dict()) == m.make_schedule("run-1", sched)


@pytest.mark.parametrize("mutate, needle", [
    (lambda d: d.pop("operations"), "missing required field 'schedule.operations'"),
    (lambda d: d.pop("makespan"), "missing required field 'schedule.makespan'"),
    (lambda d: d.update(makespan="8"), "field 'schedule.makespan' must be an integer >= 0, got '8'"),
    (lambda d: d["operations"][0].update(start="2"), "field 'schedule.operations[0].start' must be an integer"),
    (lambda d: d["operations"][0].pop("machine"), "missing required field 'schedule.operations[0].machine'"),
    (lambda d: d["agv_trips"][1].pop("loaded"), "missing required field 'schedule.agv_trips[1].loaded'"),
    (lambda d: d["agv_trips"][0].update(loaded=1), "field 'schedule.agv_trips[0].loaded' must be a boolean"),
    (lambda d: d["tool_trips"][0].update(to=-1), "field 'schedule.tool_trips[0].to' must be an integer >= 0"),
    (lambda d: d.update(operations={}), "field 'schedule.operations' must be an array, got an object"),
    (lambda d: d.update(meta=[1]), "field 'schedule.meta' must be an object"),
])
def test_schedule_message_rejects_a_broken_schedule(mutate: Any, needle: str) -> None:
    msg = examples()["schedule"]
    mutate(msg["schedule"])
    err = rejected(msg)
    assert err.code == "bad_schema" and needle in str(err), str(err)
    assert err.field is not None and err.field.startswith("schedule")


@pytest.mark.parametrize("value", [None, [], "schedule"])
def test_schedule_message_needs_an_object(value: Any) -> None:
    err = rejected(changed("schedule", schedule=value))
    assert err.field == "schedule" and "field 'schedule' must be an object" in str(err)


# ------------------------------------------------------------------------------------------------ docs/ros.md
def doc_examples() -> list[str]:
    return re.findall(r"```json\n(.*?)```", DOCS.read_text(), flags=re.S)


def test_docs_examples_decode() -> None:
    blocks = doc_examples()
    kinds = [m.kind_of(decode(b)) for b in blocks]
    assert sorted(kinds) == sorted(m.KINDS), "docs/ros.md must show exactly one example per kind"


def test_docs_schedule_example_is_a_valid_schedule() -> None:
    inst = Instance(name="tiny", jobs=((Operation(1, None, 3),),), agv_travel=((0, 2), (2, 0)), n_agvs=1)
    (block,) = [b for b in doc_examples() if m.kind_of(json.loads(b)) == "schedule"]
    assert validate_schedule(inst, Schedule.from_dict(decode(block)["schedule"])) == []


def test_docs_list_every_topic_and_kind() -> None:
    text = DOCS.read_text()
    assert "## Topics" in text and "## Messages" in text
    for kind, topic in m.TOPICS.items():
        assert f"`{topic}`" in text and f"### {kind} — `{m.SCHEMAS[kind]}` on `{topic}`" in text
    for code in m.ERROR_CODES:
        assert f"`{code}`" in text
    for kind in m.EVENT_KINDS:
        assert f"`{kind}`" in text


# ------------------------------------------------------------------------------------------------ review fixes
@pytest.mark.parametrize("text", [
    '{"schema":"fms/order/v1","order_id":"o\\ud800","jobs":[[{"machine":1,"duration":3}]]}',
    '{"schema":"fms/command/v1","run_id":"r","state_seq":0,"action":"job:0","agent":"a\\udfff"}',
])
def test_a_lone_surrogate_is_malformed(text: str) -> None:
    # accepted, it made every answer quoting the id impossible to send as UTF-8, and the shop node died on it
    err = rejected(text)
    assert err.code == "malformed_json" and "lone surrogate (U+D" in str(err)


def test_a_surrogate_pair_is_one_character_and_fine() -> None:
    msg = decode('{"schema":"fms/order/v1","order_id":"o\\ud83d\\ude00","jobs":[[{"machine":1,"duration":3}]]}')
    assert msg["order_id"] == "o\U0001F600" and decode(encode(msg)) == msg


def test_encode_refuses_a_lone_surrogate() -> None:
    msg = m.make_command("run-1", 3, "job:0", agent="a\ud800")
    with pytest.raises(MessageError, match="lone surrogate") as info:
        encode(msg)
    assert info.value.code == "bad_schema"


def test_a_schema_id_is_compared_as_written() -> None:
    err = rejected(changed("command", schema="fms/command/v01"))
    assert err.code == "bad_schema" and "must be written 'fms/command/v1'" in str(err)


def test_disruption_optional_fields_may_be_null_but_not_contradict_the_kind() -> None:
    base = {"schema": "fms/disruption/v1", "disruption_id": "d", "duration": 5}
    ok = [dict(base, kind="breakdown", machine=2, vehicle_kind=None, vehicle=None, start=None),
          dict(base, kind="outage", vehicle_kind="agv", vehicle=0, machine=None)]
    for msg in ok:
        assert decode(json.dumps(msg)) == msg
    for msg, field in [(dict(base, kind="breakdown", machine=2, vehicle_kind="agv", vehicle=0), "vehicle_kind"),
                       (dict(base, kind="outage", vehicle_kind="agv", vehicle=0, machine=2), "machine"),
                       (dict(base, kind="breakdown", machine=None), "machine")]:
        err = rejected(msg)
        assert err.code == "bad_schema" and err.field == field


@pytest.mark.parametrize("budget, wall, needle", [
    (float("nan"), 0.1, "budget_s must be a finite number of seconds >= 0, got nan"),
    (float("inf"), 0.1, "budget_s must be"),
    (1.0, -0.5, "wall_s must be a finite number of seconds >= 0, got -0.5"),
    ("1", 0.1, "budget_s must be"),
])
def test_make_replan_refuses_times_that_are_not_seconds(budget: Any, wall: Any, needle: str) -> None:
    with pytest.raises(MessageError, match=re.escape(needle)) as info:
        m.make_replan("run-1", "agent", 3, 10, "order", "adopted", budget_s=budget, wall_s=wall, before=None,
                      after=20)
    assert info.value.code == "bad_schema"
    ok = m.make_replan("run-1", "agent", 3, 10, "order", "adopted", budget_s=np.float64(0.0002), wall_s=0,
                       before=None, after=20)
    assert ok["budget_ms"] == 1 and ok["wall_ms"] == 0
