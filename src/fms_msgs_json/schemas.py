"""The versioned message kinds, their field tables, and strict ``encode``/``decode``.

Every message is one JSON object carried in the ``data`` of a ``std_msgs/String``; its ``"schema"`` field
names its kind and version, ``"fms/<kind>/v<version>"``. This module knows nothing of ROS: it works on ``str``
and ``dict`` so that every rule can be tested without rclpy.

Rules shared by all kinds:

* ``decode`` is strict about the fields it knows: required keys present, exact JSON types (``true`` is not an
  integer, ``1.0`` is not an integer), ranges, enumerations; it rejects unknown kinds and other versions.
* Keys it does not know are allowed and kept (forward compatibility: a newer sender may add fields; an older
  receiver ignores them). A newer *version* of a kind is a different schema id and is rejected.
* An optional field may be absent; ``null`` only where its table (docs/ros.md) says "or null".

Failures raise :class:`MessageError` whose ``code`` is one of :data:`ERROR_CODES` (``"malformed_json"`` for text
that is not JSON, ``"bad_schema"`` for everything else found here) and whose message is one line naming the
field, so a node can answer with an ``fms/error/v1`` message directly.
"""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Iterable
from typing import Any, Callable, NamedTuple

from fms_sim.files import DuplicateKeyError, unique_pairs
from fms_sim.schedule import Schedule, ScheduleError

from .fields import (
    Bool, Field, FieldError, Int, ListOf, MapOf, Nullable, Obj, OneOf, Str, check_object, join_path, show,
)

__all__ = [
    "SCHEMA_VERSION", "KINDS", "SCHEMAS", "schema_id",
    "SCHEMA_STATE", "SCHEMA_COMMAND", "SCHEMA_EVENT", "SCHEMA_SCHEDULE", "SCHEMA_ORDER", "SCHEMA_ERROR",
    "SCHEMA_REPLAY_REQUEST", "SCHEMA_DISRUPTION", "SCHEMA_REPLAN", "DISRUPTION_KINDS", "REPLAN_REASONS",
    "REPLAN_STATUSES",
    "TOPIC_STATE", "TOPIC_COMMAND", "TOPIC_EVENTS", "TOPIC_SCHEDULE", "TOPIC_ORDERS", "TOPIC_ERRORS",
    "TOPIC_REPLAY", "TOPIC_DISRUPTIONS", "TOPIC_REPLANS", "TOPICS",
    "EVENT_KINDS", "ERROR_CODES", "RECEIVED_MAX_CHARS", "ERROR_MAX_CHARS", "ERROR_MAX_BYTES", "bounded",
    "TOPIC_QOS", "TopicQos", "REPLAY_WHATS",
    "FEATURE_JOB_COLUMNS", "FEATURE_VEHICLE_COLUMNS",
    "MessageError", "validate", "kind_of", "encode", "decode",
]

SCHEMA_VERSION = 1
"""The one version of every kind this build reads and writes."""

KINDS: tuple[str, ...] = ("state", "command", "event", "schedule", "order", "error", "replay_request",
                          "disruption", "replan")


def schema_id(kind: str) -> str:
    """The schema id of ``kind`` at the current version, e.g. ``schema_id("state") == "fms/state/v1"``."""
    if kind not in KINDS:
        raise ValueError(f"unknown message kind {kind!r}; known kinds: {', '.join(KINDS)}")
    return f"fms/{kind}/v{SCHEMA_VERSION}"


SCHEMAS: dict[str, str] = {k: schema_id(k) for k in KINDS}
"""Kind name → schema id."""

SCHEMA_STATE = SCHEMAS["state"]
SCHEMA_COMMAND = SCHEMAS["command"]
SCHEMA_EVENT = SCHEMAS["event"]
SCHEMA_SCHEDULE = SCHEMAS["schedule"]
SCHEMA_ORDER = SCHEMAS["order"]
SCHEMA_ERROR = SCHEMAS["error"]
SCHEMA_REPLAY_REQUEST = SCHEMAS["replay_request"]
SCHEMA_DISRUPTION = SCHEMAS["disruption"]
SCHEMA_REPLAN = SCHEMAS["replan"]

TOPIC_STATE = "fms/state"
TOPIC_COMMAND = "fms/command"
TOPIC_EVENTS = "fms/events"
TOPIC_SCHEDULE = "fms/schedule"
TOPIC_ORDERS = "fms/orders"
TOPIC_ERRORS = "fms/errors"
TOPIC_REPLAY = "fms/replay_request"
TOPIC_DISRUPTIONS = "fms/disruptions"
TOPIC_REPLANS = "fms/replans"

