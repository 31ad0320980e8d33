"""Built-in benchmark instances, addressed by name.

* ``EX{s}{l}`` (``EX11``..``EX104``): Bilge & Ulusoy (1995) job set ``s`` (1..10) with layout ``l`` (1..4, the
  last digit) as AGV travel matrix; 2 AGVs, no tools.
* ``ra01``..``ra20``: the "Raj" job sets with one tool per operation (``ra01``..``ra10`` are BU sets 1..10, with
  ra03 carrying the set-3 typo M1 = 10); AGV matrix = BU layout, tool matrix = that layout's tool-transport
  matrix; 2 AGVs, 1 tool transporter. The layout comes from ``layout=`` or a suffix (``ra01L3``); default 2.
* ``sl{g}{k}`` (``sl00``..``sl79``): the large LCG benchmark, group ``g`` (sizes in :data:`SL_GROUPS`),
  instance ``k`` of the group's continued random streams (see :mod:`fms_sim.generate`); 10 AGVs,
  5 tool transporters.
* ``ta01``: Taillard's ta01, the plain 15x15 job shop (sl00's times and routing; optimum 1231).
* ``ho00``..``ho49``: not benchmarks but the fixed held-out set of generated shops (``fms_sim/data/heldout.json``,
  :mod:`fms_sim.shopsets`); they load by name like the built-ins, and :func:`builtin_names` does not list them.

The data files live in the package (``fms_sim/data``) and are read with :mod:`importlib.resources`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re
from importlib import resources
from typing import Any

from .generate import generate_instances
from .instance import Instance, InstanceError, Operation, _is_int, _plain

__all__ = ["builtin", "builtin_names", "is_builtin_name", "SL_GROUPS", "BU_OPTIMAL_MAKESPAN", "NAME_PATTERNS"]

#: (jobs, machines, tools) of the large benchmark's groups 0..7.
SL_GROUPS: tuple[tuple[int, int, int], ...] = (
    (15, 15, 15), (20, 15, 15), (20, 20, 20), (30, 15, 15),
    (30, 20, 20), (50, 15, 15), (50, 20, 20), (100, 20, 20),
)
SL_PER_GROUP = 10
SL_AGVS = 10
SL_TOOL_TRANSPORTERS = 5
BU_AGVS = 2
RA_TOOL_TRANSPORTERS = 1
RA_DEFAULT_LAYOUT = 2

#: Optimal makespans of the BU instances with 2 AGVs (shared benchmarks README), ``[(set, layout)]``;
#: (7, 1) and (7, 4) are the literature's values, not re-proven by the project (EX41's 112 is: CP-SAT proves it within
#: 60 s, docs/benchmarks.md §3).
BU_OPTIMAL_MAKESPAN: dict[tuple[int, int], int] = {
    (s, l): v
    for s, row in enumerate(
        [
            (96, 82, 84, 103), (100, 76, 86, 108), (99, 85, 86, 111), (112, 87, 89, 121),
            (87, 69, 74, 96), (118, 98, 103, 120), (111, 79, 83, 126), (161, 151, 153, 163),
            (116, 102, 105, 120), (146, 135, 137, 157),
        ],
        start=1,
    )
    for l, v in enumerate(row, start=1)
}
_BU_LITERATURE_ONLY = {(7, 1), (7, 4)}
#: the BU instances whose optimum is the literature's value, not re-proven by the project (EX71, EX74)
BU_LITERATURE_OPTIMA = frozenset(f"EX{s}{lay}" for s, lay in _BU_LITERATURE_ONLY)

NAME_PATTERNS = ("EX{set 1-10}{layout 1-4} (EX11..EX104), ra01..ra20 (optionally ra01L3), sl00..sl79, ta01, "
                 "and the held-out shops ho00..ho49")

_EX_RE = re.compile(r"ex(\d+)", re.IGNORECASE)
_RA_RE = re.compile(r"ra(\d+)(?:l(\d+))?", re.IGNORECASE)
_SL_RE = re.compile(r"sl(\d)(\d)", re.IGNORECASE)
_HO_RE = re.compile(r"ho\d+", re.IGNORECASE)


def builtin_names() -> list[str]:
    """Every built-in instance name, in canonical spelling (the ``ra`` ones at their default layout)."""
    names = [f"EX{s}{l}" for s in range(1, 11) for l in range(1, 5)]
    names += [f"ra{i:02d}" for i in range(1, 21)]
    names += [f"sl{g}{k}" for g in range(len(SL_GROUPS)) for k in range(SL_PER_GROUP)]
    names.append("ta01")
    return names


def is_builtin_name(name: str) -> bool:
    """Whether ``name`` is spelled like a built-in (``EX<digits>``, ``ra<digits>[L<digit>]``, ``sl..``, ``ta..``)
    or a held-out shop (``ho<digits>``).

    A name of that shape that is out of range (``sl99``) is still refused by :func:`builtin`, with the reason.
    """
    return bool(re.fullmatch(r"ex\d+|ra\d+(l\d+)?|sl\d+|ta\d+|ho\d+", name.strip(), re.IGNORECASE))


def _unknown(name: str, why: str = "") -> InstanceError:
    detail = f" ({why})" if why else ""
    return InstanceError(f"unknown built-in instance {name!r}{detail}; built-ins are {NAME_PATTERNS}")


def builtin(name: str, *, layout: int | None = None) -> Instance:
    """The built-in instance called ``name`` (case-insensitive); ``layout`` (1..4) applies to ``ra`` names.

    Raises :class:`InstanceError` for unknown names, a layout out of 1..4, or a layout given for a family
    that has none to choose (``EX`` carries it in its name and a conflicting ``layout`` is refused).
    """
    if not isinstance(name, str):
        raise InstanceError(f"instance name must be a string, got {name!r}")
    key = name.strip()
    if layout is not None and (not _is_int(layout) or not 1 <= layout <= 4):  # (numpy integers too, as elsewhere)
        raise InstanceError(f"layout must be 1, 2, 3 or 4, got {layout!r}")
    layout = None if layout is None else _plain(layout)

    if m := _EX_RE.fullmatch(key):
        digits = m.group(1)
        if len(digits) < 2:
            raise _unknown(name, "EX needs a set 1-10 and a layout digit 1-4, e.g. EX12")
        s, lay = int(digits[:-1]), int(digits[-1])
        if not 1 <= s <= 10 or not 1 <= lay <= 4 or digits[0] == "0":
            raise _unknown(name, "EX sets are 1-10 and layouts 1-4")
        if layout is not None and layout != lay:
            raise InstanceError(f"{name} already names layout {lay}; layout {layout} conflicts (use EX{s}{layout})")
        return _copy(_ex(s, lay))

    if m := _RA_RE.fullmatch(key):
        i = int(m.group(1))
        if len(m.group(1)) != 2 or not 1 <= i <= 20:
            raise _unknown(name, "ra instances are ra01..ra20")
        lay = layout
        if m.group(2) is not None:
            named = int(m.group(2))
            if not 1 <= named <= 4:
                raise _unknown(name, "layouts are 1-4, e.g. ra01L3")
            if layout is not None and layout != named:
                raise InstanceError(f"{name} already names layout {named}; layout {layout} conflicts "
                                    f"(use ra{i:02d}L{layout})")
            lay = named
        return _copy(_ra(i, RA_DEFAULT_LAYOUT if lay is None else lay))

    if m := _SL_RE.fullmatch(key):
        _no_layout(name, layout)
        g, k = int(m.group(1)), int(m.group(2))
        if g >= len(SL_GROUPS):
            raise _unknown(name, f"sl groups are 0-{len(SL_GROUPS) - 1}")
        return _copy(_sl_group(g)[k])

    if key.lower() == "ta01":
        _no_layout(name, layout)
        return _copy(_ta01())

    if _HO_RE.fullmatch(key):
        _no_layout(name, layout)
        from .shopsets import heldout_shop  # shopsets builds on this module

        return heldout_shop(key)

    raise _unknown(name)


def _no_layout(name: str, layout: int | None) -> None:
    if layout is not None:
        raise InstanceError(f"{name} has a fixed travel matrix; layout applies only to ra instances")


def _copy(inst: Instance) -> Instance:
    # Cached instances are shared; give each caller its own meta dict so that edits do not leak.
    return dataclasses.replace(inst, meta=dict(inst.meta))


# ---------------------------------------------------------------------------------------------- data
@functools.lru_cache(maxsize=None)
def _data(filename: str) -> dict[str, Any]:
    text = resources.files("fms_sim").joinpath("data").joinpath(filename).read_text(encoding="utf-8")
    return json.loads(text)


def _bu_layout(lay: int) -> list[list[int]]:
    return _data("bu_layouts.json")["layouts"][str(lay)]


@functools.lru_cache(maxsize=None)
def _ex(s: int, lay: int) -> Instance:
    jobs = _data("bu_jobsets.json")["jobsets"][f"set{s}"]["jobs"]
    meta: dict[str, Any] = {"source": "Bilge & Ulusoy (1995)", "set": s, "layout": lay,
                            "optimal_makespan": BU_OPTIMAL_MAKESPAN[(s, lay)]}
    if (s, lay) in _BU_LITERATURE_ONLY:
        meta["optimum_from_literature_only"] = True
    return Instance(
        name=f"EX{s}{lay}",
        jobs=tuple(tuple(Operation(mach, None, t) for mach, t in ops) for ops in jobs),
        agv_travel=_bu_layout(lay),
        n_agvs=BU_AGVS,
        meta=meta,
    )


@functools.lru_cache(maxsize=None)
def _ra(i: int, lay: int) -> Instance:
    data = _data("raj_bu_tools.json")
    entry = data["instances"][f"ra{i:02d}"]
    return Instance(
        name=f"ra{i:02d}" if lay == RA_DEFAULT_LAYOUT else f"ra{i:02d}L{lay}",
        jobs=tuple(tuple(Operation(op["machine"], op["tool"], op["time"]) for op in ops) for ops in entry["jobs"]),
        agv_travel=_bu_layout(lay),
        tool_travel=data["tool_transport"][str(lay)],
        n_agvs=BU_AGVS,
        n_tool_transporters=RA_TOOL_TRANSPORTERS,
        n_machines=entry["n_machines"],
        n_tools=entry["n_tools"],
        meta={"source": "Raj/BU job sets with tools", "layout": lay},
    )


@functools.lru_cache(maxsize=None)
def _sl_group(g: int) -> tuple[Instance, ...]:
    n, m, t = SL_GROUPS[g]
    group = generate_instances(n, m, t, SL_PER_GROUP, n_agvs=SL_AGVS, n_tool_transporters=SL_TOOL_TRANSPORTERS)
    return tuple(
        dataclasses.replace(inst, name=f"sl{g}{k}", meta={**inst.meta, "group": g}) for k, inst in enumerate(group)
    )


@functools.lru_cache(maxsize=None)
def _ta01() -> Instance:
    sl00 = _sl_group(0)[0]
    return Instance(
        name="ta01",
        jobs=tuple(tuple(Operation(op.machine, None, op.duration) for op in ops) for ops in sl00.jobs),
        n_machines=sl00.n_machines,
        meta={"source": "Taillard (1993) ta01", "optimal_makespan": 1231},
    )
