"""The RL environment as the agent sees it: :class:`FastShopEnv` and the padding profiles.

:class:`FastShopEnv` is :class:`fms_sim.env.ShopEnv` with the observation and the shaped reward's lower bound
computed from per-instance tables (suffix sums per job, remaining load per machine) with numpy instead of
re-summing every job's operations at every decision. The values are the same as the base class's (a test
compares them bit for bit); what changes is the cost: a 100x20 instance no longer spends most of its time
in feature sums, which keeps training and inference on the large benchmark (sl70 in a few seconds) feasible
on two cores. It also offers :meth:`FastShopEnv.attach`, so that inference and lookahead can observe any live
:class:`~fms_sim.shop.Shop` without stepping through the Gymnasium API.

Padding profiles (``PADDING``) name the maximum layouts of the shipped models: ``"large"`` (100 jobs x 20
machines x 20 tools, 10 AGVs, 5 transporters: every large-benchmark instance) and ``"bu"`` (8 jobs x 4 machines,
2 AGVs, no tools: the Bilge-Ulusoy sets).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from fms_sim.env import (AGV_FEATURES, GLOBAL_FEATURES, JOB_FEATURES, MACHINE_FEATURES, OBS_HIGH, TOOL_FEATURES,
                         ShopEnv)
from fms_sim.instance import Instance
from fms_sim.shop import Shop

__all__ = ["FastShopEnv", "PADDING", "padding_for", "obs_layout"]

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


def obs_layout(padding: dict[str, int]) -> dict[str, int]:
    """Block sizes of the flat observation (rows and features per block), for the entity policy."""
    return dict(n_global=len(GLOBAL_FEATURES), jobs=padding["max_jobs"], job_f=len(JOB_FEATURES),
                machines=padding["max_machines"], machine_f=len(MACHINE_FEATURES),
                tools=padding["max_tools"], tool_f=len(TOOL_FEATURES),
                agvs=padding["max_agvs"], agv_f=len(AGV_FEATURES),
                tts=padding["max_tts"], tt_f=len(AGV_FEATURES))


class _Tables:
    """Per-instance constant arrays: operation machines/durations/tools and suffix sums per job."""

    def __init__(self, inst: Instance):
        n = inst.n_jobs
        L = max(len(ops) for ops in inst.jobs)
        m = inst.n_machines
        self.instance = inst
        self.n = n
        self.nops = np.array([len(ops) for ops in inst.jobs], dtype=np.int64)
        self.mach = np.zeros((n, L + 1), dtype=np.int64)
        self.dur = np.zeros((n, L + 1), dtype=np.int64)
        self.tool = np.zeros((n, L + 1), dtype=np.int64)
        self.suffix = np.zeros((n, L + 1), dtype=np.int64)            # remaining work from op k on
        self.load_suffix = np.zeros((n, L + 1, m + 1), dtype=np.int64)  # remaining work per machine from op k on
        for j, ops in enumerate(inst.jobs):
            for k, op in enumerate(ops):
                self.mach[j, k] = op.machine
                self.dur[j, k] = op.duration
                self.tool[j, k] = op.tool or 0
            for k in range(len(ops) - 1, -1, -1):
                self.suffix[j, k] = self.suffix[j, k + 1] + ops[k].duration
                self.load_suffix[j, k] = self.load_suffix[j, k + 1]
                self.load_suffix[j, k, ops[k].machine] += ops[k].duration
        self.rows = np.arange(n)


class FastShopEnv(ShopEnv):
    """:class:`ShopEnv` with table-driven features (same values, less time); see the module docstring."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._tables: _Tables | None = None
        self._tables_for: Instance | None = None

    # ------------------------------------------------------------------ live shops
    def attach(self, shop: Shop) -> None:
        """Observe ``shop`` (any state) as if it were this env's episode; does not reset or step it."""
        inst = shop.instance
        self._check_fits(inst)
        self.shop = shop
        self.instance = inst
        self._scale = max(1.0, sum(o.duration for ops in inst.jobs for o in ops) / inst.n_machines)
        self._total_ops = inst.n_operations

    def observe(self) -> tuple[np.ndarray, np.ndarray]:
        """(observation, action mask) of the attached shop."""
        return self._obs(), self.action_masks()

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

    def _t(self) -> _Tables:
        inst = self.shop.instance
        if self._tables_for is not inst:
            tb = self._tables
            if tb is None or (tb.instance is not inst and tb.instance.jobs != inst.jobs):
                tb = _Tables(inst)
            self._tables, self._tables_for = tb, inst
        return self._tables

    # ------------------------------------------------------------------ features (same values as ShopEnv)
    def _lower_bound(self) -> int:
        s, inst = self.shop, self.instance
        tb = self._t()
        now = s.now
        lb = max(now, s.makespan)
        k = np.asarray(s.job_started_ops, dtype=np.int64)
        rem = tb.suffix[tb.rows, k]
        if rem.size and rem.max() > 0:
            lb = max(lb, now + int(rem.max()))
        load = tb.load_suffix[tb.rows, k].sum(axis=0)
        busy = np.maximum(np.asarray(s.machine_busy_until, dtype=np.int64), now)
        lb = max(lb, int((busy[1:] + load[1:]).max()))
        return lb

    def _obs(self) -> np.ndarray:
        s, inst = self.shop, self.instance
        tb = self._t()
        sc = self._scale
        now = s.now
        n = tb.n
        mm = self.max_machines
        legal = s.legal_actions()
        kinds = s.decision_kind() or ""
        g = np.array((now / sc, sum(s.job_done_ops) / self._total_ops, "job" in kinds, "agv" in kinds,
                      "tt" in kinds, inst.n_jobs / self.max_jobs, inst.n_machines / self.max_machines),
                     dtype=np.float32)
        req = s.awaiting_agv()

        k = np.asarray(s.job_started_ops, dtype=np.int64)
        loc = np.full(n, -1, dtype=np.int64)
        for tok in s.p_parts.tokens():
            c = tok.colour
            loc[c[0]] = c[2]
        present = loc >= 0
        has_next = k < tb.nops
        kk = np.minimum(k, tb.nops)  # tables are padded with zeros past the last operation
        J = np.zeros((self.max_jobs, len(JOB_FEATURES)), dtype=np.float64)
        Jn = J[:n]
        Jn[:, 0] = 1.0
        legal_jobs = [a for a in legal if a < n]
        Jn[legal_jobs, 1] = 1.0
        Jn[:, 2] = present
        Jn[:, 3] = np.where(has_next, tb.mach[tb.rows, kk] / mm, 0.0)
        Jn[:, 4] = np.where(has_next, tb.dur[tb.rows, kk] / sc, 0.0)
        Jn[:, 9] = np.where(has_next, tb.tool[tb.rows, kk] / max(1, self.max_tools), 0.0)
        Jn[:, 5] = tb.suffix[tb.rows, kk] / sc
        Jn[:, 6] = (tb.nops - k) / np.maximum(1, tb.nops)
        Jn[:, 7] = loc / mm
        ready = np.asarray(s.job_ready_since, dtype=np.int64)
        Jn[:, 8] = np.where(present, (now - ready) / sc, 0.0)
        if req is not None:
            Jn[req[0], 10] = 1.0

        M = np.zeros((mm, len(MACHINE_FEATURES)), dtype=np.float64)
        nm = inst.n_machines
        until = np.asarray(s.machine_busy_until[1:nm + 1], dtype=np.int64)
        Mn = M[:nm]
        Mn[:, 0] = 1.0
        Mn[:, 1] = until > now
        Mn[:, 2] = np.maximum(0, until - now) / sc
        count = np.zeros(nm + 1, dtype=np.int64)
        work = np.zeros(nm + 1, dtype=np.int64)
        for tok in s.p_buffer.tokens():
            j, kop, m, _ = tok.colour
            count[m] += 1
            work[m] += tb.dur[j, kop]
        Mn[:, 3] = count[1:] / inst.n_jobs
        Mn[:, 4] = work[1:] / sc

        T = np.zeros((self.max_tools, len(TOOL_FEATURES)), dtype=np.float64)
        if inst.has_tools:
            nt = inst.n_tools
            T[:nt, 0] = 1.0
            T[:nt, 1] = np.asarray(s.tool_loc[1:nt + 1], dtype=np.float64) / mm
            for tok in s.p_tool_free.tokens():
                T[tok.colour[0] - 1, 2] = 1.0
        A = self._vehicles(self.max_agvs, s.n_agvs, s.agv_loc, s.agv_free_at, s.agv_work,
                           {c[0] for c in s.idle_agvs()}, inst.agv_travel, req[2] if req else None, now, sc, mm)
        treq = s.awaiting_transporter()
        R = self._vehicles(self.max_tts, s.n_tts, s.tt_loc, s.tt_free_at, s.tt_work,
                           {c[0] for c in s.idle_transporters()}, inst.tool_travel, treq[1] if treq else None,
                           now, sc, mm)
        obs = np.concatenate([g, J.astype(np.float32).ravel(), M.astype(np.float32).ravel(),
                              T.astype(np.float32).ravel(), A.ravel(), R.ravel()])
        return np.clip(obs, -1.0, OBS_HIGH, out=obs)
