"""The plan's assignments in a guided model's run (``Agent.plan_assigns``): the same decisions, at what speed.

Where a guided model's only choice is an assignment (which vehicle carries a part or tool, which pending request
a tool serves next) and its plan names a legal answer, ``Agent.act`` takes that answer without computing the
observation and running the network. This bench runs each shop twice with the same plan, once with the network
answering every choice and once with the plan's assignments, and checks that both make the same decisions (the
same schedule, operation by operation) at each of the assignments: it counts the assignments where the network
would have chosen otherwise (it asks the network at each of them) and reports both runs' times (best of
``--repeat``). Plans: the plain list schedule (reproducible); runs nominal and, with ``--noise``, in one seeded
scenario of noisy durations per shop (the run's re-planner on, as ``fms solve`` runs it). Every schedule is
validated.

``--record`` (with ``--model NAME``) writes the check into the model's card (``metrics.json``, key
``plan_assignments``: the assignments, those where the network chose otherwise, the shops, the command): a model
whose card records assignments and none chosen otherwise takes them in its runs without running its network
(``fms_dispatch.rl.models.checked_assignments``).

Usage: python bench/plan_assignments.py [--shops SPEC ...] [--model ppo] [--noise 0.2] [--repeat 2] [--json PATH]
                                        [--record]
(``--shops``: names or generator specs, as ``fms train --shops``; default: the validation shops of
docs/benchmarks.md §9.)
"""

from __future__ import annotations

import argparse
import platform
import time
from typing import Any

from checks import checked, finite, output_file, positive, report

#: the shops the default model was checked on (generated, never used for training or reported elsewhere)
VALIDATION = ["gen:10x5x5*3@216", "gen:20x10x10*2@216", "gen:10x5x5*3@219/notools", "genbu:**3@31",
              "gen:50x10x10*1@216", "gen:100x20x20*1@216", "gen:60x15x15*1@219/notools"]


def _shops(specs: list[str]) -> list[Any]:
    """The shops of ``specs`` (:func:`fms_sim.shopsets.expand_specs`); a built-in name or file ending in
    ``/notools`` without its tools (``fms solve --no-tools``)."""
    from fms_sim.formats import load_instance
    from fms_sim.shopsets import expand_specs

    out = []
    for spec in specs:
        base = spec.removesuffix("/notools")
        if base != spec and not base.startswith(("gen:", "genbu:")):
            out.append(load_instance(base, no_tools=True))
        else:
            out += expand_specs([spec])
    return out


def _scenario(inst: Any, noise: float) -> Any:
    import numpy as np

    from fms_sim.env import episode_scenario

    return episode_scenario(inst, {"noise": noise}, np.random.default_rng(7)) if noise else None


def _start(agent: Any, inst: Any, scenario: Any, assign: bool) -> tuple[Any, Any]:
    """A fresh run's shop, planned, and what chooses in it (the re-planner in a disrupted run, as ``fms solve``)."""
    from fms_sim.full_shop import make_shop
    from fms_dispatch.rl.agent import GuideReplanner

    agent.forget()
    agent.plan_assigns = assign
    shop = make_shop(inst, agent.decisions, scenario)
    agent.guide_of(shop)
    return shop, (GuideReplanner(agent) if scenario is not None else agent.act)


def run_once(agent: Any, inst: Any, scenario: Any, assign: bool) -> tuple[Any, float, int]:
    """One timed run with the plain list schedule's plan: (schedule, seconds, the plan's assignments taken)."""
    shop, choose = _start(agent, inst, scenario, assign)
    n0 = agent.assigned
    t0 = time.perf_counter()
    while not shop.done:
        shop.act(choose(shop))
    return shop.schedule(), time.perf_counter() - t0, agent.assigned - n0


