"""Re-planning after a live order on a large shop: is it done within its budget + 1 s, and do decisions keep
flowing meanwhile? (issue goal; docs/benchmarks.md §8)

In-process, the shop service and the agent logic exchange the same JSON messages as the nodes do over ROS 2
(without the middleware's latency). The agent runs ``plan:PLAN`` with re-planning on; after ``--at`` answered
states an order of ``--jobs`` random jobs arrives. Printed: the re-plan's wall time against its budget, the
slowest answer from the order (or breakdown) on and the number of states answered while the re-plan ran, and
the realised makespan (the run is validated).

    .venv/bin/python bench/replan.py                       # sl70, plan:list, budget 2 s
    .venv/bin/python bench/replan.py --instance sl70 --plan plan:cpsat:10 --budget 2
    .venv/bin/python bench/replan.py --replan-in thread     # the re-plan in a thread of the agent (default: a
                                                            # forked process on Linux)
    .venv/bin/python bench/replan.py --pace 0.004           # a shop that takes at least 4 ms per state (without
                                                            # it the shop moves on as fast as the agent answers)
    .venv/bin/python bench/replan.py --plan ppo --breakdown 1000   # the default model, its guide re-planned when
                                                            # machine 1 breaks down at time 1000 (no order)

With ``--breakdown T`` the shop has one breakdown (``--machine``, from shop time T for ``--duration``) and no order
arrives: a guided ``ppo`` model re-plans its guide when the breakdown begins (a plan solver re-plans too).
"""

from __future__ import annotations

import argparse
import platform
import random
import time

from fms_dispatch import agent_logic
from fms_dispatch.agent_logic import AgentLogic
from fms_msgs_json import encode, make_order
from fms_sim.benchmarks import builtin
from fms_sim.shop_service import ShopService

