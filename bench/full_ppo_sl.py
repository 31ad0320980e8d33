"""A full-net PPO model on the large benchmark against the full-net rules and CP-SAT (issue 19's large goal).

Goal: PPO better than the best full-net rule in every size group, within 10 % of CP-SAT (10 s) in every group,
sl70 in <= 5 s. The references (``rules:full``: the best full-net rule combination or list schedule per
instance; ``cpsat``: 10 s) are read from ``fms bench`` caches made by ``bench/decisions.py`` (they take hours);
this script only runs the model::

    python bench/full_ppo_sl.py --model full --per-group 3 \\
        [--reference 'results/decisions/bench_cache.jsonl'] [--json results/full_ppo_sl.json]

Per group and mode it prints the model's mean makespan and seconds, the reference means over the same instances,
the gap to CP-SAT and whether PPO beats the best full-net rule. Every schedule is validated. ``--lookahead-guide``
runs a guided model with its plan's empty trips (``lookahead="guide"``).
"""

from __future__ import annotations

import argparse
import glob
import json
import statistics
import sys
import time
from pathlib import Path

from fms_dispatch.rl import ppo_solver
from fms_sim.benchmarks import SL_GROUPS, builtin

from checks import checked, output_file, positive, write_json

MODES = {"agvs+tools": False, "agvs": True}


#: the CP-SAT limit the goal is stated against (seconds); cached CP-SAT rows with another limit are left out
CPSAT_LIMIT = 10.0


def references(pattern: str) -> dict[tuple[str, str, str], int]:
    """(instance, variant, method) -> makespan from the cache files matching ``pattern``; CP-SAT only from its runs
    with the goal's limit (:data:`CPSAT_LIMIT`: a cache can hold runs with other limits, which would otherwise
    replace each other by file order), the others counted in a note."""
    out: dict[tuple[str, str, str], int] = {}
    other = 0
    for path in sorted(glob.glob(pattern)):
        for line in Path(path).read_text().splitlines():
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                continue
            if r.get("benchmark") == "sl" and r.get("valid") and r.get("makespan"):
                if r.get("method") == "cpsat" and r.get("time_limit") != CPSAT_LIMIT:
                    other += 1
                    continue
                out[r["instance"], r["variant"], r["method"]] = int(r["makespan"])
    if other:
        print(f"note: {other} cached CP-SAT runs with a limit other than {CPSAT_LIMIT:g} s left out", file=sys.stderr)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="full")
    ap.add_argument("--per-group", type=positive, default=10, help="instances per group (the first N)")
    ap.add_argument("--reference", default="results/decisions/bench_cache.jsonl",
                    help="glob of fms bench caches (default: where bench/decisions.py writes)")
    ap.add_argument("--json", type=output_file, help="write the rows here")
    ap.add_argument("--lookahead-guide", action="store_true", help="a guided model with its plan's empty trips")
    a = ap.parse_args(argv)
    if a.per_group > 10:
        ap.error("--per-group: a group has 10 instances")
    ref = references(a.reference)
    if not ref:
        print(f"note: no fms bench cache matches {a.reference!r}: the model's rows only, no table", file=sys.stderr)
    solve = ppo_solver(f"ppo:{a.model}")
    rows = []
    for g in range(len(SL_GROUPS)):
        for k in range(a.per_group):
            for variant, strip in MODES.items():
                inst = builtin(f"sl{g}{k}")
                inst = inst.without_tools() if strip else inst
                t0 = time.perf_counter()
                sched = solve(inst, lookahead="guide" if a.lookahead_guide else False)
                dt = time.perf_counter() - t0
                row = {"group": g, "instance": f"sl{g}{k}", "variant": variant,
                       "ppo": checked(inst, sched, f"ppo:{a.model} ({variant})"),
                       "seconds": round(dt, 2)}
                for method in ("rules:full", "list", "cpsat"):
                    row[method] = ref.get((f"sl{g}{k}", variant, method))
                rows.append(row)
                print(row, flush=True)
    print(f"| mode | group | n | PPO | best full-net rule | CP-SAT {CPSAT_LIMIT:g} s | PPO gap to CP-SAT | PPO < rule? | max s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for variant in MODES:
        for g in range(len(SL_GROUPS)):
            sel = [r for r in rows if r["group"] == g and r["variant"] == variant and r["rules:full"] and r["cpsat"]]
            if not sel:
                continue
            ppo, rule, cp = (statistics.mean(r[k] for r in sel) for k in ("ppo", "rules:full", "cpsat"))
            print(f"| {variant} | {g} | {len(sel)} | {ppo:.1f} | {rule:.1f} | {cp:.1f} | {100 * (ppo / cp - 1):+.1f} % | "
                  f"{'yes' if ppo < rule else 'no'} ({100 * (ppo / rule - 1):+.1f} %) | "
                  f"{max(r['seconds'] for r in sel):.1f} |")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        write_json(a.json, rows)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
