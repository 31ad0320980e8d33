"""How much room PPO has over a model: its deterministic runs against runs sampled from it, on validation shops.

PPO improves a policy only through the runs it samples from it: where no sampled run beats the deterministic
one, the policy gradient has nothing to climb, and where the sampled runs never leave the deterministic one, it
sees no alternative at all. This measures both for a model (default: the guided clone), on generated validation
shops (checked like training specs), nominal or disrupted (noise on every duration, machine breakdowns; the
decider learns a duration only when it ends)::

    python bench/ppo_headroom.py [--model guided] [--shops 'genbu:**1@31' ...] [--samples 10]
                                 [--temperatures 1 4 8] [--noise 0 0.2] [--breakdowns 1] [--seeds 2] [--seed 0]

Per temperature and disruption level: the mean makespan of the deterministic runs (arg-max, as the solver
decides), the mean of the sampled runs (each decision drawn from softmax(logits / temperature); temperature 1
is PPO's own sampling), the mean of the best sampled run per shop and scenario, in how many runs the best
sample beats the deterministic run, and the share of sampled decisions that differ from the arg-max. Guided
models plan with the solver's default effort without a tabu search (``--guide-tabu 0``), so every run of a shop
acts out the same plan. Every schedule is validated.
"""

from __future__ import annotations

import argparse
import math
import statistics

import numpy as np

from fms_dispatch.full_rules import run_full
from fms_dispatch.rl.guide import effort_from
from fms_dispatch.rl.models import load_agent
from fms_dispatch.rl.train import expand_instances
from fms_sim.disruptions import Scenario
from fms_sim.shopsets import check_training_specs

from checks import at_least_zero, checked, positive


def _run(agent, inst, scenario, temperature: float, rng: np.random.Generator, stats: list[int]) -> int:
    """One run of ``agent`` (arg-max at temperature 0, else sampled); ``stats`` counts [decisions, deviations]."""

    def choose(shop) -> int:
        legal = shop.legal_actions()
        if len(legal) == 1:
            return legal[0]
        logits, mask = agent.logits(shop)
        best = int(np.argmax(logits))
        if temperature <= 0:
            pick = best
        else:
            z = (logits[mask] - logits[mask].max()) / temperature
            p = np.exp(z)
            pick = int(np.flatnonzero(mask)[rng.choice(p.size, p=p / p.sum())])
            stats[0] += 1
            stats[1] += pick != best
        return agent._env(shop).to_net_action(pick)

    return checked(inst, run_full(inst, choose, scenario), f"T={temperature:g}", scenario)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="guided")
    ap.add_argument("--shops", nargs="+", default=["genbu:**1@31", "gen:10x5x5*2@216", "gen:10x5x5*2@219/notools"],
                    help="generated validation shop specs (not training or held-out shops)")
    ap.add_argument("--samples", type=positive, default=10, help="sampled runs per shop, scenario and temperature")
    ap.add_argument("--temperatures", type=float, nargs="+", default=[1.0, 4.0, 8.0])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.2],
                    help="disruption levels: the spread of the lognormal noise on durations (0: nominal)")
    ap.add_argument("--breakdowns", type=at_least_zero, default=1, help="machine breakdowns per disrupted run")
    ap.add_argument("--seeds", type=positive, default=2, help="scenarios per shop and disrupted level")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    for noise in a.noise:  # -0.5 ran nominal runs labelled -0.5
        if not 0 <= noise <= 1:
            ap.error(f"--noise: a spread from 0 to 1, got {noise:g}")
    for temp in a.temperatures:  # NaN failed after the deterministic runs ("Probabilities contain NaN")
        if not 0 < temp < math.inf:
            ap.error(f"--temperatures: positive, finite numbers, got {temp:g}")
    check_training_specs({"train": [], "eval": a.shops})
    insts = expand_instances(a.shops)
    agent = load_agent(a.model)
    if agent.guide is not None:
        agent.use_guide_effort(effort_from(tabu=0.0))
    rng = np.random.default_rng(a.seed)
    print(f"{len(insts)} shops, model {a.model}, {a.samples} samples per run")
    print("| noise | temperature | deterministic | sampled (mean) | best sample | best < deterministic | "
          "sampled decisions off the arg-max |")
    print("|---|---|---|---|---|---|---|")
    for noise in a.noise:
        runs = []
        for inst in insts:
            horizon = int(sum(o.duration for ops in inst.jobs for o in ops) / inst.n_machines)
            for s in range(a.seeds if noise > 0 else 1):
                sc = (Scenario.draw(inst, noise=noise, breakdowns=a.breakdowns, horizon=horizon, seed=s)
                      if noise > 0 else None)
                runs.append((inst, sc, _run(agent, inst, sc, 0.0, rng, [0, 0])))
        for temp in a.temperatures:
            stats = [0, 0]
            det, mean, best, wins = [], [], [], 0
            for inst, sc, d in runs:
                got = [_run(agent, inst, sc, temp, rng, stats) for _ in range(a.samples)]
                det.append(d)
                mean.append(statistics.mean(got))
                best.append(min(got))
                wins += min(got) < d
            print(f"| {noise:g} | {temp:g} | {statistics.mean(det):.1f} | {statistics.mean(mean):.1f} | "
                  f"{statistics.mean(best):.1f} | {wins}/{len(runs)} | {stats[1] / max(1, stats[0]):.2%} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
