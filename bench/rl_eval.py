"""Measure the shipped PPO models against the dispatching rules (targets of the RL issue, not timed tests).

* ``python bench/rl_eval.py bu [--model bu]`` — BU layout 2 (EX12..EX102, 2 AGVs): PPO makespan with and
  without lookahead, seconds per instance, the best of the 24 rule pairs per instance, the optimum.
  Targets: average <= 99 with lookahead, every instance <= best rule pair, <= 0.1 s per instance.
* ``python bench/rl_eval.py sl [--model large] [--no-tools] [--per-group N] [--groups G ...] [--rules-cache F]
  [--rules-only]`` — the large benchmark (10 AGVs,
  5 transporters): per size group the PPO mean (and with ``--lookahead`` the lookahead mean), the mean of the
  best single rule pair of the group, and the mean of the per-instance best pair (over the 36 pairs of the
  baselines: 12 job rules x first / least-work / nearest). Target: PPO better than the best rule pair in every
  group; sl70 (100x20x20) in <= 5 s. ``--lookahead-fast`` runs the lookahead without retries of rejected
  moves instead (``retry=False`` of ``LookaheadPlanner``; several times faster on 50-100 jobs). ``--jobs N``
  measures N instances at once (a line per instance goes to stderr as it finishes). ``--vehicles RULE`` also runs a probe: the model's job choices with the
  vehicle rule's AGV and transporter choices (which half of the policy is weaker).

Every schedule is validated. ``--json FILE`` writes the results; ``--write-metrics`` stores them under
``"benchmark"`` in the model's ``metrics.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from fms_dispatch.rl.lookahead import run_agent
from fms_dispatch.rl.models import load_agent, resolve_model
from fms_dispatch.rules import all_rule_pairs, parse_rule_name
from fms_sim.benchmarks import BU_OPTIMAL_MAKESPAN, SL_GROUPS, builtin
from fms_sim.full_shop import make_shop
from fms_sim.shop import Shop, run_policy
from fms_sim.validate import validate

from checks import checked, output_file, positive, write_json


CPU: dict[str, float] = {}  # CPU seconds of the last run_ppo call (wall time suffers on a shared machine)


def with_vehicle_rule(agent, rule: str):
    """A policy that takes the model's job choices and ``rule``'s vehicle choices (a diagnostic probe)."""
    vehicles = parse_rule_name(f"FIFO+{rule}")

    def choose(shop: Shop) -> int:
        legal = shop.legal_actions()
        return vehicles(shop) if any(a >= shop.n_jobs for a in legal) else agent.act(shop)

    return choose


def run_ppo(agent, inst, lookahead: bool | str, vehicles: str | None = None) -> tuple[int, float]:
    """Makespan and seconds of PPO on ``inst``; ``lookahead``: False, True or "fast" (no retries)."""
    t0, c0 = time.perf_counter(), time.process_time()
    choose = agent.act if vehicles is None else with_vehicle_rule(agent, vehicles)
    s = run_agent(make_shop(inst, agent.decisions), choose, lookahead=bool(lookahead), retry=lookahead != "fast")
    dt = time.perf_counter() - t0
    CPU["last"] = time.process_time() - c0
    problems = validate(inst, s)
    if problems:
        raise SystemExit(f"INFEASIBLE {inst.name} (lookahead={lookahead}): {problems[0]}")
    return s.makespan, dt


RULE_CACHE: dict[str, dict[str, int]] = {}  # instance key -> rule pair -> makespan (see --rules-cache)


def _key(inst) -> str:
    return f"{inst.name}|tools={inst.has_tools}|agvs={inst.n_agvs}|tts={inst.n_tool_transporters}"


def rule_makespans(inst, include_nearest: bool = False) -> dict[str, int]:
    """Makespan of every rule pair: the paper's 24, or all 36 with ``include_nearest`` (cached)."""
    key = _key(inst) + ("|36" if include_nearest else "")
    if key in RULE_CACHE:
        return RULE_CACHE[key]
    out = {name: checked(inst, run_policy(inst, parse_rule_name(name)), name)
           for name in all_rule_pairs(include_nearest)}
    RULE_CACHE[key] = out
    return out


