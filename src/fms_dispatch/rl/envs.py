"""The RL environment as the agent sees it: :class:`FastShopEnv` and the padding profiles.

:class:`FastShopEnv` is :class:`fms_sim.env.ShopEnv` (whose features are table-driven, fast enough for sl70
in a few seconds) plus :meth:`FastShopEnv.attach`, so that inference and lookahead can observe any live
:class:`~fms_sim.shop.Shop` without stepping through the Gymnasium API and share instance tables with twins.

Padding profiles (``PADDING``) name the maximum layouts of the shipped models: ``"large"`` (100 jobs x 20
machines x 20 tools, 10 AGVs, 5 transporters: every large-benchmark instance) and ``"bu"`` (8 jobs x 4 machines,
2 AGVs, no tools: the Bilge-Ulusoy sets).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from fms_sim.env import (AGV_FEATURES, FULL_GLOBAL_FEATURES, FULL_JOB_FEATURES, FULL_TOOL_FEATURES, GLOBAL_FEATURES,
                         JOB_FEATURES, MACHINE_FEATURES, TOOL_FEATURES, ShopEnv)
from fms_sim.instance import Instance
from fms_sim.shop import Shop

__all__ = ["FastShopEnv", "PADDING", "padding_for", "obs_layout", "obs_size"]

#: Maximum layouts (env keyword arguments) by profile name.
PADDING: dict[str, dict[str, int]] = {
    "large": dict(max_jobs=100, max_machines=20, max_tools=20, max_agvs=10, max_tts=5),
    "bu": dict(max_jobs=8, max_machines=4, max_tools=0, max_agvs=2, max_tts=0),
}


def padding_for(profile: str | dict[str, int] | None, instances: Sequence[Instance]) -> dict[str, int]:
    """Env padding: a named profile, an explicit dict, or ``None``/``"auto"`` = the largest of ``instances``."""
    if isinstance(profile, dict):
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


def obs_layout(padding: dict[str, int], decisions: str = "paper") -> dict[str, int]:
    """Block sizes of the flat observation (rows and features per block), for the entity policy.

    With ``decisions="full"`` the layout also has ``full=1`` and the sizes of the full net's extra blocks,
    which follow the paper's in the observation: ``full_g`` global features, ``full_job_f`` features per job
    and ``full_tool_f`` per tool (:data:`fms_sim.env.FULL_GLOBAL_FEATURES` etc.)."""
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
    return lay


def obs_size(layout: dict[str, int]) -> int:
    """Length of the flat observation of an :func:`obs_layout`."""
    n = layout["n_global"] + sum(layout[r] * layout[f] for r, f in (
        ("jobs", "job_f"), ("machines", "machine_f"), ("tools", "tool_f"), ("agvs", "agv_f"), ("tts", "tt_f")))
    if layout.get("full"):
        n += layout["full_g"] + layout["jobs"] * layout["full_job_f"] + layout["tools"] * layout["full_tool_f"]
    return n


class FastShopEnv(ShopEnv):
    """:class:`ShopEnv` that can observe a live shop; see the module docstring."""

    # ------------------------------------------------------------------ live shops
    def attach(self, shop: Shop) -> None:
        """Observe ``shop`` (any state) as if it were this env's episode; does not reset or step it."""
        inst = shop.instance
        self._check_fits(inst)
        self.shop = shop
        self.instance = inst
        self._map_actions()
        self._scale = max(1.0, sum(o.duration for ops in inst.jobs for o in ops) / inst.n_machines)
        self._total_ops = inst.n_operations

    def observe(self) -> tuple[np.ndarray, np.ndarray]:
        """(observation, action mask) of the attached shop."""
        return self._obs(), self.action_masks()

    def potential(self) -> int:
        """The shaped reward's potential of the attached shop: its makespan lower bound (the makespan once done);
        a decision's shaped reward is ``-(potential after - potential before) / scale``."""
        return self.shop.makespan if self.shop.done else self._lower_bound()

    def to_net_action(self, a: int) -> int | None:
        """Net action index of padded action ``a`` (None for an empty slot)."""
        return self._to_net(int(a))

    def from_net_action(self, a: int) -> int:
        """Padded action index of the net's action ``a``."""
        return self._from_net(int(a))

    def adopt_tables(self, other: "FastShopEnv") -> None:
        """Reuse ``other``'s instance tables (a twin's shop has an equal copy of the instance)."""
        if other._tables is not None:
            self._tables, self._tables_for = other._tables, None
