"""Schedules: what every solver returns and every node publishes, with their JSON form.

A schedule lists every operation with its start and end, every AGV trip and every tool-transporter trip.
Empty (deadheading) trips have ``loaded = False`` and ``job``/``op``/``tool`` set to ``None``; a trip whose
origin equals its destination may be omitted. ``fms_sim.validate`` checks a schedule against its instance
without using the Petri net.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["OperationRecord", "AgvTrip", "ToolTrip", "Schedule", "ScheduleError"]


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

    def to_dict(self) -> dict[str, Any]:
        return {"transporter": self.transporter, "tool": self.tool, "job": self.job, "op": self.op,
                "from": self.from_, "to": self.to, "start": self.start, "end": self.end, "loaded": self.loaded}


@dataclass
class Schedule:
    """A complete schedule; ``makespan`` is the latest operation end."""

    instance: str
    makespan: int
    n_agvs: int = 0
    n_tool_transporters: int = 0
    operations: list[OperationRecord] = field(default_factory=list)
    agv_trips: list[AgvTrip] = field(default_factory=list)
    tool_trips: list[ToolTrip] = field(default_factory=list)
    meta: dict[str, Any] = field(default_factory=dict)
    """Free-form facts about how it was made (solver, wall time, bound); exported under ``"meta"``."""

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "instance": self.instance,
            "makespan": self.makespan,
            "n_agvs": self.n_agvs,
            "n_tool_transporters": self.n_tool_transporters,
            "operations": [asdict(o) for o in sorted(self.operations, key=lambda o: (o.start, o.job, o.op))],
            "agv_trips": [t.to_dict() for t in sorted(self.agv_trips, key=lambda t: (t.agv, t.start, t.end))],
            "tool_trips": [t.to_dict() for t in sorted(self.tool_trips, key=lambda t: (t.transporter, t.start, t.end))],
        }
        if self.meta:
            out["meta"] = self.meta
        return out

    def to_json(self, indent: int | None = 1) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json() + "\n")

    @classmethod
    def from_dict(cls, d: Any) -> "Schedule":
        try:
            return cls(
                instance=d["instance"],
                makespan=int(d["makespan"]),
                n_agvs=int(d.get("n_agvs", 0)),
                n_tool_transporters=int(d.get("n_tool_transporters", 0)),
                operations=[OperationRecord(o["job"], o["op"], o["machine"], o.get("tool"), o["start"], o["end"])
                            for o in d["operations"]],
                agv_trips=[AgvTrip(t["agv"], t.get("job"), t.get("op"), t["from"], t["to"], t["start"], t["end"],
                                   bool(t["loaded"])) for t in d.get("agv_trips", [])],
                tool_trips=[ToolTrip(t["transporter"], t.get("tool"), t.get("job"), t.get("op"), t["from"], t["to"],
                                     t["start"], t["end"], bool(t["loaded"])) for t in d.get("tool_trips", [])],
                meta=dict(d.get("meta", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ScheduleError(f"malformed schedule: {type(exc).__name__}: {exc}") from None

    @classmethod
    def from_json(cls, text: str) -> "Schedule":
        try:
            return cls.from_dict(json.loads(text))
        except json.JSONDecodeError as exc:
            raise ScheduleError(f"malformed JSON: {exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> "Schedule":
        return cls.from_json(Path(path).read_text())
