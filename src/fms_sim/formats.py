"""Reading instances: the two classic plain job-shop text formats, the project's JSON, and built-in names.

Text formats (detected automatically by :func:`parse_text_jobshop`):

* OR-Library "standard": a header line ``n m``, then ``n`` lines of ``m`` pairs ``machine time`` with
  0-based machines (``ft06``, ``abz5``, ...).
* Taillard's: a header line ``n m`` (possibly followed by more numbers: seeds, bounds), then ``n`` lines of
  ``m`` times, then ``n`` lines of ``m`` 1-based machines; optional ``Times`` / ``Machines`` label lines.

In both, blank lines and lines starting with ``#`` are ignored, and text lines before the header (a title,
Taillard's "Nb of jobs, Nb of Machines, ..." line) are skipped. Instances read from text are plain job shops
(no AGVs, no tools) with 1-based machines; :func:`format_standard` and :func:`format_taillard` write them back.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .benchmarks import NAME_PATTERNS, builtin, is_builtin_name
from .files import read_text
from .instance import MAX_COUNT, MAX_TIME, Instance, InstanceError, Operation, _is_int

__all__ = ["parse_text_jobshop", "format_standard", "format_taillard", "load_instance"]

_LABELS = {"times", "machines"}


def _int(tok: str) -> int | None:
    """``tok`` as an integer if it is one written in ASCII digits (an optional sign), else None: ``int()`` alone took
    ``1_000`` and other scripts' digits (``٣``), which no OR-Library or Taillard file holds."""
    digits = tok[1:] if tok[:1] in ("+", "-") else tok
    if not (digits.isascii() and digits.isdigit()) or len(digits) > _MAX_DIGITS:
        return None  # (beyond Python's conversion limit a raw ValueError named no file nor line)
    return int(tok)


#: digits of the longest number a text instance holds (every count and time is far below 10**18)
_MAX_DIGITS = 18


def _lines(text: str) -> list[tuple[int, list[str]]]:
    """Non-blank, non-comment lines as ``(line number, tokens)``."""
    out = []
    for no, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            out.append((no, line.split()))
    return out


def _check_time(no: int, t: int) -> None:
    """A processing time read on line ``no``: refused, naming the line, unless from 0 to :data:`MAX_TIME`
    (``Operation`` refused a larger one without the line)."""
    if t < 0:
        raise InstanceError(f"line {no}: negative processing time {t}")
    if t > MAX_TIME:
        raise InstanceError(f"line {no}: processing time {t} is above the largest, {MAX_TIME:,}")


def _ints(no: int, toks: list[str]) -> list[int]:
    vals = []
    for tok in toks:
        v = _int(tok)
        if v is None:
            shown = tok if len(tok) <= 40 else f"{tok[:20]}...{tok[-8:]} ({len(tok)} characters)"
            digits = tok[1:] if tok[:1] in ("+", "-") else tok
            if digits.isascii() and digits.isdigit():  # (a number, only too long)
                raise InstanceError(f"line {no}: the number {shown!r} is too large (more than {_MAX_DIGITS} digits)")
            raise InstanceError(f"line {no}: expected integers, got {shown!r}")
        vals.append(v)
    return vals


def parse_text_jobshop(text: str, name: str) -> Instance:
    """Parse an OR-Library "standard" or a Taillard job-shop text (detected from the line structure).

    The standard format has ``n`` body lines of ``2m`` numbers, Taillard's ``2n`` body lines of ``m`` numbers
    (or ``Times``/``Machines`` labels); anything else, non-integers, negative times or machines out of
    range raise :class:`InstanceError` naming the line.
    """
    lines = _lines(text)
    # Skip leading text lines (titles); the header is the first line that starts with a number.
    i = 0
    while i < len(lines) and _int(lines[i][1][0]) is None:
        i += 1
    if i == len(lines):
        raise InstanceError(f"{name}: no header line 'n_jobs n_machines' found")
    hno, htoks = lines[i]
    # a header the parser could not read as one ('2,2') was skipped as a title, and a job's line read as the header
    title = (f" (line {lines[0][0]}, {' '.join(lines[0][1])!r}, was skipped as a title: the header is the first "
             "line that starts with a number, 'n_jobs n_machines' separated by spaces)") if i else ""
    try:
        header = _ints(hno, htoks)
    except InstanceError as exc:
        raise InstanceError(f"{exc}{title}") from None
    if len(header) < 2:
        raise InstanceError(f"line {hno}: the header needs at least 'n_jobs n_machines', got {' '.join(htoks)!r}"
                            f"{title}")
    n, m = header[0], header[1]
    if n < 1 or m < 1:
        raise InstanceError(f"line {hno}: n_jobs and n_machines must be >= 1, got {n} and {m}{title}")
    body = lines[i + 1:]
    labelled = any(len(t) == 1 and t[0].rstrip(":").lower() in _LABELS for _, t in body)
    if labelled:
        return _parse_taillard(body, n, m, name, labelled=True)
    widths = [len(t) for _, t in body]
    if len(body) == n and all(w == 2 * m for w in widths):
        return _parse_standard(body, n, m, name)
    if len(body) == 2 * n and all(w == m for w in widths):
        return _parse_taillard(body, n, m, name)
    # Neither structure: report against the format the first body line suggests.
    if body and len(body[0][1]) == 2 * m:
        fmt, rows, width = "standard", n, 2 * m
    else:
        fmt, rows, width = "Taillard", 2 * n, m
    for k, (no, toks) in enumerate(body):
        _ints(no, toks)  # non-integers are the clearest error
        if k >= rows:
            raise InstanceError(f"line {no}: unexpected extra line (a {fmt} {n}x{m} instance has {rows} "
                                f"lines after the header)")
        if len(toks) != width:
            raise InstanceError(f"line {no}: expected {width} numbers ({fmt} format, {n} jobs x {m} machines), "
                                f"got {len(toks)}")
    raise InstanceError(f"{name}: expected {rows} lines after the header ({fmt} format, {n} jobs x {m} "
                        f"machines), got {len(body)}")


