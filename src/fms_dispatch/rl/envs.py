"""The RL environment as the agent sees it: :class:`FastShopEnv` and the padding profiles.

:class:`FastShopEnv` is :class:`fms_sim.env.ShopEnv` (whose features are table-driven, fast enough for sl70
in a few seconds) plus :meth:`FastShopEnv.attach`, so that inference and lookahead can observe any live
:class:`~fms_sim.shop.Shop` without stepping through the Gymnasium API and share instance tables with twins.

Padding profiles (``PADDING``) name the maximum layouts of the shipped models: ``"large"`` (100 jobs x 20
machines x 20 tools, 10 AGVs, 5 transporters: every large-benchmark instance) and ``"bu"`` (8 jobs x 4 machines,
2 AGVs, no tools: the Bilge-Ulusoy sets).

Guide (``guide="list"``, full net only): when a run starts the better of the earliest-start and
earliest-completion list schedules is planned once, improved by ``guide_effort``'s randomised restarts
(:func:`fms_dispatch.rl.guide.guide_plan`; none by default, as in training), and every observation ends with
that plan's orders as read from the state (:class:`fms_dispatch.rl.guide.PlanGuide`): per job, tool, AGV and
transporter whether its planned next order can be carried out now, and each job's rank and lateness in the plan
(``GUIDE_*_FEATURES``). A policy can then follow the plan, which replayed through the net is the plan's list
schedule, and learn where to depart from it.
Twins of a shop share its guide (:meth:`FastShopEnv.adopt_tables`); a shop first seen after it started, or
after its jobs changed (a live order), gets a plan from its state.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Sequence

import numpy as np
from gymnasium import spaces

from fms_sim.env import (AGV_FEATURES, FULL_GLOBAL_FEATURES, FULL_JOB_FEATURES, FULL_TOOL_FEATURES, GLOBAL_FEATURES,
                         JOB_FEATURES, MACHINE_FEATURES, OBS_HIGH, TOOL_FEATURES, ShopEnv)
from fms_sim.instance import Instance
from fms_sim.schedule import Schedule
from fms_sim.full_shop import FullShop
from fms_sim.shop import Shop

from .guide import (GUIDE_AGV_FEATURES, GUIDE_JOB_FEATURES, GUIDE_TOOL_FEATURES, GUIDE_TT_FEATURES, REPLAN_MARGIN,
                    GuideReplan, PlanEffort, PlanGuide, at_start, replan_search)

__all__ = ["FastShopEnv", "PADDING", "padding_for", "obs_layout", "obs_size", "GUIDES", "check_guide"]

#: observation guides (see the module docstring); None: no guide
GUIDES = ("list",)
#: the guide's blocks: (layout key, rows, features), in the observation's order
_GUIDE_BLOCKS = (("guide_job_f", "jobs", GUIDE_JOB_FEATURES), ("guide_tool_f", "tools", GUIDE_TOOL_FEATURES),
                 ("guide_agv_f", "agvs", GUIDE_AGV_FEATURES), ("guide_tt_f", "tts", GUIDE_TT_FEATURES))

#: Maximum layouts (env keyword arguments) by profile name.
PADDING: dict[str, dict[str, int]] = {
    "large": dict(max_jobs=100, max_machines=20, max_tools=20, max_agvs=10, max_tts=5),
    "bu": dict(max_jobs=8, max_machines=4, max_tools=0, max_agvs=2, max_tts=0),
}


def padding_for(profile: str | dict[str, int] | None, instances: Sequence[Instance]) -> dict[str, int]:
    """Env padding: a named profile, an explicit dict, or ``None``/``"auto"`` = the largest of ``instances``."""
    if isinstance(profile, dict):
        keys = set(PADDING["large"])
        missing = [k for k in PADDING["large"] if k not in profile]
        unknown = sorted(set(profile) - keys)
        if missing or unknown:  # a bare KeyError, or a misspelt key silently dropped
            raise ValueError(f"a padding names {', '.join(PADDING['large'])}"
                             + (f"; missing: {', '.join(missing)}" if missing else "")
                             + (f"; unknown: {', '.join(unknown)}" if unknown else ""))
        return {k: int(profile[k]) for k in PADDING["large"]}
    if profile in (None, "auto"):
        if not instances:
            raise ValueError("automatic padding needs at least one instance")
        return dict(max_jobs=max(i.n_jobs for i in instances), max_machines=max(i.n_machines for i in instances),
                    max_tools=max(i.n_tools if i.has_tools else 0 for i in instances),
                    max_agvs=max(i.n_agvs if i.has_agvs else 0 for i in instances),
                    max_tts=max(i.n_tool_transporters if i.has_tools else 0 for i in instances))
    if profile not in PADDING:
        raise ValueError(f"unknown padding profile {profile!r}; choose from auto, {', '.join(PADDING)}")
    return dict(PADDING[profile])


def check_guide(guide: str | None, decisions: str) -> None:
    """Raise ValueError for an unknown guide or a guide on the paper's net."""
    if guide is None:
        return
    if guide not in GUIDES:
        raise ValueError(f"unknown guide {guide!r}; choose from {', '.join(GUIDES)} (or none)")
    if decisions != "full":
        raise ValueError(f"the guide {guide!r} describes full-net decisions: set decisions to full")


