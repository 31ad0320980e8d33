"""The validated data model of an FMS instance.

Everything else in the project (the Petri net, the validator, the solvers, the nodes) reads this model;
nothing else defines what an instance is.

Numbering (the project's contract):

* location 0 is the load/unload station (L/U) and the tool magazine; machine ``k`` is location ``k``;
* machines and tools are numbered from 1;
* jobs, operations, AGVs and tool transporters are numbered from 0.

Modes follow from the data:

* AGVs are modelled iff ``agv_travel`` is given (then ``n_agvs >= 1``);
* tools are modelled iff ``tool_travel`` is given (then ``n_tool_transporters >= 1``); an operation whose
  ``tool`` is ``None`` needs no tool.
"""

from __future__ import annotations

import json
import numbers
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable, Sequence

from .files import loads, write_atomically

__all__ = ["Operation", "Instance", "InstanceError", "require_instance"]

Matrix = tuple[tuple[int, ...], ...]


class InstanceError(ValueError):
    """An instance (or instance file) that breaks the data model; the message says what and where."""


def _is_int(x: Any) -> bool:
    """An integer, Python's or another library's (numpy's ``int64``: shops generated with numpy were refused as
    "must be an integer, got np.int64(1)"); not a bool. The data model stores them as Python ints (:func:`_plain`)."""
    return type(x) is int or (isinstance(x, numbers.Integral) and not isinstance(x, bool))


def _plain(x: Any) -> Any:
    """A numpy array as nested lists and a numpy integer as a Python int (what JSON and the solvers take); anything
    else as it is."""
    if isinstance(x, (list, tuple, dict, str)) or x is None:
        return x
    if hasattr(x, "tolist"):  # an array, or a numpy scalar
        return x.tolist()
    return int(x) if _is_int(x) else x


#: The largest duration or travel time: sums of many still fit CP-SAT's and numpy's 64-bit integers (a time of
#: 10**30 was "valid" to the list schedulers and crashed cpsat and ppo).
MAX_TIME = 10**9
#: The most machines, tools, AGVs or tool transporters of one shop (10**8 AGVs ran out of memory).
MAX_COUNT = 1000


@dataclass(frozen=True, slots=True)
class Operation:
    """One operation: processed on ``machine`` (1-based) for ``duration`` time units, needing ``tool``."""

    machine: int
    tool: int | None
    duration: int

    def __deepcopy__(self, memo: dict) -> "Operation":
        return self  # a value: twins share it

    def __post_init__(self) -> None:
        if type(self.machine) is not int or type(self.duration) is not int or (  # (the common case: nothing to do)
                self.tool is not None and type(self.tool) is not int):
            for name in ("machine", "tool", "duration"):
                value = getattr(self, name)
                if type(value) is not int and _is_int(value):
                    object.__setattr__(self, name, int(value))
        if not _is_int(self.machine) or not 1 <= self.machine <= MAX_COUNT:
            raise InstanceError(f"machine must be an integer from 1 to {MAX_COUNT}, got {self.machine!r}")
        if self.tool is not None and (not _is_int(self.tool) or not 1 <= self.tool <= MAX_COUNT):
            raise InstanceError(f"tool must be null or an integer from 1 to {MAX_COUNT}, got {self.tool!r}")
        if not _is_int(self.duration) or not 0 <= self.duration <= MAX_TIME:
            raise InstanceError(f"duration must be a non-negative integer (at most {MAX_TIME:,}), got "
                                f"{self.duration!r}")


def _matrix(name: str, rows: Any, size: int) -> Matrix:
    rows = _plain(rows)
    if not isinstance(rows, (list, tuple)) or len(rows) != size:
        got = len(rows) if isinstance(rows, (list, tuple)) else type(rows).__name__
        raise InstanceError(f"{name} must be a {size}x{size} matrix (L/U + {size - 1} machines), got {got} rows")
    out = []
    for i, row in enumerate(rows):
        if not isinstance(row, (list, tuple)) or len(row) != size:
            got = len(row) if isinstance(row, (list, tuple)) else type(row).__name__
            raise InstanceError(f"{name} row {i} must have {size} entries, got {got}")
        plain = True
        for j, x in enumerate(row):
            if type(x) is not int:
                plain = False
            if not _is_int(x):
                raise InstanceError(f"{name}[{i}][{j}] must be an integer, got {x!r}")
            if x < 0:
                raise InstanceError(f"{name}[{i}][{j}] is negative ({x}); travel times must be >= 0")
            if x > MAX_TIME:
                raise InstanceError(f"{name}[{i}][{j}] is {x}; travel times must be from 0 to {MAX_TIME:,}")
        out.append(tuple(row) if plain else tuple(int(x) for x in row))
    for i in range(size):
        if out[i][i] != 0:
            raise InstanceError(f"{name}[{i}][{i}] must be 0 (no travel within a location), got {out[i][i]}")
    return tuple(out)