def _parse_standard(body: list[tuple[int, list[str]]], n: int, m: int, name: str) -> Instance:
    jobs = []
    for no, toks in body:
        vals = _ints(no, toks)
        ops = []
        for o in range(m):
            mach, t = vals[2 * o], vals[2 * o + 1]
            if not 0 <= mach < m:
                raise InstanceError(f"line {no}: machine {mach} out of range 0..{m - 1} (standard format is 0-based)")
            _check_time(no, t)
            ops.append(Operation(mach + 1, None, t))
        jobs.append(tuple(ops))
    return Instance(name=name, jobs=tuple(jobs), n_machines=m, meta={"format": "standard"})


def _parse_taillard(
    body: list[tuple[int, list[str]]], n: int, m: int, name: str, *, labelled: bool = False
) -> Instance:
    sections: dict[str, list[tuple[int, list[int]]]] = {"times": [], "machines": []}
    current = "times"
    for no, toks in body:
        if len(toks) == 1 and toks[0].rstrip(":").lower() in _LABELS:
            current = toks[0].rstrip(":").lower()
            if sections[current]:
                raise InstanceError(f"line {no}: a second {toks[0]!r} section")
            continue
        vals = _ints(no, toks)
        if len(vals) != m:
            raise InstanceError(f"line {no}: expected {m} numbers (Taillard format, {n} jobs x {m} machines), "
                                f"got {len(vals)}")
        if not labelled and current == "times" and len(sections["times"]) == n:
            current = "machines"  # unlabelled: the machines follow the n time rows
        if len(sections[current]) == n:
            raise InstanceError(f"line {no}: more than {n} {current} rows")
        sections[current].append((no, vals))
    for what, rows in sections.items():
        if len(rows) != n:
            raise InstanceError(f"{name}: expected {n} {what} rows (Taillard format), got {len(rows)}")
    jobs = []
    for (tno, times), (mno, machines) in zip(sections["times"], sections["machines"]):
        for t in times:
            _check_time(tno, t)
        for mach in machines:
            if not 1 <= mach <= m:
                raise InstanceError(f"line {mno}: machine {mach} out of range 1..{m} (Taillard format is 1-based)")
        jobs.append(tuple(Operation(mach, None, t) for mach, t in zip(machines, times)))
    return Instance(name=name, jobs=tuple(jobs), n_machines=m, meta={"format": "taillard"})


def _rectangular(instance: Instance) -> int:
    m = instance.n_machines
    for j, ops in enumerate(instance.jobs):
        if len(ops) != m:
            raise InstanceError(f"job {j} has {len(ops)} operations; the text formats need exactly {m} per job")
    return m


def format_standard(instance: Instance) -> str:
    """The OR-Library "standard" text of ``instance``'s job shop (AGVs and tools are not representable)."""
    m = _rectangular(instance)
    lines = [f"{instance.n_jobs} {m}"]
    lines += [" ".join(f"{op.machine - 1} {op.duration}" for op in ops) for ops in instance.jobs]
    return "\n".join(lines) + "\n"


def format_taillard(instance: Instance) -> str:
    """Taillard's text of ``instance``'s job shop, with ``Times``/``Machines`` labels."""
    m = _rectangular(instance)
    lines = [f"{instance.n_jobs} {m}", "Times"]
    lines += [" ".join(str(op.duration) for op in ops) for ops in instance.jobs]
    lines.append("Machines")
    lines += [" ".join(str(op.machine) for op in ops) for ops in instance.jobs]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------- loading
