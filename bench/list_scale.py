"""How the ``first`` and ``list`` solvers scale with the size of a shop, and how fast the list schedule alone is on
the built-in shops (the inner loop of the guide's plan search: ``fms_dispatch.exact.greedy_schedule``).

A ladder of generated shops (``gen:Jx{M}x{T}*1@SEED`` for each J of ``--sizes``; with ``--notools`` each size also
without its tools, ``.../notools``) is solved by each solver of ``--solvers`` as ``fms solve SHOP --solver NAME``
runs it (``first`` on the full-decision net, the default of ``fms solve``; ``first:paper`` on the paper's net), and
each of ``--builtins`` gets ``--repeat`` earliest-start list schedules, the best time reported. Every schedule is
validated (``fms_sim.validate``). Each source runs in a fresh interpreter.

Each solve runs ``--rounds`` times, the best time reported. With ``--baseline REV`` the same measurement runs on the
source of git revision REV (a temporary worktree), the two sources taking turns solve by solve so that both see the
same machine load, and the ratios (baseline / this checkout) are printed; the bench stops if any schedule differs
between the two (every operation, trip and time: the same decisions, ties included).

Usage: python bench/list_scale.py [--sizes 100 300 1000] [--machines 10] [--tools 5] [--seed 1] [--notools]
                                  [--solvers first list] [--builtins EX104 ra01 sl00 sl31 sl70] [--repeat 3]
                                  [--rounds 3] [--baseline REV] [--json PATH]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

from checks import checked, output_file, positive, report, run_worker

sys.path.insert(0, str(Path(__file__).resolve().parent))
from decide_speed import _sources  # noqa: E402  (the baseline's temporary worktree)

ROOT = Path(__file__).resolve().parent.parent


def _t(seconds: float) -> str:
    """A time for the table: seconds, or milliseconds below one second."""
    return f"{seconds:8.3f} s " if seconds >= 1 else f"{1000 * seconds:8.3f} ms"


def fingerprint(sched: Any) -> str:
    """A digest of everything a schedule fixes: each operation, AGV trip and tool trip with its times, in order."""
    text = repr((sched.makespan, sched.operations, sched.agv_trips, sched.tool_trips))  # (dataclass reprs: every field)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def solve_one(spec: str, solver: str) -> dict:
    """One solve of the generated shop ``spec`` by ``solver`` (``first``/``first:paper``: the full / paper net),
    timed as ``fms solve`` times it, validated."""
    from fms_dispatch.solvers import solve
    from fms_sim.shopsets import expand_specs

    inst = expand_specs([spec])[0]
    name, _, net = solver.partition(":")
    opts = {"decisions": net or "full"} if name == "first" else {}
    t0 = time.perf_counter()
    sched = solve(inst, solver if name != "first" else "first", **opts)
    seconds = time.perf_counter() - t0
    return {"shop": spec, "solver": solver, "operations": sum(len(j) for j in inst.jobs), "seconds": seconds,
            "makespan": checked(inst, sched, solver), "fingerprint": fingerprint(sched)}


def list_only(name: str, repeat: int) -> dict:
    """The best of ``repeat`` earliest-start list schedules of the built-in ``name`` (the plan search's unit)."""
    from fms_dispatch.exact import greedy_schedule
    from fms_sim.formats import load_instance

    inst = load_instance(name)
    best = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        plan = greedy_schedule(inst, rule="est")
        dt = time.perf_counter() - t0
        best = dt if best is None else min(best, dt)
    return {"shop": name, "solver": "greedy", "operations": sum(len(j) for j in inst.jobs), "seconds": best,
            "makespan": checked(inst, plan, "list schedule"), "fingerprint": fingerprint(plan)}


def _worker(src: Path, task: list[str], repeat: int) -> dict:
    """One task (``solve SPEC SOLVER`` or ``greedy NAME``) in a fresh interpreter on the package source at ``src``."""
    return run_worker(src, __file__, [*task, "--repeat", str(repeat)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=positive, nargs="*", default=[100, 300, 1000], help="jobs per generated shop")
    ap.add_argument("--machines", type=positive, default=10)
    ap.add_argument("--tools", type=positive, default=5)
    ap.add_argument("--seed", type=positive, default=1)
    ap.add_argument("--notools", action="store_true", help="each size also without its tools")
    ap.add_argument("--solvers", nargs="+", default=["first", "list"], choices=["first", "first:paper", "list"])
    ap.add_argument("--builtins", nargs="*", default=["EX104", "ra01", "sl00", "sl31", "sl70"],
                    help="built-in shops whose list schedule alone is timed")
    ap.add_argument("--repeat", type=positive, default=3, help="list schedules per built-in shop (best reported)")
    ap.add_argument("--rounds", type=positive, default=3,
                    help="solves per generated shop and source, the sources taking turns (best reported)")
    ap.add_argument("--baseline", help="git revision to measure alongside, shop by shop")
    ap.add_argument("--json", type=output_file, help="write the rows and summary here")
    ap.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        kind, what = a.worker
        print(json.dumps(list_only(what, a.repeat) if kind == "greedy" else solve_one(what, kind)))
        return
    specs = [f"gen:{j}x{a.machines}x{a.tools}*1@{a.seed}" + tail for j in a.sizes
             for tail in (["", "/notools"] if a.notools else [""])]
    tasks = [[s, spec] for spec in specs for s in a.solvers] + [["greedy", n] for n in a.builtins]
    here = ROOT / "src"
    rows = []
    head = (f"{platform.node()} {time.strftime('%Y-%m-%d')}, {platform.processor() or platform.machine()}, "
            f"best of {a.rounds} solves per shop, of {a.repeat} list schedules per built-in"
            + (f", baseline {a.baseline} alternating" if a.baseline else ""))
    print(head, flush=True)
    lines = [head]
    with _sources(here, a.baseline) as sources:
        for task in tasks:
            got: dict[str, dict] = {}
            for _ in range(a.rounds if task[0] != "greedy" else 1):  # (a built-in's list schedules: --repeat)
                for who, src in sources:
                    r = _worker(src, task, a.repeat)
                    old = got.get(who)
                    if old is not None and (old["makespan"], old["fingerprint"]) != (r["makespan"], r["fingerprint"]):
                        raise SystemExit(f"{r['shop']} ({r['solver']}): two runs of the {who} source made different "
                                         "schedules")
                    if old is None or r["seconds"] < old["seconds"]:
                        got[who] = r
            n = got["new"]
            row = dict(n)
            line = f"{n['shop']:28s} {n['solver']:12s} {n['operations']:6d} ops  {_t(n['seconds'])}"
            if a.baseline:
                b = got["base"]
                if (b["makespan"], b["fingerprint"]) != (n["makespan"], n["fingerprint"]):
                    raise SystemExit(f"{n['shop']} ({n['solver']}): the baseline's schedule differs (makespan "
                                     f"{b['makespan']} against {n['makespan']}, fingerprint {b['fingerprint']} against "
                                     f"{n['fingerprint']})")
                row["baseline_seconds"] = b["seconds"]
                line += f"  against {_t(b['seconds'])}, {b['seconds'] / n['seconds']:6.2f}x"
            line += f"  makespan {n['makespan']}" + (" (same schedule)" if a.baseline else "")
            print(line, flush=True)
            lines.append(line)
            rows.append(row)
    report(lines, rows, a.json, shown=len(lines))


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
