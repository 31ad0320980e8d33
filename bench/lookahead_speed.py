"""Speed of the PPO lookahead: trial-run twins and the cached trajectory against the reference planner.

``python bench/lookahead_speed.py [--instances EX12,...,sl00,sl00a] [--repeat N] [--fast]``

For each instance, runs PPO with lookahead twice in this process: with the reference planner
(``LookaheadPlanner(reference=True)``: every twin a deep copy of the shop, a fresh prediction rollout at every
idle stop — the first implementation) and with the default planner (twins are trial runs on the shop itself,
predictions read from the cached plain completion). Both must give the same schedule (checked, and validated);
prints the seconds of each (best of ``--repeat``) and the ratio. ``slNNa`` is slNN without tools (AGVs only).
Models: ``bu`` for EX instances, ``large`` / ``large-agv`` for sl instances.

``--fast`` also runs the fast lookahead (``retry=False``: rejected moves are not verified again until some
are kept) and prints its makespan, seconds and speed-up against the default planner. Its schedules differ
(so they are not compared), but they are validated and must be no worse than plain PPO.
"""

from __future__ import annotations

import argparse
import time

from fms_dispatch.rl.lookahead import run_agent, run_with_lookahead
from fms_dispatch.rl.models import load_agent
from fms_sim.benchmarks import builtin
from fms_sim.shop import Shop
from fms_sim.validate import validate

from checks import positive

DEFAULT = ",".join([f"EX{s}2" for s in range(1, 11)] + ["sl00a", "sl10a", "sl00"])


def instance_and_model(name: str):
    if name.startswith("sl"):
        agv_only = name.endswith("a")
        inst = builtin(name.rstrip("a"))
        return (inst.without_tools(), "large-agv") if agv_only else (inst, "large")
    return builtin(name), "bu"


def timed(inst, agent, reference: bool, repeat: int, retry: bool = True):
    best, sched = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        sched = run_with_lookahead(Shop(inst), agent.act, reference=reference, retry=retry)
        best = min(best, time.perf_counter() - t0)
    problems = validate(inst, sched)
    if problems:
        raise SystemExit(f"INFEASIBLE {inst.name}: {problems[0]}")
    return sched, best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--instances", default=DEFAULT)
    ap.add_argument("--repeat", type=positive, default=1, help="runs per planner (the best time counts)")
    ap.add_argument("--fast", action="store_true", help="also time the fast lookahead (retry=False)")
    args = ap.parse_args()
    shops = [(name, *instance_and_model(name)) for name in args.instances.split(",")]  # an unknown one: now
    agents: dict[str, object] = {}
    tot_ref = tot_new = tot_fast = 0.0
    fast_head = f" {'fast makespan':>13} {'fast s':>8} {'fast speed-up':>13}" if args.fast else ""
    print(f"{'instance':10} {'makespan':>8} {'reference s':>12} {'trial+cache s':>14} {'speed-up':>9}{fast_head}")
    for name, inst, model in shops:
        agent = agents.setdefault(model, load_agent(model))
        ref, t_ref = timed(inst, agent, True, args.repeat)
        new, t_new = timed(inst, agent, False, args.repeat)
        if new.to_dict() != ref.to_dict():
            raise SystemExit(f"{name}: the planners' schedules differ ({new.makespan} vs {ref.makespan})")
        tot_ref += t_ref
        tot_new += t_new
        fast_cols = ""
        if args.fast:
            fast, t_fast = timed(inst, agent, False, args.repeat, retry=False)
            plain = run_agent(Shop(inst), agent.act).makespan
            if fast.makespan > plain:
                raise SystemExit(f"{name}: the fast lookahead is worse than plain PPO ({fast.makespan} > {plain})")
            tot_fast += t_fast
            fast_cols = f" {fast.makespan:13d} {t_fast:8.3f} {t_new / t_fast:12.2f}x"
        print(f"{name:10} {new.makespan:8d} {t_ref:12.3f} {t_new:14.3f} {t_ref / t_new:8.2f}x{fast_cols}", flush=True)
    fast_total = f" {'':13} {tot_fast:8.3f} {tot_new / tot_fast:12.2f}x" if args.fast else ""
    print(f"{'total':10} {'':8} {tot_ref:12.3f} {tot_new:14.3f} {tot_ref / tot_new:8.2f}x{fast_total}")


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