def obs_layout(padding: dict[str, int], decisions: str = "paper", guide: str | None = None) -> dict[str, int]:
    """Block sizes of the flat observation (rows and features per block), for the entity policy.

    With ``decisions="full"`` the layout also has ``full=1`` and the sizes of the full net's extra blocks,
    which follow the paper's in the observation: ``full_g`` global features, ``full_job_f`` features per job
    and ``full_tool_f`` per tool (:data:`fms_sim.env.FULL_GLOBAL_FEATURES` etc.). With a ``guide``, ``guide=1``
    and the guide's features per job, tool, AGV and transporter (``guide_job_f``, ``guide_tool_f``,
    ``guide_agv_f``, ``guide_tt_f``; :mod:`fms_dispatch.rl.guide`) come last, in that order."""
    check_guide(guide, decisions)
    lay = dict(n_global=len(GLOBAL_FEATURES), jobs=padding["max_jobs"], job_f=len(JOB_FEATURES),
               machines=padding["max_machines"], machine_f=len(MACHINE_FEATURES),
               tools=padding["max_tools"], tool_f=len(TOOL_FEATURES),
               agvs=padding["max_agvs"], agv_f=len(AGV_FEATURES),
               tts=padding["max_tts"], tt_f=len(AGV_FEATURES))
    if decisions == "full":
        lay.update(full=1, full_g=len(FULL_GLOBAL_FEATURES), full_job_f=len(FULL_JOB_FEATURES),
                   full_tool_f=len(FULL_TOOL_FEATURES))
    elif decisions != "paper":
        raise ValueError(f"unknown decisions {decisions!r}; choose paper or full")
    if guide is not None:
        lay.update(guide=1, **{key: len(f) for key, _, f in _GUIDE_BLOCKS})
    return lay


def obs_size(layout: dict[str, int]) -> int:
    """Length of the flat observation of an :func:`obs_layout`."""
    n = layout["n_global"] + sum(layout[r] * layout[f] for r, f in (
        ("jobs", "job_f"), ("machines", "machine_f"), ("tools", "tool_f"), ("agvs", "agv_f"), ("tts", "tt_f")))
    if layout.get("full"):
        n += layout["full_g"] + layout["jobs"] * layout["full_job_f"] + layout["tools"] * layout["full_tool_f"]
    if layout.get("guide"):
        n += sum(layout[rows] * layout[key] for key, rows, _ in _GUIDE_BLOCKS)
    return n


def _same_fleet(a: Instance, b: Instance) -> bool:
    """Whether two instances with the same jobs have the same vehicles, tools and travel times."""
    return (a.n_agvs, a.n_tool_transporters, a.has_agvs, a.has_tools, a.agv_travel, a.tool_travel) == (
        b.n_agvs, b.n_tool_transporters, b.has_agvs, b.has_tools, b.agv_travel, b.tool_travel)