TOPICS: dict[str, str] = {
    "state": TOPIC_STATE, "command": TOPIC_COMMAND, "event": TOPIC_EVENTS, "schedule": TOPIC_SCHEDULE,
    "order": TOPIC_ORDERS, "error": TOPIC_ERRORS, "replay_request": TOPIC_REPLAY,
    "disruption": TOPIC_DISRUPTIONS, "replan": TOPIC_REPLANS,
}
"""Kind name → the topic that carries it."""


class TopicQos(NamedTuple):
    """The quality of service every node uses on one topic, as plain data (the nodes turn it into an rclpy
    ``QoSProfile``; this package stays free of ROS). All topics are reliable and keep the last ``depth``
    messages; ``latched`` means TRANSIENT_LOCAL durability: a subscriber that joins late still receives the
    last ``depth`` messages (a restarted agent gets the current state)."""

    depth: int
    latched: bool


TOPIC_QOS: dict[str, TopicQos] = {
    "state": TopicQos(1, True),          # only the newest state matters; a late or restarted agent gets it
    "command": TopicQos(100, False),
    "event": TopicQos(10000, False),     # bursts (replays); losses are repaired by replay requests
    "schedule": TopicQos(1, True),       # a late or restarted recorder still gets the final schedule
    "order": TopicQos(100, True),        # an order sent before the shop subscribes is still delivered
                                         # (order ids are accepted once, so re-delivery adds nothing)
    "error": TopicQos(100, False),
    "replay_request": TopicQos(10, False),
    "disruption": TopicQos(100, True),   # like orders: delivered to a shop that subscribes late, accepted once
    "replan": TopicQos(100, True),       # a late or restarted recorder still gets a run's re-plans
}
"""Kind name → the QoS of its topic (see docs/ros.md, "Quality of service")."""

EVENT_KINDS: tuple[str, ...] = (
    "op_start", "op_end", "agv_trip_start", "agv_trip_end", "tool_trip_start", "tool_trip_end",
    "order_accepted", "run_start", "run_end", "disruption_accepted",
)

ERROR_CODES: tuple[str, ...] = (
    "malformed_json", "bad_schema", "stale_state", "unknown_run", "forbidden_action", "bad_order", "internal",
    "bad_disruption", "run_conflict",
)

RECEIVED_MAX_CHARS = 1000
"""An error message quotes at most this many characters of the offending text."""

ERROR_MAX_CHARS: dict[str, int] = {"source": 200, "message": 500, "run_id": 200, "received": RECEIVED_MAX_CHARS}
"""The most characters each string field of an ``fms/error/v1`` may have: :func:`make_error` cuts longer ones
(marking the cut with ``…``), :func:`decode` rejects them (``bad_schema``)."""

ERROR_MAX_BYTES = 12 * 1024
"""Bound on an encoded ``fms/error/v1`` in UTF-8 bytes: every capped field at its worst (each character
escaped as ``\\uXXXX``, 6 bytes), the longest code, the keys and the schema id fit (checked below)."""

_ERROR_OVERHEAD = len('{"schema":"fms/error/v1","source":"","code":"forbidden_action","message":"","run_id":"",'
                      '"received":""}')
assert _ERROR_OVERHEAD + 6 * sum(ERROR_MAX_CHARS.values()) <= ERROR_MAX_BYTES


def bounded(text: str, max_chars: int) -> str:
    """``text`` itself, or its first ``max_chars - 1`` characters and ``…`` if it is longer."""
    return text if len(text) <= max_chars else text[:max_chars - 1] + "…"

_SCHEMA_RE = re.compile(r"fms/([a-z][a-z0-9_]*)/v([0-9]+)")


class MessageError(ValueError):
    """A message that cannot be accepted. ``code`` is one of :data:`ERROR_CODES`; ``field`` the offending
    field's path when one is to blame (else ``None``); ``str(exc)`` is a one-line explanation."""

    def __init__(self, code: str, message: str, field: str | None = None) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}; known codes: {', '.join(ERROR_CODES)}")
        super().__init__(message)
        self.code = code
        self.field = field


# ---------------------------------------------------------------------------------------------- field tables
_RUN_ID = Field("run_id", Str())
_OPTIONAL_STR = Nullable(Str(nonempty=False))

