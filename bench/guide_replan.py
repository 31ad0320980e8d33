"""Re-planning a guided model's plan when a machine breaks down, against acting the stale plan out.

A guided model plans at the start of the run; a breakdown (with noise on every duration) makes that plan stale.
This runs a guided model on generated shops in fixed disrupted scenarios (``fms_sim.env.episode_scenario``, as
``bench/disrupted.py``), three ways in the same scenario: acting the start's plan out (``plan``: ``fms solve
--no-guide-replan``), re-planning its guide from the shop's state when each breakdown begins and always adopting
the new plan (``replan``: ``GuideReplanner(agent, margin=None)``), and adopting it only where it ends ``--margin``
earlier than the plan in force continued from that state (``replan-margin``: the solver's and the agent node's
default, ``REPLAN_MARGIN``). ``--margins`` adds a ``replan-margin`` way per margin, for choosing one::

    python bench/guide_replan.py [--model guided-dagger] [--shops SPEC ...] [--noise 0.2] [--breakdowns 1]
                                 [--scenarios 2] [--margins M ...] [--guide-tabu S] [--heldout] [--json FILE]

Validation shops by default (checked like training specs); ``--heldout`` runs the 50 held-out shops, for reported
figures only. Prints the total makespan of each way and in how many runs each re-planning way is below / above the
plan acted out. Every schedule is validated against its scenario.
"""

from __future__ import annotations

import argparse
import json
import time

from fms_dispatch.cli import add_guide_args, guide_effort_from_args
from fms_dispatch.rl.agent import GuideReplanner
from fms_dispatch.rl.guide import REPLAN_MARGIN
from fms_dispatch.rl.models import load_agent
from fms_dispatch.rl.train import expand_instances
from fms_sim.env import check_disruptions, episode_scenario
from fms_sim.full_shop import FullShop
from fms_sim.shopsets import check_training_specs, heldout_shops

from checks import checked, report

#: validation shops (seeds no model trains or is selected on), as bench/disrupted.py's selection run
DEFAULT_SHOPS = ["genbu:**3@31", "genbu:**5@33", "gen:10x5x5*3@216", "gen:20x10x10*2@216", "gen:10x5x5*3@219/notools",
                 "gen:20x10x10*2@219/notools", "gen:50x15x15*1@217", "gen:50x15x15*1@220/notools"]


def run(agent, inst, scenario, margin: float | None, replan: bool = True):
    """One disrupted run of ``agent``, re-planning at each breakdown with ``margin`` (unless not ``replan``)."""
    agent.forget()  # every run plans from scratch
    shop = FullShop(inst, scenario=scenario)
    choose = GuideReplanner(agent, margin) if replan else agent.act
    while not shop.done:
        shop.act(choose(shop))
    return shop.schedule()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="guided-dagger", help="a guided model (name or folder)")
    ap.add_argument("--shops", nargs="+", default=DEFAULT_SHOPS, help="validation shop specs")
    ap.add_argument("--heldout", action="store_true", help="the 50 held-out shops instead (reported figures only)")
    ap.add_argument("--noise", type=float, default=0.2, help="spread of the lognormal noise on durations")
    ap.add_argument("--breakdowns", type=int, default=1, help="machine breakdowns per scenario")
    ap.add_argument("--scenarios", type=int, default=2, help="fixed scenarios per shop")
    ap.add_argument("--margins", type=float, nargs="+", default=[REPLAN_MARGIN],
                    help=f"the margins of the replan-margin ways (default {REPLAN_MARGIN}, the default's)")
    ap.add_argument("--json", help="write the rows and the summary here")
    add_guide_args(ap)
    a = ap.parse_args(argv)
    if a.heldout:
        insts = heldout_shops()
    else:
        check_training_specs({"train": a.shops, "eval": [], "warm_start": {}})
        insts = expand_instances(a.shops)
    agent = load_agent(a.model)
    if agent.guide is None:
        raise SystemExit(f"model {a.model} has no plan guide: nothing to re-plan")
    agent.use_guide_effort(guide_effort_from_args(a))
    ways = {"plan": None, "replan": None, **{f"replan-margin {m:g}": m for m in a.margins}}
    rows = []
    t0 = time.perf_counter()
    for inst in insts:
        for k in range(a.scenarios):
            sc = episode_scenario(inst, check_disruptions(
                {"noise": a.noise, "breakdowns": a.breakdowns, "fixed": True, "seed": k}))
            row: dict = {"shop": inst.name, "tools": inst.has_tools, "scenario": k}
            for way, margin in ways.items():
                row[way] = checked(inst, run(agent, inst, sc, margin, way != "plan"), way, sc)
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = [f"{len(rows)} runs, noise {a.noise:g}, {a.breakdowns} breakdown(s), model {a.model}:"]
    for way in ways:
        total = sum(r[way] for r in rows)
        below = sum(r[way] < r["plan"] for r in rows)
        above = sum(r[way] > r["plan"] for r in rows)
        lines.append(f"  {way:12s} total {total:8d}  {total / sum(r['plan'] for r in rows):.4f} x plan   "
                     f"below / above plan: {below} / {above}")
    lines.append(f"({time.perf_counter() - t0:.0f} s)")
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
