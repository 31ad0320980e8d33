"""Run the exact CP-SAT model on the Bilge–Ulusoy instances (default: EX12..EX102, layout 2, 2 AGVs).

Usage: python bench/cpsat_bu.py [--time-limit 60] [--workers 2] [--layout 2] [--seed 0] [--log] [SET ...]

Prints one line per instance: name, known optimum, makespan, proven lower bound, status, wall seconds, and
whether the schedule passes the validator; exits with status 1 if a schedule is invalid or a proven optimum
contradicts the known one.
"""

from __future__ import annotations

import argparse

from fms_dispatch.exact import solve_exact
from fms_sim.benchmarks import BU_OPTIMAL_MAKESPAN, builtin
from fms_sim.validate import validate

from checks import positive


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("sets", nargs="*", type=int, default=list(range(1, 11)), help="job sets 1..10")
    ap.add_argument("--time-limit", type=float, default=60.0)
    ap.add_argument("--workers", type=positive, default=2)
    ap.add_argument("--layout", type=int, default=2, choices=(1, 2, 3, 4))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--log", action="store_true", help="print the CP-SAT search log")
    args = ap.parse_args()
    bad = [s for s in args.sets if not 1 <= s <= 10]
    if bad:  # (set 11 was reported as an unknown instance EX112)
        ap.error(f"job sets are 1..10, got {bad[0]}")
    failed = False
    for s in args.sets:
        inst = builtin(f"EX{s}{args.layout}")
        r = solve_exact(inst, time_limit=args.time_limit, workers=args.workers, seed=args.seed, log=args.log)
        assert r.schedule is not None
        bad = validate(inst, r.schedule)
        known = BU_OPTIMAL_MAKESPAN.get((s, args.layout))
        wrong = r.status == "OPTIMAL" and known is not None and r.schedule.makespan != known
        failed |= bool(bad) or wrong
        print(f"{inst.name:6s} known={known} makespan={r.schedule.makespan} bound={r.lower_bound} "
              f"status={r.status} time={r.wall_time:.1f}s valid={not bad}"
              + (f" INVALID: {bad[0]}" if bad else "") + (" MISMATCH" if wrong else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