@dataclass(frozen=True)
class Instance:
    """A flexible-manufacturing job shop with AGVs and shared tools.

    ``jobs[j][k]`` is operation ``k`` of job ``j``. ``agv_travel[a][b]`` and ``tool_travel[a][b]`` are
    travel times from location ``a`` to ``b`` ((m+1)x(m+1), index 0 = L/U / tool magazine); loaded and empty
    trips use the same matrix. ``n_machines`` is derived from the matrices (or from the operations of a plain
    job shop) unless given; ``n_tools`` likewise from the operations. A given count smaller than what an operation
    uses is refused. Tools (``n_tools`` or an operation's tool) and tool transporters come with ``tool_travel``, AGVs
    with ``agv_travel``: a count without its matrix is refused, as is a matrix without its fleet.
    """

    name: str
    jobs: tuple[tuple[Operation, ...], ...]
    agv_travel: Matrix | None = None
    tool_travel: Matrix | None = None
    n_agvs: int = 0
    n_tool_transporters: int = 0
    n_machines: int = 0
    n_tools: int = 0
    meta: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)

    def __deepcopy__(self, memo: dict) -> "Instance":
        """An instance is a value (frozen, its tables tuples): twins of a shop share it."""
        return self

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        for name in ("jobs", "agv_travel", "tool_travel", "n_machines", "n_tools", "n_agvs", "n_tool_transporters"):
            set_(self, name, _plain(getattr(self, name)))  # numpy arrays and integers as Python's
        if not isinstance(self.name, str) or not self.name:
            raise InstanceError("instance name must be a non-empty string")
        if not self.name.isprintable():  # a lone surrogate ("\ud800" in JSON) crashed the output after the solve (not
            # UTF-8), and a line break or a control character made a name that printed as two or a garbled line
            raise InstanceError(f"instance name {self.name[:60]!r} holds a character that cannot be printed (a line "
                                "break, a control or format character, or half a surrogate pair); rename it")
        jobs = tuple(tuple(_op(j, k, op) for k, op in enumerate(ops)) for j, ops in enumerate(_seq(self.jobs, "jobs")))
        if not jobs:
            raise InstanceError("instance has no jobs")
        for j, ops in enumerate(jobs):
            if not ops:
                raise InstanceError(f"job {j} has no operations")
        set_(self, "jobs", jobs)
        used_m = max(op.machine for ops in jobs for op in ops)
        used_t = max((op.tool for ops in jobs for op in ops if op.tool is not None), default=0)
        m = self.n_machines
        if not _is_int(m) or not 0 <= m <= MAX_COUNT:
            raise InstanceError(f"n_machines must be an integer from 0 to {MAX_COUNT} (0: derived), got {m!r}")
        derived = ""  # where the machine count came from, when it was not given
        if not m:
            sizes = {}
            for name in ("agv_travel", "tool_travel"):
                rows = getattr(self, name)
                if rows is not None:
                    if not isinstance(rows, (list, tuple)) or len(rows) < 2:
                        raise InstanceError(f"{name} must be an (m+1)x(m+1) matrix")
                    sizes[name] = len(rows)
            if len(set(sizes.values())) > 1:
                raise InstanceError(f"agv_travel has {sizes['agv_travel']} rows and tool_travel "
                                    f"{sizes['tool_travel']}: both must be (m+1)x(m+1) for the same m machines")
            if sizes:
                name, rows_n = next(iter(sizes.items()))
                m, derived = rows_n - 1, f" (from the {rows_n} rows of {name}: L/U + {rows_n - 1} machines)"
                if m > MAX_COUNT:  # (taken, it wrote a file that n_machines' own check then refused)
                    raise InstanceError(f"{name} has {rows_n} rows: L/U + {m} machines, more than {MAX_COUNT}")
        m = m or used_m
        if used_m > m:
            raise InstanceError(f"an operation uses machine {used_m} but the instance has only {m} machines{derived}")
        set_(self, "n_machines", m)
        for name in ("agv_travel", "tool_travel"):
            rows = getattr(self, name)
            if rows is not None:
                set_(self, name, _matrix(name, rows, m + 1))
        t = self.n_tools
        if not _is_int(t) or not 0 <= t <= MAX_COUNT:
            raise InstanceError(f"n_tools must be an integer from 0 to {MAX_COUNT} (0: derived), got {t!r}")
        if t and used_t > t:
            raise InstanceError(f"an operation uses tool {used_t} but the instance has only {t} tools (n_tools)")
        set_(self, "n_tools", t or used_t)
        for name in ("n_agvs", "n_tool_transporters"):
            v = getattr(self, name)
            if not _is_int(v) or not 0 <= v <= MAX_COUNT:
                raise InstanceError(f"{name} must be an integer from 0 to {MAX_COUNT}, got {v!r}")
        # a fleet and its travel matrix come together (a count without its matrix was set to 0 without a word)
        for count, matrix, what, matrix_words, shop_without in (
                ("n_agvs", "agv_travel", "AGVs", "an AGV", "AGVs"),
                ("n_tool_transporters", "tool_travel", "tool transporters", "a tool", "tools")):
            n = getattr(self, count)
            if getattr(self, matrix) is not None and n < 1:
                raise InstanceError(f"the instance has {matrix_words} travel matrix but no {what} ({count} is 0): give "
                                    f"{count}, or leave {matrix} out for a shop without {shop_without}")
            if n and getattr(self, matrix) is None:
                raise InstanceError(f"{count} is {n} but {matrix} is missing: {what} need a travel matrix (or leave "
                                    f"{count} out)")
        if self.tool_travel is None:
            if used_t:
                raise InstanceError("operations need tools but tool_travel is null: give a tool travel matrix, or "
                                    "operations without tools")  # (it said --no-tools, which reads the file first)
            if self.n_tools:  # (kept: a "plain job shop" of 3 tools, which padded an env's observations by 3 tools)
                raise InstanceError(f"n_tools is {self.n_tools} but tool_travel is missing: tools need a tool travel "
                                    "matrix and transporters (give tool_travel and n_tool_transporters, or leave "
                                    "n_tools out for a shop without tools)")

    # ------------------------------------------------------------------ derived facts
    @property
    def n_jobs(self) -> int:
        return len(self.jobs)

    @property
    def n_operations(self) -> int:
        return sum(len(ops) for ops in self.jobs)

    @property
    def has_agvs(self) -> bool:
        return self.agv_travel is not None

    @property
    def has_tools(self) -> bool:
        return self.tool_travel is not None

    @property
    def mode(self) -> str:
        """``"jobshop"``, ``"agvs"``, ``"tools"`` (tools, parts move instantly) or ``"agvs+tools"``."""
        if self.has_agvs:
            return "agvs+tools" if self.has_tools else "agvs"
        return "tools" if self.has_tools else "jobshop"

    def describe(self) -> str:
        fleet = []
        if self.has_agvs:
            fleet.append(_count(self.n_agvs, "AGV"))
        if self.has_tools:
            fleet.append(f"{_count(self.n_tools, 'tool')}, {_count(self.n_tool_transporters, 'tool transporter')}")
        return (
            f"{self.name}: {_count(self.n_jobs, 'job')} x {_count(self.n_machines, 'machine')}, "
            f"{_count(self.n_operations, 'operation')}"
            + (f", {', '.join(fleet)}" if fleet else ", plain job shop")
        )

    # ------------------------------------------------------------------ variants
    def with_fleet(self, n_agvs: int | None = None, n_tool_transporters: int | None = None) -> "Instance":
        """The same instance with other fleet sizes (``None`` keeps the current one)."""
        return replace(
            self,
            n_agvs=self.n_agvs if n_agvs is None else n_agvs,
            n_tool_transporters=self.n_tool_transporters if n_tool_transporters is None else n_tool_transporters,
        )

    def without_tools(self) -> "Instance":
        """Drop tools: no tool needs, no tool transport."""
        jobs = tuple(tuple(Operation(op.machine, None, op.duration) for op in ops) for ops in self.jobs)
        return replace(self, jobs=jobs, tool_travel=None, n_tool_transporters=0, n_tools=0)

    def without_agvs(self) -> "Instance":
        """Drop AGVs: parts move instantly (a plain job shop if there are no tools either)."""
        return replace(self, agv_travel=None, n_agvs=0)

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "jobs": [[{"machine": o.machine, "tool": o.tool, "duration": o.duration} for o in ops] for ops in self.jobs],
            "agv_travel": [list(r) for r in self.agv_travel] if self.agv_travel is not None else None,
            "tool_travel": [list(r) for r in self.tool_travel] if self.tool_travel is not None else None,
            "n_agvs": self.n_agvs,
            "n_tool_transporters": self.n_tool_transporters,
            "n_machines": self.n_machines,
            "n_tools": self.n_tools,
        }

    def to_json(self, indent: int | None = None) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    @classmethod
    def from_dict(cls, data: Any) -> "Instance":
        if not isinstance(data, dict):
            raise InstanceError("an instance must be a JSON object")
        if "jobs" not in data and "operations" in data and "makespan" in data:  # said: missing the field 'name'
            raise InstanceError("this is a schedule, not an instance (it has operations and a makespan, no jobs)")
        for key in ("name", "jobs"):
            if key not in data:
                raise InstanceError(f"instance is missing the field {key!r}")
        unknown = sorted(set(data) - set(_FIELDS))
        if unknown:  # a misspelt field would otherwise be dropped without a word (n_agv: no AGVs)
            raise InstanceError(f"unknown instance field {unknown[0]!r}; the fields are {', '.join(_FIELDS)}")
        for count, matrix, what in (("n_agvs", "agv_travel", "AGVs"),
                                    ("n_tool_transporters", "tool_travel", "tool transporters")):
            if data.get(matrix) is not None and count not in data:  # it said "n_agvs = 0; use --no-agvs"
                raise InstanceError(f"{matrix} is given but {count} is missing: give the number of {what} "
                                    f"({count}), or leave {matrix} out")

        def given(key: str) -> Any:  # null: derived; false, "" or [] are not counts (they were read as 0)
            v = data.get(key)
            return 0 if v is None else v

        return cls(
            name=data["name"],
            jobs=data["jobs"],
            agv_travel=data.get("agv_travel"),
            tool_travel=data.get("tool_travel"),
            n_agvs=given("n_agvs"),
            n_tool_transporters=given("n_tool_transporters"),
            n_machines=given("n_machines"),
            n_tools=given("n_tools"),
        )

    @classmethod
    def from_json(cls, text: str) -> "Instance":
        try:
            data = loads(text)
        except json.JSONDecodeError as exc:
            raise InstanceError(f"malformed JSON: {exc}") from None
        return cls.from_dict(data)

    def save(self, path: str | Path) -> None:
        """Write the JSON form to ``path``; a failed write leaves an existing file as it was (:mod:`.files`)."""
        write_atomically(path, self.to_json(indent=1) + "\n")


