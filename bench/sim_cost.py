"""What a run of a plan through the net costs against one list schedule of the same work, in a re-plan's state:
the measurement behind ``fms_dispatch.replan.SIM_COST`` (a re-plan simulates only where three such runs take at
most half its budget; docs/benchmarks.md §8).

Each shop's earliest-start plan is replayed for a share of its operations (``--share``, default 0.1), then, at
the next state a snapshot can be taken of, the earliest-start list schedule of the remaining work is made (timed)
and run through a nominal copy of the net (timed). Printed per shop: the work left, both times and their
ratio (the median of ``--repeat`` timings each); the run's end is checked against the schedule it followed.

    .venv/bin/python bench/sim_cost.py
    .venv/bin/python bench/sim_cost.py --shops EX74 sl00 sl70 --json results/sim_cost.json
"""

from __future__ import annotations

import argparse
import copy
import platform
import statistics
import time

from fms_dispatch.exact import greedy_schedule
from fms_dispatch.replan import SIM_COST, simulate
from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop
from fms_sim.replay import PlanPolicy
from fms_sim.snapshot import can_snapshot, nominal_copy, snapshot
from fms_sim.stepping import Stepper

from checks import checked, output_file, positive, report

SHOPS = ["EX74", "ra05", "sl00", "sl20", "sl40", "sl45", "sl70"]


def _state(name: str, share: float) -> FullShop:
    """``name``'s shop after its earliest-start plan ran through ``share`` of its operations' worth of answers."""
    inst = builtin(name)
    plan = greedy_schedule(inst, rule="est")
    checked(inst, plan, "est")
    shop = FullShop(inst)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    pol = PlanPolicy(inst, plan)
    cut = int(share * sum(len(j) for j in inst.jobs) * 3)  # about three answers per operation
    n = 0
    while st.kind != "done" and (n < cut or not can_snapshot(shop)):
        label = pol.answer(st)
        pol.apply(st, label)
        st.apply(label)
        n += 1
    return shop


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--shops", nargs="+", default=SHOPS)
    p.add_argument("--share", type=float, default=0.1, help="share of the run done before the re-plan's state")
    p.add_argument("--repeat", type=positive, default=3)
    p.add_argument("--json", type=output_file, help="write the rows and the summary here")
    a = p.parse_args()
    if not 0 <= a.share < 1:
        raise ValueError(f"--share must be in [0, 1), got {a.share}")
    for name in a.shops:  # an unknown name stops the bench now, not after the shops before it
        builtin(name)
    rows, lines = [], []
    print(f"{platform.node()}, {time.strftime('%Y-%m-%d')}; SIM_COST = {SIM_COST}")
    for name in a.shops:
        shop = _state(name, a.share)
        snap = snapshot(shop)
        sim = nominal_copy(shop)
        lists, runs = [], []
        for _ in range(a.repeat):
            t = time.perf_counter()
            plan = greedy_schedule(snap.instance, rule="est", origin=snap)
            lists.append(time.perf_counter() - t)
            copy_ = copy.deepcopy(sim)
            t = time.perf_counter()
            made = simulate(copy_, plan)
            runs.append(time.perf_counter() - t)
            if made is None or made > plan.makespan:
                raise SystemExit(f"{name}: the run through the net ended at {made}, its plan at {plan.makespan}")
        one, run = statistics.median(lists), statistics.median(runs)
        row = {"shop": name, "remaining": snap.remaining, "list_ms": round(one * 1000, 2),
               "run_ms": round(run * 1000, 1), "ratio": round(run / one, 1)}
        rows.append(row)
        line = (f"{name:6s} {snap.remaining:5d} operations left: list schedule {row['list_ms']:8.2f} ms, run through "
                f"the net {row['run_ms']:8.1f} ms, ratio {row['ratio']:5.1f}")
        print(line, flush=True)
        lines.append(line)
    lines.append(f"ratio {min(r['ratio'] for r in rows)}-{max(r['ratio'] for r in rows)} (SIM_COST = {SIM_COST})")
    report(lines, rows, a.json, shown=len(lines) - 1)  # (the shops' lines were printed as they came)


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
