"""Generated shops for training, the fixed held-out set, and the check that keeps both off the test set.

Learned dispatching policies are trained and selected on *generated* shops only: no reported benchmark
instance (``EX11``..``EX104``, ``ra01``..``ra20`` on any layout, ``sl00``..``sl79``, ``ta01``; see
:mod:`fms_sim.benchmarks`) may be in a training set, an evaluation (model-selection) set or a warm-start
stage, and neither may the 50 held-out shops ``ho00``..``ho49`` that judge generalisation.

Two generated families:

* :func:`bu_shop` — random job sets on the four Bilge–Ulusoy layouts (the ``EX`` family; ranges below);
* the large benchmark's Taillard-LCG shops (:func:`fms_sim.generate.generate_instances`), any size and fleet.

Instance specs (:func:`expand_specs`; ``fms train`` and model configs use them):

* a built-in name (``EX12``, ``ra01L3``, ``sl00``, ``ho07``) or an instance file, as ``fms solve`` takes them;
* a shell pattern over those names: ``'EX?2'``, ``'sl[0-2]?'``, ``'ho*'``;
* ``gen:JxMxT*COUNT@SEED`` — COUNT Taillard-LCG shops of J jobs x M machines x T tools, their time, routing
  and tool streams seeded from SEED (``derived_seed(SEED, 1..3)``), the large benchmark's travel matrices for
  M machines, 10 AGVs and 5 tool transporters, named ``genJxMsSEED_00``.. (unchanged since the first models:
  the same spec gives the same shops and names); all are built at once, so COUNT x J x M is at most 10**7
  operations (``generate.MAX_GENERATED_OPERATIONS``, about 850 MB);
* ``gen:JxMxT*COUNT@SEED/OPT[/OPT]`` — the same shops with a fleet of their own; OPT is ``aN`` (N AGVs),
  ``tN`` (N tool transporters), both as ``aNtN``, or ``notools`` (operations without tools, no tool
  transport; the tool stream is not drawn). The names carry the options: ``gen20x15s7-a4t2_00``;
* ``genbu:L*COUNT@SEED[/aN]`` — COUNT random BU job sets on layout L (1..4), or on each of the four layouts
  for ``L = *`` (job set ``k`` on layouts 1..4, then ``k + 1``: ``4 * COUNT`` shops, as the EX family puts
  every job set on every layout), 2 AGVs unless ``/aN``. Job set ``k`` is ``bu_shop(L, SEED * 1000 + k)``
  (so COUNT <= 1000), named ``buLsSEED_00``.. (``buLsSEED-aN_00`` with an option).

A config's ``fleet`` (``agvs``, ``tool_transporters``, ``no_tools``) applies to every spec; a spec's own
options win over it for that spec. Malformed specs raise :class:`ValueError` naming the spec and the forms.

Reserved seeds: generator seeds ``SEED >= 900000`` (:data:`HELDOUT_SEED_MIN`) belong to the held-out set and
``gen``/``genbu`` specs refuse them (``bu_shop`` seeds from ``900000 * 1000`` on are therefore never drawn by a
spec). Held-out ``gen`` shops also derive their stream seeds with their own salts (:data:`HELDOUT_SALTS`,
11..13 instead of 1..3), and a training ``gen`` spec whose derived stream seed equals a held-out one is refused
too. Seeds only make collisions unlikely; :func:`check_training_specs` compares contents.

The held-out set (``src/fms_sim/data/heldout.json``, loaded by :func:`heldout_shops`): 50 shops ``ho00``..
``ho49`` from 5 jobs x 4 machines to 100 x 20 — 12 BU-layout shops (3 per layout, 1–3 AGVs) and 38 Taillard-LCG
shops (5x4 .. 100x20, 23 with tools, 2–10 AGVs, 1–5 transporters). Each entry lists its generator and every
seed, so the file alone defines the set. The names load wherever an instance name is accepted
(``fms solve ho07``).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import functools
import hashlib
import json
import numbers
import re
from importlib import resources
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .benchmarks import BU_AGVS, _bu_layout, builtin, builtin_names
from .generate import generate_instances
from .instance import Instance, InstanceError, Operation

__all__ = [
    "bu_shop", "expand_specs", "derived_seed", "heldout_shops", "heldout_shop", "heldout_names",
    "check_training_specs", "is_reserved", "job_fingerprint", "SPEC_FORMS", "HELDOUT_SEED_MIN",
    "HELDOUT_SALTS", "BU_RANGES",
]

# ---------------------------------------------------------------------------------------------- BU family
#: Ranges of the ten Bilge–Ulusoy job sets (``fms_sim/data/bu_jobsets.json``), which :func:`bu_shop` keeps.
BU_RANGES: dict[str, tuple[int, int]] = {
    "jobs": (5, 8),            # sets have 5 (4 sets), 6 (5 sets) or 8 (set 7) jobs
    "ops_per_job": (2, 5),     # 16 jobs with 2, 30 with 3, 11 with 4, 1 with 5 operations
    "total_ops": (13, 21),     # operations per job set
    "time": (3, 22),           # processing times
    "machines": (4, 4),
}
#: How often the BU jobs have 2, 3, 4, 5 operations (58 jobs in all); :func:`bu_shop` draws with these weights.
_BU_OPS_COUNTS = {2: 16, 3: 30, 4: 11, 5: 1}
#: Share of BU jobs that visit a machine twice (3 of 58, all in set 4, never twice in a row).
_BU_REVISIT_SHARE = 3 / 58
_BU_SEED_STRIDE = 1000


def bu_shop(layout: int, seed: int, name: str | None = None, *, n_agvs: int = BU_AGVS) -> Instance:
    """A random job set in the style of Bilge & Ulusoy (1995) on BU ``layout`` (1..4), from ``seed``.

    Like the ``EX`` instances: 4 machines, the layout's AGV travel matrix, ``n_agvs`` AGVs (2 as in BU), no
    tools. The job set keeps the ranges of the ten BU sets (:data:`BU_RANGES`): 5–8 jobs, 2–5 operations per
    job (drawn with the BU frequencies 16:30:11:1), 13–21 operations in all (redrawn until inside),
    processing times uniform in 3..22. A job's machines are distinct (a random ordered choice) except that,
    as in 3 of the 58 BU jobs, a job may revisit a machine (and one of 5 operations must), never twice in a
    row. The job set depends only on ``seed`` (``np.random.default_rng(seed)``), so one seed on the four
    layouts gives four shops sharing their jobs, as ``EX{s}1``..``EX{s}4`` do.

    The project's BU names (``EX{set}{layout}``) encode no processing-time scaling, so none is reproduced.
    """
    # (2.0 was a KeyError; numpy integers pass, as Python's)
    if isinstance(layout, bool) or not isinstance(layout, (int, np.integer)) or layout not in (1, 2, 3, 4):
        raise InstanceError(f"BU layout must be 1, 2, 3 or 4, got {layout!r}")
    layout = int(layout)
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:  # (np.int64: as the layout)
        raise InstanceError(f"seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    rng = np.random.default_rng(seed)
    lengths = _bu_job_lengths(rng)
    jobs = tuple(_bu_job(rng, k) for k in lengths)
    return Instance(
        name=name or f"bu{layout}s{seed}",
        jobs=jobs,
        agv_travel=_bu_layout(layout),
        n_agvs=n_agvs,
        n_machines=4,
        meta={"generator": "bu", "layout": layout, "seed": seed},
    )


def _bu_job_lengths(rng: np.random.Generator) -> list[int]:
    """Operations per job: a job count in 5..8 and BU-frequency lengths, redrawn until 13..21 in all."""
    sizes = np.array(list(_BU_OPS_COUNTS))
    weights = np.array(list(_BU_OPS_COUNTS.values()), dtype=float)
    lo_jobs, hi_jobs = BU_RANGES["jobs"]
    lo_ops, hi_ops = BU_RANGES["total_ops"]
    while True:
        n = int(rng.integers(lo_jobs, hi_jobs + 1))
        lengths = [int(x) for x in rng.choice(sizes, size=n, p=weights / weights.sum())]
        if lo_ops <= sum(lengths) <= hi_ops:
            return lengths


def _bu_job(rng: np.random.Generator, n_ops: int) -> tuple[Operation, ...]:
    """One job of ``n_ops`` operations on machines 1..4 (see :func:`bu_shop` for the routing rule)."""
    lo, hi = BU_RANGES["time"]
    if n_ops <= 4 and rng.random() >= _BU_REVISIT_SHARE:
        machines = [int(m) + 1 for m in rng.permutation(4)[:n_ops]]
    else:  # any machine but the previous one
        machines = [int(rng.integers(1, 5))]
        while len(machines) < n_ops:
            others = [m for m in range(1, 5) if m != machines[-1]]
            machines.append(others[int(rng.integers(len(others)))])
    times = rng.integers(lo, hi + 1, size=n_ops)
    return tuple(Operation(m, None, int(t)) for m, t in zip(machines, times))


# ---------------------------------------------------------------------------------------------- specs
#: First generator seed reserved for the held-out set; training specs must use smaller ones.
HELDOUT_SEED_MIN = 900_000
#: Salts of the held-out ``gen`` shops' time, routing and tool streams (training specs use 1, 2, 3).
HELDOUT_SALTS = (11, 12, 13)
_TRAIN_SALTS = (1, 2, 3)
_M31 = 2**31 - 1

#: The accepted spec forms, quoted by every spec error.
SPEC_FORMS = (
    "a built-in name or instance file (EX12, ra01L3, sl00, ho07, path.json), a shell pattern over the "
    "built-in and held-out names ('EX?2', 'sl[0-2]?'), 'gen:JxMxT*COUNT@SEED' with optional '/aN', '/tN', "
    "'/aNtN', '/notools', or 'genbu:L*COUNT@SEED' (L = 1..4 or *) with optional '/aN'; "
    f"SEED < {HELDOUT_SEED_MIN} (larger seeds are reserved for the held-out set)"
)

# ASCII digits only: \d took other scripts' digits ('gen:5x3x3*2@\u0663' was seed 3, another spec's shops and names)
_GEN_RE = re.compile(r"gen:(\d+)x(\d+)x(\d+)\*(\d+)@(\d+)((?:/[^/]*)*)", re.IGNORECASE | re.ASCII)
_GENBU_RE = re.compile(r"genbu:([1-4*])\*(\d+)@(\d+)((?:/[^/]*)*)", re.IGNORECASE | re.ASCII)
_OPT_RE = re.compile(r"(?:a(\d+))?(?:t(\d+))?|(notools)", re.IGNORECASE | re.ASCII)

_DEFAULT_FLEET: dict[str, Any] = {"agvs": None, "tool_transporters": None, "no_tools": False}


def derived_seed(seed: int, salt: int) -> int:
    """A Taillard-LCG seed (1..2^31-2) for stream ``salt`` of spec seed ``seed`` (the ``gen:`` rule)."""
    return (seed * 1_000_003 + salt * 7_919 + 12_345) % (_M31 - 1) + 1


def _spec_error(spec: str, why: str) -> ValueError:
    return ValueError(f"bad instance spec {spec!r}: {why}. Accepted: {SPEC_FORMS}")


def expand_specs(specs: Sequence[str], fleet: dict[str, Any] | None = None) -> list[Instance]:
    """The instances of ``specs`` (forms in the module docstring), in order, with ``fleet`` applied.

    ``fleet`` has the keys of a model config's ``fleet`` (``agvs``, ``tool_transporters``, ``no_tools``;
    ``None``/``False`` keep the instance's own). Raises :class:`ValueError` (an :class:`InstanceError` for
    names and files) that names the offending spec.
    """
    if isinstance(specs, str):
        raise ValueError(f"instance specs must be a list of strings, got the string {specs!r}")
    if fleet is not None and not isinstance(fleet, dict):  # a TypeError from dict(**...)
        raise ValueError(f"the fleet must be a dict ({', '.join(_DEFAULT_FLEET)}), got {type(fleet).__name__}")
    unknown = sorted(set(fleet or ()) - set(_DEFAULT_FLEET))
    if unknown:  # a misspelt "agv" was ignored
        raise ValueError(f"unknown fleet key(s) {', '.join(map(repr, unknown))}; the keys are "
                         f"{', '.join(_DEFAULT_FLEET)}")
    fleet = dict(fleet or {})
    for key in ("agvs", "tool_transporters"):
        v = fleet.get(key)
        if v is not None and (not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < 1):  # 0: default 10
            raise ValueError(f"fleet {key} must be an integer >= 1 or None (the shop's own), got {v!r}")
        if v is not None:
            fleet[key] = int(v)  # numpy's integers as Python's
    if not isinstance(fleet.get("no_tools", False), (bool, type(None))):  # "false" dropped the tools
        raise ValueError(f"fleet no_tools must be true, false or None, got {fleet.get('no_tools')!r}")
    if fleet.get("no_tools") and fleet.get("tool_transporters") is not None:  # (gen: specs dropped the count
        # without a word; a built-in's load refused it)
        raise ValueError("fleet: set the number of tool transporters or drop the tools, not both (tool_transporters "
                         "/ no_tools)")
    fl = dict(_DEFAULT_FLEET, **fleet)
    out: list[Instance] = []
    for spec in specs:
        out.extend(_expand_one(spec, fl))
    return out


def _expand_one(spec: Any, fleet: dict[str, Any]) -> list[Instance]:
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"an instance spec must be a non-empty string, got {spec!r}. Accepted: {SPEC_FORMS}")
    key = spec.strip()
    low = key.lower()
    if low.startswith("gen:"):
        return _expand_gen(key, fleet)
    if low.startswith("genbu:"):
        return _expand_genbu(key, fleet)
    if any(c in key for c in "*?[") and not Path(key).exists():
        names = [n for n in _pattern_names() if fnmatch.fnmatchcase(n.lower(), low)]
        if not names:
            raise ValueError(f"pattern {spec!r} matches no built-in instance (built-ins and held-out shops: "
                             f"{_names_hint()})")
    else:
        names = [key]
    return [_load(name, fleet) for name in names]


def _pattern_names() -> list[str]:
    return builtin_names() + heldout_names()


def _names_hint() -> str:
    from .benchmarks import NAME_PATTERNS

    return NAME_PATTERNS


def _load(name: str, fleet: dict[str, Any]) -> Instance:
    from .benchmarks import is_builtin_name
    from .formats import load_instance

    if not Path(name).exists() and not is_builtin_name(name):
        raise InstanceError(f"bad instance spec {name!r}: no such file or built-in name. Accepted: {SPEC_FORMS}")
    return load_instance(name, agvs=fleet["agvs"], tool_transporters=fleet["tool_transporters"],
                         no_tools=bool(fleet["no_tools"]))


def _options(spec: str, text: str, allowed: str) -> dict[str, Any]:
    """Parse a spec's ``/OPT`` suffix into ``{"agvs", "tool_transporters", "notools"}`` (each at most once).

    ``allowed`` is the option letters the generator accepts (``"atn"`` for gen, ``"a"`` for genbu).
    """
    opts: dict[str, Any] = {"agvs": None, "tool_transporters": None, "notools": False}
    for token in text.split("/")[1:]:
        m = _OPT_RE.fullmatch(token)
        if not token or m is None:
            raise _spec_error(spec, f"unknown option {'/' + token!r}")
        a, t, notools = m.groups()
        for key, value, letter in (("agvs", a, "a"), ("tool_transporters", t, "t")):
            if value is None:
                continue
            if letter not in allowed:
                raise _spec_error(spec, f"option {'/' + token!r} does not apply to this generator")
            if opts[key] is not None:
                raise _spec_error(spec, f"{letter}N is given twice")
            if int(value) < 1:
                raise _spec_error(spec, f"{letter}{value}: a fleet needs at least 1 vehicle")
            opts[key] = int(value)
        if notools:
            if "n" not in allowed:
                raise _spec_error(spec, "'/notools' does not apply to this generator (it has no tools)")
            if opts["notools"]:  # (as aN and tN: each option at most once)
                raise _spec_error(spec, "'/notools' is given twice")
            opts["notools"] = True
    if opts["notools"] and opts["tool_transporters"] is not None:
        raise _spec_error(spec, "'/notools' and a tool-transporter count conflict")
    return opts


def _option_tag(opts: dict[str, Any]) -> str:
    """The name part of a spec's options: ``""`` (none), ``"-a4t2"``, ``"-notools"``, ``"-a3-notools"``."""
    fleet = (f"a{opts['agvs']}" if opts["agvs"] else "") + (
        f"t{opts['tool_transporters']}" if opts["tool_transporters"] else "")
    parts = [p for p in (fleet, "notools" if opts["notools"] else "") if p]
    return "".join("-" + p for p in parts)


