"""The held-out shops ``ho00``..``ho49`` (issue 19): PPO models against CP-SAT, list schedules and full-net rules.

No model is trained or selected on these shops (``fms_sim.shopsets``; ``fms train`` refuses them), so the
figures say how the policies do on shops they never saw::

    python bench/heldout.py --models ppo:full ppo [--cpsat 10] [--limit N | --only hoNN ...] [--json F]
                            [--lookahead-max-jobs N] [--lookahead-guide] [--write-metrics]
    python bench/heldout.py --models ppo:other --reference results/heldout.json --json results/heldout2.json

Per shop: CP-SAT within ``--cpsat`` seconds (the reference; two workers), the earliest-start and
earliest-completion list schedules executed through the full net (``list``, ``list:ect``; the better one is
``list``), the best of the 12 job rules with the nearest vehicle and the earliest-start tool rule on the full net
(``rule``), and each model plain and with the lookahead (``+la``; without retries from 50 jobs on). Every schedule
is validated. The summary gives each method's mean gap to CP-SAT and, per model, on how many shops it is at most
the list schedule. With ``--lookahead-guide`` a guided model's ``+la`` is its guide's empty trips
(``lookahead="guide"``, on every size) instead of the verified lookahead. A guided model's ``+la`` run acts out
the plan its plain run searched (the same plan both ways), so its seconds leave out the plan search (within the
1 s budget). ``--guide-restarts N --guide-budget S
--[no-]guide-rules --guide-tabu S --guide-exact S`` set a guided model's plan search
(:class:`fms_dispatch.rl.guide.PlanEffort`; default: the solver's ``DEFAULT_EFFORT``) and label its columns
``SPEC~rN[-rules]-tT-xS`` (T: seconds of tabu search per operation, S: seconds of CP-SAT polish). A model
that does not fit a shop (padding) is skipped there and the count says so.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from fms_dispatch.cli import add_guide_args, guide_effort_from_args
from fms_dispatch.full_rules import FullRulePolicy, run_full
from fms_dispatch.rl import ppo_solver
from fms_dispatch.rl.models import load_agent
from fms_dispatch.rules import JOB_RULES
from fms_dispatch.solvers import solve
from fms_sim.shopsets import heldout_shops

from checks import at_least_zero, checked, output_file, positive, write_json


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _has_guide(spec: str, inst) -> bool:
    """Whether the model a PPO spec uses on ``inst`` reads a plan guide."""
    from fms_dispatch.rl.models import default_model_name, resolve_model

    name = spec.split(":", 1)[1] if ":" in spec else default_model_name(inst)
    return resolve_model(name).guide is not None


def label(spec: str, effort) -> str:
    """The column of a model spec run with ``effort`` (None: the solver's default)."""
    if effort is None:
        return spec
    return f"{spec}~r{effort.restarts}" + ("-rules" if effort.rules else "") + f"-t{effort.tabu:g}-x{effort.exact:g}"


def spec_of(label: str) -> str:
    return label.split("~r", 1)[0]


def measure(inst, models: list[str], cpsat_s: float, known: dict | None = None, la_max_jobs: int = 100,
            guide_moves: bool = False, effort=None) -> dict:
    row: dict = {"shop": inst.name, "size": f"{inst.n_jobs}x{inst.n_machines}", "tools": inst.has_tools,
                 "agvs": inst.n_agvs, "tts": inst.n_tool_transporters if inst.has_tools else 0}
    if known:  # the references of an earlier run (--reference): the same CP-SAT figures for every model
        row.update({k: known[k] for k in ("cpsat", "cpsat_s", "list", "rule")})
    else:
        s, dt = _timed(lambda: solve(inst, "cpsat", time_limit=cpsat_s, workers=2))
        row["cpsat"] = checked(inst, s, "cpsat")
        row["cpsat_s"] = round(dt, 2)
        lists = [checked(inst, solve(inst, name), name) for name in ("list", "list:ect")]
        row["list"] = min(lists)
        row["rule"] = min(checked(inst, run_full(inst, FullRulePolicy(j, "nearest", "earliest-start")), j)
                          for j in JOB_RULES)
    for spec in models:
        solver = ppo_solver(spec)
        guided = _has_guide(spec, inst)
        kw = {"guide_effort": effort} if guided and effort is not None else {}
        for la in (False, True):
            key = label(spec, effort) + ("+la" if la else "")
            mode: bool | str = ("fast" if inst.n_jobs >= 50 else True) if la else False
            if la and guide_moves and guided:  # the guide's empty trips: cheap on any size
                mode = "guide"
            elif la and inst.n_jobs > la_max_jobs:
                row[key] = None
                row[key + "_why"] = f"lookahead not run above {la_max_jobs} jobs (--lookahead-max-jobs)"
                continue
            try:
                s, dt = _timed(lambda: solver(inst, lookahead=mode, **kw))
            except ValueError as exc:  # larger than the model's padding
                row[key] = None
                row[key + "_why"] = str(exc)
                continue
            row[key] = checked(inst, s, key)
            row[key + "_s"] = round(dt, 2)
            row[key + "_model"] = s.meta.get("model")
    return row


def summary(rows: list[dict], models: list[str]) -> list[str]:
    keys = ["list", "rule"] + [m + suf for m in models for suf in ("", "+la")]
    out = [f"{len(rows)} held-out shops; mean gap to CP-SAT ({rows[0]['cpsat_s'] if rows else '?'} s first):"]
    for k in keys:
        got = [r for r in rows if r.get(k) is not None]
        if not got:
            continue
        gap = statistics.mean(100 * (r[k] / r["cpsat"] - 1) for r in got)
        line = f"  {k:24s} {gap:+7.2f} %  ({len(got)} shops"
        if k not in ("list", "rule"):
            line += f", <= list on {sum(r[k] <= r['list'] for r in got)}, mean {statistics.mean(r[k] for r in got):.1f}"
            line += f" vs list {statistics.mean(r['list'] for r in got):.1f}"
        out.append(line + ")")
    return out


def write_metrics(rows: list[dict], models: list[str], command: str, effort=None) -> None:
    """Store, per model folder, its held-out figures (per shop and means) in its ``metrics.json``; a guided
    model's entry says how its plan was searched (``guide_effort``)."""
    from fms_dispatch.rl.guide import DEFAULT_EFFORT
    from fms_dispatch.rl.models import resolve_model

    folders: dict[Path, dict] = {}
    for lab in models:
        spec = spec_of(lab)
        if spec.endswith(".zip"):  # other weights of a folder (e.g. warm_start.zip): not the folder's model
            continue
        for suffix in ("", "+la"):
            key = lab + suffix
            for r in rows:
                name = r.get(key + "_model")
                if r.get(key) is None or not name:
                    continue
                ref = resolve_model(name if spec == "ppo" else spec.split(":", 1)[1])
                entry = folders.setdefault(ref.folder, {"command": command, "date": time.strftime("%Y-%m-%d"),
                                                        "shops": {}})
                if ref.guide is not None:
                    entry["guide_effort"] = (effort or DEFAULT_EFFORT).as_dict()
                shop = entry["shops"].setdefault(r["shop"], {"cpsat": r["cpsat"], "list": r["list"],
                                                             "rule": r["rule"]})
                shop["ppo+lookahead" if suffix else "ppo"] = r[key]
    for folder, entry in folders.items():
        shops = entry["shops"].values()
        for k in ("ppo", "ppo+lookahead", "list", "rule"):
            got = [s for s in shops if k in s]
            if got:
                entry[f"mean_gap_to_cpsat_{k}"] = round(statistics.mean(100 * (s[k] / s["cpsat"] - 1) for s in got), 2)
        entry["ppo_at_most_list"] = sum(s["ppo"] <= s["list"] for s in shops if "ppo" in s)
        path = folder / "metrics.json"
        metrics = json.loads(path.read_text()) if path.exists() else {}  # (a missing one was an error at the end)
        metrics["heldout"] = entry
        write_json(path, metrics)
        print(f"held-out figures of {len(entry['shops'])} shops written to {path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="*", default=["ppo"], help="PPO solver specs (ppo, ppo:NAME, ppo:FOLDER)")
    ap.add_argument("--cpsat", type=float, help="CP-SAT seconds per shop (reference; default 10, or the --reference "
                                                "file's, whose shops keep their figures)")
    ap.add_argument("--limit", type=positive, help="only the first N shops")
    ap.add_argument("--lookahead-max-jobs", type=at_least_zero, default=100,
                    help="run the lookahead only on shops with at most this many jobs (it takes minutes on 100)")
    ap.add_argument("--lookahead-guide", action="store_true",
                    help="'+la' of a guided model is its guide's empty trips (lookahead='guide', every size)")
    add_guide_args(ap, replan=False)
    ap.add_argument("--only", nargs="*", help="only these shops (ho names)")
    ap.add_argument("--json", type=output_file, help="write the rows and the summary here")
    ap.add_argument("--write-metrics", action="store_true",
                    help="store each model's held-out figures under 'heldout' in its metrics.json")
    ap.add_argument("--reference", help="a JSON file of an earlier run: reuse its CP-SAT, list and rule figures "
                                        "(and rows of models measured there)")
    a = ap.parse_args(argv)
    if a.write_metrics and (a.only or a.limit):  # the record is the whole set's: a part of it would replace it
        ap.error("--write-metrics records the whole held-out set; it cannot be combined with --only or --limit")
    shops = heldout_shops()
    if a.only:
        unknown = sorted(set(a.only) - {s.name for s in shops})
        if unknown:
            ap.error(f"--only: no held-out shop {unknown[0]!r} (ho00..ho49)")
        shops = [s for s in shops if s.name in set(a.only)]
    shops = shops[:a.limit] if a.limit else shops
    ref = json.loads(Path(a.reference).read_text()) if a.reference else {}
    earlier = {r["shop"]: r for r in ref.get("rows", [])}
    if a.reference:  # one CP-SAT limit per table: the reference's figures are of its own limit
        if a.cpsat is not None and a.cpsat != ref.get("cpsat_seconds"):
            ap.error(f"--cpsat {a.cpsat:g}: the reference {a.reference} holds CP-SAT figures of "
                     f"{ref.get('cpsat_seconds')} s; its shops and the others must share one limit")
        a.cpsat = ref.get("cpsat_seconds", 10.0)
    elif a.cpsat is None:
        a.cpsat = 10.0
    effort = guide_effort_from_args(a)
    for spec in a.models:  # an unknown model stops the bench now, not after the first shop's CP-SAT run
        ppo_solver(spec)
        if ":" in spec:
            load_agent(spec.split(":", 1)[1].strip())
    rows = []
    t0 = time.perf_counter()
    for inst in shops:
        row = measure(inst, a.models, a.cpsat, earlier.get(inst.name), a.lookahead_max_jobs, a.lookahead_guide,
                      effort)
        for k, v in earlier.get(inst.name, {}).items():  # keep the earlier run's model figures too
            row.setdefault(k, v)
        rows.append(row)
        cols = " ".join(f"{k}={row[k]}" for k in row if k in ("cpsat", "list", "rule") or
                        (k.startswith("ppo") and not k.endswith(("_s", "_why", "_model"))))
        print(f"{inst.name} {row['size']}{' tools' if row['tools'] else ''}: {cols}", file=sys.stderr, flush=True)
    models = [label(m, effort) for m in a.models]
    models += [m for m in ref.get("models", []) if m not in models]
    lines = summary(rows, models)
    print("\n".join(lines))
    print(f"({time.perf_counter() - t0:.0f} s)")
    if a.json:  # (before the metrics: a failure there lost the rows)
        write_json(a.json, {"cpsat_seconds": a.cpsat, "models": models, "rows": rows, "summary": lines})
    if a.write_metrics:
        write_metrics(rows, models, " ".join(["python", "bench/heldout.py"] + (argv or sys.argv[1:])), effort)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