# The optional "features" of a state: what dispatching rules read, so that an agent decides from the message
# alone (no twin of the shop). Columns: entry i of every array of "jobs" is job i; of "agvs"/"transporters"
# vehicle i. The requests describe the transport that the next AGV / transporter choice serves.
FEATURE_JOB_COLUMNS = ("entry", "n_ops", "next_op", "next_duration", "remaining_work", "total_work", "ready_since")
FEATURE_VEHICLE_COLUMNS = ("loc", "free_at", "work")
_FEATURE_JOBS = Obj(tuple(Field(c, ListOf(Int(0))) for c in FEATURE_JOB_COLUMNS), expected="an object of job columns")
_FEATURE_VEHICLES = Obj(tuple(Field(c, ListOf(Int(0))) for c in FEATURE_VEHICLE_COLUMNS),
                        expected="an object of vehicle columns")
_AGV_REQUEST = Obj((
    Field("job", Int(0)), Field("op", Int(0)), Field("pickup", Int(0)), Field("to", Int(0)),
    Field("empty_travel", ListOf(Int(0))),
), expected="an AGV request object")
_TT_REQUEST = Obj((
    Field("tool", Int(1)), Field("job", Int(0)), Field("op", Int(0)), Field("pickup", Int(0)), Field("to", Int(0)),
    Field("empty_travel", ListOf(Int(0))),
), expected="a tool-transport request object")
_FEATURES = Obj((
    Field("jobs", _FEATURE_JOBS),
    Field("agvs", _FEATURE_VEHICLES),
    Field("transporters", _FEATURE_VEHICLES),
    Field("agv_request", Nullable(_AGV_REQUEST), required=False),
    Field("tt_request", Nullable(_TT_REQUEST), required=False),
), expected="a features object")

# The optional "history" of a state: everything applied to the run since state 0, so that an agent holding
# the same instance can replay it into a twin of the shop (the net is deterministic). "actions" is the
# applied action labels in order, separated by single spaces (one string: cheap to send, check and split);
# "orders" are the accepted orders' jobs, each with "at" = the number of actions applied before it.
# A shop started with history_delta sends only what was applied since the state its last command answered:
# "actions_from", "orders_from" and "disruptions_from" then say where the given entries begin in the whole run (0,
# or absent: the whole history; "at" values stay counted from the run's start).
_HISTORY_ORDER = Obj((
    Field("at", Int(0)),
    Field("jobs", ListOf(ListOf(Obj((
        Field("machine", Int(1)),
        Field("tool", Nullable(Int(1)), required=False),
        Field("duration", Int(0)),
    ), expected="an operation object {machine, tool, duration}"), nonempty=True), nonempty=True)),
), expected="an order object {at, jobs}")
DISRUPTION_KINDS: tuple[str, ...] = ("breakdown", "outage")

_DISRUPTION_BODY = (
    Field("disruption_id", Str()),
    Field("kind", OneOf(DISRUPTION_KINDS)),
    Field("machine", Nullable(Int(1)), required=False),
    Field("vehicle_kind", Nullable(OneOf(("agv", "tt"))), required=False),
    Field("vehicle", Nullable(Int(0)), required=False),
    Field("start", Nullable(Int(0)), required=False),
    Field("duration", Int(1)),
)


def _disruption_complete(msg: dict[str, Any], path: str) -> None:
    """A breakdown names its machine; an outage its vehicle's kind and number. The rule of a disruption message
    (``path`` ``""``) and of each disruption in a state's history (a breakdown without its machine there was
    accepted, and a twin that replays the history could not apply it)."""
    def at(key: str) -> str:
        return join_path(path, key)

    if msg["kind"] == "breakdown":
        if msg.get("machine") is None:
            raise FieldError(at("machine"), f"a breakdown needs field {at('machine')!r} (1..)")
        for key in ("vehicle_kind", "vehicle"):
            if msg.get(key) is not None:  # a message that names both: which one is down is not clear
                raise FieldError(at(key), f"a breakdown names a machine, not field {at(key)!r}")
    if msg["kind"] == "outage":
        if msg.get("vehicle_kind") is None or msg.get("vehicle") is None:
            raise FieldError(at("vehicle"), f"an outage needs fields {at('vehicle_kind')!r} (agv or tt) and "
                                            f"{at('vehicle')!r} (0..)")
        if msg.get("machine") is not None:
            raise FieldError(at("machine"), f"an outage names a vehicle, not field {at('machine')!r}")


