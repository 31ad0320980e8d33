"""Make the fixed schedules that the replay tests feed through the shop net (test data kept in the repo).

Writes one gzip-compressed schedule, ``tests/data/replay/NAME_MODE_METHOD.json.gz`` (``Schedule.to_json``
with ``indent=None``), per (instance, mode, method), and ``tests/data/replay/index.json`` listing them:

1. the 40 Bilge–Ulusoy instances EX11..EX104 (no tools: mode ``agvs``), CP-SAT with a 20 s limit;
2. ra01..ra20 with tools (default layout, mode ``tools``), CP-SAT with a 20 s limit;
3. sl00, sl30, sl70 with tools (``tools``) and without (``instance.without_tools()``, ``agvs``), CP-SAT
   with a 10 s limit and the earliest-start list schedule ``greedy_schedule(inst, rule="est")`` (``list``).

CP-SAT runs on one worker (``workers=1``, seed 0). Every schedule must pass ``fms_sim.validate.validate``;
the script aborts otherwise. Files that already exist are kept (the run can be resumed); ``--only PATTERN``
(an ``fnmatch`` pattern on the file stem ``NAME_MODE_METHOD``, e.g. ``'sl70_*'`` or ``'EX1?_agvs_cpsat'``)
redoes the matching files only. The index is rebuilt from the files on disk every run.

The tests replay these files and never re-solve them: CP-SAT with a time limit is not deterministic, so a
rerun may give other (equally valid) schedules. Regenerate with (about 20-30 minutes of one core)::

    nice -n 10 .venv/bin/python bench/make_replay_data.py [--only PATTERN]
"""

from __future__ import annotations

import argparse
import fnmatch
import gzip
import json
import time
from pathlib import Path

from fms_dispatch.exact import cpsat, greedy_schedule
from fms_sim.benchmarks import builtin
from fms_sim.instance import Instance
from fms_sim.schedule import Schedule
from fms_sim.validate import validate

OUT = Path(__file__).resolve().parent.parent / "tests" / "data" / "replay"

#: (instance name, mode, method, cpsat time limit in seconds or None for the list schedule)
JOBS: list[tuple[str, str, str, float | None]] = (
    [(f"EX{s}{l}", "agvs", "cpsat", 20.0) for s in range(1, 11) for l in range(1, 5)]
    + [(f"ra{i:02d}", "tools", "cpsat", 20.0) for i in range(1, 21)]
    + [(name, mode, method, 10.0 if method == "cpsat" else None)
       for name in ("sl00", "sl30", "sl70") for mode in ("tools", "agvs") for method in ("cpsat", "list")]
)


def stem(name: str, mode: str, method: str) -> str:
    return f"{name}_{mode}_{method}"


def instance_for(name: str, mode: str) -> Instance:
    inst = builtin(name)
    if mode == "agvs":
        inst = inst.without_tools()
    elif not inst.has_tools:
        raise ValueError(f"{name} has no tools; mode 'tools' makes no sense")
    return inst


def write_gz(path: Path, text: str) -> None:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as gz:
        gz.write(text.encode())  # mtime=0 and no file name: the same schedule gives the same bytes
    tmp.replace(path)


def _untimed(sch: Schedule) -> dict:
    """The schedule as JSON data without its meta's wall time (which differs run by run for the same schedule)."""
    data = json.loads(sch.to_json(indent=None))
    data.get("meta", {}).pop("wall_time", None)
    return data


def read_gz(path: Path) -> Schedule:
    with gzip.open(path, "rt") as f:
        return Schedule.from_json(f.read())


def make(name: str, mode: str, method: str, limit: float | None) -> tuple[Schedule, float]:
    inst = instance_for(name, mode)
    t0 = time.monotonic()
    if method == "cpsat":
        assert limit is not None
        sch = cpsat(inst, time_limit=limit, workers=1, seed=0)
    else:
        sch = greedy_schedule(inst, rule="est")
        sch.meta = {"solver": "list", "rule": "est"}
    secs = time.monotonic() - t0
    bad = validate(inst, sch)
    if bad:
        raise SystemExit(f"ABORT: {stem(name, mode, method)} is not valid ({len(bad)} problems): {bad[0]}")
    return sch, secs


def entry(name: str, mode: str, method: str, limit: float | None, sch: Schedule) -> dict:
    meta = sch.meta
    return {
        "file": stem(name, mode, method) + ".json.gz",
        "instance": name,
        "mode": mode,
        "method": method,
        "makespan": sch.makespan,
        "optimal": (meta.get("status") == "OPTIMAL") if method == "cpsat" else None,
        "lower_bound": meta.get("lower_bound"),
        "time_limit": limit,
        "valid": True,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--only", metavar="PATTERN", help="redo only the files whose stem matches (fnmatch)")
    args = ap.parse_args()
    if args.only is not None and not any(fnmatch.fnmatchcase(stem(*job[:3]), args.only) for job in JOBS):
        ap.error(f"--only {args.only!r} matches no file (stems such as sl00_tools_list, EX11_agvs_cpsat)")
    OUT.mkdir(parents=True, exist_ok=True)
    index = []
    for name, mode, method, limit in JOBS:
        s = stem(name, mode, method)
        path = OUT / (s + ".json.gz")
        redo = args.only is not None and fnmatch.fnmatchcase(s, args.only)
        if path.exists() and not redo:
            sch = read_gz(path)
            bad = validate(instance_for(name, mode), sch)
            if bad:
                raise SystemExit(f"ABORT: existing {path.name} is not valid: {bad[0]}")
        elif args.only is not None and not redo and not path.exists():
            continue  # not asked for: leave it for a full run
        else:
            sch, secs = make(name, mode, method, limit)
            same = path.exists() and _untimed(read_gz(path)) == _untimed(sch)
            if same:  # the same schedule: the file keeps its bytes (only the solver's wall time would change)
                sch = read_gz(path)
            else:
                write_gz(path, sch.to_json(indent=None) + "\n")
            status = sch.meta.get("status", "-")
            print(f"{name:5s} {mode:5s} {method:5s} makespan={sch.makespan:6d} {status:8s} {secs:6.1f}s"
                  + (" (unchanged)" if same else ""), flush=True)
        index.append(entry(name, mode, method, limit, sch))
    (OUT / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    print(f"{len(index)} schedules indexed in {OUT / 'index.json'}", flush=True)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
