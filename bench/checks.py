"""What the benches share: every schedule a bench reports passes the project's validator, or the bench stops; the
summary is printed and, on request, written with the rows and the command that made them.

The bench scripts run as ``python bench/NAME.py``, which puts this folder on the import path (``from checks import
checked``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

from fms_sim.files import output_problem, write_atomically
from fms_sim.validate import validate


def checked(inst: Any, sched: Any, what: str, scenario: Any = None) -> int:
    """The makespan of ``sched``, once :func:`fms_sim.validate.validate` accepts it as a schedule of ``inst`` (in
    the disrupted run of ``scenario``, if given); a schedule it rejects ends the bench with a message naming the
    shop, ``what`` produced it and the first violation."""
    problems = validate(inst, sched, scenario)
    if problems:
        raise SystemExit(f"INFEASIBLE {inst.name} ({what}): {problems[0]}")
    return sched.makespan


def report(lines: list[str], rows: list[dict], path: str | None, shown: int = 0) -> None:
    """Print the summary ``lines`` (but the first ``shown``, printed as the bench went); with ``path``, write them
    all there as JSON with the ``rows`` and the command."""
    print("\n".join(lines[shown:]))
    if path:
        write_json(path, {"rows": rows, "summary": lines, "command": " ".join(sys.argv)})


def output_file(text: str) -> str:
    """An argparse type for a file a bench writes when it ends (``--json``, a cache): a path no file can be written
    to (a folder, a path inside a file, one this user may not write) is refused before any work, not after the whole
    run with its rows lost. A missing folder is made when the file is written (:func:`write_json`)."""
    problem = output_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(f"{text}: {problem}")
    return text


def write_json(path: str | os.PathLike, doc: Any, indent: int | None = 2) -> None:
    """Write ``doc`` as JSON to ``path``: its folder made if missing, the file replaced only by a complete one
    (:func:`fms_sim.files.write_atomically`)."""
    write_atomically(path, json.dumps(doc, indent=indent) + "\n")


def versus(rows: list[dict], key: str, ref: str) -> tuple[int, float, int, int]:
    """Column ``key`` of ``rows`` against column ``ref``: its total, the ratio of the totals, and in how many rows
    it is below / above ``ref``."""
    total = sum(r[key] for r in rows)
    return (total, total / sum(r[ref] for r in rows), sum(r[key] < r[ref] for r in rows),
            sum(r[key] > r[ref] for r in rows))


def versus_line(rows: list[dict], key: str, ref: str) -> str:
    """The summary line of column ``key`` against ``ref`` (:func:`versus`): total, ratio, below / above."""
    total, ratio, below, above = versus(rows, key, ref)
    return f"  {key:12s} total {total:7d}  {ratio:.4f} x {ref}   below / above: {below} / {above}"


def limits_label(rows: list[dict], method: str = "cpsat") -> str:
    """The time limits of ``method``'s rows (``fms bench`` rows carry ``time_limit``) for a column's title:
    ``10 s``, or ``10 s, 60 s`` where the rows mix limits, or ``limit not recorded``; so a table says which limit its
    figures came from rather than the limit a script usually asks for."""
    limits = sorted({r.get("time_limit") for r in rows if r.get("method") == method}, key=lambda x: (x is None, x))
    if not limits or limits == [None]:
        return "limit not recorded"
    return ", ".join("?" if x is None else f"{x:g} s" for x in limits)


def _integer(text: str, low: int) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if n < low:
        raise argparse.ArgumentTypeError(f"must be >= {low}, got {n}")
    return n


def positive(text: str) -> int:
    """An argparse type: an integer >= 1 (a count of shops, scenarios, samples, runs)."""
    return _integer(text, 1)


def at_least_zero(text: str) -> int:
    """An argparse type: an integer >= 0 (a size bound where 0 means none: -1 was taken and meant none too)."""
    return _integer(text, 0)


def finite(text: str) -> float:
    """An argparse type: a finite number (NaN and infinity were taken and ran as something else)."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return x


def run_worker(src: str | os.PathLike, script: str, args: Sequence[str]) -> Any:
    """Run ``script --worker ARGS`` in a fresh interpreter on the package source at ``src`` (a ``--baseline``
    revision's or this checkout's) and return the JSON of its last line of output. A refusal of the input there
    (:func:`run_main`'s one error line) is a ValueError here; any other failure ends the bench with the worker's
    output."""
    env = dict(os.environ, PYTHONPATH=str(src))
    out = subprocess.run([sys.executable, script, "--worker", *args], env=env, capture_output=True, text=True,
                         cwd=Path(src).parent)
    if out.returncode:
        last = (out.stderr.strip().splitlines() or ["(no output)"])[-1]
        if ": error: " in last:  # a refusal of the input (run_main in the worker): that one line, exit 2
            raise ValueError(last.split(": error: ", 1)[1])
        raise SystemExit(f"the run on {src} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_main(main: Callable[[], Any]) -> None:
    """Run a bench's ``main``: a bad input (an unknown instance, model or shop spec, a file that cannot be read, a
    value a library refuses) ends it with one line ``bench/NAME.py: error: ...`` and exit code 2, not a
    traceback; what ``main`` returns is the exit code."""
    try:
        code = main()
    except (ValueError, OSError) as exc:  # InstanceError, ModelNotFoundError, ScenarioError are ValueErrors
        msg = " ".join(str(exc).split("\n")) or type(exc).__name__
        print(f"bench/{os.path.basename(sys.argv[0])}: error: {msg}", file=sys.stderr)
        raise SystemExit(2) from None
    raise SystemExit(code)