_HISTORY_DISRUPTION = Obj((
    Field("at", Int(0)),
    Field("orders_before", Int(0)),
    Field("disruption", Obj(_DISRUPTION_BODY, extra=_disruption_complete)),  # (the message's rules: one table)
), expected="a disruption object {at, orders_before, disruption}")
_HISTORY = Obj((
    Field("actions", Str(nonempty=False, what="action labels separated by single spaces")),
    Field("orders", ListOf(_HISTORY_ORDER)),
    Field("disruptions", ListOf(_HISTORY_DISRUPTION), required=False),
    Field("scenario", Obj(()), required=False),
    Field("actions_from", Int(0), required=False),
    Field("orders_from", Int(0), required=False),
    Field("disruptions_from", Int(0), required=False),
), expected="a history object {actions, orders[, disruptions, scenario, actions_from, orders_from, "
            "disruptions_from]}")

# The optional "idle" of a state, sent by a shop that stops at idle-vehicle moments (for pre-positioning; see
# fms_sim.stepping): the vehicles offered now, or [] at a decision. Absent (or null) if the shop does not stop
# there. At an idle stop no action is enabled; the answer is the command action "wait" or
# "reposition:KIND:V:LOC[,KIND:V:LOC...]".
_IDLE_VEHICLE = Obj((
    Field("kind", OneOf(("agv", "tt"))), Field("vehicle", Int(0)), Field("location", Int(0)),
), expected="an idle vehicle object {kind, vehicle, location}")

_STATE = (
    _RUN_ID,
    Field("seq", Int(0)),
    Field("time", Int(0)),
    Field("marking", MapOf(Int(0))),
    Field("actions", ListOf(Str(what="an action label"), unique=True)),
    Field("mask", ListOf(Bool())),
    Field("done", Bool()),
    Field("instance", _OPTIONAL_STR, required=False),
    Field("makespan", Nullable(Int(0)), required=False),
    Field("features", Nullable(_FEATURES), required=False),
    Field("history", Nullable(_HISTORY), required=False),
    Field("idle", Nullable(ListOf(_IDLE_VEHICLE)), required=False),
)

_COMMAND = (
    _RUN_ID,
    Field("state_seq", Int(0)),
    Field("action", Str(what="an action label, not an index")),
    Field("agent", _OPTIONAL_STR, required=False),
)

_EVENT_DATA = (  # all optional: which ones are present depends on the event kind (see docs/ros.md)
    Field("job", Nullable(Int(0)), required=False),
    Field("op", Nullable(Int(0)), required=False),
    Field("machine", Int(1), required=False),
    Field("tool", Nullable(Int(1)), required=False),
    Field("agv", Int(0), required=False),
    Field("transporter", Int(0), required=False),
    Field("from", Int(0), required=False),
    Field("to", Int(0), required=False),
    Field("loaded", Bool(), required=False),
    Field("order_id", Str(), required=False),
    Field("jobs", ListOf(Int(0)), required=False),
    Field("instance", Str(nonempty=False), required=False),
    Field("incarnation", Str(), required=False),
    Field("makespan", Nullable(Int(0)), required=False),
    Field("start", Int(0), required=False),
    Field("disruption_id", Str(), required=False),
    Field("disruption", Str(), required=False),
    Field("vehicle_kind", Str(), required=False),
    Field("vehicle", Int(0), required=False),
    Field("duration", Int(1), required=False),
)

_EVENT = (
    _RUN_ID,
    Field("seq", Int(0)),
    Field("time", Int(0)),
    Field("kind", OneOf(EVENT_KINDS)),
    Field("data", Obj(_EVENT_DATA)),
    Field("incarnation", Str(), required=False),
)