def _check_seed(spec: str, seed: int) -> None:
    if seed >= HELDOUT_SEED_MIN:
        raise _spec_error(spec, f"seed {seed} is reserved for the held-out set (seeds >= {HELDOUT_SEED_MIN})")


def _expand_gen(spec: str, fleet: dict[str, Any]) -> list[Instance]:
    m = _GEN_RE.fullmatch(spec)
    if m is None:
        raise _spec_error(spec, "expected gen:JxMxT*COUNT@SEED[/OPT...]")
    j, mm, t, count, seed = (int(x) for x in m.groups()[:5])
    opts = _options(spec, m.group(6), "atn")
    _check_seed(spec, seed)
    seeds = [derived_seed(seed, salt) for salt in _TRAIN_SALTS]
    clash = set(seeds) & _heldout_stream_seeds()
    if clash:
        raise _spec_error(spec, f"derived stream seed {min(clash)} is a held-out shop's; choose another SEED")
    no_tools = opts["notools"] or bool(fleet["no_tools"])
    if no_tools and opts["tool_transporters"] is not None:
        raise _spec_error(spec, "a tool-transporter count conflicts with the fleet's no_tools")
    try:
        return generate_instances(
            j, mm, t, count, time_seed=seeds[0], route_seed=seeds[1], tool_seed=seeds[2], tools=not no_tools,
            n_agvs=opts["agvs"] or fleet["agvs"] or 10,
            n_tool_transporters=opts["tool_transporters"] or fleet["tool_transporters"] or 5,
            name_prefix=f"gen{j}x{mm}s{seed}{_option_tag(opts)}_")
    except InstanceError as exc:
        raise _spec_error(spec, str(exc)) from None


