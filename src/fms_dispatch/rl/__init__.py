"""Reinforcement-learning dispatcher: MaskablePPO agents on the shop net, with an optional lookahead twin.

* :mod:`.envs` — the agent's environment (fast features, padding profiles, the optional plan guide);
* :mod:`.guide` — a list schedule's orders read from any full-net state, and the follower that acts them out;
* :mod:`.plan_expert` — plan experts and DAgger labels on the full net;
* :mod:`.policy` — the entity policy network (torch);
* :mod:`.actors` — its actor in numpy, and the ``.actor.npz`` export;
* :mod:`.agent` — the deterministic :class:`~.agent.Agent` (numpy at inference; torch only without an export);
* :mod:`.lookahead` — running an agent, with pre-positioning of idle vehicles;
* :mod:`.beside` — a guided model's plan search on the other core while its run goes on;
* :mod:`.models` — model folders, shipped models and the default choice per instance;
* :mod:`.train` — ``fms train``.

Solver entry point: :func:`ppo_solver` (``"ppo"`` or ``"ppo:MODEL"``).
"""

from __future__ import annotations

import time
from typing import Any, Callable

from fms_sim.instance import Instance, require_instance
from fms_sim.schedule import Schedule

from ..progress import say
from .train import add_train_parser

__all__ = ["ppo_solver", "add_train_parser"]


