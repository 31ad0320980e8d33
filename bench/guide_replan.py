"""Re-planning a guided model's plan when it goes stale, against acting the start's plan out.

A guided model plans at the start of the run; noise on every duration and machine breakdowns make that plan stale.
This runs a guided model on generated shops in fixed disrupted scenarios (``fms_sim.env.episode_scenario``, as
``bench/disrupted.py``), several ways in the same scenario: acting the start's plan out (``plan``: ``fms solve
--no-guide-replan``), re-planning its guide when each breakdown begins and always adopting the new plan
(``replan``: ``GuideReplanner(agent, margin=None, drift=None)``), and the ways ``margin M, drift D, budget B`` of
``GuideReplanner``: re-planned at breakdowns and (with a drift) when an operation starts late against the plan,
within B seconds, the new plan adopted where it ends M earlier than the plan in force continued from the state.
By default only the solver's and the agent node's setting (``REPLAN_MARGIN``, ``REPLAN_DRIFT``,
``REPLAN_BUDGET``); ``--margins``, ``--drifts`` (``none``: breakdowns only) and ``--budgets`` (``none``: the plan
search's own) add one way per combination, for choosing them; ``--replan-tabu`` adds the default way with re-plans
searched with other tabu search times than the start's plan (``--guide-tabu``; with ``0`` every way starts from the
same plan), to measure what the tabu search brings to re-plans (``--replan-margins``: with these margins)::

    python bench/guide_replan.py [--model guided-dagger] [--shops SPEC ...] [--noise 0.2] [--breakdowns 1]
                                 [--scenarios 2] [--margins M ...] [--drifts D ...] [--budgets B ...]
                                 [--guide-tabu S] [--replan-tabu S ...] [--replan-margins M ...] [--heldout]
                                 [--json FILE]

Validation shops by default (checked like training specs); ``--heldout`` runs the 50 held-out shops, for reported
figures only. Prints each way's total makespan, in how many runs it is below / above the plan acted out, its
re-plans and their wall time. Every schedule is validated against its scenario.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

from fms_dispatch.cli import add_guide_args, guide_effort_from_args
from fms_dispatch.rl.agent import GuideReplanner
from fms_dispatch.rl.guide import REPLAN_BUDGET, REPLAN_DRIFT, REPLAN_MARGIN
from fms_dispatch.rl.models import load_agent
from fms_dispatch.rl.train import expand_instances
from fms_sim.env import check_disruptions, episode_scenario
from fms_sim.full_shop import FullShop
from fms_sim.shopsets import check_training_specs, heldout_shops

from checks import checked, output_file, positive, report, versus

#: validation shops (seeds no model trains or is selected on), as bench/disrupted.py's selection run
DEFAULT_SHOPS = ["genbu:**3@31", "genbu:**5@33", "gen:10x5x5*3@216", "gen:20x10x10*2@216", "gen:10x5x5*3@219/notools",
                 "gen:20x10x10*2@219/notools", "gen:50x15x15*1@217", "gen:50x15x15*1@220/notools"]


def run(agent, inst, scenario, setting: tuple | None):
    """One disrupted run of ``agent``: re-planned by ``GuideReplanner(agent, *setting)``, or not (None); returns
    the schedule and the re-plan events."""
    agent.forget()  # every run plans from scratch
    shop = FullShop(inst, scenario=scenario)
    rp = None if setting is None else GuideReplanner(agent, *setting)
    while not shop.done:
        shop.act(rp(shop) if rp is not None else agent.act(shop))
    return shop.schedule(), ([] if rp is None else rp.events)


def _opt(text: str) -> float | None:
    """An argparse type: a number of seconds or a fraction, or ``none``."""
    if text.lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or none, got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="guided-dagger", help="a guided model (name or folder)")
    ap.add_argument("--shops", nargs="+", default=DEFAULT_SHOPS, help="validation shop specs")
    ap.add_argument("--heldout", action="store_true", help="the 50 held-out shops instead (reported figures only)")
    ap.add_argument("--noise", type=float, default=0.2, help="spread of the lognormal noise on durations")
    ap.add_argument("--breakdowns", type=int, default=1, help="machine breakdowns per scenario")
    ap.add_argument("--scenarios", type=positive, default=2, help="fixed scenarios per shop")
    ap.add_argument("--margins", type=float, nargs="+", default=[REPLAN_MARGIN],
                    help=f"margins to try (default {REPLAN_MARGIN}, the solver's)")
    ap.add_argument("--drifts", type=_opt, nargs="+", default=[REPLAN_DRIFT],
                    help=f"drifts to try ('none': breakdowns only; default {REPLAN_DRIFT}, the solver's)")
    ap.add_argument("--budgets", type=_opt, nargs="+", default=[REPLAN_BUDGET],
                    help=f"re-plan budgets in seconds to try ('none': the plan search's; default {REPLAN_BUDGET})")
    ap.add_argument("--replan-tabu", type=float, nargs="+", default=[],
                    help="also re-plan with these tabu search times (s per operation; the default margin, drift and "
                         "budget) while the start's plan keeps --guide-tabu's: the tabu search's share of re-plans")
    ap.add_argument("--replan-margins", type=float, nargs="+", default=[],
                    help="with --replan-tabu: these margins for its ways (default: the solver's)")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    add_guide_args(ap, replan=False)
    a = ap.parse_args(argv)
    if a.replan_margins and not a.replan_tabu:  # they would be ignored
        ap.error("--replan-margins sets the margins of the --replan-tabu ways; give --replan-tabu too")
    if a.heldout:
        insts = heldout_shops()
    else:
        check_training_specs({"train": a.shops, "eval": [], "warm_start": {}})
        insts = expand_instances(a.shops)
    agent = load_agent(a.model)
    if agent.guide is None:
        raise ValueError(f"model {a.model} has no plan guide: nothing to re-plan")
    agent.use_guide_effort(guide_effort_from_args(a))
    ways: dict[str, tuple | None] = {"plan": None, "replan": (None, None, None)}
    for m in a.margins:
        for d in a.drifts:
            for b in a.budgets:
                ways[f"margin {m:g}, drift {d}, budget {b}"] = (m, d, b)
    for s in a.replan_tabu:
        for m in a.replan_margins or [REPLAN_MARGIN]:
            label = f"re-planned with tabu {s:g}" + (f", margin {m:g}" if a.replan_margins else "")
            ways[label] = (m, REPLAN_DRIFT, REPLAN_BUDGET, dataclasses.replace(agent.guide_effort, tabu=s))
    rows = []
    t0 = time.perf_counter()
    for inst in insts:
        for k in range(a.scenarios):
            sc = episode_scenario(inst, check_disruptions(
                {"noise": a.noise, "breakdowns": a.breakdowns, "fixed": True, "seed": k}))
            row: dict = {"shop": inst.name, "tools": inst.has_tools, "scenario": k}
            for way, setting in ways.items():
                sched, events = run(agent, inst, sc, setting)
                row[way] = checked(inst, sched, way, sc)
                row[way + " replans"] = [len(events), round(sum(e["wall_time"] for e in events), 3)]
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = [f"{len(rows)} runs, noise {a.noise:g}, {a.breakdowns} breakdown(s), model {a.model}:"]
    for way in ways:
        total, ratio, below, above = versus(rows, way, "plan")
        n, wall = (sum(r[way + " replans"][i] for r in rows) for i in (0, 1))
        lines.append(f"  {way:44s} total {total:8d}  {ratio:.4f} x plan   "
                     f"below / above plan: {below:2d} / {above:2d}   {n} re-plans, {wall:.1f} s")
    lines.append(f"({time.perf_counter() - t0:.0f} s)")
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