def _expand_genbu(spec: str, fleet: dict[str, Any]) -> list[Instance]:
    m = _GENBU_RE.fullmatch(spec)
    if m is None:
        raise _spec_error(spec, "expected genbu:L*COUNT@SEED[/aN] with L = 1..4 or *")
    lay, count, seed = m.group(1), int(m.group(2)), int(m.group(3))
    opts = _options(spec, m.group(4), "a")
    _check_seed(spec, seed)
    if not 1 <= count <= _BU_SEED_STRIDE:
        raise _spec_error(spec, f"COUNT must be 1..{_BU_SEED_STRIDE}, got {count}")
    if fleet["tool_transporters"] is not None:
        raise _spec_error(spec, "BU-layout shops have no tools, so the fleet's tool_transporters cannot apply")
    layouts = [1, 2, 3, 4] if lay == "*" else [int(lay)]
    agvs = opts["agvs"] or fleet["agvs"] or BU_AGVS
    tag = _option_tag(opts)
    try:
        return [bu_shop(L, seed * _BU_SEED_STRIDE + k, f"bu{L}s{seed}{tag}_{k:02d}", n_agvs=agvs)
                for k in range(count) for L in layouts]
    except InstanceError as exc:  # a fleet above the largest: the message named no spec (as gen: specs do)
        raise _spec_error(spec, str(exc)) from None


