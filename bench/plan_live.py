"""Live plan execution over ROS 2 against the offline plan: ``fms up INSTANCE --solver plan:cpsat:S`` per instance.

For each instance: the offline ``cpsat`` makespan with the same time limit (measured in the same run), the
makespan of the live run (the agent node plans at the first state, then executes the plan through the shop
node, recorder attached), their gap, the wall time of ``fms up`` and whether the run is at the proven optimum
(BU instances carry their optimum). Goals (issue 18): within 1 % of the offline makespan on sl00-sl79, exactly
the optimum on the BU instances that cpsat proves.

Usage: ``python bench/plan_live.py [--set bu|sl] [--per-group K] [--skip K] [--limit N] [--time-limit S] [--json F]``
(ROS 2 Jazzy installed; each run gets a random ROS domain).
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fms_dispatch.solvers import solve
from fms_sim.benchmarks import builtin
from fms_sim.schedule import Schedule

from checks import checked, output_file, positive, write_json


def live(name: str, solver: str, work: Path) -> tuple[int | None, float, str]:
    out = work / f"{name}.json"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", name, "--solver", solver, "--out", str(out),
                          "--db", str(work / "fms.sqlite"), "--domain-id", str(random.randint(1, 101)), "-q",
                          "--timeout", "500"],
                         env=env, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        return None, wall, (res.stderr.strip().splitlines() or ["?"])[-1]
    sched = Schedule.load(out)
    return checked(builtin(name), sched, f"fms up --solver {solver}"), wall, ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", choices=("bu", "sl"), default="bu")
    ap.add_argument("--limit", type=positive, help="only the first N instances")
    ap.add_argument("--per-group", type=positive, default=10, help="sl: instances per group (default all 10)")
    ap.add_argument("--skip", type=int, default=0,
                    help="sl: skip the first K instances of each group (e.g. --skip 5: sl05-sl09, ..., sl75-sl79)")
    ap.add_argument("--time-limit", type=float, default=10.0)
    ap.add_argument("--json", type=output_file, help="also write the rows here")
    a = ap.parse_args()
    if not 0 <= a.skip <= 9:
        ap.error(f"--skip must be 0..9 (the instances of an sl group), got {a.skip}")
    names = ([f"EX{s}{lay}" for lay in range(1, 5) for s in range(1, 11)] if a.set == "bu"
             else [f"sl{g}{k}" for g in range(8) for k in range(a.skip, a.skip + a.per_group) if k < 10])[:a.limit]
    solver = f"plan:cpsat:{a.time_limit:g}"
    rows = []
    print(f"| instance | offline cpsat {a.time_limit:g} s | live {solver} | gap | optimum | fms up wall s |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            inst = builtin(name)
            offline = solve(inst, "cpsat", time_limit=a.time_limit)
            checked(inst, offline, "cpsat")
            span, wall, err = live(name, solver, Path(tmp))
            opt = inst.meta.get("optimal_makespan")
            gap = None if span is None else round(100 * (span - offline.makespan) / offline.makespan, 2)
            rows.append({"instance": name, "offline": offline.makespan, "offline_status": offline.meta["status"],
                         "live": span, "gap_pct": gap, "optimum": opt, "wall_s": round(wall, 2), "error": err})
            print(f"| {name} | {offline.makespan} ({offline.meta['status'].lower()}) | {span if span else err} | "
                  f"{gap if gap is not None else '—'} % | {opt if opt else '—'} | {wall:.1f} |", flush=True)
    ok = [r for r in rows if r["live"] is not None]
    within = sum(1 for r in ok if r["gap_pct"] <= 1.0)
    proven = [r for r in ok if r["offline_status"] == "OPTIMAL"]
    print(f"\nlive within 1 % of offline: {within}/{len(rows)}; at the proven optimum: "
          f"{sum(1 for r in proven if r['live'] == r['offline'])}/{len(proven)}; failed runs: {len(rows) - len(ok)}")
    if a.json:
        write_json(a.json, rows, indent=1)


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