class FastShopEnv(ShopEnv):
    """:class:`ShopEnv` that can observe a live shop, optionally with a plan's guide; see the module
    docstring."""

    def __init__(self, instances, *, guide: str | None = None, guide_effort: PlanEffort = PlanEffort(), **kwargs):
        super().__init__(instances, **kwargs)
        check_guide(guide, self.decisions)
        if not isinstance(guide_effort, PlanEffort):  # it failed at the first reset, deep in the plan search
            raise TypeError(f"guide_effort must be a PlanEffort, got {type(guide_effort).__name__}")
        self.guide = guide
        self.guide_effort = guide_effort
        self._plan_guide: PlanGuide | None = None
        self._guide_for: Instance | None = None  # the instance the guide was last checked against
        self._new_run = False  # within reset: the observation is a new episode's first (see reset)
        if guide is not None:
            padding = dict(max_jobs=self.max_jobs, max_machines=self.max_machines, max_tools=self.max_tools,
                           max_agvs=self.max_agvs, max_tts=self.max_tts)
            size = obs_size(obs_layout(padding, self.decisions, guide))
            self.observation_space = spaces.Box(low=-1.0, high=OBS_HIGH, shape=(size,), dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """:meth:`ShopEnv.reset`; a new episode whose first observation comes after its start (nothing could be
        decided at time 0: a machine broken down from time 0) gets a guide planned from its state, as a fresh env
        gives it. It kept the last episode's guide (a plan from scratch, or from another run's state), so one seed
        gave other observations after other episodes."""
        self._new_run = True
        try:
            return super().reset(seed=seed, options=options)
        finally:
            self._new_run = False

    def _obs(self) -> np.ndarray:
        obs = super()._obs()
        if self.guide is None:
            return obs
        legal_tools = self.legal_of_kind(self.shop.legal_actions(), "tool").tolist()
        rows = self._guide().features(self.shop, legal_tools, self.max_jobs, self.max_tools, self.max_agvs,
                                      self.max_tts)
        return np.concatenate([obs] + [r.ravel() for r in rows])

    def plan_guide(self) -> PlanGuide:
        """The guide of the observed shop (see :meth:`_guide`); raises ValueError for an env without a guide."""
        if self.guide is None:
            raise ValueError("this env has no plan guide (guide=None)")
        self._attached()
        return self._guide()

    def _guide(self) -> PlanGuide:
        """The guide of the observed shop: this env's own, or the one a twin adopted with the real shop's tables
        (:meth:`adopt_tables`), if it describes this run; else a new one for the shop. A guide describes a run
        of the same jobs, fleet and travel times, planned from scratch for a run at its start, or from a state
        of the run for shops at or after that state's time, with this env's ``guide_effort`` (or given whole)."""
        shop, inst = self.shop, self.instance
        guide = self._plan_guide
        if guide is not None and self._guide_for is not inst:
            same = guide.instance is inst or (guide.instance.jobs == inst.jobs and _same_fleet(guide.instance, inst))
            self._guide_for = inst if same else None
            if not same:
                guide = None
        if guide is not None and self._new_run and isinstance(shop, FullShop) and not at_start(shop):
            guide = None  # another episode's plan: this run is first seen after its start (see reset)
        if guide is not None and guide.effort not in (None, self.guide_effort):
            guide = None  # planned with another search effort than this env's
        if guide is not None:
            if guide.fits_start(shop) if at_start(shop) else (guide.origin is None or shop.now >= guide.origin):
                return guide
        guide = self._plan_guide = PlanGuide.for_shop(shop, self.guide_effort)
        self._guide_for = inst
        return guide

    def replan_guide(self, margin: float | None = REPLAN_MARGIN, budget: float | None = None,
                     effort: PlanEffort | None = None) -> GuideReplan:
        """Re-plan the observed shop's guide from its state now (a residual plan searched with ``effort``, by default
        this env's ``guide_effort``, within ``budget`` seconds if that is shorter than its own), e.g. when a machine
        breaks down and the plan goes stale. The new plan is adopted (the observation then shows its heads) if it ends
        at least ``margin`` (a fraction) earlier than the plan in force continued from the state
        (:func:`~fms_dispatch.rl.guide.retimed_plan`); ``margin=None`` adopts it whatever it promises. Raises
        ValueError for an env without a guide, a margin outside [0, 1) or a negative budget."""
        old, effort = self.replan_inputs(margin, budget, effort)
        t0 = time.perf_counter()
        plan, before = replan_search(self.shop, old, effort)
        adopted = self.adopt_replan(plan, before, margin)
        return GuideReplan(adopted, before, plan.makespan, time.perf_counter() - t0, effort.budget)

    def replan_inputs(self, margin: float | None = REPLAN_MARGIN, budget: float | None = None,
                      effort: PlanEffort | None = None) -> tuple[Schedule, PlanEffort]:
        """What a re-plan of the guide needs besides the shop (:func:`~fms_dispatch.rl.guide.replan_search`): the plan
        in force and the search (``effort``, by default this env's, cut to ``budget`` seconds). Checked as
        :meth:`replan_guide` says."""
        self._attached()
        if margin is not None and not 0 <= margin < 1:
            raise ValueError(f"the re-planning margin must be in [0, 1) or None, got {margin!r}")
        if budget is not None and not budget >= 0:
            raise ValueError(f"the re-planning budget must be >= 0 seconds or None, got {budget!r}")
        old = self.plan_guide().plan
        effort = self.guide_effort if effort is None else effort
        if budget is not None and (effort.budget is None or budget < effort.budget):
            effort = dataclasses.replace(effort, budget=budget)
        return old, effort

    def adopt_replan(self, plan: Schedule, before: int | None, margin: float | None = REPLAN_MARGIN,
                     retime: bool = False) -> bool:
        """Put ``plan`` (a re-plan from a state of this run) in force as the guide if it ends ``margin`` earlier
        than ``before`` (the plan in force continued from that state; None: it could not be, so ``plan`` is
        taken); returns whether it was. With ``retime`` (the run moved on since that state) the guide is the plan's
        order re-timed from the shop's state now, or the earliest-start list schedule from it where that ends
        earlier (:func:`fms_dispatch.replan.retime_from`; the state must allow a snapshot)."""
        adopted = margin is None or before is None or plan.makespan < before * (1 - margin)
        if adopted:
            if retime:
                from fms_sim.snapshot import snapshot

                from ..replan import retime_from

                plan = retime_from(snapshot(self.shop), plan)
            # labelled with the env's effort (what the guide is searched with), whatever the re-plan's budget
            self._plan_guide, self._guide_for = PlanGuide(self.instance, plan, self.guide_effort), self.instance
            self._plan_guide.mark(self.shop)
        return adopted

    def bridge_guide(self) -> Schedule | None:
        """After jobs joined the observed shop (a live order): put in force at once the plan in force's order
        continued from the state with the new jobs after it, or the earliest-start list schedule from the state where
        that ends earlier (:func:`fms_dispatch.replan.retime_from`: two list schedules, where planning the guide
        afresh searches for its whole budget), so that the model decides on while a full search runs beside it.
        Returns that plan, or None where there is no plan in force to continue (the env then plans as usual)."""
        from ..replan import retime_from
        from .guide import _state

        old = self._plan_guide
        if self.guide is None or old is None or at_start(self.shop):
            return None
        plan = retime_from(_state(self.shop), old.plan)
        self.adopt_replan(plan, None, None)
        return plan

    # ------------------------------------------------------------------ live shops
    def attach(self, shop: Shop) -> None:
        """Observe ``shop`` (any state) as if it were this env's episode; does not reset or step it. Stepping
        goes on from its state (the shaped reward from its potential now)."""
        if isinstance(shop, FullShop) != (self.decisions == "full"):  # the other way round crashed in _obs
            raise ValueError(f"an env with decisions={self.decisions!r} observes a "
                             f"{'FullShop' if self.decisions == 'full' else 'paper-net Shop'}, not a "
                             f"{type(shop).__name__}")
        inst = shop.instance
        self._check_fits(inst)
        self.shop = shop
        self.instance = inst
        self._map_actions()
        self._scale = max(1.0, sum(o.duration for ops in inst.jobs for o in ops) / inst.n_machines)
        self._total_ops = inst.n_operations
        self._ended = shop.done  # a new shop: not the end of the last episode
        self._lb = self.potential()  # the shaped reward counts from here

    def _attached(self) -> Shop:
        """The observed shop; a clear error before :meth:`reset` or :meth:`attach` (not an AttributeError)."""
        if self.shop is None:
            raise RuntimeError("no shop to observe: call reset() or attach(shop) first")
        return self.shop

    def observe(self) -> tuple[np.ndarray, np.ndarray]:
        """(observation, action mask) of the attached shop."""
        self._attached()
        return self._obs(), self.action_masks()

    def potential(self) -> int:
        """The shaped reward's potential of the attached shop: its makespan lower bound (the makespan once done);
        a decision's shaped reward is ``-(potential after - potential before) / scale``."""
        shop = self._attached()
        return shop.makespan if shop.done else self._lower_bound()

    def to_net_action(self, a: int) -> int | None:
        """Net action index of padded action ``a`` (None for an empty slot)."""
        self._attached()
        return self._to_net(int(a))

    def from_net_action(self, a: int) -> int:
        """Padded action index of the net's action ``a``."""
        return self._from_net(int(a))

    def adopt_tables(self, other: "FastShopEnv") -> None:
        """Reuse ``other``'s instance tables and plan guide (a twin's shop has an equal copy of the instance and
        continues its run)."""
        if other._tables is not None:
            self._tables, self._tables_for = other._tables, None
        self._plan_guide, self._guide_for = other._plan_guide, None  # a twin follows its shop's plan
