"""A trained model ready to dispatch: ``Agent(weights, padding).act(shop) -> net action`` (deterministic).

The agent chooses the arg-max of the masked logits of the model's actor (a single legal action is taken
without a forward pass). It decides with the numpy actor (:mod:`fms_dispatch.rl.actors`): from the model's
``.actor.npz`` export when one exists for exactly these weights (checked by SHA-256) — then torch is never
imported, which saves seconds at start-up — else from the weights loaded with sb3-contrib and torch (CPU,
one thread). :func:`export_actor` writes the export; ``fms train`` does so for every model it saves.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fms_sim.full_shop import FullShop
from fms_sim.instance import Instance
from fms_sim.shop import Shop

from .actors import Actor, actor_path, file_sha256, load_actor, save_actor
from .envs import FastShopEnv
from .guide import ASSIGNMENT_KINDS, REPLAN_BUDGET, REPLAN_DRIFT, REPLAN_MARGIN, GuideReplan, at_start

__all__ = ["Agent", "GuideReplanner", "export_actor", "load_torch_policy"]


def load_torch_policy(weights: str | Path) -> Any:
    """The MaskablePPO policy of a weights file, on the CPU, in evaluation mode (imports torch). A file that is
    not a MaskablePPO save (cut short, overwritten, another library's) raises ValueError naming it."""
    import torch
    from sb3_contrib import MaskablePPO

    torch.set_num_threads(1)
    if not Path(weights).is_file():  # sb3 adds ".zip" and names that file: "nope.zip.zip"
        raise ValueError(f"the weights {weights} are no file")
    try:
        policy = MaskablePPO.load(str(weights), device="cpu").policy
    except OSError:
        raise
    except Exception as exc:  # sb3 reports a broken save as whatever its unzip or unpickle met first
        cause = str(exc).removeprefix("Error: ").replace(f"the file {weights} ", "the file ").strip()
        cause = cause or type(exc).__name__
        raise ValueError(f"the weights {weights} are not a readable MaskablePPO model ({cause})") from None
    policy.set_training_mode(False)
    return policy


def export_actor(weights: str | Path) -> Path:
    """Write the numpy actor of ``weights`` next to it (``X.zip`` → ``X.actor.npz``); returns its path."""
    from .policy import actor_from_policy

    actor = actor_from_policy(load_torch_policy(weights))
    if actor is None:
        raise ValueError(f"the policy in {weights} has layers the numpy actor does not support")
    return save_actor(actor, actor_path(weights), file_sha256(weights))


class Agent:
    """A trained model ready to dispatch (see the module docstring).

    ``torch=True`` forces loading the weights with torch (and keeps the torch policy for
    :meth:`logits` with ``fast=False``, which tests compare with the numpy actor).
    """

    def __init__(self, model_path: str | Path, padding: dict[str, int], name: str = "", torch: bool = False,
                 decisions: str = "paper", guide: str | None = None, plan_assigns: bool = False):
        path = Path(model_path)
        if not path.is_file():
            raise ValueError(f"model file {path} does not exist")
        self.name = name or path.parent.name
        if decisions not in ("paper", "full"):
            raise ValueError(f"model {self.name}: unknown decisions {decisions!r}; choose paper or full")
        self.decisions = decisions
        """The net the model was trained on and decides through (its config's ``decisions``)."""
        from .envs import check_guide

        check_guide(guide, decisions)
        self.guide = guide
        """The observation's plan guide (its config's ``guide``; :mod:`fms_dispatch.rl.envs`)."""
        from .guide import DEFAULT_EFFORT

        self.guide_effort = DEFAULT_EFFORT
        """How hard the guide's plan of a new run is searched (:class:`~fms_dispatch.rl.guide.PlanEffort`);
        read when the run's first observation is made."""
        self.plan_assigns = bool(plan_assigns) and guide is not None
        """Whether :meth:`act` takes the plan's assignment, where a guided model's only choice is one and the plan
        names a legal answer, without running the network (:meth:`plan_assignment`): for a model whose card records
        that its network chose those answers at every one checked (:func:`fms_dispatch.rl.models.checked_assignments`,
        the shipped guided models); never for a model in training, whose network is what is measured."""
        self.assigned = 0
        """How many of :meth:`act`'s answers were the plan's assignments (a running count)."""
        self.path = path
        missing = [k for k in ("max_jobs", "max_machines", "max_tools", "max_agvs", "max_tts") if k not in padding]
        if missing:  # a KeyError deep inside
            raise ValueError(f"model {self.name}: the padding lacks {', '.join(missing)}")
        self.padding = dict(padding)
        self.policy: Any = None  # the torch policy, when loaded
        self.actor: Actor | None = None if torch else self._exported_actor()
        if self.actor is None:
            from .policy import actor_from_policy

            self.policy = load_torch_policy(path)
            self.actor = actor_from_policy(self.policy)
        self._check_net()
        self._envs: dict[int, FastShopEnv] = {}
        self._last: FastShopEnv | None = None

    def _check_net(self) -> None:
        """Refuse weights made for another net or layout than the config says (they would read garbage)."""
        from .actors import NumpyEntityActor
        from .envs import obs_layout, obs_size

        want = obs_size(obs_layout(self.padding, self.decisions, self.guide))
        if isinstance(self.actor, NumpyEntityActor):
            if bool(self.actor.lay.get("full")) != (self.decisions == "full"):
                made = "full" if self.actor.lay.get("full") else "paper"
                raise ValueError(f"model {self.name} was trained on the {made!r} net, but its config says "
                                 f"{self.decisions!r}")
            if bool(self.actor.lay.get("guide")) != (self.guide is not None):
                made = "with" if self.actor.lay.get("guide") else "without"
                raise ValueError(f"model {self.name} was trained {made} a plan guide, but its config says guide "
                                 f"{self.guide!r}")
            got = obs_size(self.actor.lay)
        elif self.actor is not None:
            got = int(self.actor.layers[0][0].shape[0])
        else:
            return
        if got != want:
            raise ValueError(f"model {self.name} reads observations of size {got}, its config's padding and net "
                             f"give {want}")

    @property
    def uses_torch(self) -> bool:
        return self.policy is not None

    def _exported_actor(self) -> Actor | None:
        npz = actor_path(self.path)
        if not npz.is_file():
            return None
        try:
            actor, sha = load_actor(npz)
        except ValueError:
            return None
        return actor if sha == file_sha256(self.path) else None  # a stale export is never used

    def _sizes(self, inst: Instance) -> list[tuple[str, int, int]]:
        """``(what, the instance's count, the model's padding)`` for each padded dimension."""
        p = self.padding
        return [("jobs", inst.n_jobs, p["max_jobs"]), ("machines", inst.n_machines, p["max_machines"]),
                ("tools", inst.n_tools if inst.has_tools else 0, p["max_tools"]),
                ("AGVs", inst.n_agvs if inst.has_agvs else 0, p["max_agvs"]),
                ("tool transporters", inst.n_tool_transporters if inst.has_tools else 0, p["max_tts"])]

    def fits(self, inst: Instance) -> bool:
        """Whether ``inst`` fits this model's padded layout."""
        return all(n <= top for _, n, top in self._sizes(inst))

    def misfit(self, inst: Instance) -> str:
        """The error message for an ``inst`` that does not :meth:`fit <fits>` this model: what exceeds its padded
        layout, and which solvers take any size (a model decides only within the padding it was trained with)."""
        over = ", ".join(f"{n} {what if n != 1 else what[:-1]} (at most {top})"  # "1 tool", not "1 tools"
                         for what, n, top in self._sizes(inst) if n > top)
        return (f"instance {inst.name} is larger than model {self.name} allows: {over}; a rule (rule:MTWR+nearest) "
                "or a plan (plan:list, plan:tabu:5) solves shops of any size")

    def layout(self) -> str:
        """The padded layout in words, for messages: ``"up to 8 jobs, 4 machines, 0 tools, 2 AGVs, 0 tool
        transporters"``."""
        p = self.padding
        return (f"up to {p['max_jobs']} jobs, {p['max_machines']} machines, {p['max_tools']} tools, "
                f"{p['max_agvs']} AGVs, {p['max_tts']} tool transporters")

    def _env(self, shop: Shop) -> FastShopEnv:
        env = self._envs.get(id(shop))
        if env is None or env.shop is not shop:
            if not self.fits(shop.instance):
                raise ValueError(self.misfit(shop.instance))
            if isinstance(shop, FullShop) != (self.decisions == "full"):
                raise ValueError(f"model {self.name} decides through the {self.decisions} net, not through a "
                                 f"{type(shop).__name__}")
            env = FastShopEnv(shop.instance, decisions=self.decisions, guide=self.guide,
                              guide_effort=self.guide_effort, **self.padding)
            env.attach(shop)
            if self._last is not None:
                env.adopt_tables(self._last)  # twins share the real shop's instance tables
            if len(self._envs) >= 4:  # the live shop and a twin or two; drop stale ones
                self._envs.clear()
            self._envs[id(shop)] = env
        elif env.instance is not shop.instance:
            env.attach(shop)
        self._last = env
        return env

    def logits(self, shop: Shop, fast: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Masked-out logits are -inf; returns (logits over padded actions, mask).

        ``fast`` uses the numpy actor; ``fast=False`` the torch policy (only if loaded with torch).
        """
        env = self._env(shop)
        obs, mask = env.observe()
        if fast and self.actor is not None:
            return self.actor.logits(obs, mask), mask
        if self.policy is None:
            raise ValueError(f"model {self.name} was loaded without torch; use Agent(..., torch=True)")
        import torch

        with torch.no_grad():
            x = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
            feats = self.policy.extract_features(x, self.policy.pi_features_extractor)
            latent = self.policy.mlp_extractor.forward_actor(feats)
            out = self.policy.action_net(latent)[0].numpy().astype(np.float64)
        out[~mask] = -np.inf
        return out, mask

    def use_guide_effort(self, effort: Any = None) -> None:
        """Search the plans of the next runs with ``effort`` (a :class:`~fms_dispatch.rl.guide.PlanEffort`; None:
        :data:`~fms_dispatch.rl.guide.DEFAULT_EFFORT`). Loaded agents are shared (cached), so every caller sets it
        for its own runs. Raises TypeError for another type and ValueError for an effort given to a model without
        a guide."""
        from .guide import DEFAULT_EFFORT, PlanEffort

        if effort is not None and not isinstance(effort, PlanEffort):
            raise TypeError(f"guide_effort must be a PlanEffort, not {type(effort).__name__}")
        if effort is not None and self.guide is None:
            raise ValueError(f"model {self.name} reads no plan guide: a guide effort does not apply to it")
        self.guide_effort = effort or DEFAULT_EFFORT

    def forget(self) -> None:
        """Drop what earlier runs left behind (their envs, instance tables and plan guides): the next run of the same
        shop plans from scratch instead of adopting the last run's plan (benchmarks that time each run)."""
        self._envs.clear()
        self._last = None

    def guide_of(self, shop: Shop) -> Any:
        """The plan guide the model reads in ``shop`` (:class:`fms_dispatch.rl.guide.PlanGuide`); raises
        ValueError for a model without a guide."""
        if self.guide is None:
            raise ValueError(f"model {self.name} has no plan guide")
        return self._env(shop).plan_guide()

    def replan_guide(self, shop: Shop, margin: float | None = REPLAN_MARGIN, budget: float | None = None,
                     effort: Any = None) -> GuideReplan:
        """Re-plan the guide the model reads in ``shop`` from its state now (searched with ``effort``, by default the
        model's, within ``budget`` seconds if shorter than its plan search's), adopting the new plan if it ends
        ``margin`` earlier than the plan in force (:meth:`fms_dispatch.rl.envs.FastShopEnv.replan_guide`). Raises
        ValueError for a model without a guide."""
        if self.guide is None:
            raise ValueError(f"model {self.name} has no plan guide")
        return self._env(shop).replan_guide(margin, budget, effort)

    def replan_inputs(self, shop: Shop, margin: float | None = REPLAN_MARGIN, budget: float | None = None,
                      effort: Any = None) -> tuple[Any, Any]:
        """The plan in force and the search of a re-plan of the guide in ``shop``, for
        :func:`~fms_dispatch.rl.guide.replan_search` run elsewhere (the agent node's forked re-plans); then
        :meth:`adopt_replan`. Raises ValueError as :meth:`replan_guide` does."""
        if self.guide is None:
            raise ValueError(f"model {self.name} has no plan guide")
        return self._env(shop).replan_inputs(margin, budget, effort)

    def adopt_replan(self, shop: Shop, plan: Any, before: int | None, margin: float | None = REPLAN_MARGIN,
                     retime: bool = False) -> bool:
        """Make ``plan`` (a re-plan from a state of ``shop``'s run) the guide in ``shop`` if it ends ``margin``
        earlier than ``before``, re-timed from the state now with ``retime``; returns whether it did
        (:meth:`fms_dispatch.rl.envs.FastShopEnv.adopt_replan`)."""
        if self.guide is None:
            raise ValueError(f"model {self.name} has no plan guide")
        return self._env(shop).adopt_replan(plan, before, margin, retime)

    def bridge_guide(self, shop: Shop) -> Any:
        """After jobs joined ``shop``: its guide continued at once from the state with the new jobs
        (:meth:`fms_dispatch.rl.envs.FastShopEnv.bridge_guide`); None where there is none to continue."""
        if self.guide is None:
            raise ValueError(f"model {self.name} has no plan guide")
        return self._env(shop).bridge_guide()

    def plan_assignment(self, shop: Shop, legal: list[int] | None = None) -> int | None:
        """Where the only choice now is an assignment — which vehicle carries the part (``agv``) or tool (``tt``)
        awaiting one, or which pending request the chosen tool serves next (``use``) — the plan's answer (its
        planned carrier, its next use of the tool) if that is legal; else None (another kind of choice, no guide,
        or the plan's answer not offered: a vehicle out of service, a run that left the plan).

        A guided model reads those answers in its observation (the guide's ``planned`` and request-head flags) and
        was cloned from the follower that takes them (:class:`~fms_dispatch.rl.guide.GuideFollower`); the shipped
        guided models chose them at every such decision checked on validation shops, nominal and with noise
        (``bench/plan_assignments.py``, docs/benchmarks.md §9). They are a quarter of a 100-job tool shop's
        decisions, each of which costs the observation and the network about 0.3 ms."""
        if self.guide is None:
            return None
        if legal is None:
            legal = shop.legal_actions()
        if not legal:
            return None
        kind = shop.action_kind(legal[0])[0]
        if kind not in ASSIGNMENT_KINDS:  # (the net offers such a choice alone)
            return None
        return self.guide_of(shop).planned_assignment(shop, kind, legal)

    def act(self, shop: Shop) -> int:
        """The net action the policy picks now (arg-max of the masked logits, lowest index on ties); for a guided
        model whose only choice is an assignment the plan makes, that assignment (:attr:`plan_assigns`)."""
        legal = shop.legal_actions()
        if len(legal) == 1:
            return legal[0]
        if self.plan_assigns and self.guide is not None:
            planned = self.plan_assignment(shop, legal)
            if planned is not None:
                self.assigned += 1
                return planned
        env = self._env(shop)
        logits, _ = self.logits(shop)
        a = env.to_net_action(int(np.argmax(logits)))
        if a is None or a not in legal:  # cannot happen with a correct mask; never hand out an illegal action
            raise RuntimeError(f"policy chose a masked action at time {shop.now}")
        return a


class GuideReplanner:
    """``choose(shop) -> net action`` of a guided agent that re-plans its guide when its plan goes stale.

    Before each decision in a disrupted shop (one with a scenario: noise, breakdowns, outages; a nominal shop keeps
    to the plan and is never re-planned) it checks two triggers, as plan re-planning does
    (:mod:`fms_dispatch.replan`): a machine breakdown of ``shop``'s scenario that has begun and was not yet
    answered (reason ``breakdown``; ``outage`` for a vehicle out of service, also where a breakdown began with it; a
    window that began and ended while a re-plan ran beside the run triggers nothing: :meth:`_collected`), and, with
    ``drift``, an operation started since the last check later than the
    plan in force says by more than ``drift`` times that plan's makespan (``late``). After a re-plan that kept the
    plan in force, lateness is not a trigger again until the shop's clock has moved on by that much (so a stale plan
    is re-planned at most about ``1 / drift`` times over its horizon, not at every late operation). Each trigger calls
    :meth:`Agent.replan_guide` once (with ``margin``, within ``budget`` seconds, searched with ``effort``: None, the
    model's plan search) and records the re-plan in
    :attr:`events` (``{reason, time, wall_time, budget, before, after, status, method}``, as plan re-planning
    records them). A shop seen at its start begins a new run; another shop object of the same run (a twin rebuilt
    from the history) keeps what was answered and checks the operations it starts from then on. Only the run's own
    shop should be checked (lookahead twins are not: pass them the agent's ``act``). After an outage the new plan is
    put in force whatever it promises: the plan in force routes carries through the vehicle out of service (its
    order continued from the state, which the margin compares against, lets a list schedule choose other vehicles).
    A live order re-plans the guide by itself (the jobs changed), and the lateness check follows the new plan."""

    def __init__(self, agent: Agent, margin: float | None = REPLAN_MARGIN, drift: float | None = REPLAN_DRIFT,
                 budget: float | None = REPLAN_BUDGET, effort: Any = None) -> None:
        if agent.guide is None:
            raise ValueError(f"model {agent.name} has no plan guide to re-plan")
        if drift is not None and not drift > 0:
            raise ValueError(f"the re-planning drift must be positive or None, got {drift!r}")
        self.agent, self.margin, self.drift, self.budget, self.effort = agent, margin, drift, budget, effort
        self.events: list[dict[str, Any]] = []
        self._shop: Shop | None = None
        self._answered: set[tuple] = set()  # the breakdowns and outages re-planned for (kind, which, start)
        self._guide: Any = None  # the guide whose plan the lateness check reads
        self._planned: dict[tuple[int, int], int] = {}
        self._tol = 0.0
        self._quiet_until = 0.0  # no lateness trigger before this time (after a re-plan that kept the plan)
        self._seen = 0  # operations of the shop's record checked for lateness

    def _late(self, shop: Shop) -> bool:
        """Whether an operation started since the last check is late against the plan in force (advances the
        check)."""
        guide = self.agent.guide_of(shop)
        if guide is not self._guide:  # a new run, a re-plan adopted, or the guide re-planned for an order
            self._guide = guide
            self._planned = {(r.job, r.op): r.start for r in guide.plan.operations}
            self._tol = max(1.0, (self.drift or 0.0) * guide.plan.makespan)
        ops = shop.rec.ops  # type: ignore[attr-defined]  # a guided model runs a FullShop
        late = shop.now >= self._quiet_until and any(
            r.start - self._planned.get((r.job, r.op), r.start) > self._tol for r in ops[self._seen:])
        self._seen = len(ops)
        return late

    def trigger(self, shop: Shop) -> str | None:
        """Why the guide should be re-planned in ``shop`` now (``breakdown``, ``outage`` or ``late``; each trigger is answered
        once), or None. :meth:`check` re-plans at once; the agent node starts the re-plan beside its decisions
        (:meth:`inputs`, then :meth:`adopt`)."""
        if shop is not self._shop:
            if self._shop is None or at_start(shop):
                self._answered, self._guide, self._quiet_until = set(), None, 0.0
            self._shop = shop
            self._seen = len(shop.rec.ops)  # type: ignore[attr-defined]
        scenario = getattr(shop, "scenario", None)
        if scenario is None:  # a nominal shop keeps to the plan: nothing to re-plan (a live order re-plans anyway)
            return None
        reason = None
        begun = self._begun(shop) - self._answered
        if begun:  # an outage too: the plan's carries for the vehicle waited out its window (EX12: 100,088 for 98)
            self._answered |= begun
            # an outage's rule (put in force whatever it promises) wins where one began with a breakdown: both began
            # while a re-plan ran, and the outage was re-planned under the breakdown's margin
            reason = "outage" if any(b[0] == "outage" for b in begun) else "breakdown"
        if self.drift is not None and self._late(shop) and reason is None:
            reason = "late"
        return reason

    @staticmethod
    def _begun(shop: Shop, over: bool = False) -> set[tuple]:
        """The breakdowns and outages of ``shop``'s scenario begun by now (``over``: only those over by now)."""
        sc, now = getattr(shop, "scenario", None), shop.now
        if sc is None:
            return set()
        return ({("breakdown", b.machine, b.start) for b in sc.breakdowns
                 if b.start <= now and (not over or b.end <= now)}
                | {("outage", o.kind, o.vehicle, o.start) for o in sc.outages
                   if o.start <= now and (not over or o.end <= now)})

    def _collected(self, shop: Shop) -> None:
        """A re-plan made beside the run comes in: the breakdowns and outages that began and ended while it ran are
        over, so none triggers a re-plan now (an outage over for a thousand time units was re-planned for, and its
        plan put in force whatever it promised); those still in force trigger their own. (Offline the shop waits for
        each re-plan: nothing begins meanwhile.)"""
        self._answered |= self._begun(shop, over=True)

    def check(self, shop: Shop) -> dict[str, Any] | None:
        """Re-plan if a trigger fired in ``shop`` since the last check; returns the event or None."""
        reason = self.trigger(shop)
        if reason is None:
            return None
        result = self.agent.replan_guide(shop, self._margin(reason), self.budget, self.effort)
        return self._record(shop, reason, result)

    def _margin(self, reason: str) -> float | None:
        """The margin a re-plan for ``reason`` must beat the plan in force by: none after an outage (see the class
        docstring: the plan in force has the out vehicle's carries)."""
        return None if reason == "outage" else self.margin

    def inputs(self, shop: Shop) -> tuple[Any, Any]:
        """``(plan in force, search)`` of a re-plan from ``shop`` now, to run
        :func:`~fms_dispatch.rl.guide.replan_search` beside the run."""
        return self.agent.replan_inputs(shop, self.margin, self.budget, self.effort)

    def adopt(self, shop: Shop, reason: str, time: int, plan: Any, before: int | None, wall_time: float,
              budget: float | None, moved: bool = False) -> dict[str, Any]:
        """Put a re-plan made beside the run (from its state at ``time``) in force in ``shop`` if it ends the margin
        earlier than ``before``, as :meth:`check` does; records and returns the event (its ``time`` the trigger's).
        If the run ``moved`` on meanwhile, the plan put in force is the new plan's order re-timed from ``shop``'s state
        now, or the earliest-start list schedule from it where that ends earlier
        (:func:`fms_dispatch.replan.retime_from`; ``shop`` must allow a snapshot): the decisions taken meanwhile
        (hundreds on a large simulated shop) leave a plan's start times and vehicle routes behind, and a guide
        read from them leads the model astray."""
        self._collected(shop)
        adopted = self.agent.adopt_replan(shop, plan, before, self._margin(reason), retime=moved)
        event = self._record(shop, reason, GuideReplan(adopted, before, plan.makespan, wall_time, budget), time)
        if moved and adopted:
            event["retimed"] = self.agent.guide_of(shop).plan.meta.get("retime")
        return event

    def failed(self, shop: Shop, reason: str, time: int, status: str, wall_time: float, budget: float | None,
               error: str) -> dict[str, Any]:
        """Record a re-plan made beside the run that brought no plan (``status`` ``failed`` or ``timeout``, ``error``
        says why): the plan in force stays, and as after a kept plan lateness does not trigger again at once."""
        self._quiet_until = shop.now + self._tol
        self._collected(shop)
        event = {"reason": reason, "time": time, "wall_time": round(wall_time, 4), "budget": budget, "before": None,
                 "after": None, "status": status, "method": "guide", "error": error}
        self.events.append(event)
        return event

    def _record(self, shop: Shop, reason: str, result: GuideReplan, time: int | None = None) -> dict[str, Any]:
        if not result.adopted:
            self._quiet_until = shop.now + self._tol
        event = result.event(reason, shop.now if time is None else time)
        self.events.append(event)
        return event

    def __call__(self, shop: Shop) -> int:
        self.check(shop)
        return self.agent.act(shop)