def bench_bu(model: str) -> dict:
    agent = load_agent(model)
    rows = []
    for s in range(1, 11):
        inst = builtin(f"EX{s}2")
        plain, t_plain = run_ppo(agent, inst, False)
        c_plain = CPU["last"]
        look, t_look = run_ppo(agent, inst, True)
        c_look = CPU["last"]
        rules = rule_makespans(inst)
        best = min(rules.values())
        rows.append(dict(instance=inst.name, ppo=plain, ppo_lookahead=look, best_rule=best,
                         optimum=BU_OPTIMAL_MAKESPAN[(s, 2)], seconds=round(t_plain, 4),
                         seconds_lookahead=round(t_look, 4), cpu_seconds=round(c_plain, 4),
                         cpu_seconds_lookahead=round(c_look, 4)))
        print(f"{inst.name:6s} ppo {plain:4d}  +lookahead {look:4d}  best rule {best:4d}  opt "
              f"{BU_OPTIMAL_MAKESPAN[(s, 2)]:4d}  {t_plain:.3f} s / {t_look:.3f} s wall, "
              f"{c_plain:.3f} / {c_look:.3f} s CPU", flush=True)
    summary = dict(
        mean_ppo=statistics.mean(r["ppo"] for r in rows),
        mean_ppo_lookahead=statistics.mean(r["ppo_lookahead"] for r in rows),
        mean_best_rule=statistics.mean(r["best_rule"] for r in rows),
        mean_optimum=statistics.mean(r["optimum"] for r in rows),
        max_seconds=max(r["seconds"] for r in rows),
        max_seconds_lookahead=max(r["seconds_lookahead"] for r in rows),
        max_cpu_seconds=max(r["cpu_seconds"] for r in rows),
        max_cpu_seconds_lookahead=max(r["cpu_seconds_lookahead"] for r in rows),
        instances_at_or_below_best_rule=sum(r["ppo_lookahead"] <= r["best_rule"] for r in rows),
        instances_at_or_below_best_rule_plain=sum(r["ppo"] <= r["best_rule"] for r in rows),
    )
    print(json.dumps(summary, indent=1))
    return {"set": "BU layout 2 (EX12-EX102)", "rows": rows, "summary": summary}


def instance_result(model: str, inst, lookahead: bool | str, vehicles: str | None) -> dict:
    """Everything ``bench_sl`` measures on one instance (a top-level function, so a process pool can run it)."""
    agent = load_agent(model)  # load_agent caches the agent per weights file, so once per process
    t0 = time.perf_counter()
    m, dt = run_ppo(agent, inst, False)
    out = dict(ppo=m, seconds=dt, cpu=CPU["last"])
    if lookahead:
        out["lookahead"] = run_ppo(agent, inst, lookahead)[0]
    if vehicles:
        out["probe"] = run_ppo(agent, inst, False, vehicles)[0]
    out["rules"] = rule_makespans(inst, include_nearest=True)
    out["total_seconds"] = time.perf_counter() - t0
    return out


def bench_sl(model: str, no_tools: bool, per_group: int, lookahead: bool | str, groups: list[int],
             vehicles: str | None = None, jobs: int = 1) -> dict:
    out_groups = []
    pool = None
    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(jobs)
    for g in groups:
        insts = []
        for k in range(per_group):
            inst = builtin(f"sl{g}{k}")
            insts.append(inst.without_tools() if no_tools else inst)
        ppo, secs, cpus, look, rules, probe = [], [], [], [], [], []
        args = [(model, inst, lookahead, vehicles) for inst in insts]
        results = pool.map(instance_result, *zip(*args)) if pool else (instance_result(*x) for x in args)
        for n, (inst, r) in enumerate(zip(insts, results)):
            RULE_CACHE[_key(inst) + "|36"] = r["rules"]  # workers' caches do not come back by themselves
            ppo.append(r["ppo"])
            secs.append(r["seconds"])
            cpus.append(r["cpu"])
            if lookahead:
                look.append(r["lookahead"])
            if vehicles:
                probe.append(r["probe"])
            rules.append(r["rules"])
            la = f", lookahead {r['lookahead']}" if lookahead else ""
            print(f"  {inst.name} ({n + 1}/{len(insts)}): ppo {r['ppo']}{la}, best pair "
                  f"{min(r['rules'].values())} ({r['total_seconds']:.0f} s)", file=sys.stderr, flush=True)
        pair_means = {p: statistics.mean(r[p] for r in rules) for p in rules[0]}
        best_pair = min(pair_means, key=pair_means.get)
        row = dict(group=g, size="x".join(map(str, SL_GROUPS[g])), instances=[i.name for i in insts],
                   ppo=ppo, mean_ppo=statistics.mean(ppo), best_pair=best_pair,
                   mean_best_pair=pair_means[best_pair],
                   mean_instance_best=statistics.mean(min(r.values()) for r in rules),
                   max_seconds=round(max(secs), 3), max_cpu_seconds=round(max(cpus), 3))
        if lookahead:
            row["lookahead_mode"] = "fast" if lookahead == "fast" else "full"
            row["ppo_lookahead"] = look
            row["mean_ppo_lookahead"] = statistics.mean(look)
        if vehicles:
            row[f"ppo_jobs_{vehicles}_vehicles"] = probe
            row[f"mean_ppo_jobs_{vehicles}_vehicles"] = statistics.mean(probe)
        out_groups.append(row)
        la = f"  +lookahead {row['mean_ppo_lookahead']:.1f}" if lookahead else ""
        if vehicles:
            la += f"  (jobs ppo, vehicles {vehicles}: {row[f'mean_ppo_jobs_{vehicles}_vehicles']:.1f})"
        print(f"group {g} ({row['size']}): ppo {row['mean_ppo']:.1f}{la}  best pair {best_pair} "
              f"{row['mean_best_pair']:.1f}  per-instance best {row['mean_instance_best']:.1f}  "
              f"max {row['max_seconds']:.2f} s wall / {row['max_cpu_seconds']:.2f} s CPU", flush=True)
    if pool is not None:
        pool.shutdown()
    return {"set": f"large benchmark ({'AGVs only' if no_tools else 'AGVs + tools'}), {per_group} per group",
            "groups": out_groups}