# ---------------------------------------------------------------------------------------------- held-out set
@functools.lru_cache(maxsize=None)
def _heldout_entries() -> tuple[dict[str, Any], ...]:
    text = resources.files("fms_sim").joinpath("data").joinpath("heldout.json").read_text(encoding="utf-8")
    return tuple(json.loads(text)["shops"])


def heldout_names() -> list[str]:
    """``ho00``..``ho49``, in file order."""
    return [e["name"] for e in _heldout_entries()]


@functools.lru_cache(maxsize=None)
def _heldout_stream_seeds() -> frozenset[int]:
    """The LCG stream seeds of the held-out ``gen`` shops (no instance is built)."""
    return frozenset(e[k] for e in _heldout_entries() if e["generator"] == "taillard-lcg"
                     for k in ("time_seed", "route_seed", "tool_seed"))


def _build_entry(entry: dict[str, Any]) -> Instance:
    """One held-out shop from its entry in ``heldout.json``."""
    name = entry["name"]
    if entry["generator"] == "bu":
        inst = bu_shop(entry["layout"], entry["seed"], name, n_agvs=entry["n_agvs"])
    elif entry["generator"] == "taillard-lcg":
        (inst,) = generate_instances(
            entry["n_jobs"], entry["n_machines"], entry["n_tools"], 1, time_seed=entry["time_seed"],
            route_seed=entry["route_seed"], tool_seed=entry["tool_seed"], agv_seed=entry["agv_seed"],
            tool_travel_seed=entry["tool_travel_seed"], tools=entry["tools"], n_agvs=entry["n_agvs"],
            n_tool_transporters=entry["n_tool_transporters"], name_prefix=name)
        inst = dataclasses.replace(inst, name=name)
    else:
        raise InstanceError(f"heldout.json: {name} has an unknown generator {entry['generator']!r}")
    return dataclasses.replace(inst, meta={**inst.meta, "heldout": True})


