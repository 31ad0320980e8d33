"""Builders: one function per message kind, returning a dict that already passed validation.

The builders accept what the nodes naturally hold — tuples, ``numpy`` scalars and arrays (anything with a
``tolist()``), :class:`fms_sim.schedule.Schedule` and :class:`fms_sim.instance.Operation` objects — and turn it
into plain JSON values, so ``encode(make_...(...))`` never fails on types. A value that breaks the kind's rules
raises :class:`~fms_msgs_json.schemas.MessageError` (``bad_schema``) right where the message is built, not at
the receiver.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping
from typing import Any

from fms_sim.schedule import Schedule

from .schemas import (
    ERROR_MAX_CHARS, RECEIVED_MAX_CHARS, SCHEMA_COMMAND, SCHEMA_DISRUPTION, SCHEMA_ERROR, SCHEMA_EVENT,
    SCHEMA_ORDER, SCHEMA_REPLAN, SCHEMA_REPLAY_REQUEST, SCHEMA_SCHEDULE, SCHEMA_STATE, MessageError, bounded,
    validate,
)

__all__ = [
    "make_state", "make_command", "make_event", "make_schedule", "make_order", "make_error", "error_reply",
    "make_replay_request", "make_disruption", "make_replan",
]


_SCALARS = frozenset((int, bool, str, float, type(None)))


def _plain(x: Any) -> Any:
    """``x`` as plain JSON values: numpy via ``tolist()``, mappings → dicts, other iterables → lists. A value nested
    too deeply for that (thousands of levels: it was a bare RecursionError) is a :class:`MessageError`
    (``bad_schema``), as :func:`~fms_msgs_json.schemas.encode` says of one."""
    try:
        return _plain_values(x)
    except RecursionError:
        raise MessageError("bad_schema", "a value of the message is nested too deeply to be sent as JSON (an "
                                         "object or array holds thousands of levels)") from None


def _plain_values(x: Any) -> Any:
    """:func:`_plain`, recursively."""
    t = type(x)
    if t in _SCALARS:  # fast paths for what the nodes build: plain scalars, dicts and flat lists
        return x
    if t is dict:
        return {k: _plain_values(v) for k, v in x.items()}
    if t is list and set(map(type, x)) <= _SCALARS:
        return list(x)
    if not isinstance(x, (str, bytes, int, float, type(None))) and hasattr(x, "tolist"):
        x = x.tolist()
    if isinstance(x, Mapping):
        return {k: _plain_values(v) for k, v in x.items()}
    if isinstance(x, Iterable) and not isinstance(x, (str, bytes)):
        return [_plain_values(v) for v in x]
    return x


def _checked(msg: dict[str, Any]) -> dict[str, Any]:
    validate(msg)
    return msg


def make_state(run_id: str, seq: int, time: int, marking: Mapping[str, int], actions: Iterable[str],
               mask: Iterable[bool], done: bool, *, instance: str | None = None,
               makespan: int | None = None, features: Mapping[str, Any] | None = None,
               idle: Iterable[Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """An ``fms/state/v1``: the shop's state number ``seq`` of run ``run_id`` at simulation ``time``.

    ``marking`` counts tokens per place name; ``actions[i]`` is the label of action index ``i`` and ``mask[i]``
    says whether it is enabled now; ``makespan`` is set once the run is ``done``. ``features`` (optional) are
    the per-job and per-vehicle figures that dispatching rules read (see docs/ros.md); omitted when ``None``.
    ``idle`` (optional, from a shop with idle stops) lists the idle vehicles offered now as ``{kind, vehicle,
    location}`` (``[]`` at a decision); omitted when ``None``.
    """
    msg: dict[str, Any] = {"schema": SCHEMA_STATE, "run_id": run_id}
    if instance is not None:
        msg["instance"] = instance
    msg.update(seq=_plain(seq), time=_plain(time), marking=_plain(marking), actions=_plain(actions),
               mask=_plain(mask), done=_plain(done), makespan=_plain(makespan))
    if features is not None:
        msg["features"] = _plain(features)
    if idle is not None:
        msg["idle"] = _plain(list(idle))
    return _checked(msg)


def make_command(run_id: str, state_seq: int, action: str, *, agent: str | None = None) -> dict[str, Any]:
    """An ``fms/command/v1``: fire the action labelled ``action`` in answer to state ``state_seq``."""
    msg: dict[str, Any] = {"schema": SCHEMA_COMMAND, "run_id": run_id, "state_seq": _plain(state_seq),
                           "action": action}
    if agent is not None:
        msg["agent"] = agent
    return _checked(msg)


def make_event(run_id: str, seq: int, time: int, kind: str, data: Mapping[str, Any] | None = None, *,
               incarnation: str | None = None, **details: Any) -> dict[str, Any]:
    """An ``fms/event/v1`` number ``seq`` of run ``run_id``: something of ``kind`` happened at ``time``.

    The details go into ``data``, from the mapping and/or keyword arguments; a trailing underscore is dropped
    from a keyword so that ``from_=0`` gives ``"from": 0`` (keywords win over the mapping). ``incarnation`` names
    the start of the shop that sent it (a shop restarted under the same run id sends another; the recorder tells
    the two runs apart by it even where the new one's ``run_start`` was lost).
    """
    body = _plain(data) if data is not None else {}
    for key, value in details.items():
        body[key[:-1] if key.endswith("_") else key] = _plain(value)
    msg = {"schema": SCHEMA_EVENT, "run_id": run_id, "seq": _plain(seq), "time": _plain(time), "kind": kind,
           "data": body}
    if incarnation is not None:
        msg["incarnation"] = incarnation
    return _checked(msg)


def make_schedule(run_id: str, schedule: Schedule | Mapping[str, Any]) -> dict[str, Any]:
    """An ``fms/schedule/v1`` carrying ``schedule`` (a ``Schedule`` or its ``to_dict()`` form) for ``run_id``."""
    body = schedule.to_dict() if isinstance(schedule, Schedule) else _plain(schedule)
    return _checked({"schema": SCHEMA_SCHEDULE, "run_id": run_id, "schedule": body})


def _order_op(op: Any) -> Any:
    """One operation as ``{"machine", "tool", "duration"}`` from a mapping, an ``Operation``-like object, or a
    ``(machine, tool, duration)`` / ``(machine, duration)`` sequence; anything else is left for validation."""
    if isinstance(op, Mapping):
        out = _plain(op)
        out.setdefault("tool", None)
        return out
    if all(hasattr(op, a) for a in ("machine", "tool", "duration")):
        return {"machine": _plain(op.machine), "tool": _plain(op.tool), "duration": _plain(op.duration)}
    if isinstance(op, (list, tuple)) and len(op) == 3:
        return {"machine": _plain(op[0]), "tool": _plain(op[1]), "duration": _plain(op[2])}
    if isinstance(op, (list, tuple)) and len(op) == 2:
        return {"machine": _plain(op[0]), "tool": None, "duration": _plain(op[1])}
    return _plain(op)


def _is_sequence(x: Any) -> bool:
    return isinstance(x, Iterable) and not isinstance(x, (str, bytes, Mapping))


def _order_job(ops: Any) -> Any:
    return [_order_op(op) for op in ops] if _is_sequence(ops) else _plain(ops)


def make_order(order_id: str, jobs: Iterable[Iterable[Any]], *, run_id: str | None = None) -> dict[str, Any]:
    """An ``fms/order/v1``: new jobs for the shop, each a list of operations (see :func:`_order_op`).

    Only the shape is checked here; whether the machines and tools exist is for the shop to check.
    """
    body = ([_order_job(ops) for ops in jobs] if _is_sequence(jobs) else _plain(jobs))
    msg: dict[str, Any] = {"schema": SCHEMA_ORDER, "order_id": order_id, "jobs": body}
    if run_id is not None:
        msg["run_id"] = run_id
    return _checked(msg)


def make_disruption(disruption_id: str, kind: str, duration: int, *, machine: int | None = None,
                    vehicle_kind: str | None = None, vehicle: int | None = None, start: int | None = None,
                    run_id: str | None = None) -> dict[str, Any]:
    """An ``fms/disruption/v1``: a machine breakdown (``kind="breakdown"``, ``machine``) or a vehicle out of
    service (``kind="outage"``, ``vehicle_kind`` agv or tt, ``vehicle``) from ``start`` (None: now) for
    ``duration``. Whether the machine or vehicle exists is for the shop to check."""
    msg: dict[str, Any] = {"schema": SCHEMA_DISRUPTION, "disruption_id": disruption_id, "kind": kind,
                           "duration": _plain(duration)}
    for key, value in (("machine", machine), ("vehicle_kind", vehicle_kind), ("vehicle", vehicle),
                       ("start", start), ("run_id", run_id)):
        if value is not None:
            msg[key] = _plain(value)
    return _checked(msg)


def make_replan(run_id: str, source: str, state_seq: int, time: int, reason: str, status: str, *, budget_s: float,
                wall_s: float, before: int | None, after: int | None, method: str | None = None,
                message: str | None = None) -> dict[str, Any]:
    """An ``fms/replan/v1``: the agent ``source`` re-planned at state ``state_seq`` (shop time ``time``) for
    ``reason``; ``status`` adopted, kept, failed or timeout; budget and wall time in seconds (sent as whole
    milliseconds, a budget of at least 1 ms); predicted makespans ``before`` (keeping the plan) and ``after``
    (the new plan). A time that is not a finite number of seconds >= 0 is a ``bad_schema`` MessageError."""
    msg: dict[str, Any] = {"schema": SCHEMA_REPLAN, "run_id": run_id, "source": source, "state_seq": state_seq,
                           "time": _plain(time), "reason": reason, "status": status,
                           "budget_ms": max(1, _ms("budget_s", budget_s)), "wall_ms": _ms("wall_s", wall_s),
                           "before": _plain(before), "after": _plain(after)}
    if method is not None:
        msg["method"] = method
    if message is not None:
        msg["message"] = bounded(_one_line(message), ERROR_MAX_CHARS["message"])
    return _checked(msg)


def _ms(name: str, seconds: Any) -> int:
    """``seconds`` as whole milliseconds; a negative, infinite or NaN time, or a non-number, is refused."""
    if not isinstance(seconds, numbers.Real) or isinstance(seconds, bool) or not 0 <= seconds < math.inf:
        raise MessageError("bad_schema", f"{SCHEMA_REPLAN}: {name} must be a finite number of seconds >= 0, "
                                         f"got {seconds!r}", name)
    return round(float(seconds) * 1000)


def _one_line(text: str) -> str:
    return " ".join(text.splitlines()).strip()


def make_error(source: str, code: str, message: str, *, run_id: str | None = None,
               received: str | bytes | None = None) -> dict[str, Any]:
    """An ``fms/error/v1`` from node ``source``: ``code`` (one of ``ERROR_CODES``) and a one-line ``message``.

    Every string field is cut to its ``ERROR_MAX_CHARS`` (the cut marked with ``…``; ``received``, the
    offending raw text, is cut plainly), so an encoded error never exceeds ``ERROR_MAX_BYTES`` whatever it
    reports on; bytes are decoded as UTF-8 with replacement characters.
    """
    def cap(field: str, value: Any) -> Any:
        return bounded(value, ERROR_MAX_CHARS[field]) if isinstance(value, str) else value

    msg: dict[str, Any] = {"schema": SCHEMA_ERROR, "source": cap("source", source), "code": code,
                           "message": cap("message", _one_line(message) if isinstance(message, str) else message)}
    if run_id is not None:
        msg["run_id"] = cap("run_id", run_id)
    if received is not None:
        if isinstance(received, (bytes, bytearray)):
            received = bytes(received).decode("utf-8", errors="replace")
        msg["received"] = received[:RECEIVED_MAX_CHARS] if isinstance(received, str) else received
    return _checked(msg)


def error_reply(source: str, exc: BaseException, *, received: str | bytes | None = None,
                run_id: str | None = None) -> dict[str, Any]:
    """The ``fms/error/v1`` answering a failure: a :class:`MessageError` keeps its code, anything else is
    reported as ``"internal"`` with its type and message."""
    if isinstance(exc, MessageError):
        code, text = exc.code, str(exc)
    else:
        code, text = "internal", f"{type(exc).__name__}: {exc}"
    return make_error(source, code, text or type(exc).__name__, run_id=run_id, received=received)


def make_replay_request(run_id: str, from_seq: int, requester: str, what: str = "events") -> dict[str, Any]:
    """An ``fms/replay_request/v1``: ``requester`` asks the shop to re-publish run ``run_id``'s events
    (``"*"``: the current run) from event number ``from_seq`` on, or with ``what="state"`` its current state with
    the run's whole history (``from_seq`` is then not read)."""
    msg = {"schema": SCHEMA_REPLAY_REQUEST, "run_id": run_id, "from_seq": _plain(from_seq), "requester": requester}
    if what != "events":
        msg["what"] = what
    return _checked(msg)
