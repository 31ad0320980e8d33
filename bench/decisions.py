"""Decisions through the full net against the paper's net, the list schedule and CP-SAT (issue figures).

Runs (resumable, through ``fms bench``'s cache) the methods ``rules:paper`` (the best of the paper net's 36
rule pairs), ``rules:full`` (the best full-net rule combination or list schedule), ``list`` (the earliest-start
list schedule executed through the full net) and ``cpsat`` (10 s) on the 40 Bilge–Ulusoy instances (layouts
1-4) and the 80 large instances in both modes, then prints the summary: per BU layout the mean gap to the
optimum, per sl group and mode the mean gap to ``cpsat``, each against its goal (BU: best full-net rule within
5 % of the optima; sl: within 10 % of cpsat with tools, 8 % without).

Usage: ``nice python bench/decisions.py [--results-dir results/decisions] [--jobs 1] [--summary]``
(``--summary``: only print the summary of what the cache holds). About 4 hours on one core of the 2-core
machine, most of it ``rules:full`` on the 100-job instances with tools (158 runs each, 5-8 minutes).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from fms_dispatch.benchmark import CACHE_NAME, bu_tasks, read_cache, run_bench, sl_tasks
from fms_sim.benchmarks import SL_GROUPS

from checks import positive

METHODS = ["rules:paper", "rules:full", "list", "cpsat"]
GOALS = {"bu": 5.0, "agvs+tools": 10.0, "agvs": 8.0}
#: CP-SAT's limit (seconds) in this bench's runs and its summary's reference
CPSAT_LIMIT = 10.0


def run(results_dir: Path, jobs: int) -> None:
    tasks = []
    for layout in (1, 2, 3, 4):
        tasks += bu_tasks(METHODS, layout=layout, cpsat_time_limit=CPSAT_LIMIT, cpsat_workers=1)
    tasks += sl_tasks(METHODS, groups=range(len(SL_GROUPS)), cpsat_time_limit=CPSAT_LIMIT, cpsat_workers=1)
    run_bench(tasks, jobs=jobs, results_dir=results_dir, progress=True)


def _gap(x: float, ref: float) -> float:
    return 100.0 * (x - ref) / ref


def summary(results_dir: Path) -> str:
    rows = [r for r in read_cache(results_dir / CACHE_NAME).values() if r["valid"]]
    # the goals are stated against CP-SAT with this bench's limit; a cache shared with other runs can hold other
    # limits, which would replace each other by file order
    other = [r for r in rows if r["method"] == "cpsat" and r.get("time_limit") != CPSAT_LIMIT]
    rows = [r for r in rows if not (r["method"] == "cpsat" and r.get("time_limit") != CPSAT_LIMIT)]
    cells: dict[tuple, dict[str, int]] = defaultdict(dict)
    for r in rows:
        cells[r["benchmark"], r["variant"], r["instance"]][r["method"]] = r["makespan"]
    out = ["| set | mode | n | rules:paper | rules:full | list | cpsat | reference | goal | met |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[dict[str, float]]] = defaultdict(list)
    for (bench, variant, inst), ms in cells.items():
        if bench == "bu":
            from fms_sim.benchmarks import builtin

            ref = builtin(inst).meta["optimal_makespan"]
            key = ("bu", f"layout {inst[-1]}", variant)
        else:
            if "cpsat" not in ms:
                continue
            ref = ms["cpsat"]
            key = ("sl", f"group {inst[2]}", variant)
        if all(m in ms for m in METHODS):
            groups[key].append({m: _gap(ms[m], ref) for m in METHODS})
    for (bench, name, variant), gaps in sorted(groups.items()):
        mean = {m: statistics.mean(g[m] for g in gaps) for m in METHODS}
        goal = GOALS["bu" if bench == "bu" else variant]
        ref = "optimum" if bench == "bu" else f"cpsat {CPSAT_LIMIT:g} s"
        met = "yes" if mean["rules:full"] <= goal else f"**missed** (+{mean['rules:full']:.1f} %)"
        out.append(f"| {bench} {name} | {variant} | {len(gaps)} | " + " | ".join(f"{mean[m]:+.1f} %" for m in METHODS)
                   + f" | {ref} | ≤ {goal:g} % | {met} |")
    if other:
        out.append(f"\n({len(other)} cached CP-SAT runs with a limit other than {CPSAT_LIMIT:g} s left out.)")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results-dir", default="results/decisions")
    ap.add_argument("--jobs", type=positive, default=1)
    ap.add_argument("--summary", action="store_true", help="only summarise the cache")
    a = ap.parse_args()
    results = Path(a.results_dir)
    if not a.summary:
        run(results, a.jobs)
    if not (results / CACHE_NAME).is_file():
        sys.exit(f"no results in {results} (run without --summary first)")
    print(summary(results))


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