def parse_groups(text: str) -> list[int]:
    """An argparse type: sl size groups as ``LO-HI`` or ``G,G,...``, each 0..7 (``3-1`` ran nothing and exited 0;
    a negative group was int()'s message)."""
    try:
        if "-" in text and "," not in text:
            lo, hi = (int(x) for x in text.split("-"))
            groups = list(range(lo, hi + 1))
        else:
            groups = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO-HI or G,G,... (groups 0..7), got {text!r}") from None
    if not groups or not all(0 <= g <= 7 for g in groups):
        raise argparse.ArgumentTypeError(f"groups are 0..7 (LO <= HI), got {text!r}")
    return groups


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("which", choices=("bu", "sl"))
    ap.add_argument("--model", help="model name/folder (default: bu for bu, large / large-agv for sl)")
    ap.add_argument("--no-tools", action="store_true", help="sl without tools (AGV-only)")
    ap.add_argument("--per-group", type=positive, default=10, help="sl instances per group (1-10)")
    ap.add_argument("--groups", type=parse_groups, default="0-7", help="sl groups, e.g. 0-7 or 0,3,7")
    ap.add_argument("--lookahead", action="store_true", help="sl: also run with lookahead")
    ap.add_argument("--lookahead-fast", action="store_true",
                    help="sl: also run with the fast lookahead (no retries of rejected moves)")
    ap.add_argument("--vehicles", choices=("first", "least-work", "nearest"),
                    help="sl: also run the model's job choices with this rule's vehicle choices (probe)")
    ap.add_argument("--jobs", type=positive, default=1,
                    help="sl: instances measured at once in separate processes (default 1; the seconds columns "
                         "are then measured on a busier machine)")
    ap.add_argument("--json", type=output_file, help="write the results here")
    ap.add_argument("--rules-cache", type=output_file, help="JSON file caching the rule pairs' makespans (read and updated)")
    ap.add_argument("--rules-only", action="store_true", help="sl: only compute (and cache) the rule pairs")
    ap.add_argument("--write-metrics", action="store_true", help="store results in the model's metrics.json")
    a = ap.parse_args()
    if a.per_group > 10:  # (it ran the rules for seconds, then asked for sl010)
        ap.error("--per-group: a group has 10 instances")
    if a.rules_cache and Path(a.rules_cache).is_file():
        try:
            cached = json.loads(Path(a.rules_cache).read_text())
        except (OSError, ValueError) as exc:
            ap.error(f"--rules-cache {a.rules_cache}: not a cache this script wrote ({exc})")
        if not isinstance(cached, dict) or not all(isinstance(v, dict) for v in cached.values()):
            ap.error(f"--rules-cache {a.rules_cache}: not a cache this script wrote (expected an object of "
                     "instance -> rule pair -> makespan)")
        RULE_CACHE.update(cached)
    try:
        run(a)
    finally:
        if a.rules_cache:
            write_json(a.rules_cache, RULE_CACHE, indent=None)


def run(a: argparse.Namespace) -> None:
    if a.rules_only:
        for g in a.groups:
            for k in range(a.per_group):
                inst = builtin(f"sl{g}{k}")
                rule_makespans(inst.without_tools() if a.no_tools else inst, include_nearest=a.which == "sl")
            print(f"rules cached for group {g}", flush=True)
        return
    if a.which == "bu":
        model = a.model or "bu"
        res = bench_bu(model)
        key = "bu_layout2"
    else:
        model = a.model or ("large-agv" if a.no_tools else "large")
        groups = a.groups
        if a.lookahead and a.lookahead_fast:
            raise ValueError("give --lookahead or --lookahead-fast, not both")
        look: bool | str = "fast" if a.lookahead_fast else a.lookahead
        res = bench_sl(model, a.no_tools, a.per_group, look, groups, a.vehicles, a.jobs)
        key = "sl_no_tools" if a.no_tools else "sl"
        sl70 = builtin("sl70").without_tools() if a.no_tools else builtin("sl70")
        m, dt = run_ppo(load_agent(model), sl70, False)
        res["sl70"] = {"makespan": m, "seconds": round(dt, 3), "cpu_seconds": round(CPU["last"], 3)}
        print(f"sl70: makespan {m}, {dt:.2f} s wall, {CPU['last']:.2f} s CPU")
    if a.json:
        write_json(a.json, res, indent=1)
    if a.write_metrics:
        ref = resolve_model(model)
        path = ref.folder / "metrics.json"
        metrics = json.loads(path.read_text()) if path.is_file() else {}
        metrics.setdefault("benchmark", {})[key] = res
        write_json(path, metrics, indent=1)
        print(f"metrics: {path}")


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
