"""A guided model on shops whose travel is one-way cheap: does the clone still act out its plan?

The guided models were cloned from the guide follower (:class:`fms_dispatch.rl.guide.GuideFollower`, the expert
that does what the plan's heads say) on generated shops whose travel times are the same both ways. Real AGV guide
paths are often one-way. This bench takes the held-out shops (inference only; no model trains or is selected on
them), makes each travel time between two places ``f`` times its value one way and ``1/f`` times it the other
(rounded, at least 1 where it was not 0; the same for the tool transporters), and runs on each the model, the
follower acting out the same plan search, and the list schedule::

    python bench/asymmetric.py [--model guided-dagger] [--skew 1 0.5 0.2] [--max-jobs 60] [--json FILE]

The plan search is the model's default with ``--guide-tabu 0`` (reproducible where the 1 s budget does not cut
it), so the model and the follower act out the same plan. Prints per skew the model's and the list schedule's mean
gap to the follower and on how many shops the model ends elsewhere than the follower. Every schedule is
validated.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace
from typing import Any

from fms_dispatch.rl import ppo_solver
from fms_dispatch.rl.guide import GuideFollower, effort_from
from fms_dispatch.rl.models import load_agent
from fms_dispatch.solvers import solve
from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop

from checks import checked, output_file, positive, report, run_main

HELD_OUT = [f"ho{i:02d}" for i in range(50)]


def skewed(matrix: Any, f: float) -> Any:
    """``matrix`` with each entry above the diagonal times ``f`` and each below it times ``1/f`` (rounded, at least
    1 where it was not 0)."""
    if matrix is None:
        return None
    n = len(matrix)
    return tuple(tuple(matrix[i][j] if i == j or not matrix[i][j]
                       else max(1, round(matrix[i][j] * (f if i < j else 1 / f))) for j in range(n))
                 for i in range(n))


def _skew(text: str) -> float:
    x = float(text)
    if not 0 < x <= 1:
        raise argparse.ArgumentTypeError(f"a skew is a factor in (0, 1], got {text!r}")
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="guided-dagger", help="a guided model (name or folder)")
    ap.add_argument("--skew", type=_skew, nargs="+", default=[1.0, 0.5, 0.2],
                    help="factors f in (0, 1]: travel one way times f, the other way times 1/f (1: as they are)")
    ap.add_argument("--max-jobs", type=positive, default=60, help="held-out shops of at most this many jobs")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    a = ap.parse_args(argv)
    agent = load_agent(a.model)
    if agent.guide is None:
        raise ValueError(f"model {agent.name} has no plan guide: it has no plan to act out")
    solver = ppo_solver(f"ppo:{a.model}")
    effort = effort_from(tabu=0.0)
    shops = [inst for inst in map(builtin, HELD_OUT) if inst.n_jobs <= a.max_jobs]
    if not shops:
        raise ValueError(f"no held-out shop has at most {a.max_jobs} jobs (the smallest have 5)")
    rows: list[dict] = []
    lines = [f"{agent.name} against the guide follower on {len(shops)} held-out shops of at most {a.max_jobs} jobs "
             "with one-way cheap travel (the plan search without tabu)"]
    t0 = time.perf_counter()
    for f in a.skew:
        for base in shops:
            inst = replace(base, name=f"{base.name}-skew{f:g}", agv_travel=skewed(base.agv_travel, f),
                           tool_travel=skewed(base.tool_travel, f))
            shop = FullShop(inst)
            follower = GuideFollower(effort=effort)
            while not shop.done:
                shop.act(follower(shop))
            expert = checked(inst, shop.schedule(), "the guide follower")
            agent.forget()  # each run plans from scratch
            model = checked(inst, solver(inst, guide_effort=effort), agent.name)
            listed = checked(inst, solve(inst, "list"), "list")
            rows.append({"skew": f, "instance": base.name, "follower": expert, "model": model, "list": listed})
            print(f"[skew {f:g}] {base.name}: follower {expert}, model {model}, list {listed}", flush=True)
        mine = [r for r in rows if r["skew"] == f]
        gap = [r["model"] / r["follower"] - 1 for r in mine]
        lgap = [r["list"] / r["follower"] - 1 for r in mine]
        lines.append(f"  skew {f:g}: model {100 * statistics.mean(gap):+.2f} % against the follower (at most "
                     f"{100 * max(gap):+.1f} %; elsewhere on {sum(r['model'] != r['follower'] for r in mine)} of "
                     f"{len(mine)}), list schedule {100 * statistics.mean(lgap):+.2f} %")
    lines.append(f"({time.perf_counter() - t0:.0f} s)")
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    run_main(main)
