"""ROS 2 speed: decisions per second over topics, and the wall time of ``fms up`` end to end.

For each instance (default EX12 and sl00) the script runs ``python -m fms_dispatch.up INSTANCE --solver S``
``--repeat`` times (shop, agent and recorder as separate processes, on the ROS domain ``ROS_DOMAIN_ID`` names,
else on a fresh random one each time; the last column lists the domains fms up used) and reports medians (and
the best run, the figure least disturbed by other load on the machine):

* ``fms up`` wall time — process start, discovery, the whole run, recording, the Gantt chart and a clean
  stop, measured around the command (goal for EX12: <= 5 s);
* decisions/s over topics — decisions / ``decision_time``, where the shop measures ``decision_time`` from
  the first command it applies to the end of the run (so the rate covers state -> agent -> command -> shop
  round trips, events and recording, but not process start-up; goal: >= 500 decisions/s);
* the in-process rate of the same shop/agent logic with the messages encoded and decoded but no ROS
  (``ShopService`` + ``AgentLogic``), which bounds what the topics can reach.

Every schedule is validated. Usage: ``python bench/ros_speed.py [--instances EX12 sl00] [--solver S]
[--repeat 3]``; set ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (the launcher defaults to it).
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fms_msgs_json import TOPIC_STATE, encode
from fms_sim.benchmarks import builtin
from fms_sim.schedule import Schedule
from fms_sim.shop_service import ShopService
from fms_sim.validate import validate
from fms_dispatch.agent_logic import AgentLogic, needs_full_net, needs_idle_stops, needs_twin

from checks import positive


def in_process_rate(name: str, solver: str, seconds: float = 1.0) -> float:
    """Decisions/s of ShopService + AgentLogic exchanging encoded messages in one process."""
    inst = builtin(name)
    agent = AgentLogic(solver, instance=inst)  # loaded once (a PPO model takes seconds to load)
    # the same shop settings as fms up uses for this solver (fms_dispatch.up): a plan: solver and a full-net model
    # (the default ppo) run the full net; a plan: solver also reads the history, and answers idle stops
    twin = needs_twin(solver) or needs_full_net(solver)
    full = needs_full_net(solver) or getattr(agent.decide, "decisions", "paper") == "full"
    n = 0
    t0 = time.perf_counter()
    for run in itertools.count():
        if n and time.perf_counter() - t0 >= seconds:
            break
        svc = ShopService(inst, run_id=f"bench-{run}", history=twin, features=not twin, history_delta=twin,
                          idle_stops=needs_idle_stops(solver) or needs_full_net(solver),
                          decisions="full" if full else "paper")
        out = svc.start()
        while not svc.done:
            state = [o.msg for o in out if o.topic == TOPIC_STATE][-1]
            (cmd,) = agent.on_state(encode(state, check=False))
            out = svc.handle_command(encode(cmd.msg, check=False))
            for o in out:
                encode(o.msg, check=False)
        n += svc.decisions
    return n / (time.perf_counter() - t0)


def fms_up(name: str, solver: str, work: Path, run: int) -> tuple[float, Schedule, int]:
    """One ``fms up`` run; returns its wall time, the schedule it wrote and the ROS domain it ran on."""
    out = work / f"{name}-{run}.schedule.json"
    cmd = [sys.executable, "-m", "fms_dispatch.up", name, "--solver", solver, "--out", str(out),
           "--db", str(work / "bench.sqlite")]
    env = dict(os.environ)  # fms up uses ROS_DOMAIN_ID when it is set, else a fresh random domain per run
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    t0 = time.perf_counter()
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        last = (res.stderr.strip().splitlines() or ["(no output)"])[-1]
        if res.returncode == 2 and ": error: " in last:  # a refusal of the input: that one line, exit 2
            raise ValueError(last.split(": error: ", 1)[1])
        raise SystemExit(f"fms up {name} failed ({res.returncode}):\n{res.stderr}")
    sched = Schedule.load(out)
    problems = validate(builtin(name), sched)
    if problems:
        raise SystemExit(f"fms up {name}: invalid schedule: {problems[0]}")
    domain = re.search(r"; ROS_DOMAIN_ID=(\d+)(;|$)", res.stderr, re.M)  # fms up's start line says which it used
    if domain is None:
        raise SystemExit(f"fms up {name} did not say its ROS domain:\n{res.stderr}")
    return wall, sched, int(domain.group(1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--instances", nargs="+", default=["EX12", "sl00"])
    ap.add_argument("--solver", default="rule:SPTN+nearest", help="agent solver (default rule:SPTN+nearest)")
    ap.add_argument("--repeat", type=positive, default=3)
    a = ap.parse_args()
    for name in a.instances:  # an unknown name is one line and exit 2 now, not fms up's failure (two lines, exit 1)
        builtin(name)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# ros_speed: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python "
          f"{platform.python_version()}, load average {load:.1f} at start; solver {a.solver}; "
          f"median (best) of {a.repeat} runs; ROS domain {os.environ.get('ROS_DOMAIN_ID') or 'random per run'}")
    print(f"{'instance':>9} {'decisions':>9} {'fms up wall s (best)':>20} {'decisions/s topics (best)':>25} "
          f"{'decisions/s in-process':>22} {'makespan':>8}  ROS domains")
    with tempfile.TemporaryDirectory(prefix="fms-ros-speed-") as tmp:
        for name in a.instances:
            walls, rates, domains = [], [], []
            sched = None
            for run in range(a.repeat):
                wall, sched, domain = fms_up(name, a.solver, Path(tmp), run)
                walls.append(wall)
                domains.append(str(domain))
                rates.append(sched.meta["decisions"] / max(sched.meta["decision_time"], 1e-9))
            assert sched is not None
            wall_txt = f"{statistics.median(walls):.2f} ({min(walls):.2f})"
            rate_txt = f"{statistics.median(rates):.0f} ({max(rates):.0f})"
            print(f"{name:>9} {sched.meta['decisions']:>9} {wall_txt:>20} {rate_txt:>25} "
                  f"{in_process_rate(name, a.solver):>22.0f} {sched.makespan:>8}  {','.join(domains)}", flush=True)


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
