"""Models in disrupted shops: every shop in the same fixed scenarios for every method, and nominal.

What a PPO phase adds to a model that acts out a plan is judged where the plan goes stale: noise on every
duration and machine breakdowns, learnt by the decider only as they happen. This runs models (and the list
schedule's plan executed live, ``plan:list``, as the baseline; with ``--follower`` also the guide follower, the
expert the guided models are cloned from) on generated shops, each in ``--scenarios`` fixed
scenarios per disruption level (``fms_sim.env.episode_scenario``: seeded by the shop's name and the scenario's
number, breakdowns within the shop's work per machine), the same for every method::

    python bench/disrupted.py --models ppo:guided ppo:FOLDER [ppo:guided+lookahead-guide] [--shops SPEC ...]
                              [--noise 0 0.2] [--breakdowns 1]
                              [--scenarios 3] [--guide-tabu S] [--heldout] [--json FILE]

Validation shops by default (checked like training specs); ``--heldout`` runs the 50 held-out shops instead, for
reported figures only (never for choosing). Guided models plan with the solver's default effort unless
``--guide-*`` options say otherwise, and re-plan at breakdowns as the solver does unless ``--no-guide-replan``
(the guide follower never re-plans: compare models with it under ``--no-guide-replan``). A model's name may carry
a lookahead as the solver's names do (``ppo:guided-dagger+lookahead-guide``: the plan's empty trips). Per level:
each method's mean makespan, its mean ratio to ``plan:list``, and in how many runs it is below and above the first
model. Every schedule is validated against its scenario.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from fms_dispatch.cli import add_guide_args, guide_effort_from_args
from fms_dispatch.full_rules import run_full
from fms_dispatch.rl.guide import DEFAULT_EFFORT, GuideFollower
from fms_dispatch.rl.train import expand_instances
from fms_dispatch.solvers import get_solver, solve
from fms_sim.env import check_disruptions, episode_scenario
from fms_sim.shopsets import check_training_specs, heldout_shops

from checks import checked, output_file, positive, report

#: validation shops (seeds no model trains or is selected on): BU size, small and mid-size with and without tools
DEFAULT_SHOPS = ["genbu:**2@31", "gen:10x5x5*3@216", "gen:20x10x10*2@216", "gen:10x5x5*3@219/notools",
                 "gen:20x10x10*2@219/notools"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", required=True,
                    help="PPO solver names (ppo:NAME, ppo:FOLDER; +lookahead-guide etc. for a lookahead)")
    ap.add_argument("--shops", nargs="+", default=DEFAULT_SHOPS, help="generated validation shop specs")
    ap.add_argument("--heldout", action="store_true", help="the 50 held-out shops instead (reported figures only)")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.2],
                    help="disruption levels: spread of the lognormal noise on durations; 0 is the nominal level "
                         "(no noise and no breakdowns, one run per shop)")
    ap.add_argument("--breakdowns", type=int, default=1,
                    help="machine breakdowns per run of each level above 0")
    ap.add_argument("--scenarios", type=positive, default=3, help="scenarios per shop and disrupted level")
    ap.add_argument("--follower", action="store_true",
                    help="also the guide follower (the expert the guided models are cloned from) on the same plans")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    add_guide_args(ap)
    a = ap.parse_args(argv)
    if a.heldout:
        insts = heldout_shops()
    else:
        check_training_specs({"train": a.shops, "eval": [], "warm_start": {}})
        insts = expand_instances(a.shops)
    effort = guide_effort_from_args(a)
    replan = {} if a.guide_replan is None else {"guide_replan": a.guide_replan}
    methods = ["plan:list"] + (["guide-follower"] if a.follower else []) + list(a.models)
    solvers = {m: get_solver(m) for m in a.models}  # an unknown name or model stops the bench before any run
    rows = []
    t_start = time.perf_counter()
    for noise in a.noise:
        nominal = noise == 0
        for inst in insts:
            for k in range(1 if nominal else a.scenarios):
                sc = None if nominal else episode_scenario(inst, check_disruptions(
                    {"noise": noise, "breakdowns": a.breakdowns, "fixed": True, "seed": k}))
                row: dict = {"shop": inst.name, "tools": inst.has_tools, "noise": noise, "scenario": k}
                for m in methods:
                    t0 = time.perf_counter()
                    if m == "plan:list":
                        s = solve(inst, m, scenario=sc)
                    elif m == "guide-follower":
                        s = run_full(inst, GuideFollower(effort=effort or DEFAULT_EFFORT), sc)
                    else:
                        s = solvers[m](inst, scenario=sc, guide_effort=effort, **replan)
                    row[m] = checked(inst, s, m, sc)
                    row[m + "_s"] = round(time.perf_counter() - t0, 2)
                rows.append(row)
                print(json.dumps(row), flush=True)
    lines = []
    first = a.models[0]
    for noise in a.noise:
        part = [r for r in rows if r["noise"] == noise]
        for m in methods:
            mean = statistics.mean(r[m] for r in part)
            ratio = statistics.mean(r[m] / r["plan:list"] for r in part)
            below = sum(r[m] < r[first] for r in part)
            above = sum(r[m] > r[first] for r in part)
            lines.append(f"noise {noise:g}: {m:28s} mean {mean:9.1f}  {ratio:.4f} x plan:list  "
                         f"below / above {first}: {below} / {above} of {len(part)}")
    lines.append(f"({time.perf_counter() - t_start:.0f} s)")
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
