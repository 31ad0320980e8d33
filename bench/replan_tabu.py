"""Plan re-planning with and without the tabu search, on the same plans in the same disrupted scenarios.

Each validation shop gets one nominal plan (CP-SAT, ``--cpsat`` seconds, made once and shared by every way), which
is executed through the full net in fixed disrupted scenarios (noise, machine breakdowns in the first half of the
plan, as ``fms experiment disruptions`` draws them) with re-planning on (``fms_dispatch.replan``, ``--budget``
seconds per re-plan): once per tabu search time in ``--tabu`` (seconds per operation left to plan; ``0``: the list
schedules, the CP-SAT-guided schedule and the restarts alone)::

    python bench/replan_tabu.py [--shops SPEC ...] [--tabu 0 0.0025] [--seeds 3] [--noise 0.1] [--budget 1]
                                [--breakdowns 2] [--cpsat 5] [--json FILE]

Prints each way's total realised makespan, how many runs it ends below / above the first way, and its re-plans.
Every schedule is validated against its scenario.
"""

from __future__ import annotations

import argparse
import time

from fms_dispatch.replan import solve_with_replanning
from fms_dispatch.rl.train import expand_instances
from fms_dispatch.solvers import solve
from fms_sim.disruptions import Scenario
from fms_sim.shopsets import check_training_specs

from checks import checked, output_file, positive, report, versus_line

DEFAULT_SHOPS = ["genbu:**1@31", "gen:10x5x5*2@216", "gen:10x5x5*2@219/notools", "gen:20x10x10*2@216",
                 "gen:20x10x10*2@219/notools"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shops", nargs="+", default=DEFAULT_SHOPS, help="validation shop specs")
    ap.add_argument("--tabu", type=float, nargs="+", default=[0.0, 0.0025], help="tabu search times to compare")
    ap.add_argument("--seeds", type=positive, default=3, help="scenarios per shop")
    ap.add_argument("--noise", type=float, default=0.1)
    ap.add_argument("--breakdowns", type=int, default=2)
    ap.add_argument("--budget", type=float, default=1.0, help="seconds per re-plan")
    ap.add_argument("--cpsat", type=float, default=5.0, help="seconds for each shop's nominal CP-SAT plan")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    a = ap.parse_args(argv)
    check_training_specs({"train": a.shops, "eval": [], "warm_start": {}})
    rows = []
    t0 = time.perf_counter()
    for inst in expand_instances(a.shops):
        plan = solve(inst, "cpsat", time_limit=a.cpsat)
        checked(inst, plan, "cpsat (the plan)")
        for seed in range(a.seeds):
            sc = Scenario.draw(inst, noise=a.noise, breakdowns=a.breakdowns, horizon=max(1, plan.makespan // 2),
                               duration=(max(1, plan.makespan // 20), max(1, plan.makespan // 7)), seed=seed)
            row: dict = {"shop": inst.name, "seed": seed, "plan": plan.makespan}
            for s in a.tabu:
                out = solve_with_replanning(inst, plan, budget=a.budget, scenario=sc, seed=seed, tabu=s)
                row[f"tabu {s:g}"] = checked(inst, out, f"tabu {s:g}", sc)
                row[f"tabu {s:g} replans"] = len(out.meta["replans"])
            rows.append(row)
            print(row, flush=True)
    first = f"tabu {a.tabu[0]:g}"
    lines = [f"{len(rows)} runs, noise {a.noise:g}, {a.breakdowns} breakdowns, {a.budget:g} s per re-plan:"]
    for s in a.tabu:
        k = f"tabu {s:g}"
        lines.append(versus_line(rows, k, first) + f"   {sum(r[k + ' replans'] for r in rows)} re-plans")
    lines.append(f"({time.perf_counter() - t0:.0f} s)")
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
