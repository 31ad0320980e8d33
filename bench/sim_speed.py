"""Simulation speed: random masked episodes through both shop nets (and through the Gymnasium env).

Prints decisions per second and seconds per episode for EX12, ra01 (+tools) and sl70 (100x20x20, 10 AGVs,
5 tool transporters), with and without tools, for the paper's net (``Shop``) and the full-decision net
(``FullShop``: dispatch ahead, machine sequencing, tool-request selection, hold). Baseline, measured in the same
run: the same engine with incremental enabling switched off (every transition re-evaluated at every step,
``incremental=False``). Goals (2-core machine), for both nets: >= 20,000 decisions/s on EX12 and a full random
sl70 episode with tools in <= 1 s. Usage: python bench/sim_speed.py [--quick] [--env] [--nets paper,full]
"""

from __future__ import annotations

import argparse
import platform
import random
import time

import numpy as np

from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop
from fms_sim.shop import Shop
from fms_sim.validate import validate

NETS = {"paper": Shop, "full": FullShop}


def net_episodes(inst, seconds: float, min_episodes: int, seed: int = 0, incremental: bool = True,
                 net: str = "paper"):
    rng = random.Random(seed)
    n_dec = n_ep = 0
    t0 = time.perf_counter()
    while n_ep < min_episodes or time.perf_counter() - t0 < seconds:
        shop = NETS[net](inst, incremental=incremental)
        while not shop.done:
            shop.act(rng.choice(shop.legal_actions()))
            n_dec += 1
        n_ep += 1
    dt = time.perf_counter() - t0
    assert validate(inst, shop.schedule()) == []  # the last schedule of each run is checked
    return n_dec / dt, dt / n_ep, n_dec / n_ep


def env_episodes(inst, seconds: float, min_episodes: int, seed: int = 0):
    from fms_sim.env import ShopEnv

    env = ShopEnv(inst, reward="shaped")
    rng = np.random.default_rng(seed)
    n_dec = n_ep = 0
    t0 = time.perf_counter()
    while n_ep < min_episodes or time.perf_counter() - t0 < seconds:
        env.reset(seed=n_ep)
        done = False
        while not done:
            a = int(rng.choice(np.flatnonzero(env.action_masks())))
            _, _, done, _, _ = env.step(a)
            n_dec += 1
        n_ep += 1
    dt = time.perf_counter() - t0
    return n_dec / dt, dt / n_ep, n_dec / n_ep


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="short runs (for smoke tests)")
    ap.add_argument("--env", action="store_true", help="also measure through the Gymnasium env (paper net)")
    ap.add_argument("--nets", default="paper,full", help="comma-separated: paper, full (default both)")
    a = ap.parse_args()
    nets = [n.strip() for n in a.nets.split(",") if n.strip()]
    unknown = [n for n in nets if n not in NETS]
    if unknown or not nets:
        ap.error(f"--nets takes paper and/or full, got {a.nets!r}")
    secs = 0.3 if a.quick else 3.0
    cases = [("EX12", builtin("EX12")), ("ra01", builtin("ra01")),
             ("sl70 AGVs only", builtin("sl70").without_tools()), ("sl70 AGVs+tools", builtin("sl70"))]
    print(f"# {platform.processor() or platform.machine()}, Python {platform.python_version()}")
    print("| net | instance | decisions/episode | net: decisions/s | net: s/episode | baseline: decisions/s | speed-up |"
          + (" env: decisions/s | env: s/episode |" if a.env else ""))
    print("|---|---|---|---|---|---|---|" + ("---|---|" if a.env else ""))
    for net in nets:
        for name, inst in cases:
            dps, spe, dpe = net_episodes(inst, secs, 1 if a.quick else 3, net=net)
            bdps, _, _ = net_episodes(inst, secs, 1, incremental=False, net=net)
            row = f"| {net} | {name} | {dpe:.0f} | {dps:,.0f} | {spe:.4f} | {bdps:,.0f} | {dps / bdps:.1f}x |"
            if a.env and net == "paper":
                edps, espe, _ = env_episodes(inst, secs, 1)
                row += f" {edps:,.0f} | {espe:.4f} |"
            elif a.env:  # the env is measured on the paper net only: its cells stay empty here
                row += " | |"
            print(row, flush=True)


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
