"""Disruptions of a run: machine breakdowns, vehicles out of service, and noise on durations.

A :class:`Scenario` is data, like an instance: it is checked against the instance it disrupts, read from and
written to JSON (``fms/scenario/v1``), and drawn at random (seeded) for experiments. What each disruption means
(docs/semantics.md, "Disruptions"):

* **breakdown** ``(machine, start, duration)``: the machine works on nothing in ``[start, start + duration)``.
  An operation running at ``start`` is suspended and resumes at the repair (it ends ``duration`` later); no
  operation starts in the window. Nobody knows of it before ``start``.
* **outage** ``(kind, vehicle, start, duration)``: the AGV (``kind="agv"``) or tool transporter (``"tt"``)
  starts no trip in the window; a trip under way at ``start`` is finished.
* **noise** ``spread`` (with ``seed``): every operation and every trip takes its nominal time times a
  lognormal factor ``exp(N(0, spread))``, rounded, at least 1 (a zero travel time stays 0). The factor of
  operation (j, k) and of the n-th trip of a vehicle are fixed by the seed, so a run is reproducible and the
  validator can recompute every realised time; deciders learn a duration only when the activity ends.

Windows of one machine or one vehicle may not overlap. A scenario names machines and vehicles that exist.
"""

from __future__ import annotations

import json
import math
import numbers
import random
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from .files import loads, read_text, write_atomically
from .instance import MAX_TIME, Instance, _is_int

__all__ = ["Breakdown", "Outage", "Scenario", "ScenarioError", "SCENARIO_SCHEMA", "VEHICLE_KINDS", "MAX_NOISE"]

SCENARIO_SCHEMA = "fms/scenario/v1"
VEHICLE_KINDS = ("agv", "tt")
MAX_NOISE = 1.0
"""The largest noise spread: at 1 one activity in six already takes 2.7 times its nominal time or more; beyond,
factors overflow into meaningless makespans (a spread of 50 gave one of 3e47, 1000 an OverflowError)."""


class ScenarioError(ValueError):
    """A scenario that is malformed or does not fit its instance (unknown machine or vehicle, bad window)."""


def _int(d: dict[str, Any], key: str, where: str) -> int:
    v = d.get(key)
    if not isinstance(v, int) or isinstance(v, bool):
        raise ScenarioError(f"{where}: '{key}' must be an integer, got {v!r}")
    return v


class _Window:
    """A time window ``[start, start + duration)``."""

    start: int
    duration: int

    def _check(self, what: str, ids: dict[str, Any]) -> None:
        for key, v in {**ids, "start": self.start, "duration": self.duration}.items():
            if not _is_int(v):
                raise ScenarioError(f"{what}: {key} must be an integer, got {v!r}")
            object.__setattr__(self, key, int(v))  # a numpy integer is kept as Python's (JSON, hashing, messages)

    @property
    def end(self) -> int:
        return self.start + self.duration


@dataclass(frozen=True)
class Breakdown(_Window):
    """Machine ``machine`` is down in the window."""

    machine: int
    start: int
    duration: int

    def __post_init__(self) -> None:
        self._check("breakdown", {"machine": self.machine})


@dataclass(frozen=True)
class Outage(_Window):
    """AGV (``kind="agv"``) or tool transporter (``"tt"``) ``vehicle`` is out of service in the window."""

    kind: str
    vehicle: int
    start: int
    duration: int

    def __post_init__(self) -> None:
        if self.kind not in VEHICLE_KINDS:
            raise ScenarioError(f"outage kind must be agv or tt, got {self.kind!r}")
        self._check(f"outage of {self.kind}", {"vehicle": self.vehicle})


