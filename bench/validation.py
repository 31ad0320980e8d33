"""Model selection on generated validation shops: which model serves which kind of shop by default.

The default model per kind of shop (``fms_dispatch.rl.models.default_model_name``) is a selection, so it is made
on generated shops that are neither training shops of any model nor held-out shops nor benchmarks (the specs
are checked like training specs), never on the shops the reported figures come from::

    python bench/validation.py --models ppo:guided ppo:large --shops 'gen:20x10x10*2@216' ... [--lookahead]

Per shop: the list schedule (the better of ``list`` and ``list:ect``, executed through the full net) and each
model (plain, and with ``--lookahead`` also with the lookahead: a guided model's guide empty trips with
``--lookahead-guide``, acting out the plan of the plain run: its seconds leave out the plan search); guided models
plan with the solver's default effort; every schedule validated. The summary gives
each method's mean ratio to the list schedule, with and without tools.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from fms_dispatch.rl import ppo_solver
from fms_dispatch.rl.models import default_model_name, load_agent
from fms_dispatch.rl.train import expand_instances
from fms_dispatch.solvers import solve
from fms_sim.shopsets import check_training_specs

from checks import checked, output_file, report

#: the validation shops of the default choice in docs/benchmarks.md §9 (seeds used by no model's config)
DEFAULT_SHOPS = ["gen:20x10x10*2@216", "gen:50x15x15*2@217", "gen:100x20x20*1@218", "gen:20x10x10*2@219/notools",
                 "gen:50x15x15*2@220/notools", "gen:100x20x20*1@221/notools"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", required=True, help="PPO solver specs (ppo:NAME, ppo:FOLDER)")
    ap.add_argument("--shops", nargs="+", default=DEFAULT_SHOPS, help="generated shop specs (not held out)")
    ap.add_argument("--lookahead", action="store_true", help="also each model with the lookahead")
    ap.add_argument("--lookahead-guide", action="store_true",
                    help="with --lookahead: a guided model's lookahead is its guide's empty trips")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    a = ap.parse_args(argv)
    if a.lookahead_guide and not a.lookahead:  # it was ignored
        ap.error("--lookahead-guide chooses the lookahead of --lookahead; give both")
    check_training_specs({"train": a.shops, "eval": [], "warm_start": {}})
    for spec in a.models:  # an unknown model is refused before the runs, not reported as a row of nulls
        if "+" in spec:  # (it was looked up as a model named 'guided+lookahead-guide')
            ap.error(f"--models {spec}: give model names without a lookahead (--lookahead runs each with one)")
        if ":" in spec:
            load_agent(spec.split(":", 1)[1])
    rows = []
    for inst in expand_instances(a.shops):
        row: dict = {"shop": inst.name, "tools": inst.has_tools, "jobs": inst.n_jobs}
        row["list"] = min(checked(inst, solve(inst, n), n) for n in ("list", "list:ect"))
        for spec in a.models:
            for la in ((False, True) if a.lookahead else (False,)):
                key = spec + ("+la" if la else "")
                t0 = time.perf_counter()
                try:
                    mode: bool | str = ("fast" if inst.n_jobs >= 50 else True) if la else False
                    model = spec.split(":", 1)[1] if ":" in spec else default_model_name(inst)
                    if la and a.lookahead_guide and load_agent(model).guide is not None:
                        mode = "guide"
                    s = ppo_solver(spec)(inst, lookahead=mode)
                except ValueError as exc:  # the model does not fit the shop or its net
                    row[key] = None
                    row[key + "_why"] = str(exc)
                    continue
                row[key] = checked(inst, s, key)
                row[key + "_s"] = round(time.perf_counter() - t0, 2)
        rows.append(row)
        print(json.dumps(row), flush=True)
    keys = [k for k in rows[0] if k not in ("shop", "tools", "jobs", "list") and not k.endswith(("_s", "_why"))]
    lines = []
    for tools in (True, False):
        part = [r for r in rows if r["tools"] == tools]
        for k in keys:
            got = [r for r in part if r.get(k) is not None]
            if got:
                ratio = statistics.mean(r[k] / r["list"] for r in got)
                lines.append(f"{'tools' if tools else 'AGVs only'}: {k:28s} {ratio:.4f} x list ({len(got)} shops)")
    report(lines, rows, a.json)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
