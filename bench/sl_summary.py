"""Per-size-group summary of a large-benchmark run (``fms bench sl ... --results-dir DIR``).

``python bench/sl_summary.py results/sl_full/bench_sl.json`` prints, per mode (AGVs only, AGVs + tools), one
Markdown table with a row per size group (group g = sl{g}0..sl{g}9, only the instances present in the run):

* the mean CP-SAT lower bound (the best bound any method reported for the instance, i.e. CP-SAT's);
* the mean makespan of CP-SAT, of PPO, of the best single rule pair of the group (the pair with the lowest
  mean over the group's instances, named) and of the per-instance best rule pair;
* the gaps of PPO and of the best single pair to the bound, ``(x - bound) / bound`` of the means;
* whether PPO's mean is below the best single pair's (the RL issue's target: "better on average than the best
  rule pair of the baselines in every size group");

followed by PPO's wall time on the largest group present (target <= 5 s per instance on sl70..sl79).
Instances where a method failed or has no valid schedule are left out of that method's mean and counted; the gaps
and the verdict compare means over the instances where the bound, PPO and the best pair are all present (the
verdict says over how many where that is not every instance).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from collections import defaultdict
from pathlib import Path

from checks import limits_label

MODES = (("agvs", "AGVs only"), ("agvs+tools", "AGVs + tools"))


def _group(instance: str) -> int:
    return int(instance[2:]) // 10


def _mean(xs):
    return statistics.fmean(xs) if xs else float("nan")


def _num(x: float) -> str:
    """A mean for a table cell; a dash where nothing was measured (every run of the kind missing)."""
    return "—" if math.isnan(x) else f"{x:.1f}"


def _gap(x: float, bound: float) -> str:
    return "—" if math.isnan(x) or math.isnan(bound) else f"{100.0 * (x - bound) / bound:+.1f} %"


def summarize(rows: list[dict], variant: str) -> tuple[list[str], dict]:
    """Markdown lines of one mode's table and the raw figures per group (the CP-SAT column titled with the limits
    of its runs)."""
    by_inst: dict[str, dict[str, dict]] = defaultdict(dict)
    for r in rows:
        if r["variant"] == variant:
            by_inst[r["instance"]][r["method"]] = r
    groups: dict[int, list[str]] = defaultdict(list)
    for inst in sorted(by_inst):
        groups[_group(inst)].append(inst)

    def ok(r):
        return r is not None and r.get("valid") and r.get("makespan") is not None

    lines = [
        f"| group | instances | CP-SAT bound | CP-SAT ({limits_label([r for r in rows if r['variant'] == variant])}) | PPO (shipped) | best single rule pair | "
        "per-instance best pair | PPO gap to bound | best pair gap to bound | PPO < best pair (mean)? | "
        "instances PPO < best pair |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    figures = {}
    for g in sorted(groups):
        insts = groups[g]
        bounds, cps, ppos, best_inst = [], [], [], []
        bound_of: dict[str, float] = {}
        missing = defaultdict(int)
        pair_ms: dict[str, list[int]] = defaultdict(list)
        for inst in insts:
            ms = by_inst[inst]
            cp = ms.get("cpsat")
            bound = None
            if ok(cp) and cp.get("lower_bound") is not None:
                bound = cp["lower_bound"]
            else:
                bound = next((r.get("reference") for r in ms.values() if r.get("reference") is not None), None)
            if bound is None:
                missing["bound"] += 1
            else:
                bounds.append(bound)
                bound_of[inst] = bound
            if ok(cp):
                cps.append(cp["makespan"])
            else:
                missing["cpsat"] += 1
            pp = ms.get("ppo")
            if ok(pp):
                ppos.append(pp["makespan"])
            else:
                missing["ppo"] += 1
            rule_ms = {m: r["makespan"] for m, r in ms.items() if m.startswith("rule:") and ok(r)}
            for m, v in rule_ms.items():
                pair_ms[m].append(v)
            if rule_ms:
                best_inst.append(min(rule_ms.values()))
        # best single pair: lowest mean over the group's instances, among pairs valid on all of them
        complete = {m: v for m, v in pair_ms.items() if len(v) == len(insts)}
        best_pair = min(complete, key=lambda m: (_mean(complete[m]), m)) if complete else None
        bp_mean = _mean(complete[best_pair]) if best_pair else float("nan")
        ties = sum(1 for m in complete if m != best_pair and _mean(complete[m]) == bp_mean)
        # instances where PPO beats the best single pair (same instance order: rows follow ``insts``)
        wins = sum(1 for inst in insts if ok(by_inst[inst].get("ppo")) and best_pair
                   and ok(by_inst[inst].get(best_pair))
                   and by_inst[inst]["ppo"]["makespan"] < by_inst[inst][best_pair]["makespan"])
        b, c, p, bi = _mean(bounds), _mean(cps), _mean(ppos), _mean(best_inst)
        # the gaps and the verdict compare means over one set: the instances where the bound, PPO and the best pair
        # are all present (normally all; means over different sets compared a failed large instance's absence)
        common = [i for i in insts if i in bound_of and ok(by_inst[i].get("ppo")) and best_pair is not None]
        cb = _mean([bound_of[i] for i in common])
        cp_ = _mean([by_inst[i]["ppo"]["makespan"] for i in common])
        cbp = _mean([by_inst[i][best_pair]["makespan"] for i in common]) if best_pair else float("nan")
        verdict = "—" if not common else "yes" if cp_ < cbp else "no"
        if common and len(common) < len(insts):
            verdict += f", over {len(common)}"
        figures[g] = {"n": len(insts), "bound": b, "cpsat": c, "ppo": p, "best_pair": best_pair,
                      "best_pair_mean": bp_mean, "best_per_instance": bi, "ppo_better": bool(common) and cp_ < cbp,
                      "compared": len(common), "ppo_wins": wins, "ties": ties, "missing": dict(missing)}
        first, last = insts[0], insts[-1]
        tie = f", {ties + 1} tied" if ties else ""
        note = "" if not missing else " (" + ", ".join(f"{k} missing on {v}" for k, v in missing.items()) + ")"
        lines.append(
            f"| {g} ({first}–{last}) | {len(insts)}{note} | {_num(b)} | {_num(c)} | {_num(p)} | "
            f"{best_pair.removeprefix('rule:') if best_pair else '—'} ({_num(bp_mean)}{tie}) | {_num(bi)} | "
            f"{_gap(cp_, cb)} | {_gap(cbp, cb)} | {verdict} ({_gap(cp_, cbp)}) | "
            f"{wins}/{len(insts)} |")
    return lines, figures


def ppo_times(rows: list[dict]) -> list[str]:
    groups = sorted({_group(r["instance"]) for r in rows})
    if not groups:
        return []
    g = groups[-1]
    lines = [f"PPO wall time per instance on group {g} (sl{g}0–sl{g}9; target ≤ 5 s on sl70–sl79):", "",
             "| mode | instances | mean | max |", "|---|---|---|---|"]
    for variant, label in MODES:
        ts = [r["wall_time"] for r in rows if r["method"] == "ppo" and r["variant"] == variant
              and _group(r["instance"]) == g and r.get("valid") and r.get("wall_time") is not None]
        if ts:
            lines.append(f"| {label} | {len(ts)} | {_mean(ts):.2f} s | {max(ts):.2f} s |")
    return lines if len(lines) > 4 else []  # no timed PPO run: no table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("json", nargs="?", default="results/sl_full/bench_sl.json", type=Path)
    args = ap.parse_args(argv)
    try:
        data = json.loads(args.json.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{args.json} is not JSON: {exc}") from None
    rows = data.get("rows") if isinstance(data, dict) else None
    if not isinstance(rows, list) or not all(isinstance(r, dict) and {"variant", "method"} <= set(r) for r in rows):
        raise ValueError(f"{args.json} is not the output of fms bench sl (a 'rows' list of variant/method rows)")
    total_ok = {}
    for variant, label in MODES:
        if not any(r["variant"] == variant for r in rows):
            continue
        lines, figs = summarize(rows, variant)
        total_ok[label] = sum(f["ppo_better"] for f in figs.values()), len(figs)
        print(f"**{label}** (means over each group's instances)\n")
        print("\n".join(lines))
        print()
    for label, (k, n) in total_ok.items():
        print(f"- {label}: PPO better than the best single rule pair in {k} of {n} groups.")
    print()
    print("\n".join(ppo_times(rows)))
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