# The Schedule JSON of fms_sim.schedule.Schedule.to_dict(), field by field (precise messages); the parse with
# Schedule.from_dict afterwards stays the authority on the format.
_SCHEDULE_OP = Obj((
    Field("job", Int(0)), Field("op", Int(0)), Field("machine", Int(1)),
    Field("tool", Nullable(Int(1)), required=False), Field("start", Int(0)), Field("end", Int(0)),
))
_AGV_TRIP = Obj((
    Field("agv", Int(0)), Field("job", Nullable(Int(0)), required=False), Field("op", Nullable(Int(0)), required=False),
    Field("from", Int(0)), Field("to", Int(0)), Field("start", Int(0)), Field("end", Int(0)), Field("loaded", Bool()),
))
_TOOL_TRIP = Obj((
    Field("transporter", Int(0)), Field("tool", Nullable(Int(1)), required=False),
    Field("job", Nullable(Int(0)), required=False), Field("op", Nullable(Int(0)), required=False),
    Field("from", Int(0)), Field("to", Int(0)), Field("start", Int(0)), Field("end", Int(0)), Field("loaded", Bool()),
))
_SCHEDULE_BODY = (
    Field("instance", Str(nonempty=False)),
    Field("makespan", Int(0)),
    Field("n_agvs", Int(0), required=False),
    Field("n_tool_transporters", Int(0), required=False),
    Field("operations", ListOf(_SCHEDULE_OP)),
    Field("agv_trips", ListOf(_AGV_TRIP), required=False),
    Field("tool_trips", ListOf(_TOOL_TRIP), required=False),
    Field("meta", Obj(()), required=False),
)


class _ScheduleDict:
    """A dict in the Schedule JSON format: checked by the table above, then parsed by ``Schedule.from_dict``."""

    expected = "a schedule object (fms_sim Schedule JSON)"

    def __call__(self, value: Any, path: str) -> None:
        check_object(value, _SCHEDULE_BODY, path)
        try:
            Schedule.from_dict(value, strict=False)  # unknown extra fields are allowed in messages (docs/ros.md)
        except ScheduleError as exc:
            raise FieldError(path, f"field {path!r} is not a valid schedule: {exc}") from None


_SCHEDULE = (_RUN_ID, Field("schedule", _ScheduleDict()))

_ORDER_OP = Obj((
    Field("machine", Int(1)),
    Field("tool", Nullable(Int(1)), required=False),
    Field("duration", Int(0)),
), expected="an operation object {machine, tool, duration}")

_ORDER = (
    Field("order_id", Str()),
    Field("jobs", ListOf(ListOf(_ORDER_OP, nonempty=True), nonempty=True)),
    Field("run_id", _OPTIONAL_STR, required=False),
)

_ERROR = (
    Field("source", Str(max_len=ERROR_MAX_CHARS["source"], what="the reporting node's name")),
    Field("code", OneOf(ERROR_CODES)),
    Field("message", Str(max_len=ERROR_MAX_CHARS["message"])),
    Field("run_id", Nullable(Str(nonempty=False, max_len=ERROR_MAX_CHARS["run_id"])), required=False),
    Field("received", Nullable(Str(nonempty=False, max_len=ERROR_MAX_CHARS["received"])), required=False),
)

# A disruption at run time (docs/ros.md): a machine breakdown or a vehicle out of service, from ``start`` (the
# shop's current time if absent, null or past) for ``duration``; accepted once per ``disruption_id``.
_DISRUPTION = _DISRUPTION_BODY + (Field("run_id", _OPTIONAL_STR, required=False),)



REPLAN_REASONS: tuple[str, ...] = ("order", "breakdown", "outage", "late", "stuck")
REPLAN_STATUSES: tuple[str, ...] = ("adopted", "kept", "failed", "timeout")

# A re-plan by the agent (docs/ros.md): why, at which state and shop time, how long it took against its budget,
# the predicted makespans of keeping the plan (before; null when it did not cover the shop's jobs) and of the
# new plan (after; null when none was made), and what became of it.
_REPLAN = (
    _RUN_ID,
    Field("source", Str(what="the agent node's name")),
    Field("state_seq", Int(0)),
    Field("time", Int(0)),
    Field("reason", OneOf(REPLAN_REASONS)),
    Field("status", OneOf(REPLAN_STATUSES)),
    Field("budget_ms", Int(1)),
    Field("wall_ms", Int(0)),
    Field("before", Nullable(Int(0))),
    Field("after", Nullable(Int(0))),
    Field("method", _OPTIONAL_STR, required=False),
    Field("message", Nullable(Str(nonempty=False, max_len=ERROR_MAX_CHARS["message"])), required=False),
)

REPLAY_WHATS: tuple[str, ...] = ("events", "state")
"""What a replay request asks for: the run's events from ``from_seq`` on (the default), or the current state
again with the run's whole history (an agent of a ``history_delta`` shop that cannot follow the deltas)."""

_REPLAY_REQUEST = (
    Field("run_id", Str(what='a run id, or "*" for the current run')),
    Field("from_seq", Int(0)),
    Field("requester", Str()),
    Field("what", OneOf(REPLAY_WHATS), required=False),
)


