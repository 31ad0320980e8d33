"""A guided model on shops whose jobs arrive over time, with and without the tabu search in its plans.

``fms experiment dynamic`` on generated validation shops, without its SOS reference: the jobs are split into
``--parts`` partitions (default 10; at most one per job) arriving every Δ = the shop's simple lower bound / that
number (``fms_dispatch.experiments.run_arrivals``); at
each arrival the guided model plans again from the live shop's state (a residual plan with its plan search) and
continues. Each tabu search time in ``--tabu`` (seconds per operation to plan, for the start's plan of the first
partition and every re-plan; ``0``: the list search alone) runs every shop once, with the default effort
otherwise::

    python bench/arrivals.py [--model guided] [--shops SPEC ...] [--tabu 0 0.0025] [--parts 10] [--json FILE]

Prints each setting's total final makespan and on how many shops it is below / above the first setting. Every
final schedule is validated.
"""

from __future__ import annotations

import argparse
import time

from fms_dispatch.experiments import lower_bound, partition_jobs, run_arrivals
from fms_dispatch.rl.guide import effort_from
from fms_dispatch.rl.models import load_agent
from fms_dispatch.rl.train import expand_instances
from fms_sim.shopsets import check_training_specs

from checks import checked, output_file, positive, report, versus_line

DEFAULT_SHOPS = ["gen:10x5x5*3@216", "gen:20x10x10*3@216", "gen:20x10x10*2@219/notools", "gen:50x15x15*1@217",
                 "gen:50x15x15*1@220/notools"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="guided", help="a guided model (name or folder)")
    ap.add_argument("--shops", nargs="+", default=DEFAULT_SHOPS, help="validation shop specs")
    ap.add_argument("--tabu", type=float, nargs="+", default=[0.0, 0.0025],
                    help="tabu search times to compare (s per operation to plan)")
    ap.add_argument("--parts", type=positive, default=10, help="partitions per shop")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    a = ap.parse_args(argv)
    if len(set(a.tabu)) < len(a.tabu):  # one column each: a repeated time overwrote its own
        ap.error(f"--tabu: each time once, got {' '.join(f'{s:g}' for s in a.tabu)}")
    check_training_specs({"train": a.shops, "eval": [], "warm_start": {}})
    insts = expand_instances(a.shops)
    agent = load_agent(a.model)
    if agent.guide is None:
        raise ValueError(f"model {a.model} has no plan guide")
    rows = []
    t0 = time.perf_counter()
    for inst in insts:
        groups = [p for p in partition_jobs(inst.n_jobs, a.parts) if p]
        delta = lower_bound(inst) / len(groups)  # (more parts than jobs: one job each)
        arrival = [p * delta for p in range(len(groups))]
        row: dict = {"shop": inst.name, "parts": len(groups)}
        for s in a.tabu:
            agent.use_guide_effort(effort_from(tabu=s))
            agent.forget()
            shop, _ = run_arrivals(agent, inst, groups, arrival)
            row[f"tabu {s:g}"] = checked(shop.instance, shop.schedule(), f"tabu {s:g}")
        rows.append(row)
        print(row, flush=True)
    first = f"tabu {a.tabu[0]:g}"
    lines = [f"{len(rows)} shops, {a.parts} partitions (at most one per job), model {a.model}:"]
    lines += [versus_line(rows, f"tabu {s:g}", first) for s in a.tabu]
    lines.append(f"({time.perf_counter() - t0:.0f} s)")
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