@functools.lru_cache(maxsize=None)
def _heldout_cache() -> dict[str, Instance]:
    return {e["name"]: _build_entry(e) for e in _heldout_entries()}


def heldout_shops() -> list[Instance]:
    """The 50 held-out shops ``ho00``..``ho49`` (built once, then copied)."""
    return [_copy(inst) for inst in _heldout_cache().values()]


def heldout_shop(name: str) -> Instance:
    """The held-out shop called ``name`` (``ho00``..``ho49``, case-insensitive)."""
    key = name.strip().lower()
    entries = {e["name"]: e for e in _heldout_entries()}
    if key not in entries:
        raise InstanceError(f"unknown held-out shop {name!r}: they are {heldout_names()[0]}..{heldout_names()[-1]}")
    return _copy(_heldout_cache()[key])


def _copy(inst: Instance) -> Instance:
    return dataclasses.replace(inst, meta=dict(inst.meta))


# ---------------------------------------------------------------------------------------------- separation
def job_fingerprint(instance: Instance) -> str:
    """A hash of the instance's jobs: each job's (machine, processing time) sequence, jobs in sorted order.

    The comparison key of :func:`is_reserved`. It ignores the name, the job order, tools, travel matrices and
    fleet on purpose: the benchmarks are also run with other fleets, without tools (``large-agv``) and on
    other layouts (``ra01L3``), and every such variant still carries the test set's jobs.
    """
    jobs = sorted(tuple((op.machine, op.duration) for op in ops) for ops in instance.jobs)
    return hashlib.sha256(json.dumps(jobs, separators=(",", ":")).encode()).hexdigest()


