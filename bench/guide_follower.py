"""How faithfully a state-read policy acts out a list schedule through the full net (the guide's expert).

    python bench/guide_follower.py sl00 sl10 sl20 sl30 sl50 sl70 [--json results/guide_follower.json]

Per instance: the guide's plan (the better of the earliest-start and earliest-completion list schedules), its
exact replay (``fms_sim.replay``, orders consumed as they are carried out), the plan acted out by
``PlanPriorityPolicy`` (the full-net rule skeleton with the plan's start times as priorities: the expert of the
``full`` model) and by ``GuideFollower`` (the heads of the plan's orders read from each state: the expert of the
``guided`` model), with the follower's wall time. Every schedule is validated.
"""

from __future__ import annotations

import argparse
import time

from fms_dispatch.full_rules import run_full
from fms_dispatch.rl.guide import GuideFollower, GuideMoves, PlanGuide, guide_plan
from fms_dispatch.rl.lookahead import run_with_lookahead
from fms_dispatch.rl.plan_expert import PlanPriorityPolicy
from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop
from fms_sim.replay import replay
from fms_sim.validate import validate

from checks import output_file, write_json


def _valid(inst, s):
    problems = validate(inst, s)
    if problems:
        raise SystemExit(f"INFEASIBLE {inst.name}: {problems[0]}")
    return s.makespan


def follower_with_empty_trips(inst) -> int:
    """The follower, and at every idle stop each idle vehicle sent to the start of its next planned carry
    (:class:`GuideMoves`, the ``+lookahead-guide`` of a guided model)."""
    shop = FullShop(inst)
    guide = PlanGuide(inst, guide_plan(shop))
    return _valid(inst, run_with_lookahead(shop, GuideFollower(guide), planner=GuideMoves(lambda _: guide)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("instances", nargs="+")
    ap.add_argument("--json", type=output_file, help="write the rows here")
    a = ap.parse_args(argv)
    insts = [builtin(name) for name in a.instances]  # an unknown name stops the bench now, not after the others
    rows = []
    print("| instance | list plan | replay | PlanPriorityPolicy | GuideFollower | follower s | + empty trips |")
    print("|---|---|---|---|---|---|---|")
    for name, inst in zip(a.instances, insts):
        plan = guide_plan(FullShop(inst))
        t0 = time.perf_counter()
        follower = _valid(inst, run_full(inst, GuideFollower()))
        dt = time.perf_counter() - t0
        row = dict(instance=name, plan=_valid(inst, plan), replay=_valid(inst, replay(inst, plan)),
                   priority=_valid(inst, run_full(inst, PlanPriorityPolicy(plan))), follower=follower,
                   follower_s=round(dt, 2), with_empty_trips=follower_with_empty_trips(inst))
        rows.append(row)
        cells = [name] + [row[k] for k in ("plan", "replay", "priority", "follower", "follower_s", "with_empty_trips")]
        print("| " + " | ".join(map(str, cells)) + " |", flush=True)
    if a.json:
        write_json(a.json, rows)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
