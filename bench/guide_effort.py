"""How hard to search the guide's plan: plan quality and time per plan search effort, on validation shops.

The default search (``fms_dispatch.rl.guide.DEFAULT_EFFORT``) is a choice, so it is made on generated validation
shops that no model trains on and no reported figure comes from (the specs are checked like training specs)::

    python bench/guide_effort.py [--shops 'genbu:**3@31' 'genbu:**5@33' ...] [--efforts 0 64+rules ...]

An effort is ``N`` (restarts) with ``+rules`` for the rule pairs' schedules, ``+tabuS`` for S seconds of tabu search
per operation and ``+exactS`` for S seconds of CP-SAT polish; every effort runs without an overall time limit (so
the figures show what each costs) unless ``--budget`` sets one, as the solver does (1 s), for larger shops::

    python bench/guide_effort.py --shops 'gen:8x5x5*4@216' 'gen:20x10x10*2@216' --budget 1 --efforts 64+tabu0.0025 ...

Per effort: the mean ratio of the planned makespan to the list schedule's, the mean and largest seconds of the
search, and the same for the guided model acting the plan out (plain ``ppo:guided``, each run planning from scratch),
every schedule validated. CP-SAT is started before the timing where an effort uses it.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

from fms_dispatch.rl import ppo_solver
from fms_dispatch.rl.guide import PlanEffort, guide_plan
from fms_dispatch.rl.models import load_agent
from fms_dispatch.rl.train import expand_instances
from fms_sim.full_shop import FullShop
from fms_sim.shopsets import check_training_specs
from fms_sim.validate import validate


def parse_effort(text: str) -> PlanEffort:
    """``N[+rules][+exactS][+tabuS]``: N restarts, the rule pairs, S seconds of CP-SAT polish, S seconds of tabu
    search per operation."""
    n, *extra = text.split("+")
    rules, exact, tabu = False, 0.0, 0.0
    try:
        for part in extra:
            if part == "rules":
                rules = True
            elif part.startswith("exact"):
                exact = float(part[5:])
            elif part.startswith("tabu"):
                tabu = float(part[4:])
            else:
                raise ValueError(part)
        return PlanEffort(restarts=int(n), rules=rules, exact=exact, tabu=tabu)
    except ValueError:
        raise ValueError(f"bad effort {text!r}: use N[+rules][+exactS][+tabuS]") from None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shops", nargs="+", default=["genbu:**3@31", "genbu:**5@33"],
                    help="generated shop specs (not held out)")
    ap.add_argument("--efforts", nargs="+", default=["0", "64", "64+rules", "1024+rules", "64+rules+exact0.25",
                                                     "64+exact0.25", "0+tabu0.0025", "32+tabu0.003", "64+tabu0.001",
                                                     "64+tabu0.002", "64+tabu0.0025", "64+tabu0.003", "64+tabu0.005",
                                                     "64+tabu0.01", "64+tabu0.0025+exact0.25"])
    ap.add_argument("--budget", type=float, default=None,
                    help="overall time limit of each plan search in seconds (default: none; larger shops: give the "
                         "solver's 1 s, where the budget shapes the search)")
    a = ap.parse_args(argv)
    efforts = {text: parse_effort(text) for text in a.efforts}  # a typo fails before the shops are planned
    check_training_specs({"train": a.shops, "eval": [], "warm_start": {}})
    shops = list(expand_instances(a.shops))
    solve = ppo_solver("ppo:guided")
    solve(shops[0])  # load the model before timing
    agent = load_agent("guided")  # (the agent the solver runs: loaded agents are shared)
    if any(e.exact for e in efforts.values()):  # start CP-SAT before timing (its first solve loads the solver)
        guide_plan(FullShop(shops[0]), PlanEffort(restarts=0, exact=0.05))
    base = [guide_plan(FullShop(inst)).makespan for inst in shops]  # (by name, two shops of one name shared one)
    print(f"{len(shops)} shops; ratio to the list schedule, seconds (mean / max)")
    for text in a.efforts:
        effort = dataclasses.replace(efforts[text], budget=a.budget)
        plan_r, run_r, plan_s, run_s = [], [], [], []
        for inst, list_makespan in zip(shops, base):
            t0 = time.perf_counter()
            plan = guide_plan(FullShop(inst), effort)
            plan_s.append(time.perf_counter() - t0)
            agent.forget()  # plan from scratch: a repeated effort would otherwise act out the plan it made before
            t0 = time.perf_counter()
            sched = solve(inst, guide_effort=effort)
            run_s.append(time.perf_counter() - t0)
            for s in (plan, sched):
                if validate(inst, s):
                    raise SystemExit(f"INFEASIBLE {inst.name} ({text})")
            plan_r.append(plan.makespan / list_makespan)
            run_r.append(sched.makespan / list_makespan)
        print(f"{text:12s} plan {statistics.mean(plan_r):.4f} ({statistics.mean(plan_s):.3f} / {max(plan_s):.3f} s)"
              f"  guided {statistics.mean(run_r):.4f} ({statistics.mean(run_s):.3f} / {max(run_s):.3f} s)",
              flush=True)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