@dataclass(frozen=True)
class Scenario:
    """Breakdowns, outages and noise for one run (module docstring); immutable, compared by value."""

    breakdowns: tuple[Breakdown, ...] = ()
    outages: tuple[Outage, ...] = ()
    noise: float = 0.0
    seed: int = 0
    #: the noise factors drawn so far (a memo of :meth:`_factor`); not an argument, so that ``dataclasses.replace``
    #: with another noise or seed starts an empty one (it handed the memo on, and the new scenario realised the old
    #: one's durations)
    _factors: dict = field(default_factory=dict, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.noise, numbers.Real) or isinstance(self.noise, bool) \
                or not 0 <= self.noise <= MAX_NOISE:
            raise ScenarioError(f"noise must be a spread from 0 to {MAX_NOISE:g}, got {self.noise!r}")
        if type(self.noise) not in (int, float):  # numpy's numbers are kept as Python's (np.float64 is a float)
            object.__setattr__(self, "noise", float(self.noise))
        if not _is_int(self.seed):
            raise ScenarioError(f"seed must be an integer, got {self.seed!r}")
        object.__setattr__(self, "seed", int(self.seed))
        for what, items, kind in (("breakdowns", self.breakdowns, Breakdown), ("outages", self.outages, Outage)):
            if not isinstance(items, (tuple, list)) or not all(isinstance(w, kind) for w in items):
                raise ScenarioError(f"{what} must be a sequence of {kind.__name__}, got {items!r}")
            object.__setattr__(self, what, tuple(items))  # a list given is kept as a tuple: hashable, immutable
        for b in self.breakdowns:
            if not (0 <= b.start <= MAX_TIME and 0 < b.duration <= MAX_TIME):
                raise ScenarioError(f"breakdown of machine {b.machine}: start must be from 0 and duration from 1 to "
                                    f"{MAX_TIME:,} (as an instance's times), got start {b.start}, duration "
                                    f"{b.duration}")
        for o in self.outages:
            if o.kind not in VEHICLE_KINDS:
                raise ScenarioError(f"outage kind must be agv or tt, got {o.kind!r}")
            if not (0 <= o.start <= MAX_TIME and 0 < o.duration <= MAX_TIME):
                raise ScenarioError(f"outage of {o.kind} {o.vehicle}: start must be from 0 and duration from 1 to "
                                    f"{MAX_TIME:,} (as an instance's times), got start {o.start}, duration "
                                    f"{o.duration}")
        _no_overlap(((b.machine, b) for b in self.breakdowns), "machine")
        _no_overlap((((o.kind, o.vehicle), o) for o in self.outages), "vehicle")

    def adding(self, d: "Breakdown | Outage") -> "Scenario":
        """This scenario with the breakdown or outage ``d`` added (checked as the constructor checks), sharing the
        noise factors drawn so far: the same noise and seed draw the same factors."""
        new = replace(self, breakdowns=self.breakdowns + (d,)) if isinstance(d, Breakdown) \
            else replace(self, outages=self.outages + (d,))
        object.__setattr__(new, "_factors", self._factors)
        return new

    def windows(self, machine: int) -> list[Breakdown]:
        """The machine's breakdowns, by start."""
        return sorted((b for b in self.breakdowns if b.machine == machine), key=lambda b: b.start)

    def op_end(self, machine: int, start: int, duration: int) -> int:
        """When an operation of realised ``duration`` started at ``start`` on ``machine`` ends: later by every
        breakdown that begins while it runs, at its first instant included (it is suspended until the repair)."""
        end = start + duration
        for b in self.windows(machine):
            if start <= b.start < end:
                end += b.duration
        return end

    @property
    def empty(self) -> bool:
        return not self.breakdowns and not self.outages and not self.noise

    def check(self, instance: Instance) -> None:
        """Raise :class:`ScenarioError` unless every machine and vehicle named exists in ``instance``."""
        for b in self.breakdowns:
            if not 1 <= b.machine <= instance.n_machines:
                raise ScenarioError(f"breakdown names machine {b.machine}; {instance.name} has machines "
                                    f"1..{instance.n_machines}")
        fleets = {"agv": instance.n_agvs if instance.has_agvs else 0,
                  "tt": instance.n_tool_transporters if instance.has_tools else 0}
        for o in self.outages:
            n = fleets[o.kind]
            if not 0 <= o.vehicle < n:
                what = "AGV" if o.kind == "agv" else "tool transporter"
                raise ScenarioError(f"outage names {what} {o.vehicle}; {instance.name} has "
                                    + (f"{what}s 0..{n - 1}" if n else f"no {what}s"))

    # ------------------------------------------------------------------ realised times
    def _factor(self, key: str) -> float:
        f = self._factors.get(key)
        if f is None:
            f = math.exp(random.Random(f"{self.seed}:{key}").gauss(0.0, self.noise)) if self.noise else 1.0
            self._factors[key] = f
        return f

    def op_duration(self, job: int, op: int, nominal: int) -> int:
        """The realised duration of operation (job, op); a zero duration stays zero, as a zero-length trip does."""
        if not self.noise or nominal == 0:
            return nominal
        return max(1, round(nominal * self._factor(f"op:{job}:{op}")))

    def trip_time(self, kind: str, vehicle: int, n: int, nominal: int) -> int:
        """The realised time of the ``n``-th trip of a vehicle (from 0; counting its legs between two different
        places, whatever their travel time: docs/semantics.md)."""
        if not self.noise or nominal == 0:
            return nominal
        return max(1, round(nominal * self._factor(f"{kind}:{vehicle}:{n}")))

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCENARIO_SCHEMA,
                "breakdowns": [{"machine": b.machine, "start": b.start, "duration": b.duration}
                               for b in self.breakdowns],
                "outages": [{"kind": o.kind, "vehicle": o.vehicle, "start": o.start, "duration": o.duration}
                            for o in self.outages],
                "noise": self.noise, "seed": self.seed}

    @classmethod
    def from_dict(cls, d: Any) -> "Scenario":
        if not isinstance(d, dict):
            raise ScenarioError("a scenario must be a JSON object")
        schema = d.get("schema", SCENARIO_SCHEMA)
        if schema != SCENARIO_SCHEMA:
            raise ScenarioError(f"unknown scenario schema {schema!r} (this build reads {SCENARIO_SCHEMA})")
        unknown = set(d) - {"schema", "breakdowns", "outages", "noise", "seed"}
        if unknown:
            raise ScenarioError(f"unknown scenario field(s): {', '.join(sorted(unknown))}")
        bds, outs = d.get("breakdowns", []), d.get("outages", [])
        if not isinstance(bds, list) or not isinstance(outs, list):
            raise ScenarioError("'breakdowns' and 'outages' must be lists")
        breakdowns = []
        for i, b in enumerate(bds):
            if not isinstance(b, dict):
                raise ScenarioError(f"breakdown {i} must be an object")
            w = f"breakdown {i}"
            _known_keys(b, ("machine", "start", "duration"), w)
            breakdowns.append(Breakdown(_int(b, "machine", w), _int(b, "start", w), _int(b, "duration", w)))
        outages = []
        for i, o in enumerate(outs):
            if not isinstance(o, dict):
                raise ScenarioError(f"outage {i} must be an object")
            w = f"outage {i}"
            _known_keys(o, ("kind", "vehicle", "start", "duration"), w)
            outages.append(Outage(o.get("kind"), _int(o, "vehicle", w), _int(o, "start", w), _int(o, "duration", w)))
        noise = d.get("noise", 0.0)
        seed = d.get("seed", 0)
        return cls(tuple(breakdowns), tuple(outages), noise, seed)

    @classmethod
    def load(cls, path: str | Path) -> "Scenario":
        try:
            text = read_text(path)
        except OSError as exc:
            raise ScenarioError(f"cannot read scenario {path}: {exc.strerror}") from None
        except UnicodeDecodeError:
            raise ScenarioError(f"scenario {path} is not a text (UTF-8 JSON) file") from None
        try:
            data = loads(text)
        except json.JSONDecodeError as exc:
            raise ScenarioError(f"scenario {path} is not valid JSON: {exc.msg} (line {exc.lineno})") from None
        try:
            return cls.from_dict(data)
        except ScenarioError as exc:  # name the file ("unknown scenario field(s): foo" alone did not)
            raise ScenarioError(f"scenario {path}: {exc}") from None

    def save(self, path: str | Path) -> None:
        write_atomically(path, json.dumps(self.to_dict(), indent=1) + "\n")

    # ------------------------------------------------------------------ drawing
    @classmethod
    def draw(cls, instance: Instance, *, noise: float = 0.0, breakdowns: int = 0, horizon: int = 0,
             duration: tuple[int, int] = (0, 0), seed: int = 0) -> "Scenario":
        """A random scenario: ``breakdowns`` machine breakdowns starting uniformly in ``[0, horizon)`` with
        durations uniform in ``duration`` (default: 5-15 % of the horizon), at most one per machine; noise
        ``noise``. Reproducible from ``seed``. A horizon above :data:`MAX_TIME` (a shop of times near the largest,
        whose work per machine is more) counts as :data:`MAX_TIME`: a breakdown may start no later (a draw past it
        was refused by the scenario's own check, so an env with disruptions failed at its reset). Raises
        :class:`ScenarioError` for arguments that draw nothing
        sensible (a negative count or horizon, a duration range that is empty or allows 0)."""
        if not _is_int(seed):
            raise ScenarioError(f"seed must be an integer, got {seed!r}")
        if not _is_int(breakdowns) or breakdowns < 0:
            raise ScenarioError(f"breakdowns must be an integer >= 0, got {breakdowns!r}")
        if not _is_int(horizon) or horizon < 0:
            raise ScenarioError(f"horizon must be an integer >= 0 (breakdowns start in [0, horizon)), got {horizon!r}")
        if isinstance(duration, list):
            duration = tuple(duration)  # [0, 0] was refused by a message that offered (0, 0)
        if duration != (0, 0) and not (isinstance(duration, tuple) and len(duration) == 2
                                       and all(_is_int(d) for d in duration) and 1 <= duration[0] <= duration[1]):
            raise ScenarioError(f"duration must be a range (low, high) of integers with 1 <= low <= high (a breakdown "
                                f"lasts at least 1; (0, 0): 5-15 % of the horizon), got {duration!r}")
        rng = random.Random(f"scenario:{seed}")
        horizon = min(horizon, MAX_TIME)
        lo, hi = duration if duration != (0, 0) else (max(1, horizon // 20), max(1, horizon // 7))
        machines = rng.sample(range(1, instance.n_machines + 1), min(breakdowns, instance.n_machines))
        bds = tuple(Breakdown(m, rng.randrange(max(1, horizon)), rng.randint(lo, hi)) for m in machines)
        return cls(bds, (), noise, seed)


def _known_keys(d: dict[str, Any], keys: tuple[str, ...], where: str) -> None:
    unknown = sorted(set(d) - set(keys))
    if unknown:  # a misspelt 'durarion' must not leave a window that quietly means something else
        raise ScenarioError(f"{where}: unknown field(s) {', '.join(map(repr, unknown))}; its fields are "
                            f"{', '.join(keys)}")


def _no_overlap(items: Any, what: str) -> None:
    by: dict[Any, list] = {}
    for key, w in items:
        by.setdefault(key, []).append(w)
    for key, ws in by.items():
        ws = sorted(ws, key=lambda w: w.start)
        for a, b in zip(ws, ws[1:]):
            if b.start < a.end:
                name = (f"machine {key}" if what == "machine"
                        else f"{'AGV' if key[0] == 'agv' else 'tool transporter'} {key[1]}")
                raise ScenarioError(f"{name}: windows [{a.start}, {a.end}) and [{b.start}, {b.end}) overlap")
