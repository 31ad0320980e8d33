"""A guided model's lookahead (the plan's empty trips) against its plain run, acting out the same plan.

The plan's empty trips (``--lookahead-guide``, :class:`fms_dispatch.rl.guide.GuideMoves`) are not checked in a twin
as the verified lookahead's moves are, so nothing by construction keeps them from making a run worse. This bench
measures whether they do: per instance the model plans once (its plan search from scratch, the plain run), then
acts the same plan out again with the empty trips, so the two runs differ by the lookahead alone even where the
plan search stops on the clock::

    python bench/guide_lookahead.py [--model guided-dagger] [--instances NAME ...] [--guide-tabu S ...] [--json FILE]

Default instances: the 40 Bilge–Ulusoy instances and the 50 held-out shops ho00–ho49 (inference only; no model
trains or is selected on them). Prints per set how many runs the lookahead makes shorter, equal and longer, and
names every longer one. Every schedule is validated.
"""

from __future__ import annotations

import argparse
import time

from fms_dispatch.cli import add_guide_args, guide_effort_from_args
from fms_dispatch.rl import ppo_solver
from fms_dispatch.rl.models import load_agent
from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop

from checks import checked, output_file, report, run_main

BU = [f"EX{s}{lay}" for s in range(1, 11) for lay in range(1, 5)]
HELD_OUT = [f"ho{i:02d}" for i in range(50)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="guided-dagger", help="a guided model (name or folder)")
    ap.add_argument("--instances", nargs="+", help="built-in instances (default: EX11-EX104 and ho00-ho49)")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    add_guide_args(ap, replan=False)
    a = ap.parse_args(argv)
    agent = load_agent(a.model)
    if agent.guide is None:
        raise ValueError(f"model {agent.name} has no plan guide: it has no plan's empty trips to make")
    solver = ppo_solver(f"ppo:{a.model}")
    effort = guide_effort_from_args(a)
    kw = {} if effort is None else {"guide_effort": effort}
    sets = {"instances": a.instances} if a.instances else {"Bilge-Ulusoy": BU, "held-out": HELD_OUT}
    for names in sets.values():  # an unknown name stops the bench now, not after the shops before it
        for name in names:
            builtin(name)
    rows = []
    lines = [f"{agent.name}: the plan's empty trips against the plain run, the same plan acted out"]
    for label, names in sets.items():
        counts = {"shorter": 0, "equal": 0, "longer": 0}
        for i, name in enumerate(names):
            inst = builtin(name)
            agent.forget()  # the plain run searches the plan from scratch; the lookahead run acts the same plan out
            t0 = time.perf_counter()
            plain = checked(inst, solver(inst, **kw), "plain")
            plan = agent.guide_of(FullShop(inst)).plan
            t1 = time.perf_counter()
            checked(inst, plan, "the guide's plan")
            look = checked(inst, solver(inst, lookahead="guide", **kw), "+lookahead-guide")
            t2 = time.perf_counter()
            if agent.guide_of(FullShop(inst)).plan is not plan:
                raise SystemExit(f"{name}: the lookahead run did not act out the plain run's plan")
            way = "shorter" if look < plain else "longer" if look > plain else "equal"
            counts[way] += 1
            rows.append({"set": label, "instance": name, "plan": plan.makespan, "plain": plain, "lookahead": look,
                         "plain_s": round(t1 - t0, 3), "lookahead_s": round(t2 - t1, 3)})
            print(f"[{label} {i + 1}/{len(names)}] {name}: plan {plan.makespan}, plain {plain}, lookahead {look}"
                  + ("  LONGER" if way == "longer" else ""), flush=True)
        mine = [r for r in rows if r["set"] == label]
        mean = {k: sum(r[k] for r in mine) / len(mine) for k in ("plain", "lookahead", "plan")}
        lines.append(f"  {label}: {len(mine)} instances; with the lookahead shorter {counts['shorter']}, equal "
                     f"{counts['equal']}, longer {counts['longer']}; mean plain {mean['plain']:.1f}, with the "
                     f"lookahead {mean['lookahead']:.1f}, the plans {mean['plan']:.1f}")
        lines += [f"    longer: {r['instance']} {r['plain']} -> {r['lookahead']}" for r in mine
                  if r["lookahead"] > r["plain"]]
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    run_main(main)
