"""Live decision speed through the messages: a whole run of the simulated shop and the agent logic exchanging the
nodes' JSON messages in one process (``ShopService`` + ``AgentLogic``, no ROS), per state, on large shops.

Each state the agent decodes and checks the ``fms/state/v1``, brings its twin of the shop to it by replaying the
state's ``history`` (the run's applied labels so far: thousands on a 100-job shop), decides and encodes its
command; the shop applies it and publishes the next state. Reported per shop: states, the agent's milliseconds per
state (``AgentLogic.on_state``), the shop's (``handle_command`` and the state's encoding) and the makespan (every
schedule validated). The default model's plan is the plain list schedule (no restarts, no tabu search:
``--guide-restarts 0 --guide-tabu 0``), so every run makes the same decisions and only the time differs.

The shop sends history deltas by default, as ``fms up`` runs it (``history_delta``: each state carries the labels
applied since the state the last command answered); ``--history whole`` sends the whole history in every state, and
``--history both`` makes each run both ways, taking turns, and reports the whole history's times against the deltas'.

With ``--baseline REV`` the same runs are made on the source of git revision REV (a temporary worktree), the two
taking turns run by run so that both see the same machine load; the baseline must make the same schedules, or the
bench stops (a revision without history deltas runs with ``--history whole`` only).

Usage: python bench/live_speed.py [--instances sl00 sl40 sl70] [--solver ppo] [--repeat 1] [--baseline REV]
                                  [--history delta|whole|both] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

from checks import checked, output_file, positive, report, run_worker

ROOT = Path(__file__).resolve().parent.parent


def run_once(name: str, solver: str, delta: bool = True) -> dict:
    """One whole run of ``name`` by ``solver`` through the messages (``delta``: history deltas), timed."""
    from fms_dispatch.agent_logic import AgentLogic, needs_twin
    from fms_msgs_json import encode
    from fms_sim.benchmarks import builtin
    from fms_sim.shop_service import ShopService

    inst = builtin(name)
    effort = None
    if needs_twin(solver):
        from fms_dispatch.rl.guide import effort_from

        effort = effort_from(restarts=0, budget=0, tabu=0)
    try:
        agent = AgentLogic(solver, instance=inst, guide_effort=effort)
    except ValueError:  # a model without a guide takes no guide effort
        agent = AgentLogic(solver, instance=inst)
    full = getattr(agent.decide, "decisions", "paper") == "full"
    kw = {"history_delta": True} if delta else {}  # (a baseline revision may not know the parameter)
    svc = ShopService(inst, run_id="live", decisions="full" if full else "paper", history=True, idle_stops=full,
                      features=not full, **kw)
    svc.start()
    text = encode(svc.state)
    agent_s = shop_s = 0.0
    states = 0
    while not svc.done:
        t0 = time.perf_counter()
        out = agent.on_state(text)
        t1 = time.perf_counter()
        (cmd,) = [o.msg for o in out if o.topic == "fms/command"]
        svc.handle_command(encode(cmd))
        text = encode(svc.state)
        t2 = time.perf_counter()
        if states:  # the first answer also loads the model and makes the plan
            agent_s += t1 - t0
            shop_s += t2 - t1
        states += 1
    assert not getattr(agent, "history_requests", 0), "the agent lost the deltas' thread"
    return {"instance": name, "states": states, "agent_s": agent_s, "shop_s": shop_s,
            "makespan": checked(inst, svc.final_schedule, solver)}


def _worker(src: Path, names: list[str], solver: str, history: str) -> list[dict]:
    """:func:`run_once` per shop in a fresh interpreter on the package source at ``src``."""
    return run_worker(src, __file__, ["--solver", solver, "--history", history, "--instances", *names])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--instances", nargs="+", default=["sl00", "sl40", "sl70"])
    ap.add_argument("--solver", default="ppo", help="the agent's solver (default ppo: the default model)")
    ap.add_argument("--repeat", type=positive, default=1, help="runs per shop (the fastest reported)")
    ap.add_argument("--baseline", help="git revision to measure alongside, run by run")
    ap.add_argument("--history", choices=("delta", "whole", "both"), default="delta",
                    help="the states' history: deltas (as fms up runs the shop; default), whole, or both in turn")
    ap.add_argument("--json", type=output_file, help="write the rows and summary here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        print(json.dumps([run_once(n, a.solver, a.history == "delta") for n in a.instances]))
        return
    if a.history == "both" and a.baseline:
        raise ValueError("--history both compares the two ways in this checkout; give it without --baseline")
    from decide_speed import _sources

    best: dict[str, dict[str, dict]] = {"new": {}, "base": {}}
    with _sources(ROOT / "src", a.baseline) as sources:
        if a.history == "both":  # the whole history takes the baseline's place
            sources = [("base", sources[0][1], "whole"), ("new", sources[0][1], "delta")]
        else:
            sources = [(who, src, a.history) for who, src in sources]
        for _ in range(a.repeat):
            for who, src, history in sources:
                for r in _worker(src, a.instances, a.solver, history):
                    old = best[who].get(r["instance"])
                    if old is None or r["agent_s"] < old["agent_s"]:
                        best[who][r["instance"]] = r
    base_name = "whole history" if a.history == "both" else "baseline"
    lines = [f"{platform.node()} {time.strftime('%Y-%m-%d')}, solver {a.solver}, fastest of {a.repeat}, history "
             + ("deltas against whole histories, run by run" if a.history == "both" else a.history)
             + (f", baseline {a.baseline} run by run" if a.baseline else "")]
    rows = []
    for name in a.instances:
        n = best["new"][name]
        per = 1000 / max(1, n["states"] - 1)
        line = (f"{name}: {n['states']} states, agent {per * n['agent_s']:.2f} ms per state, shop "
                f"{per * n['shop_s']:.2f} ms, makespan {n['makespan']}")
        row = dict(n)
        b = best["base"].get(name)
        if b is not None:
            if (b["makespan"], b["states"]) != (n["makespan"], n["states"]):
                raise SystemExit(f"{name}: the {base_name} runs differently (makespan {b['makespan']} against "
                                 f"{n['makespan']}, states {b['states']} against {n['states']})")
            line += (f"; {base_name} agent {per * b['agent_s']:.2f} ms ({b['agent_s'] / n['agent_s']:.2f}x), shop "
                     f"{per * b['shop_s']:.2f} ms ({b['shop_s'] / n['shop_s']:.2f}x)")
            row.update(baseline_agent_s=b["agent_s"], baseline_shop_s=b["shop_s"])
        lines.append(line)
        rows.append(row)
    report(lines, rows, a.json)


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