def ppo_solver(spec: str = "ppo") -> Callable[..., Schedule]:
    """Solver for ``"ppo"`` (the shipped default, ``guided-dagger``: :func:`~fms_dispatch.rl.models.default_model_name`)
    or ``"ppo:MODEL"`` (name, folder, .zip).

    The returned ``solve(instance, lookahead=False, progress=False, **ignored)`` runs the deterministic masked
    policy (``seed`` and ``time_limit`` are ignored); ``lookahead=True`` pre-positions idle vehicles with the
    twin. ``progress`` reports on stderr every 2 s (a 100-job shop takes the plain policy about 10 s, the twin
    lookahead minutes).
    ``lookahead="fast"`` is the lookahead without retries of rejected moves (``retry=False`` of
    :class:`~fms_dispatch.rl.lookahead.LookaheadPlanner`): 1.5-3.6 times faster on 15-20-job instances and
    6-8 times on 100-job ones with tools, other schedules (docs/benchmarks.md §2).
    ``scenario`` (breakdowns, outages, noise) disrupts the run of a full-net model; with the lookahead its twins
    are then nominal copies of the shop (:func:`~fms_dispatch.rl.lookahead.nominal_twin`), which know only the past.
    ``lookahead="guide"`` (a guided model only): idle vehicles make the guide plan's empty trips
    (:class:`~fms_dispatch.rl.guide.GuideMoves`; unverified, no trial runs).
    ``guide_effort`` (a guided model only; :class:`~fms_dispatch.rl.guide.PlanEffort`, default
    :data:`~fms_dispatch.rl.guide.DEFAULT_EFFORT`) is how hard the guide's plan is searched when the run starts.
    ``guide_replan`` (default True; a guided model in a disrupted run): re-plan the guide when a machine breakdown
    begins or an operation starts late against the plan in force, adopting the new plan where it ends
    :data:`~fms_dispatch.rl.guide.REPLAN_MARGIN` earlier than the plan in force
    (:class:`~fms_dispatch.rl.agent.GuideReplanner`); the re-plans are in ``meta["replans"]``. A guided model's run
    records the makespan of the plan in force at its end in ``meta["guide_plan_makespan"]`` (the plan searched at the
    start; in a disrupted run the last re-plan adopted, a forecast): a plain run that ends later left out some of the
    plan's empty trips, which ``lookahead="guide"`` makes; ``meta["guide_search_time"]`` is the seconds of the plan
    search at the start. Where a second core is there for it, the run has no lookahead
    (:func:`~fms_dispatch.rl.beside.beside_possible`) and the budget fits fewer than 16 list schedules of the shop
    (:func:`~fms_dispatch.rl.beside.worth_beside`: the large shops), the search runs on that core while the run goes
    on with its first plan, and the run starts over only if the search found a plan that ends earlier
    (:mod:`~fms_dispatch.rl.beside`; the same schedule where the search gets the CPU time it gets before the run,
    sooner where the first plan stands):
    ``meta["guide_search_beside"]`` is then ``"kept"`` or ``"restarted"`` (None: the search ran before the run, its
    time part of the run's ``wall_time``). ``guide_beside=False`` searches before the run in any case (while another
    job keeps the second CPU busy, the search beside the run would get less time). Where a guided model's only choice
    is an assignment (a vehicle for a carry, a request for a tool) and its plan names a legal answer, the run takes
    it without running the network (:attr:`~fms_dispatch.rl.agent.Agent.plan_assigns`); ``meta["plan_assignments"]``
    counts them.
    """
    if not isinstance(spec, str):  # None was an AttributeError
        raise ValueError(f"bad PPO solver name {spec!r}; use ppo or ppo:MODEL")
    low = spec.strip()
    if low.lower() == "ppo":
        model: str | None = None
    elif low.lower().startswith("ppo:") and low[4:].strip():
        model = low[4:].strip()
    else:
        raise ValueError(f"bad PPO solver name {spec!r}; use ppo or ppo:MODEL")

    def solve(instance: Instance, lookahead: bool | str = False, progress: bool = False, scenario: Any = None,
              guide_effort: Any = None, guide_replan: bool | None = None, guide_beside: bool | None = None,
              **_: Any) -> Schedule:
        from fms_sim.full_shop import make_shop

        from ..solvers import lookahead_suffix
        from .agent import GuideReplanner
        from .beside import SearchBeside, beside_possible, run_beside, worth_beside
        from .guide import first_plan, search_from
        from .lookahead import nominal_twin, run_agent
        from .models import default_model_name, load_agent

        require_instance(instance, "a ppo solver")  # a name was an AttributeError
        suffix = lookahead_suffix(lookahead)  # also rejects a bad value before any work
        fast = lookahead == "fast"

        agent = load_agent(model or default_model_name(instance))
        if not agent.fits(instance):
            raise ValueError(agent.misfit(instance))
        agent.use_guide_effort(guide_effort)  # a cached agent: set for every run
        if guide_replan is not None and agent.guide is None:  # it was taken and ignored
            raise ValueError(f"model {agent.name} reads no plan guide: guide re-planning does not apply to it")
        guide_replan = guide_replan is not False  # default: re-plan
        disrupted = scenario is not None and not scenario.empty
        if disrupted and agent.decisions != "full":
            raise ValueError(f"model {agent.name} decides through the paper's net, which runs no disruptions; use a "
                             "full-net model: ppo (the default, guided-dagger), ppo:guided-ppo or ppo:full")
        report = say if progress else None
        planner = None
        if lookahead == "guide":
            from .guide import GuideMoves

            planner = GuideMoves.for_agent(agent)
        replanner: Any = None  # a disrupted run's GuideReplanner (start makes it)
        assigned = 0

        def start(plan: Schedule | None = None) -> tuple[Any, Any]:
            """A fresh shop of the run and what chooses in it (the model, or its re-planner in a disrupted run);
            ``plan``: the guide's plan, put in force as if searched for it (else the model plans when it reads)."""
            nonlocal replanner, assigned
            assigned = agent.assigned  # the plan's assignments of this run: counted from here
            shop = make_shop(instance, agent.decisions, scenario if disrupted else None)
            if plan is not None:
                agent.adopt_replan(shop, plan, None, None)
            replanner = GuideReplanner(agent) if disrupted and guide_replan and agent.guide is not None else None
            return shop, replanner or agent.act

        shop, choose = start()
        search_s = None
        beside = None
        if agent.guide is not None and not lookahead and guide_beside is not False \
                and beside_possible(agent.guide_effort):
            t0 = time.perf_counter()
            first = first_plan(shop)
            if worth_beside(first, agent.guide_effort):
                try:  # the plan search on the other core, the run going on with its first plan meanwhile
                    beside = SearchBeside(shop, agent.guide_effort, first)
                except OSError:  # no process could be forked now: the search runs first, as below
                    beside = None
            # the first plan, the run going on with it; or the plan searched from it before the run
            plan = first.plan if beside is not None else search_from(instance, first, agent.guide_effort)
            try:
                agent.adopt_replan(shop, plan, None, None)
            except BaseException:  # (an interrupt before the run: the search beside it ends too)
                if beside is not None:
                    beside.cancel()
                raise
            search_s = time.perf_counter() - t0
        elif agent.guide is not None:  # the plan search, timed apart from the run (which reads the same guide)
            t0 = time.perf_counter()
            agent.guide_of(shop)
            search_s = time.perf_counter() - t0
        if beside is not None:
            sched, shop, restarted = run_beside(beside, shop, choose, start, progress=report)
            search_s = beside.seconds
        else:
            if lookahead and planner is None and replanner is not None:
                # the lookahead's twins roll the plain policy out: they re-plan nothing
                from .lookahead import LookaheadPlanner

                planner = LookaheadPlanner(agent.act, retry=not fast, twin=nominal_twin)
            # in a disrupted shop the lookahead's twins are nominal copies: they know only the past
            sched = run_agent(shop, choose, lookahead=bool(lookahead), progress=report, retry=not fast,
                              twin=nominal_twin, planner=planner)
        if replanner is not None:
            sched.meta["replans"] = replanner.events
        sched.meta["solver"] = f"ppo:{agent.name}{suffix}"
        sched.meta["model"] = agent.name
        sched.meta["decisions"] = agent.decisions
        sched.meta["lookahead"] = bool(lookahead)
        if agent.guide is not None:
            sched.meta["guide_effort"] = agent.guide_effort.as_dict()
            # the plan in force at the end: the plan searched at the start, or in a disrupted run the last re-plan
            # adopted (its makespan then a forecast); a plain run can end later than its plan (no empty trips)
            sched.meta["guide_plan_makespan"] = agent.guide_of(shop).plan.makespan
            # the choices the plan's assignments answered without the network (Agent.plan_assigns; with the
            # lookahead, its trial runs' too)
            sched.meta["plan_assignments"] = agent.assigned - assigned
            sched.meta["guide_search_time"] = round(search_s, 4)
            # beside the run: the first plan stood ("kept") or the run started over with the searched plan
            sched.meta["guide_search_beside"] = None if beside is None else ("restarted" if restarted else "kept")
        if lookahead:
            sched.meta["lookahead_fast"] = fast
        return sched

    return solve