def disagreements(agent: Any, inst: Any, scenario: Any) -> tuple[Any, int, int]:
    """A run with the plan's assignments that also asks the network at each of them (after the choice, in the
    same state and with the same plan): (schedule, assignments, those where the network's arg-max is another
    action)."""
    import numpy as np

    shop, choose = _start(agent, inst, scenario, True)
    n, other = 0, 0
    while not shop.done:
        before = agent.assigned
        a = choose(shop)
        if agent.assigned > before:
            n += 1
            logits, _ = agent.logits(shop)
            other += agent._env(shop).to_net_action(int(np.argmax(logits))) != a
        shop.act(a)
    return shop.schedule(), n, other


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shops", nargs="+", default=VALIDATION)
    ap.add_argument("--model", default="ppo", help="ppo (the default model of each shop) or a model's name")
    ap.add_argument("--noise", type=finite, default=0.2, help="the disrupted runs' noise (0: nominal runs only)")
    ap.add_argument("--repeat", type=positive, default=2)
    ap.add_argument("--json", type=output_file)
    ap.add_argument("--record", action="store_true", help="write the check into --model's metrics.json")
    a = ap.parse_args()
    from fms_dispatch.rl.guide import PlanEffort
    from fms_dispatch.rl.models import default_model_name, load_agent

    rows = []
    lines = [f"{platform.node()} {time.strftime('%Y-%m-%d')}, {a.model}, list-schedule plans, best of {a.repeat}"]
    if a.noise < 0:
        raise SystemExit("--noise must be >= 0")
    if a.record and a.model == "ppo":
        raise SystemExit("--record needs --model NAME (the model whose card records the check)")
    for inst in _shops(a.shops):
        agent = load_agent(default_model_name(inst) if a.model == "ppo" else a.model)
        if agent.guide is None:
            raise SystemExit(f"model {agent.name} reads no plan guide: it makes no plan assignments")
        agent.use_guide_effort(PlanEffort())
        for noise in sorted({0.0, a.noise}):
            sc = _scenario(inst, noise)
            what = f"ppo:{agent.name} on {inst.name}"
            ref, asked, other = disagreements(agent, inst, sc)
            times: dict[bool, list[float]] = {False: [], True: []}
            spans: dict[bool, Any] = {}
            for _ in range(a.repeat):
                for assign in (False, True):
                    sched, sec, _ = run_once(agent, inst, sc, assign)
                    checked(inst, sched, what, sc)
                    times[assign].append(sec)
                    spans[assign] = sched
            same = spans[False].operations == spans[True].operations == ref.operations
            row = {"shop": inst.name, "noise": noise, "assignments": asked, "network_otherwise": other,
                   "same_schedule": same, "makespan": spans[True].makespan,
                   "seconds_network": round(min(times[False]), 4), "seconds_assigned": round(min(times[True]), 4)}
            rows.append(row)
            print(f"{inst.name} noise {noise}: {asked} assignments, network otherwise at {other}, "
                  f"{'same schedule' if same else 'OTHER SCHEDULE'} ({row['makespan']}), "
                  f"{row['seconds_network']:.3f} s -> {row['seconds_assigned']:.3f} s", flush=True)
    total = sum(r["assignments"] for r in rows)
    lines.append(f"{len(rows)} runs: {total} assignments, the network otherwise at "
                 f"{sum(r['network_otherwise'] for r in rows)}; the same schedule in "
                 f"{sum(r['same_schedule'] for r in rows)} of {len(rows)}; run time "
                 f"{sum(r['seconds_network'] for r in rows):.2f} s -> {sum(r['seconds_assigned'] for r in rows):.2f} s")
    report(lines, rows, a.json)
    if a.record:
        record(a, rows)


def _without_output(args: list[str]) -> list[str]:
    """The command's arguments but ``--json PATH`` (where this run wrote its rows: a path of this machine)."""
    out, skip = [], False
    for x in args:
        if skip:
            skip = False
        elif x == "--json":
            skip = True
        elif not x.startswith("--json="):
            out.append(x)
    return out


def record(a: argparse.Namespace, rows: list[dict]) -> None:
    """Write the check into ``--model``'s card (``metrics.json``), replacing an earlier one."""
    import json
    import sys

    from fms_sim.files import write_atomically
    from fms_dispatch.rl.models import ASSIGNMENTS_KEY, METRICS_FILE, _solving_weights_name, resolve_model

    ref = resolve_model(a.model)
    if ref.weights.name != _solving_weights_name(ref.folder):  # the card speaks of the folder's solving weights
        raise SystemExit(f"--record: {ref.weights} are not the weights {ref.folder} solves with "
                         f"({_solving_weights_name(ref.folder)}); check the folder itself (--model {ref.folder})")
    path = ref.folder / METRICS_FILE
    metrics = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
    metrics[ASSIGNMENTS_KEY] = {
        "assignments": sum(r["assignments"] for r in rows),
        "network_otherwise": sum(r["network_otherwise"] for r in rows)
        + sum(not r["same_schedule"] for r in rows),  # (another schedule: a decision differed somewhere)
        "runs": len(rows), "shops": a.shops, "noise": a.noise, "date": time.strftime("%Y-%m-%d"),
        "command": "python bench/plan_assignments.py " + " ".join(_without_output(sys.argv[1:]))}
    write_atomically(path, json.dumps(metrics, indent=2, ensure_ascii=False) + "\n")
    print(f"recorded in {path}: {metrics[ASSIGNMENTS_KEY]['assignments']} assignments, the network otherwise at "
          f"{metrics[ASSIGNMENTS_KEY]['network_otherwise']}")


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
