"""PPO on all 40 Bilge–Ulusoy instances (EX11..EX104): plain and with lookahead, against the best rule pair and
the optima (issue 19's BU goal: a policy trained without any EX instance, with lookahead mean gap <= 3 % and
<= the best rule pair on at least 36 of 40, <= 0.1 s per instance). Usage:

    python bench/bu_all.py [--model bu] [--json results/bu_all.json]
    python bench/bu_all.py --model guided --lookahead-guide [--guide-restarts N --guide-budget S --guide-tabu S ...]

The best rule pair is the best of the 36 paper-net pairs (12 job rules x first / least-work / nearest) per
instance. Every schedule is validated. With ``--lookahead-guide`` a guided model's lookahead is its guide's empty
trips (``lookahead="guide"``); ``--guide-restarts``/``--guide-budget``/``--[no-]guide-rules``/``--guide-tabu``/
``--guide-exact`` set its plan search
(:class:`fms_dispatch.rl.guide.PlanEffort`; default: the solver's ``DEFAULT_EFFORT``). Each run is timed from
scratch, its plan search included (the model is loaded before), plain and with lookahead alike.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from fms_dispatch.cli import add_guide_args, guide_effort_from_args
from fms_dispatch.rl import ppo_solver
from fms_dispatch.rl.models import load_agent
from fms_dispatch.rules import all_rule_pairs, parse_rule_name
from fms_sim.benchmarks import BU_OPTIMAL_MAKESPAN, builtin
from fms_sim.shop import run_policy
from checks import checked, output_file, write_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="bu", help="model name or folder (default bu)")
    ap.add_argument("--json", type=output_file, help="write the rows here")
    ap.add_argument("--lookahead-guide", action="store_true", help="guided model: lookahead = the guide's empty trips")
    add_guide_args(ap, replan=False)
    a = ap.parse_args(argv)
    solver = ppo_solver(f"ppo:{a.model}")
    agent = load_agent(a.model)
    solver(builtin("EX11"))  # load the model (and warm up) before timing; every timed run forgets this one
    effort = guide_effort_from_args(a)
    kw = {} if effort is None else {"guide_effort": effort}
    rows = []
    for s in range(1, 11):
        for lay in range(1, 5):
            inst = builtin(f"EX{s}{lay}")
            row = {"instance": inst.name, "optimum": BU_OPTIMAL_MAKESPAN[s, lay]}
            best = None
            for name in all_rule_pairs(True):
                ms = checked(inst, run_policy(inst, parse_rule_name(name)), name)
                best = ms if best is None else min(best, ms)
            row["rules"] = best
            for la in (False, True):
                agent.forget()  # each run plans from scratch (a run of the same shop would reuse the last plan)
                t0 = time.perf_counter()
                sched = solver(inst, lookahead=("guide" if a.lookahead_guide else True) if la else False, **kw)
                dt = time.perf_counter() - t0
                key = "ppo+la" if la else "ppo"
                row[key], row[key + "_s"] = checked(inst, sched, key), round(dt, 4)
            rows.append(row)
            print(row, flush=True)
    opt = [r for r in rows if r["optimum"]]
    for key in ("rules", "ppo", "ppo+la"):
        gap = statistics.mean(100 * (r[key] / r["optimum"] - 1) for r in opt)
        print(f"{key:7s} mean {statistics.mean(r[key] for r in rows):7.2f}  gap to optima {gap:+.2f} % "
              f"({len(opt)} with optima)" + (f", <= best rule pair on {sum(r[key] <= r['rules'] for r in rows)}/40, "
                                             f"max {max(r[key + '_s'] for r in rows):.3f} s" if key != "rules" else ""))
    for lay in range(1, 5):
        sub = [r for r in rows if r["instance"].endswith(str(lay))]
        print(f"layout {lay}: " + ", ".join(f"{k} {statistics.mean(r[k] for r in sub):.1f}"
                                           for k in ("optimum", "rules", "ppo", "ppo+la")))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        write_json(a.json, rows)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
