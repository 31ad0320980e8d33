"""Schedules: what every solver returns and every node publishes, with their JSON form.

A schedule lists every operation with its start and end, every AGV trip and every tool-transporter trip.
Empty (deadheading) trips have ``loaded = False`` and ``job``/``op``/``tool`` set to ``None``; a trip whose
origin equals its destination may be omitted. ``fms_sim.validate`` checks a schedule against its instance
without using the Petri net.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .files import loads, read_text, write_atomically

__all__ = ["OperationRecord", "AgvTrip", "ToolTrip", "Schedule", "ScheduleError", "require_schedule"]


class ScheduleError(ValueError):
    """A schedule file that cannot be read (not: a schedule that breaks the rules — see the validator)."""


@dataclass(frozen=True, slots=True)
class OperationRecord:
    job: int
    op: int
    machine: int
    tool: int | None
    start: int
    end: int

    def __deepcopy__(self, memo: dict) -> "OperationRecord":
        return self  # a frozen record: twins of a shop share it


@dataclass(frozen=True, slots=True)
class AgvTrip:
    agv: int
    job: int | None
    op: int | None
    from_: int
    to: int
    start: int
    end: int
    loaded: bool

    def __deepcopy__(self, memo: dict) -> "AgvTrip":
        return self  # a frozen record: twins of a shop share it

    def to_dict(self) -> dict[str, Any]:
        return {"agv": self.agv, "job": self.job, "op": self.op, "from": self.from_, "to": self.to,
                "start": self.start, "end": self.end, "loaded": self.loaded}


@dataclass(frozen=True, slots=True)
class ToolTrip:
    transporter: int
    tool: int | None
    job: int | None
    op: int | None
    from_: int
    to: int
    start: int
    end: int
    loaded: bool

    def __deepcopy__(self, memo: dict) -> "ToolTrip":
        return self  # a frozen record: twins of a shop share it

    def to_dict(self) -> dict[str, Any]:
        return {"transporter": self.transporter, "tool": self.tool, "job": self.job, "op": self.op,
                "from": self.from_, "to": self.to, "start": self.start, "end": self.end, "loaded": self.loaded}


#: the ``meta`` entries that change what a schedule means, compared by ``Schedule.__eq__``: the disruptions it was made
#: under, when live orders' jobs arrived (both checked by the validator) and the time a residual plan starts from
COMPARED_META = ("scenario", "arrivals", "residual")


@dataclass(eq=False)
class Schedule:
    """A complete schedule; ``makespan`` is the latest operation end.

    Two schedules are equal when their JSON forms are, but for the ``meta`` entries that only describe how they were
    made (solver, wall time, bound: :data:`COMPARED_META` are compared, the entries that change what the schedule
    means): the records in the JSON form's order, which keeps the recorded order of records that tie (it can matter
    at one instant, docs/semantics.md). A schedule so equals its JSON round trip, and two runs that made the same
    schedule are equal whatever their wall times."""

    instance: str
    makespan: int
    n_agvs: int = 0
    n_tool_transporters: int = 0
    operations: list[OperationRecord] = field(default_factory=list)
    agv_trips: list[AgvTrip] = field(default_factory=list)
    tool_trips: list[ToolTrip] = field(default_factory=list)
    meta: dict[str, Any] = field(default_factory=dict)
    """Free-form facts about how it was made (solver, wall time, bound); exported under ``"meta"``."""

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Schedule):
            return NotImplemented
        mine, theirs = ({k: x.meta.get(k) for k in COMPARED_META} for x in (self, other))
        return mine == theirs and self._records() == other._records()

    __hash__ = None  # type: ignore[assignment]  # mutable

    def _records(self) -> dict[str, Any]:
        """The JSON form without ``meta``."""
        return {
            "instance": self.instance,
            "makespan": self.makespan,
            "n_agvs": self.n_agvs,
            "n_tool_transporters": self.n_tool_transporters,
            "operations": [asdict(o) for o in sorted(self.operations, key=lambda o: (o.start, o.job, o.op))],
            "agv_trips": [t.to_dict() for t in sorted(self.agv_trips, key=lambda t: (t.agv, t.start, t.end))],
            "tool_trips": [t.to_dict() for t in sorted(self.tool_trips, key=lambda t: (t.transporter, t.start, t.end))],
        }

    def to_dict(self) -> dict[str, Any]:
        out = self._records()
        if self.meta:
            out["meta"] = copy.deepcopy(self.meta)  # the caller's to change (it changed the schedule's own)
        return out

    def to_json(self, indent: int | None = 1) -> str:
        """The JSON form; :class:`ScheduleError` naming the entry if ``meta`` holds what JSON has not (NaN, an
        infinity: Python wrote them as ``NaN``/``Infinity``, which other JSON readers and this one refuse; an object
        such as a set)."""
        try:
            return json.dumps(self.to_dict(), indent=indent, allow_nan=False)
        except (ValueError, TypeError) as exc:
            raise ScheduleError(f"meta{_unwritable(self.meta) or ''} cannot be written as JSON: {exc}") from None

    def save(self, path: str | Path) -> None:
        """Write the JSON form to ``path``; a failed write leaves an existing file as it was (:mod:`.files`)."""
        write_atomically(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, d: Any, *, strict: bool = True) -> "Schedule":
        """Parse the JSON form strictly: integers must be integers (not strings, floats or booleans), and a field the
        format does not have is refused by name (a misspelt ``tool_trip`` was dropped: dozens of violations instead
        of its name). ``strict=False`` ignores unknown fields: a schedule inside a ROS message, whose newer senders
        may add fields (docs/ros.md)."""
        if not isinstance(d, dict):
            raise ScheduleError("a schedule must be a JSON object")
        if "jobs" in d and "operations" not in d:  # it said: field 'operations' must be a list
            raise ScheduleError("this is an instance, not a schedule (it has jobs, no operations)")
        if strict:
            _known(d, _FIELDS, "schedule field")
            for key, fields in (("operations", _OP_FIELDS), ("agv_trips", _AGV_FIELDS), ("tool_trips", _TT_FIELDS)):
                rows = d.get(key)
                for row in rows if isinstance(rows, list) else ():
                    if isinstance(row, dict):
                        _known(row, fields, f"field of {key}")
        try:
            ops = [OperationRecord(_int(o, "job"), _int(o, "op"), _int(o, "machine"), _int(o, "tool", True),
                                   _int(o, "start"), _int(o, "end")) for o in _list(d, "operations")]
            agv = [AgvTrip(_int(t, "agv"), _int(t, "job", True), _int(t, "op", True), _int(t, "from"),
                           _int(t, "to"), _int(t, "start"), _int(t, "end"), _bool(t, "loaded"))
                   for t in _list(d, "agv_trips", optional=True)]
            tt = [ToolTrip(_int(t, "transporter"), _int(t, "tool", True), _int(t, "job", True),
                           _int(t, "op", True), _int(t, "from"), _int(t, "to"), _int(t, "start"), _int(t, "end"),
                           _bool(t, "loaded")) for t in _list(d, "tool_trips", optional=True)]
            name = d.get("instance")
            if not isinstance(name, str):
                raise ScheduleError("field 'instance' must be a string")
            meta = d.get("meta", {})
            if not isinstance(meta, dict):
                raise ScheduleError("field 'meta' must be an object")
            return cls(instance=name, makespan=_int(d, "makespan"), n_agvs=_int(d, "n_agvs", default=0),
                       n_tool_transporters=_int(d, "n_tool_transporters", default=0),
                       operations=ops, agv_trips=agv, tool_trips=tt, meta=dict(meta))
        except (TypeError, AttributeError) as exc:
            raise ScheduleError(f"malformed schedule: {exc}") from None

    @classmethod
    def from_json(cls, text: str, *, strict: bool = True) -> "Schedule":
        try:
            return cls.from_dict(loads(text), strict=strict)
        except json.JSONDecodeError as exc:
            raise ScheduleError(f"malformed JSON: {exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> "Schedule":
        """The schedule in a JSON file; OSError if it cannot be read, :class:`ScheduleError` (naming the file) if
        it is not a schedule."""
        try:
            text = read_text(path)
        except UnicodeDecodeError:  # was the codec's message alone, without the file's name
            raise ScheduleError(f"{path}: not a text (UTF-8 JSON) file") from None
        try:
            return cls.from_json(text)
        except ScheduleError as exc:
            raise ScheduleError(f"{path}: {exc}") from None


#: the fields of a schedule's JSON object and of its records (:meth:`Schedule.to_dict`)
_FIELDS = ("instance", "makespan", "n_agvs", "n_tool_transporters", "operations", "agv_trips", "tool_trips", "meta")
_OP_FIELDS = ("job", "op", "machine", "tool", "start", "end")
_AGV_FIELDS = ("agv", "job", "op", "from", "to", "start", "end", "loaded")
_TT_FIELDS = ("transporter", "tool", "job", "op", "from", "to", "start", "end", "loaded")


def _known(d: dict, fields: tuple[str, ...], what: str) -> None:
    unknown = sorted(k for k in d if k not in fields)
    if unknown:
        raise ScheduleError(f"unknown {what} {unknown[0]!r}; the fields are {', '.join(fields)}")


def _list(d: dict, key: str, optional: bool = False) -> list:
    if key not in d and optional:
        return []
    v = d.get(key)
    if not isinstance(v, list):
        raise ScheduleError(f"field {key!r} must be a list")
    for i, x in enumerate(v):
        if not isinstance(x, dict):
            raise ScheduleError(f"{key}[{i}] must be an object")
    return v


_MISSING = object()


def _int(d: dict, key: str, nullable: bool = False, default: Any = _MISSING) -> Any:
    if key not in d:
        if default is not _MISSING:
            return default
        raise ScheduleError(f"missing field {key!r} in {_short(d)}")
    v = d[key]
    if v is None and nullable:
        return None
    if not isinstance(v, int) or isinstance(v, bool):
        raise ScheduleError(f"field {key!r} must be an integer{' or null' if nullable else ''}, got {v!r}")
    return v


def _bool(d: dict, key: str) -> bool:
    v = d.get(key)
    if not isinstance(v, bool):
        raise ScheduleError(f"field {key!r} must be true or false, got {v!r}")
    return v


def _unwritable(v: Any, at: str = "") -> str | None:
    """Where in ``v`` (as ``['key'][index]``) the first value JSON cannot hold stands; None if there is none."""
    if isinstance(v, dict):
        for k, x in v.items():
            if k is not None and not isinstance(k, (str, int, float, bool)):
                return at
            found = _unwritable(x, f"{at}[{k!r}]")
            if found is not None:
                return found
        return None
    if isinstance(v, (list, tuple)):
        for i, x in enumerate(v):
            found = _unwritable(x, f"{at}[{i}]")
            if found is not None:
                return found
        return None
    if isinstance(v, float):
        return None if math.isfinite(v) else at
    return None if v is None or isinstance(v, (str, int, bool)) else at


def _short(d: dict) -> str:
    text = json.dumps(d)
    return text if len(text) <= 80 else text[:77] + "..."


def require_schedule(obj: object, who: str) -> "Schedule":
    """``obj`` if it is a :class:`Schedule`; else a TypeError naming ``who`` (the function given it) and how to get
    one (a dict or an instance in its place reached attribute errors deep inside, or a message naming another
    function)."""
    if isinstance(obj, Schedule):
        return obj
    hint = ("Schedule.from_dict reads one from a dict" if isinstance(obj, dict)
            else "Schedule.load reads one from a file" if isinstance(obj, (str, Path))
            else "a solver returns one; Schedule.load reads one from a file")
    raise TypeError(f"{who} takes a Schedule ({hint}), got {type(obj).__name__} {obj!r:.60}")