@functools.lru_cache(maxsize=None)
def _reserved_fingerprints() -> dict[str, tuple[str, ...]]:
    """Fingerprint -> the benchmark and held-out names that carry those jobs (built once, ~0.5 s)."""
    table: dict[str, list[str]] = {}
    named = [(f"benchmark {n}", builtin(n)) for n in builtin_names()]
    named += [(f"held-out {inst.name}", inst) for inst in _heldout_cache().values()]
    for label, inst in named:
        table.setdefault(job_fingerprint(inst), []).append(label)
    return {fp: tuple(labels) for fp, labels in table.items()}


def is_reserved(instance: Instance) -> str | None:
    """What ``instance``'s jobs collide with (``"benchmark EX21, benchmark EX22, ..."``), or ``None``."""
    labels = _reserved_fingerprints().get(job_fingerprint(instance))
    return ", ".join(labels) if labels else None


def _config_specs(config: dict[str, Any]) -> list[tuple[str, Any]]:
    """``(where, spec)`` for every spec of a model config's train, eval and warm-start refine stages."""
    out: list[tuple[str, Any]] = []
    for key in ("train", "eval"):
        out += [(key, s) for s in _spec_list(config.get(key), key)]
    stages = (config.get("warm_start") or {}).get("refine") or []
    for k, stage in enumerate(stages):
        where = f"warm_start.refine[{k}].train"
        out += [(where, s) for s in _spec_list((stage or {}).get("train"), where)]
    return out


