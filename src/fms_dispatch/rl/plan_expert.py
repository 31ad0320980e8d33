"""Plan experts on the full-decision net: demonstrations from offline plans, DAgger labels for the policy's states.

The paper's experts (rule pairs, searches over decision sequences) only exist on the paper's net. On the full
net (:class:`fms_sim.full_shop.FullShop`) every valid schedule is reachable (:mod:`fms_sim.replay`), so the
best schedules the project can compute become experts:

* :func:`plan_demonstrations` — per training shop, an offline plan (``plan:SOLVER[:SECONDS]``, e.g.
  ``plan:cpsat:5`` or ``plan:list``, solved by :func:`fms_dispatch.solvers.make_plan``) is acted out on the net
  by :class:`PlanPriorityPolicy`: the full-net rule skeleton (non-delay, hold only when nothing is due) with
  the plan's priorities (planned start times, planned carriers). Every decision with a choice is a
  demonstration ``(observation, mask, action)``.
* :func:`plan_dagger_round` — DAgger (Ross et al., 2011): the current policy drives, and every state it reaches
  is labelled by the same :class:`PlanPriorityPolicy` (the plan's priorities apply in any state). With
  ``disruptions`` the policy drives disrupted shops (a fresh scenario per shop and round,
  :func:`fms_sim.env.episode_scenario`), where the offline plan goes stale: the states a live run meets, which
  nominal demonstrations never show, labelled by the expert acting on the same plan.
* expert ``guide`` — the earliest-start list schedule acted out by :class:`fms_dispatch.rl.guide.GuideFollower`
  (the replay read from states, so it labels any state too). It is the expert of a guided model
  (``guide="list"``), whose observation shows the same plan's orders: its decisions are a function of what the
  policy sees.

Why not the plan's own execution (:class:`fms_sim.replay.PlanPolicy`, exact to the time unit)? Its waits
("hold until the planned part arrives") depend on the whole plan, not on what a state shows: a policy cloned
from exact replays of CP-SAT plans on 40 generated 10×5 shops ended 88 % above the plans, and DAgger labels from
resumed plans were mostly waits. The priority executor loses 0.2 % on those shops and is learnable.

Returns-to-go (for the value head) are exact for the ``shaped`` reward (the potential telescopes:
``-(makespan - LB_t) / scale``) and the ``makespan`` reward; NaN (unused) for ``idle``.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from fms_sim.full_shop import FullShop
from fms_sim.instance import Instance
from fms_sim.schedule import Schedule

from ..full_rules import FullRulePolicy, run_full

__all__ = ["GUIDE_EXPERT", "is_plan_expert", "expert_plan", "expert_policy", "PlanPriorityPolicy",
           "plan_trajectory", "plan_demonstrations",
           "plan_dagger_round", "plan_dagger"]


#: the guide follower's expert name (see the module docstring)
GUIDE_EXPERT = "guide"


def is_plan_expert(expert: str | None) -> bool:
    """Whether ``expert`` names a plan expert (``plan:SOLVER[:SECONDS]``, or ``guide``)."""
    return bool(expert) and (str(expert).lower().startswith("plan:") or str(expert).lower() == GUIDE_EXPERT)


def expert_plan(inst: Instance, expert: str, seed: int = 0) -> Schedule:
    """The offline plan of ``expert`` (``plan:SOLVER[:SECONDS]``) for ``inst`` (one CP-SAT worker, so several
    experts can run side by side and the result does not depend on the machine's core count); for ``guide``
    the guide's plan (the earliest-start list schedule)."""
    from ..solvers import make_plan, parse_plan_name

    if expert.lower() == GUIDE_EXPERT:
        from .guide import guide_plan

        return guide_plan(FullShop(inst))
    base, seconds = parse_plan_name(expert)
    opts: dict[str, Any] = {"seed": seed}
    if base.lower().startswith("cpsat"):
        opts["workers"] = 1
    return make_plan(inst, base, seconds, **opts)


def _ret(env: Any, reward: str, lb: int, makespan: int) -> float:
    if reward == "shaped":
        return -(makespan - lb) / env._scale
    if reward == "makespan":
        return -makespan / env._scale
    return float("nan")


def _env(inst: Instance, shop: FullShop, padding: dict[str, int], reward: str, guide: str | None = None) -> Any:
    from .envs import FastShopEnv

    env = FastShopEnv(inst, reward=reward, decisions="full", guide=guide, **padding)
    env.attach(shop)
    return env


class PlanPriorityPolicy(FullRulePolicy):
    """A plan's priorities acted out by the full-net rule skeleton (``policy(shop) -> net action``).

    The skeleton is :class:`fms_dispatch.full_rules.FullRulePolicy`'s: start what can start, take up free tools
    for current operations, dispatch ready parts (and parts whose AGV would not wait), hold only when nothing
    of that is left. Jobs and tool uses are chosen by the planned start of the operation concerned, vehicles
    are the nearest: which of several equivalent vehicles a plan assigns cannot be read from a state, and
    following the plan's carriers was 1.7 % worse (six generated 10×5 and 20×10 shops with tools). Its decisions
    stay a function of the state and the plan's priorities, so a policy can learn them, and they label any
    state the policy reaches (DAgger) without re-planning."""

    def __init__(self, plan: Schedule):
        super().__init__("FIFO", "nearest", "earliest-start")  # the job rule's key is replaced below
        self.plan = plan
        inf = float("inf")
        start = {(r.job, r.op): r.start for r in plan.operations}
        self._planned = lambda j, k: (start.get((j, k), inf), j)
        self._key = lambda view, j: self._planned(j, view.next_op(j))

    @property
    def name(self) -> str:
        return f"plan-priority:{self.plan.meta.get('solver', '?')}"

    def _use(self, shop: FullShop, legal: list[int]) -> int:
        t = shop.tool_choice
        jobs = [shop.action_kind(a)[1] for a in legal]
        return shop.action_index(f"use:{min(jobs, key=lambda j: self._planned(j, shop.request_of(t, j)))}")


def expert_policy(inst: Instance, plan: Schedule, follow: bool = False) -> Callable[[FullShop], int]:
    """The policy that acts ``plan`` out: :class:`PlanPriorityPolicy`, or with ``follow`` the guide follower."""
    if follow:
        from .guide import GuideFollower, PlanGuide

        return GuideFollower(PlanGuide(inst, plan))
    return PlanPriorityPolicy(plan)


def plan_trajectory(inst: Instance, plan: Schedule, padding: dict[str, int], reward: str,
                    rows: tuple[list, list, list, list], guide: str | None = None, follow: bool = False) -> int:
    """Run :class:`PlanPriorityPolicy` of ``plan`` (with ``follow``: the guide follower) on a fresh full net,
    appending its decisions with a choice to ``rows`` (observations, masks, env actions, returns-to-go); returns
    the makespan reached."""
    obs, masks, actions, rets = rows
    shop = FullShop(inst)
    env = _env(inst, shop, padding, reward, guide)
    policy = expert_policy(inst, plan, follow)
    lbs: list[int] = []
    while not shop.done:
        a = policy(shop)
        mask = env.action_masks()
        if mask.sum() > 1:
            obs.append(env.observe()[0])
            masks.append(mask)
            actions.append(env.from_net_action(a))
            lbs.append(env.potential())
        shop.act(a)
    rets.extend(_ret(env, reward, lb, shop.makespan) for lb in lbs)
    return shop.makespan


def plan_demonstrations(instances: Sequence[Instance], padding: dict[str, int], reward: str, expert: str,
                        seed: int = 0, progress: Callable[[str], None] | None = None,
                        plans: dict[str, Schedule] | None = None, guide: str | None = None
                        ) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """Demonstrations of the plan expert ``expert`` on ``instances`` (arrays as
    :func:`fms_dispatch.rl.imitation.demonstrations` returns them) and the makespans the net reaches with the
    plans. ``plans`` (if given) receives each instance's plan, for :func:`plan_dagger_round`; ``guide``: the
    observation's plan guide (:mod:`fms_dispatch.rl.envs`)."""
    from .imitation import _as_demos

    rows: tuple[list, list, list, list] = ([], [], [], [])
    makespans: dict[str, int] = {}
    follow = expert.lower() == GUIDE_EXPERT
    for n, inst in enumerate(instances):
        plan = expert_plan(inst, expert, seed=seed + n)
        if plans is not None:
            plans[inst.name] = plan
        makespans[inst.name] = plan_trajectory(inst, plan, padding, reward, rows, guide, follow)
        if progress is not None:
            progress(f"  {expert} demonstrations: {n + 1}/{len(instances)} shops ({inst.name}: plan "
                     f"{plan.makespan}, executed {makespans[inst.name]}, {len(rows[0])} decisions recorded)")
    return _as_demos(*rows), makespans


def plan_dagger_round(model: Any, instances: Sequence[Instance], plans: dict[str, Schedule],
                      padding: dict[str, int], reward: str, progress: Callable[[str], None] | None = None,
                      guide: str | None = None, follow: bool = False, disruptions: dict[str, Any] | None = None,
                      rng: np.random.Generator | None = None
                      ) -> tuple[dict[str, np.ndarray], dict[str, int], dict[str, int]]:
    """One DAgger round on the full net: the deterministic policy ``model`` runs each instance, and every state
    with a choice is labelled by the instance's plan (``plans``, from :func:`plan_demonstrations`) as the module
    docstring says. With ``disruptions`` (validated, :func:`fms_sim.env.check_disruptions`) each run is in a
    scenario drawn with ``rng``, and the expert runs the same scenario for comparison. Returns the labelled rows
    (``ret``: the policy's own return-to-go), the policy's makespans and, with ``disruptions``, the expert's in
    the round's scenarios (else none: :func:`plan_demonstrations` measured them)."""
    from fms_sim.env import episode_scenario

    from .imitation import _as_demos

    obs: list = []
    masks: list = []
    actions: list = []
    rets: list = []
    makespans: dict[str, int] = {}
    expert_ms: dict[str, int] = {}
    if disruptions and rng is None:
        rng = np.random.default_rng(0)
    for n, inst in enumerate(instances):
        if inst.name not in plans:
            raise ValueError(f"no expert plan for {inst.name}")
        scenario = episode_scenario(inst, disruptions, rng) if disruptions else None
        shop = FullShop(inst, scenario=scenario)
        env = _env(inst, shop, padding, reward, guide)
        label = expert_policy(inst, plans[inst.name], follow)
        lbs: list[int] = []
        while not shop.done:
            o, mask = env.observe()
            if mask.sum() > 1:
                obs.append(o)
                masks.append(mask)
                actions.append(env.from_net_action(label(shop)))
                lbs.append(env.potential())
                a = env.to_net_action(int(model.predict(o, action_masks=mask, deterministic=True)[0]))
            else:
                a = shop.legal_actions()[0]
            shop.act(a)
        rets.extend(_ret(env, reward, lb, shop.makespan) for lb in lbs)
        makespans[inst.name] = shop.makespan
        if scenario is not None:  # the expert in the same scenario: what the policy is measured against
            expert_ms[inst.name] = run_full(inst, expert_policy(inst, plans[inst.name], follow), scenario).makespan
        if progress is not None:
            progress(f"  dagger: {n + 1}/{len(instances)} shops ({inst.name}: policy makespan {shop.makespan}, "
                     f"expert {expert_ms.get(inst.name, plans[inst.name].makespan)}"
                     f"{' in the same disrupted run' if scenario is not None else ' planned'}, "
                     f"{len(obs)} states labelled)")
    return _as_demos(obs, masks, actions, rets), makespans, expert_ms


def plan_dagger(model: Any, demos: dict[str, np.ndarray], plans: dict[str, Schedule], expert_ms: dict[str, int],
                instances: Sequence[Instance], padding: dict[str, int], reward: str, rounds: int,
                epochs: int = 10, lr: float = 1e-3, seed: int = 0,
                progress: Callable[[str], None] | None = None, guide: str | None = None, follow: bool = False,
                disruptions: dict[str, Any] | None = None
                ) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """:func:`fms_dispatch.rl.imitation.dagger_rounds` with plan labels (:func:`plan_dagger_round`); the policy's
    makespans are compared with the plans as executed (``expert_ms``), with ``disruptions`` with the expert's
    runs in the same scenarios (drawn from ``seed``: the same seed, the same scenarios)."""
    from .imitation import dagger_rounds

    rng = np.random.default_rng(seed) if disruptions else None
    return dagger_rounds(model, demos,
                         lambda: plan_dagger_round(model, instances, plans, padding, reward, progress=progress,
                                                   guide=guide, follow=follow, disruptions=disruptions, rng=rng),
                         expert_ms, rounds, epochs=epochs, lr=lr, seed=seed, progress=progress, experts="plans")