def _mask_matches_actions(msg: dict[str, Any], path: str) -> None:
    """A state's ``mask`` has one entry per action label; its ``features`` (if any) are consistent."""
    if len(msg["mask"]) != len(msg["actions"]):
        raise FieldError("mask", f"field 'mask' has {len(msg['mask'])} entries but 'actions' has "
                                 f"{len(msg['actions'])}; they must have the same length")
    features = msg.get("features")
    if features is not None:
        _features_consistent(features)
    history = msg.get("history")
    if history is not None:
        _history_consistent(history)
    if msg.get("idle") and any(msg["mask"]):
        raise FieldError("idle", "field 'idle' offers idle vehicles but 'mask' enables actions; a state is either "
                                 "a decision or an idle stop")


def _history_consistent(history: dict[str, Any]) -> None:
    """History labels are separated by single spaces; orders come in order and refer to applied actions (of a
    delta, those from ``actions_from`` on: see ``_HISTORY``)."""
    text = history["actions"]
    first = history.get("actions_from", 0)
    n = first
    if text:  # (counted, not split: the text grows with the run and is checked at every state)
        if text[0] == " " or text[-1] == " " or "  " in text:
            raise FieldError("history.actions", "field 'history.actions' must separate action labels by single "
                                                "spaces (no leading, trailing or double spaces)")
        n += text.count(" ") + 1
    last = first
    for i, order in enumerate(history["orders"]):
        if not last <= order["at"] <= n:
            raise FieldError(f"history.orders[{i}].at", f"field 'history.orders[{i}].at' is {order['at']} but "
                                                        f"must be between {last} (the previous order's"
                                                        f"{' or actions_from' if first else ''}) and {n} "
                                                        "(the number of applied actions)")
        last = order["at"]


def _same_length(group: dict[str, Any], columns: tuple[str, ...], path: str) -> int:
    """All ``columns`` of ``group`` have one length; return it."""
    n = len(group[columns[0]])
    for c in columns[1:]:
        if len(group[c]) != n:
            raise FieldError(f"{path}.{c}", f"field '{path}.{c}' has {len(group[c])} entries but "
                                            f"'{path}.{columns[0]}' has {n}; columns must have the same length")
    return n


def _features_consistent(features: dict[str, Any]) -> None:
    """Columns of one group have the same length; a request lists one empty travel time per vehicle."""
    _same_length(features["jobs"], FEATURE_JOB_COLUMNS, "features.jobs")
    for group, req in (("agvs", "agv_request"), ("transporters", "tt_request")):
        n = _same_length(features[group], FEATURE_VEHICLE_COLUMNS, f"features.{group}")
        request = features.get(req)
        if request is not None and len(request["empty_travel"]) != n:
            raise FieldError(f"features.{req}.empty_travel",
                             f"field 'features.{req}.empty_travel' has {len(request['empty_travel'])} entries "
                             f"but there are {n} {group}; give one travel time per vehicle")


_Extra = Callable[[dict[str, Any], str], None] | None
_SPECS: dict[str, tuple[tuple[Field, ...], _Extra]] = {
    "state": (_STATE, _mask_matches_actions),
    "command": (_COMMAND, None),
    "event": (_EVENT, None),
    "schedule": (_SCHEDULE, None),
    "order": (_ORDER, None),
    "error": (_ERROR, None),
    "replay_request": (_REPLAY_REQUEST, None),
    "disruption": (_DISRUPTION, _disruption_complete),
    "replan": (_REPLAN, None),
}
assert set(_SPECS) == set(KINDS)


# ---------------------------------------------------------------------------------------------- API
def kind_of(msg: Any) -> str:
    """The kind name (``"state"``, ``"command"``, ...) of a message dict, from its ``schema`` field only.

    Raises :class:`MessageError` (``bad_schema``) if ``schema`` is missing, not a known kind, or another version.
    """
    if not isinstance(msg, dict):
        raise MessageError("bad_schema", f"a message must be a JSON object, got {show(msg)}")
    if "schema" not in msg:
        raise MessageError("bad_schema", "message has no 'schema' field (expected e.g. 'fms/state/v1')", "schema")
    sid = msg["schema"]
    if not isinstance(sid, str):
        raise MessageError("bad_schema", f"field 'schema' must be a string like 'fms/state/v1', got {show(sid)}",
                           "schema")
    m = _SCHEMA_RE.fullmatch(sid)
    if m is None:
        raise MessageError("bad_schema", f"unknown schema {sid[:60]!r}; expected 'fms/<kind>/v<version>'", "schema")
    kind, version = m.group(1), int(m.group(2))
    if kind not in KINDS:
        raise MessageError("bad_schema", f"unknown message kind {kind!r} in schema {sid!r}; known kinds: "
                                         f"{', '.join(KINDS)}", "schema")
    if version != SCHEMA_VERSION:
        raise MessageError("bad_schema", f"unsupported schema version {sid!r}; this build reads "
                                         f"{schema_id(kind)!r}", "schema")
    if sid != schema_id(kind):  # 'fms/command/v01': the version read as a number, but the id is compared as text
        raise MessageError("bad_schema", f"schema {sid[:60]!r} must be written {schema_id(kind)!r}", "schema")
    return kind