from checks import at_least_zero, checked, finite, positive


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--instance", default="sl70")
    p.add_argument("--plan", default="plan:list")
    p.add_argument("--budget", type=finite, default=2.0)
    p.add_argument("--at", type=at_least_zero, default=800, help="answered states before the order")
    p.add_argument("--jobs", type=positive, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pace", type=finite, default=0.0,
                   help="seconds the shop takes per state at least (0: as fast as the agent answers; a real shop "
                        "goes on at its own pace however fast the agent is)")
    p.add_argument("--wait", action="store_true",
                   help="the shop waits for each re-plan (the agent's replan_wait; fms up --replan-wait)")
    p.add_argument("--breakdown", type=int, metavar="T",
                   help="a machine breakdown from shop time T instead of the order")
    p.add_argument("--machine", type=positive, default=1, help="the machine of --breakdown")
    p.add_argument("--duration", type=positive, default=200, help="the length of --breakdown")
    p.add_argument("--no-guide-replan", action="store_true",
                   help="a guided ppo model acts its start's plan out (the baseline of --breakdown)")
    p.add_argument("--replan-in", choices=("process", "thread"),
                   help="where the re-plan runs (default: agent_logic.REPLAN_IN_PROCESS)")
    a = p.parse_args()
    if a.replan_in:
        agent_logic.REPLAN_IN_PROCESS = a.replan_in == "process"
    inst = builtin(a.instance)
    rng = random.Random(a.seed)
    jobs = [[{"machine": m, "tool": rng.randint(1, inst.n_tools) if inst.has_tools else None,
              "duration": rng.randint(1, 99)} for m in rng.sample(range(1, inst.n_machines + 1), min(5, inst.n_machines))]
            for _ in range(a.jobs)]
    scenario = None
    if a.breakdown is not None:
        from fms_sim.disruptions import Breakdown, Scenario

        scenario = Scenario((Breakdown(a.machine, a.breakdown, a.duration),), (), 0.0, a.seed)
    svc = ShopService(inst, run_id="bench", decisions="full", history=True, idle_stops=True, features=False,
                      scenario=scenario)
    t0 = time.monotonic()
    plan_solver = a.plan.lower().startswith("plan:")
    agent = AgentLogic(a.plan, instance=inst, replan_wait=a.wait, **({"replan": a.budget} if plan_solver else
                                                                     {"guide_replan": not a.no_guide_replan}))
    svc.start()
    steps, during, slowest_during, slowest, replans = 0, 0, 0.0, 0.0, []
    while not svc.done:
        if steps == a.at and scenario is None:
            refused = [o.msg for o in svc.handle_order(encode(make_order("bench-order", jobs)))
                       if o.msg["schema"] == "fms/error/v1"]
            if refused:
                raise ValueError(f"the shop refused the order: {refused[0]['message']}")
        t1 = time.monotonic()
        out = agent.on_state(encode(svc.state))
        dt = time.monotonic() - t1
        if dt < a.pace:
            time.sleep(a.pace - dt)
        job = agent.decide._job
        if job is not None and not job.done.is_set():
            during += 1
            slowest_during = max(slowest_during, dt)
        if steps >= a.at if scenario is None else svc.state["time"] >= a.breakdown:  # (not the start's planning)
            slowest = max(slowest, dt)
        replans += [o.msg for o in out if o.topic == "fms/replans"]
        (cmd,) = [o.msg for o in out if o.topic == "fms/command"]
        svc.handle_command(encode(cmd))
        steps += 1
    s = svc.final_schedule
    checked(svc.instance, s, a.plan, scenario)
    if scenario is None and steps <= a.at:  # nothing was measured (it printed the figures of a run without an order)
        raise ValueError(f"the run ended after {steps} states, before the order (--at {a.at}): give a smaller --at")
    if scenario is not None and s.makespan <= a.breakdown:
        raise ValueError(f"the run ended at t={s.makespan}, before the breakdown (--breakdown {a.breakdown}): give "
                         "an earlier one")
    where = ("a process" if agent_logic.REPLAN_IN_PROCESS else "a thread") + (", the shop waiting" if a.wait else "")
    if a.no_guide_replan:
        where = "none: the start's plan acted out"
    choose = agent.decide.choose if not plan_solver else None
    model = getattr(choose, "agent", getattr(choose, "__self__", None))  # a GuideReplanner's model, or Agent.act's
    budget = a.budget if plan_solver else (model.guide_effort.budget or 0.0)
    what = (f"order of {a.jobs} jobs after {a.at} states" if scenario is None else
            f"machine {a.machine} down at t={a.breakdown} for {a.duration}")
    print(f"{a.instance} {a.plan}, budget {budget:g} s in {where}, {what} "
          f"({platform.node()}, {time.strftime('%Y-%m-%d')}); run {time.monotonic() - t0:.1f} s, {steps} states, "
          f"makespan {s.makespan}")
    over = sum(r["wall_ms"] > budget * 1000 + 1000 for r in replans)
    job = agent.decide._job  # a re-plan the run ended before (its states counted below): it reports nothing
    running = job is not None and not job.done.is_set()
    print(f"  {len(replans)} re-plans ({sum(r['status'] == 'adopted' for r in replans)} adopted), "
          f"{over} over budget + 1 s, the longest {max((r['wall_ms'] for r in replans), default=0)} ms"
          + ("; one more still running when the run ended (--wait or --pace: let it finish)" if running else ""))
    for r in replans[:5]:
        ok = "within" if r["wall_ms"] <= budget * 1000 + 1000 else "OVER"
        print(f"  re-plan ({r['reason']}) at t={r['time']}: {r['status']}, {r['wall_ms']} ms ({ok} budget + 1 s), "
              f"predicted {r['before']} -> {r['after']}")
    print(f"  states answered while a re-plan ran: {during}, slowest of them {slowest_during * 1000:.0f} ms; "
          f"slowest answer from the {'order' if scenario is None else 'breakdown'} on {slowest * 1000:.0f} ms")


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