def _load_file(path: Path) -> Instance:
    try:
        text = read_text(path)
    except OSError as exc:
        raise InstanceError(f"cannot read {str(path)!r}: {exc}") from None
    except UnicodeDecodeError as exc:  # it showed the codec's message alone ("'utf-8' codec can't decode byte 0xff")
        raise InstanceError(f"cannot read {str(path)!r}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset "
                            f"{exc.start}): an instance file is JSON or a text job shop in UTF-8; save it so "
                            "(a spreadsheet's or an editor's UTF-16 or Latin-1 export is not)") from None
    if path.suffix.lower() == ".json" or text.lstrip().startswith(("{", "[")):
        try:
            return Instance.from_json(text)
        except InstanceError as exc:
            raise InstanceError(f"{path.name}: {exc}") from None
    name = path.stem or path.name
    try:
        return parse_text_jobshop(text, name)
    except InstanceError as exc:  # name the file, as for JSON ("line 3: ..." alone did not), once ("std.txt: std: ")
        raise InstanceError(f"{path.name}: {str(exc).removeprefix(name + ': ')}") from None


def load_instance(
    spec: str | os.PathLike[str],
    *,
    layout: int | None = None,
    agvs: int | None = None,
    tool_transporters: int | None = None,
    no_tools: bool = False,
    no_agvs: bool = False,
) -> Instance:
    """Load ``spec`` (an existing file, also as a ``Path``, else a built-in name; a folder is never an instance, so a
    folder named like a built-in does not hide it) and apply the command-line overrides.

    Files: ``.json`` or content starting with ``{`` is the project's instance JSON, anything else a text job
    shop. ``layout`` applies to built-in ``ra`` names only. Then ``no_tools``/``no_agvs`` drop tools/AGVs and
    ``agvs``/``tool_transporters`` set the fleet sizes (>= 1; refused where the instance has no such
    travel matrix or the matching ``no_*`` flag is set).
    """
    if isinstance(spec, os.PathLike):  # a Path names a file (it was refused as "must be named")
        spec = os.fspath(spec)
    if not isinstance(spec, str) or not spec.strip():
        raise InstanceError("an instance must be named: give a built-in name or a file path")
    path = Path(spec)
    if path.is_dir() and not is_builtin_name(spec):
        raise InstanceError(f"{spec!r} is a directory, not an instance file")
    if path.is_file():
        if layout is not None:
            raise InstanceError("layout applies only to built-in ra instances, not to instance files")
        inst = _load_file(path)
    elif is_builtin_name(spec):
        inst = builtin(spec, layout=layout)
    else:
        raise InstanceError(f"no built-in instance or file named {spec!r} (built-ins: {NAME_PATTERNS})")

    for flag, value in (("no_tools", no_tools), ("no_agvs", no_agvs)):
        if not isinstance(value, bool):  # "yes" (or "no") read as True
            raise InstanceError(f"{flag} must be True or False, got {value!r}")
    if agvs is not None and no_agvs:
        raise InstanceError("set the number of AGVs or drop them, not both (agvs / no_agvs: --agvs / --no-agvs)")
    if tool_transporters is not None and no_tools:
        raise InstanceError("set the number of tool transporters or drop the tools, not both (tool_transporters / "
                            "no_tools: --tool-transporters / --no-tools)")
    if no_tools:
        inst = inst.without_tools()
    if no_agvs:
        inst = inst.without_agvs()
    # a shop without the vehicles first (EX12 --tool-transporters 0 was told to use --no-tools: it has no tools)
    if agvs is not None and not inst.has_agvs:
        raise InstanceError(f"{inst.name} has no AGV travel matrix, so the number of AGVs cannot be set")
    if tool_transporters is not None and not inst.has_tools:
        raise InstanceError(f"{inst.name} has no tool travel matrix, so the number of tool transporters "
                            "cannot be set")
    if agvs is not None:
        _fleet_size("agvs", agvs, "no-agvs")
    if tool_transporters is not None:
        _fleet_size("tool_transporters", tool_transporters, "no-tools")
    if agvs is not None or tool_transporters is not None:
        inst = inst.with_fleet(agvs, tool_transporters)
    return inst


def _fleet_size(what: str, value: Any, drop_flag: str) -> None:
    if not _is_int(value) or not 1 <= int(value) <= MAX_COUNT:
        raise InstanceError(f"{what} must be an integer from 1 to {MAX_COUNT}, got {value!r} (use --{drop_flag} to "
                            "drop them)")