def validate(msg: Any) -> str:
    """Check a message dict strictly against its kind's field table; return its kind name.

    Raises :class:`MessageError` (``bad_schema``) naming the first offending field.
    """
    kind = kind_of(msg)
    fields, extra = _SPECS[kind]
    try:
        check_object(msg, fields, "", extra)
    except FieldError as exc:
        raise MessageError("bad_schema", f"{msg['schema']}: {exc}", exc.path or None) from None
    return kind


def encode(msg: dict[str, Any], *, check: bool = True) -> str:
    """Validate ``msg`` and return its compact JSON text (the ``data`` of a ``std_msgs/String``).

    ``check=False`` skips the validation, for a dict that a builder (``make_*``) has just returned and that
    nobody changed since: a publisher's hot path need not validate the same message twice.
    """
    if check:
        validate(msg)
    try:
        text = json.dumps(msg, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    except (TypeError, ValueError) as exc:  # only possible in extra (unknown) fields
        raise MessageError("bad_schema", f"{msg['schema']}: message is not JSON-serialisable: {exc}") from None
    except RecursionError:  # an extra field nested thousands deep (decode refuses such text as nested too deeply)
        raise MessageError("bad_schema", f"{msg['schema']}: message is nested too deeply to be written as JSON "
                                         "(an object or array holds thousands of levels)") from None
    clash = _key_clash(msg)
    if clash is not None:
        path, reason = clash
        raise MessageError("bad_schema", f"{msg['schema']}: {reason}", path or None)
    _check_unicode(text, "bad_schema", f"{msg['schema']}: a string of the message")
    return text


_SCALAR_TYPES = frozenset((str, int, float, bool, type(None)))


def _json_key(key: Any) -> str:
    """The key ``key`` of a dict as :func:`json.dumps` writes it (one that it writes at all: str, int, float, bool
    or None)."""
    if isinstance(key, str):
        return key
    if key is None or isinstance(key, bool):
        return {None: "null", True: "true", False: "false"}[key]
    return int.__repr__(key) if isinstance(key, int) else float.__repr__(key)


def _key_clash(msg: dict[str, Any]) -> tuple[str, str] | None:
    """Where and why ``msg`` (already written by :func:`json.dumps`: no cycle, only keys it writes) cannot be
    sent: a dict with two keys that JSON writes alike (``1`` and ``"1"``, ``True`` and ``"true"``) gave an object
    with one key twice, a message that :func:`decode` refuses. None when there is none. Walked without recursion; a
    list of plain values is passed over at C speed, so a state's long columns cost next to nothing."""
    stack: list[Any] = [msg]
    while stack:
        value = stack.pop()
        items: Iterable[Any]
        if isinstance(value, dict):
            if value and set(map(type, value)) != {str}:
                written: dict[str, Any] = {}
                for key in value:
                    other = written.setdefault(_json_key(key), key)
                    if other is not key:
                        first, second = sorted((other, key), key=lambda k: isinstance(k, str))  # the str one last
                        path = _path_to(msg, value)
                        where = f"field {path!r}" if path else "the message"
                        return path, (f"{where} has the keys {first!r} and {second!r}, which JSON writes alike "
                                      f"({_json_key(key)!r}): a JSON object holds each key once, and decode refuses "
                                      "the message; give one of them")
            items = value.values()
        elif isinstance(value, (list, tuple)):
            items = value
        else:
            continue
        if not set(map(type, items)) <= _SCALAR_TYPES:
            stack.extend(x for x in items if isinstance(x, (dict, list, tuple)))
    return None


def _path_to(msg: dict[str, Any], target: Any) -> str:
    """The dotted/indexed path of the container ``target`` inside ``msg`` (``data.extra``, ``jobs[0]``), as field
    errors name one; ``""`` for ``msg`` itself."""
    stack: list[tuple[Any, str]] = [(msg, "")]
    while stack:
        value, path = stack.pop()
        if value is target:
            return path
        if isinstance(value, dict):
            stack.extend((x, f"{path}.{_json_key(k)}" if path else _json_key(k)) for k, x in value.items()
                         if isinstance(x, (dict, list, tuple)))
        elif isinstance(value, (list, tuple)):
            stack.extend((x, f"{path}[{i}]") for i, x in enumerate(value) if isinstance(x, (dict, list, tuple)))
    return "?"


def _check_unicode(text: str, code: str, what: str) -> None:
    """Raise :class:`MessageError` if ``text`` holds a lone surrogate (a ``\\ud800`` escape in JSON decodes to
    one): such a str cannot be sent as UTF-8, so a transport would fail on it, long after it was accepted."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as exc:
        raise MessageError(code, f"{what} holds a lone surrogate (U+{ord(exc.object[exc.start]):04X}), which is "
                                 f"not Unicode text and cannot be sent as UTF-8") from None


def _normalise_expect(expect: str | Iterable[str]) -> set[str]:
    names = {expect} if isinstance(expect, str) else set(expect)
    kinds: set[str] = set()
    for name in names:
        if name in SCHEMAS:
            kinds.add(name)
        else:
            match = [k for k, sid in SCHEMAS.items() if sid == name]
            if not match:
                raise ValueError(f"expect: unknown kind or schema {name!r}; known kinds: {', '.join(KINDS)}")
            kinds.add(match[0])
    if not kinds:
        raise ValueError("expect: an empty set of kinds accepts nothing")
    return kinds


def _reject_constant(name: str) -> Any:
    raise MessageError("malformed_json", f"malformed JSON: {name} is not a JSON number")


def _finite_float(text: str) -> float:
    """A JSON number with a fraction or exponent; one too large for a float (``1e400``) is refused: it became
    infinity, which no message may hold (the recorder stored ``Infinity``, which is not JSON)."""
    value = float(text)
    if not math.isfinite(value):
        raise MessageError("malformed_json", f"malformed JSON: the number {text[:40]} is too large")
    return value


def decode(text: str, expect: str | Iterable[str] | None = None) -> dict[str, Any]:
    """Parse and strictly validate one message; return it as a dict.

    ``expect`` (a kind name such as ``"command"`` or a schema id such as ``"fms/command/v1"``, or a set of
    them) rejects every other kind. Raises :class:`MessageError`: ``malformed_json`` if ``text`` is not one
    JSON value (NaN/Infinity, a number too large for a float or with more digits than Python converts, and
    duplicate keys included), ``bad_schema`` otherwise.
    """
    kinds = _normalise_expect(expect) if expect is not None else None
    if not isinstance(text, str):
        raise MessageError("malformed_json", f"expected the message text as a str, got {type(text).__name__}")
    try:
        msg = json.loads(text, object_pairs_hook=unique_pairs, parse_constant=_reject_constant,
                         parse_float=_finite_float)
    except json.JSONDecodeError as exc:
        raise MessageError("malformed_json", f"malformed JSON at line {exc.lineno} column {exc.colno}: "
                                             f"{exc.msg}") from None
    except RecursionError:
        raise MessageError("malformed_json", "malformed JSON: nested too deeply") from None
    except DuplicateKeyError as exc:  # (the files' check: a message and a file refuse the same objects)
        raise MessageError("malformed_json", f"malformed JSON: {exc}") from None
    except MessageError:
        raise
    except ValueError:  # a number with more digits than Python converts (its limit, sys.get_int_max_str_digits)
        raise MessageError("malformed_json", f"malformed JSON: a number has more than {sys.get_int_max_str_digits()} "
                                             "digits") from None
    _check_unicode(text, "malformed_json", "the text")
    if "\\u" in text:  # an escape may decode to a lone surrogate: the decoded strings must be Unicode too
        _check_unicode(json.dumps(msg, ensure_ascii=False), "malformed_json", "a string of the message")
    kind = kind_of(msg)
    if kinds is not None and kind not in kinds:  # before the field checks: the mismatch is the real problem
        wanted = " or ".join(sorted(SCHEMAS[k] for k in kinds))
        raise MessageError("bad_schema", f"expected a {wanted} message, got {msg['schema']}", "schema")
    validate(msg)
    return msg