def _spec_list(value: Any, where: str) -> Iterable[Any]:
    if value is None:
        return []
    if isinstance(value, str) or not isinstance(value, (list, tuple)):
        raise ValueError(f"config {where} must be a list of instance specs, got {value!r}")
    return value


def check_training_specs(config: dict[str, Any]) -> None:
    """Raise :class:`ValueError` if a config trains or selects on a benchmark instance or a held-out shop.

    Looks at ``config["train"]``, ``config["eval"]`` and ``config["warm_start"]["refine"][*]["train"]``,
    expands every spec (with ``config["fleet"]``) and compares each instance's jobs with those of every
    benchmark and held-out shop (:func:`job_fingerprint`), so a renamed file copy is caught too. The message
    lists every offending spec and instance on one line, and after them any spec that does not expand (a typo, a
    reserved seed) with its error; specs that only fail to expand are reported as such ("cannot read the shop
    specs"), not as benchmarks.
    """
    fleet = config.get("fleet") or None
    problems: list[str] = []
    bad: list[str] = []
    for where, spec in _config_specs(config):
        try:
            instances = expand_specs([spec], fleet)
        except ValueError as exc:
            bad.append(f"{where}: {spec!r} does not expand: {exc}")
            continue
        hits = [f"{inst.name}, which has the jobs of {hit}" for inst in instances if (hit := is_reserved(inst))]
        if hits:  # a pattern's first few, and how many more ('ho*' listed all 50 shops on one line of 3.5 KB)
            more = f"; and {len(hits) - _SHOWN} more of it" if len(hits) > _SHOWN else ""
            problems.append("; ".join(f"{where}: {spec!r} gives {hit}" for hit in hits[:_SHOWN]) + more)
    # on one line (the command line prints an error as one line); a typo alone is not called a benchmark
    if problems:
        raise ValueError("training must use generated shops only (no benchmark instance, no held-out shop); "
                         "offending specs: " + "; ".join(problems + bad))
    if bad:
        raise ValueError("cannot read the shop specs: " + "; ".join(bad))


#: the offending shops of one spec that a refusal names
_SHOWN = 10