#: the fields of an instance's JSON object (:meth:`Instance.to_dict`)
_FIELDS = ("name", "jobs", "agv_travel", "tool_travel", "n_agvs", "n_tool_transporters", "n_machines", "n_tools")


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "s")


def _seq(x: Any, what: str) -> Sequence[Any]:
    if not isinstance(x, (list, tuple)):
        raise InstanceError(f"{what} must be a list")
    return x


def _op(j: int, k: int, op: Any) -> Operation:
    if isinstance(op, Operation):
        return op
    op = _plain(op)
    try:
        if isinstance(op, dict):
            missing = [f for f in ("machine", "duration") if f not in op]
            if missing:
                raise InstanceError(f"missing field {missing[0]!r}")
            unknown = sorted(set(op) - {"machine", "tool", "duration"})
            if unknown:  # a misspelt tool would otherwise make an operation that needs none
                raise InstanceError(f"unknown field {unknown[0]!r}; an operation has machine, tool and duration")
            return Operation(op["machine"], op.get("tool"), op["duration"])
        if isinstance(op, (list, tuple)) and len(op) in (2, 3):
            # [machine, duration] or [machine, tool, duration]
            if len(op) == 2:
                return Operation(op[0], None, op[1])
            return Operation(op[0], op[1], op[2])
        raise InstanceError(f"expected an object {{machine, tool, duration}}, got {op!r}")
    except InstanceError as exc:
        raise InstanceError(f"job {j} operation {k}: {exc}") from None


def jobs_from_rows(rows: Iterable[Iterable[tuple[int, int | None, int]]]) -> tuple[tuple[Operation, ...], ...]:
    """Build the jobs tuple from ``(machine, tool, duration)`` triples."""
    return tuple(tuple(Operation(m, t, d) for m, t, d in ops) for ops in rows)


def require_instance(obj: object, who: str) -> Instance:
    """``obj`` if it is an :class:`Instance`; else a TypeError naming ``who`` (the function or class given it) and
    how to get one: a name or a dict reached attribute errors deep inside."""
    if isinstance(obj, Instance):
        return obj
    hint = ("fms_sim.benchmarks.builtin or fms_sim.formats.load_instance reads one by name" if isinstance(obj, str)
            else "Instance.from_dict reads one from a dict" if isinstance(obj, dict)
            else "build one with Instance(...) or load it")
    raise TypeError(f"{who} takes an Instance ({hint}), got {type(obj).__name__} {obj!r:.60}")
