"""Gymnasium environment over the shop net: ``fms/Shop-v0``.

Actions are the net's controllable transitions, laid out in padded blocks so that one policy can serve every
instance up to a maximum size::

    [ job 0 .. job max_jobs-1 | AGV 0 .. AGV max_agvs-1 | transporter 0 .. max_tts-1 ]

``action_masks()`` (the sb3-contrib MaskablePPO hook, also ``info["action_mask"]``) is True exactly where the
net's guard enables the transition; padded slots are always False. An action the mask forbids is never
ignored: by default (``invalid_action="penalty"``, so that any action of the space can be stepped, as
Gymnasium requires) it ends the episode with ``invalid_penalty`` and ``info["invalid_action"] = True``; with
``invalid_action="raise"`` it raises :class:`~fms_sim.petri.InvalidAction` (the engine always raises).

Observation (float32, fixed size, zero-padded): global features, then one row per job, machine, tool, AGV and
transporter slot (see :data:`JOB_FEATURES` etc.). Times are divided by a per-instance scale (total work / number
of machines, a makespan lower bound), so instances of different sizes look alike. Features and the lower bound
are computed with numpy from per-instance tables (suffix sums per job, remaining load per machine), rebuilt
only when the instance changes (live orders), so a 100x20 instance does not re-sum every job at every step.

Rewards (``reward=``):

* ``"idle"`` — the paper's: ``-(idle machines / machines)`` after every decision but the last (0: the shop is done);
* ``"makespan"`` — sparse: ``-makespan / scale`` at the end, 0 before;
* ``"shaped"`` — ours: potential-based on a makespan estimate ``LB`` (:meth:`ShopEnv._lower_bound`): the largest of
  the clock, the latest end recorded so far, the clock plus the most work a job has not begun, and per machine its
  busy-until (or the clock) plus the work not begun on it. "Not begun" counts from the operations whose
  processing has started on the full net and from the dispatched ones on the paper's net, where a dispatched
  operation's machine is not yet busy: its work leaves ``LB`` until it starts, so ``LB`` can fall at a step and
  that step's reward be positive. Reward ``-(LB_after - LB_before) / scale``; the episode sum is ``-(makespan -
  LB_0) / scale`` whatever the steps, so it ranks schedules exactly as the makespan does while giving a signal at
  every step.

Disruptions (``disruptions=``, full net only): every episode runs in a shop disrupted by a scenario
(:class:`fms_sim.disruptions.Scenario`: noise on every duration, machine breakdowns), so that a policy can be
trained and judged where plans go stale. ``{"noise": spread, "breakdowns": n}`` draws a fresh scenario per
episode from the env's random generator (breakdowns start within the instance's work per machine); with
``"fixed": true`` the scenario depends only on the instance's name (and ``"seed"``), so evaluation rounds compare
like with like. ``reset(options={"scenario": sc})`` gives one explicitly. The policy learns a duration only when
the activity ends, as a live dispatcher does.
"""

from __future__ import annotations

import math
import numbers
import zlib
from functools import partial
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .disruptions import MAX_NOISE, Scenario
from .full_shop import DECISIONS, FullShop, make_shop
from .instance import Instance, require_instance
from .petri import InvalidAction, index_arg
from .shop import Shop

__all__ = ["ShopEnv", "padding_excess", "GLOBAL_FEATURES", "JOB_FEATURES", "MACHINE_FEATURES", "TOOL_FEATURES",
           "AGV_FEATURES", "TT_FEATURES", "REWARDS", "FULL_GLOBAL_FEATURES", "FULL_JOB_FEATURES",
           "FULL_TOOL_FEATURES", "FULL_BLOCKS", "DISRUPTION_KEYS", "check_disruptions",
           "episode_scenario"]

REWARDS = ("idle", "makespan", "shaped")
OBS_HIGH = 1000.0  # features are normalised; clipped here so the box is finite
GLOBAL_FEATURES = ("time", "ops_done", "phase_job", "phase_agv", "phase_tt", "n_jobs", "n_machines")
JOB_FEATURES = ("present", "legal", "ready", "next_machine", "next_duration", "remaining_work",
                "remaining_ops", "location", "waiting", "next_tool", "awaiting_agv")
MACHINE_FEATURES = ("present", "busy", "busy_for", "buffer", "queued_work")
TOOL_FEATURES = ("present", "location", "free")
AGV_FEATURES = ("present", "idle", "location", "busy_for", "work", "to_pickup")
TT_FEATURES = ("present", "idle", "location", "busy_for", "work", "to_tool")
#: appended with ``decisions="full"``: the full net's decision points
FULL_GLOBAL_FEATURES = ("phase_start", "phase_tool", "phase_use", "hold_allowed")
FULL_JOB_FEATURES = ("legal_start", "buffered", "legal_use", "request_due", "dispatched_ahead", "tool_due",
                     "start_estimate")
FULL_TOOL_FEATURES = ("legal_tool", "reserved", "running", "queued", "chosen", "requests", "due")
#: the full net's action blocks after the paper's (job, agv, tt), in this order
FULL_BLOCKS = ("start", "tool", "use", "hold")
#: every kind of full-net action
FULL_KINDS = ("job", "agv", "tt") + FULL_BLOCKS


#: where the full net's start, tool and use actions, and hold, are in :data:`FULL_KINDS`
_START_TOOL_USE = tuple(FULL_KINDS.index(k) for k in ("start", "tool", "use"))
_FULL_G = np.array(_START_TOOL_USE + (FULL_KINDS.index("hold"),))

DISRUPTION_KEYS = ("noise", "breakdowns", "fixed", "seed")


def check_disruptions(disruptions: dict[str, Any] | None, decisions: str = "full") -> dict[str, Any] | None:
    """The validated ``disruptions`` of an env (see the module docstring); None or an empty dict: none. Raises
    ValueError for an unknown key, a negative noise or breakdown count, or disruptions on the paper's net."""
    if not disruptions:
        return None
    if not isinstance(disruptions, dict):
        raise ValueError(f"disruptions must be a dict ({', '.join(DISRUPTION_KEYS)}), not {disruptions!r}")
    unknown = sorted(set(disruptions) - set(DISRUPTION_KEYS))
    if unknown:
        raise ValueError(f"unknown disruption keys {unknown}; use {', '.join(DISRUPTION_KEYS)}")
    noise, bds = disruptions.get("noise", 0.0), disruptions.get("breakdowns", 0)
    seed, fixed = disruptions.get("seed", 0), disruptions.get("fixed", False)
    flag = (bool, np.bool_)  # numpy's scalars are numbers like Python's (a np.int64 count was refused)
    if not isinstance(noise, numbers.Real) or isinstance(noise, flag) or not 0 <= float(noise) <= MAX_NOISE:
        raise ValueError(f"disruption noise must be a spread from 0 to {MAX_NOISE:g}, got {noise!r}")
    if not isinstance(bds, numbers.Integral) or isinstance(bds, flag) or bds < 0:
        raise ValueError(f"disruption breakdowns must be an integer >= 0, got {bds!r}")
    if not isinstance(seed, numbers.Integral) or isinstance(seed, flag):  # True was taken as seed 1
        raise ValueError(f"disruption seed must be an integer, got {seed!r}")
    if not isinstance(fixed, flag):  # "no" was taken as True
        raise ValueError(f"disruption fixed must be true or false, got {fixed!r}")
    if decisions != "full":
        raise ValueError("disruptions run on the full-decision net only (decisions='full')")
    return {"noise": float(noise), "breakdowns": int(bds), "fixed": bool(fixed), "seed": int(seed)}


def episode_scenario(inst: Instance, disruptions: dict[str, Any], rng: np.random.Generator | None = None
                     ) -> Scenario:
    """An episode's scenario on ``inst`` under validated ``disruptions`` (:func:`check_disruptions`): drawn from
    ``rng``, or with ``fixed`` (or without ``rng``) from the instance's name and the ``seed``; breakdowns start
    within the instance's work per machine."""
    d = disruptions
    if d.get("fixed") or rng is None:
        seed = zlib.crc32(f"{d.get('seed', 0)}:{inst.name}".encode())
    else:
        seed = int(rng.integers(2 ** 31))
    horizon = max(1, sum(o.duration for ops in inst.jobs for o in ops) // inst.n_machines)
    return Scenario.draw(inst, noise=d.get("noise", 0.0), breakdowns=d.get("breakdowns", 0), horizon=horizon,
                         seed=seed)


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
        self.dur_list: list[list[int]] = self.dur.tolist()  # the same, for reads of one item at a time
        self.travel: np.ndarray | None = None  # the AGV travel matrix as an array, made when first needed

    def serves(self, inst: Instance) -> bool:
        """Whether these tables describe ``inst`` too: its own, or an equal copy's (a twin's, a live order's
        continuation) — the same jobs, machines and AGV travel times (the tables hold all three; the BU shops
        share their jobs across layouts, and one layout's travel times observed another's)."""
        mine = self.instance
        return inst is mine or (inst.jobs == mine.jobs and inst.n_machines == mine.n_machines
                                and inst.agv_travel == mine.agv_travel)


def padding_excess(inst: Instance, padding: dict[str, int]) -> tuple[str, int, int] | None:
    """The first dimension in which ``inst`` exceeds ``padding`` (``max_jobs``, ``max_machines``, ``max_tools``,
    ``max_agvs``, ``max_tts``) as ``(what, the instance's count, the padded maximum)``; None if it fits."""
    for what, n, cap in (("jobs", inst.n_jobs, padding["max_jobs"]),
                         ("machines", inst.n_machines, padding["max_machines"]),
                         ("tools", inst.n_tools if inst.has_tools else 0, padding["max_tools"]),
                         ("AGVs", inst.n_agvs, padding["max_agvs"]),
                         ("tool transporters", inst.n_tool_transporters, padding["max_tts"])):
        if n > cap:
            return what, n, cap
    return None


def _draw_one(known: list[Instance], rng: np.random.Generator) -> Instance:
    """One of ``known``, drawn uniformly by ``rng``: the env's sampler over a sequence of instances."""
    return known[int(rng.integers(len(known)))]


class ShopEnv(gym.Env):
    """Dispatching environment; see the module docstring for spaces and rewards.

    ``instances``: one :class:`Instance`, a sequence (one drawn at random per episode — training on sets), or a
    callable ``rng -> Instance``. ``max_*``: padding sizes (default: the largest among the given instances).
    """

    metadata = {"render_modes": []}

    def __init__(self, instances: Instance | Sequence[Instance] | Callable[[np.random.Generator], Instance],
                 *, reward: str = "shaped", max_jobs: int | None = None, max_machines: int | None = None,
                 max_tools: int | None = None, max_agvs: int | None = None, max_tts: int | None = None,
                 invalid_action: str = "penalty", invalid_penalty: float = -10.0, decisions: str = "paper",
                 disruptions: dict[str, Any] | None = None, render_mode: str | None = None):
        if render_mode is not None:  # gymnasium passes render_mode=None to every env it makes
            # a TypeError, as for an argument the env does not take: sb3's make_vec_env asks for 'rgb_array' and
            # goes on without a render mode on a TypeError only (a ValueError stopped it)
            raise TypeError(f"this env renders nothing (no render modes), got render_mode {render_mode!r}")
        self.render_mode = None
        if decisions not in DECISIONS:
            raise ValueError(f"unknown decisions {decisions!r}; choose from {', '.join(DECISIONS)}")
        self.decisions = decisions
        self.disruptions = check_disruptions(disruptions, decisions)
        if reward not in REWARDS:
            raise ValueError(f"unknown reward {reward!r}; choose from {', '.join(REWARDS)}")
        if invalid_action not in ("raise", "penalty"):
            raise ValueError("invalid_action must be 'raise' or 'penalty'")
        if isinstance(instances, Instance):
            instances = [instances]
        if callable(instances):
            self._sample = instances
            known: list[Instance] = []
        else:
            if isinstance(instances, (str, bytes)):  # a name is not an instance (and would be read letter by letter)
                raise TypeError(f"ShopEnv takes Instance objects, not the name {instances!r} "
                                "(fms_sim.formats.load_instance reads one)")
            known = list(instances)
            if not known:
                raise ValueError("ShopEnv needs at least one instance")
            bad = next((i for i in known if not isinstance(i, Instance)), None)
            if bad is not None:
                raise TypeError(f"ShopEnv takes Instance objects, got {type(bad).__name__} {bad!r:.60}")
            self._sample = partial(_draw_one, known)  # (a lambda made the env unpicklable)
        if not known and None in (max_jobs, max_machines, max_tools, max_agvs, max_tts):
            raise ValueError("with an instance sampler, give every max_* size")
        for key, v, least in (("max_jobs", max_jobs, 1), ("max_machines", max_machines, 1), ("max_tools", max_tools, 0),
                              ("max_agvs", max_agvs, 0), ("max_tts", max_tts, 0)):
            if v is not None and (not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < least):
                raise ValueError(f"{key} must be an integer >= {least} (None: the largest of the instances), "
                                 f"got {v!r}")
        self.max_jobs = int(max_jobs) if max_jobs is not None else max(i.n_jobs for i in known)
        self.max_machines = int(max_machines) if max_machines is not None else max(i.n_machines for i in known)
        self.max_tools = int(max_tools) if max_tools is not None else max(i.n_tools for i in known)
        self.max_agvs = int(max_agvs) if max_agvs is not None else max(i.n_agvs for i in known)
        self.max_tts = int(max_tts) if max_tts is not None else max(i.n_tool_transporters for i in known)
        for i in known:
            self._check_fits(i)
        self.reward_mode = reward
        self.invalid_action = invalid_action
        if (not isinstance(invalid_penalty, (int, float, np.integer, np.floating)) or isinstance(invalid_penalty, bool)
                or not math.isfinite(invalid_penalty)):  # NaN: every invalid action's return NaN
            raise ValueError(f"invalid_penalty must be a finite number, got {invalid_penalty!r}")
        self.invalid_penalty = float(invalid_penalty)
        self.n_actions = self.max_jobs + self.max_agvs + self.max_tts
        size = (len(GLOBAL_FEATURES) + self.max_jobs * len(JOB_FEATURES) + self.max_machines * len(MACHINE_FEATURES)
                + self.max_tools * len(TOOL_FEATURES) + self.max_agvs * len(AGV_FEATURES)
                + self.max_tts * len(TT_FEATURES))
        if decisions == "full":
            # [job | agv | tt | start 0..max_jobs-1 | tool 1..max_tools | use 0..max_jobs-1 | hold]
            self._offset = {"job": 0, "agv": self.max_jobs, "tt": self.max_jobs + self.max_agvs,
                            "start": self.n_actions, "tool": self.n_actions + self.max_jobs - 1,
                            "use": self.n_actions + self.max_jobs + self.max_tools,
                            "hold": self.n_actions + 2 * self.max_jobs + self.max_tools}
            self.n_actions += 2 * self.max_jobs + self.max_tools + 1
            size += (len(FULL_GLOBAL_FEATURES) + self.max_jobs * len(FULL_JOB_FEATURES)
                     + self.max_tools * len(FULL_TOOL_FEATURES))
        self.action_space = spaces.Discrete(self.n_actions)
        self.observation_space = spaces.Box(low=-1.0, high=OBS_HIGH, shape=(size,), dtype=np.float32)
        self.shop: Shop | None = None
        self._ended = False  # the episode ended (the shop finished, or an invalid action under "penalty")
        self.instance: Instance | None = None
        self._tables: _Tables | None = None
        self._tables_for: Instance | None = None
        self._scaled: tuple | None = None  # see _scaled_tables

    def _check_fits(self, inst: Instance) -> None:
        over = padding_excess(inst, dict(max_jobs=self.max_jobs, max_machines=self.max_machines,
                                         max_tools=self.max_tools, max_agvs=self.max_agvs, max_tts=self.max_tts))
        if over is not None:
            what, n, cap = over
            raise ValueError(f"instance {inst.name} has {n} {what}, more than this env's maximum {cap}")

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if options is not None and not isinstance(options, dict):
            raise TypeError(f"reset's options must be a dict (instance, scenario) or None, got {options!r:.60}")
        unknown = sorted(map(str, set(options or ()) - {"instance", "scenario"}))
        if unknown:  # a misspelt key ran another instance, or without the scenario, silently
            raise ValueError(f"unknown reset options {unknown}; use instance, scenario")
        inst = require_instance((options or {}).get("instance") or self._sample(self.np_random),
                                "the env's episode (reset's options['instance'] or its instance sampler)")
        self._check_fits(inst)
        scenario = (options or {}).get("scenario")
        if scenario is None and self.disruptions is not None:
            scenario = self.draw_scenario(inst)
        shop = make_shop(inst, self.decisions, scenario)  # (before the env changes: a scenario refused here left the
        self.instance, self.shop = inst, shop  # new instance beside the old run, which step then went on with)
        self._ended = False
        self._map_actions()
        self._scale = max(1.0, sum(o.duration for ops in inst.jobs for o in ops) / inst.n_machines)
        self._total_ops = inst.n_operations
        self._lb = self._lower_bound()
        self._lb0 = self._lb
        return self._obs(), self._info()

    def draw_scenario(self, inst: Instance) -> Scenario:
        """The scenario of an episode on ``inst`` under this env's ``disruptions`` (see the module docstring)."""
        return episode_scenario(inst, self.disruptions or {}, self.np_random)

    def step(self, action: int):
        shop = self.shop
        if shop is None:
            raise RuntimeError("call reset() before step()")
        if self._ended:  # was answered as an invalid action (-10), as if the finished shop could go on
            raise RuntimeError("the episode has ended; call reset() before step()")
        a = index_arg(action)  # 0.9 and "0" were taken as action 0 (neither is in the action space)
        net_action = self._to_net(a)
        if net_action is None or not self._mask_net()[net_action]:
            if self.invalid_action == "raise":
                legal = [self._from_net(x) for x in shop.legal_actions()]
                raise InvalidAction(f"action {a} is not allowed now (legal: {legal})")
            self._ended = True
            return self._obs(), self.invalid_penalty, True, False, self._info(invalid=True)
        shop.act(net_action)
        terminated = self._ended = shop.done
        if self.reward_mode == "idle":
            reward = -shop.idle_machines() / self.instance.n_machines if not terminated else 0.0
        elif self.reward_mode == "makespan":
            reward = -shop.makespan / self._scale if terminated else 0.0
        else:
            lb = shop.makespan if terminated else self._lower_bound()
            reward = -(lb - self._lb) / self._scale
            self._lb = lb
        info = self._info()
        if terminated:
            info["makespan"] = shop.makespan
        return self._obs(), float(reward), terminated, False, info

    def render(self) -> None:
        """Nothing: the env has no render modes (``render_mode`` is None), and Gymnasium's ``render`` then computes
        no render and returns None. It raised NotImplementedError (gymnasium's base method), also through
        ``gym.make`` and its wrappers."""
        return None

    def action_masks(self) -> np.ndarray:
        m = np.zeros(self.n_actions, dtype=bool)
        if self.shop is None or self.shop.done or self._ended:  # ended by an invalid action too: step refuses all
            return m
        if self.decisions == "full":  # one table lookup for all legal actions
            m[self._net_to_env_arr[self.shop.legal_actions()]] = True
            return m
        for a in self.shop.legal_actions():
            m[self._from_net(a)] = True
        return m

    # ------------------------------------------------------------------ action mapping
    def _map_actions(self) -> None:
        """Build the full net's action index maps for the current shop (its actions depend on its jobs)."""
        if self.decisions != "full":
            return
        if not isinstance(self.shop, FullShop):
            raise ValueError("an env with decisions='full' observes a FullShop, not the paper's Shop")
        kinds = [self.shop.action_kind(a) for a in range(self.shop.n_actions)]
        self._net_to_env = [self._offset[k] + n for k, n in kinds]
        self._net_to_env_arr = np.array(self._net_to_env, dtype=np.int64)
        self._env_to_net = {e: a for a, e in enumerate(self._net_to_env)}
        # each net action's kind (index in FULL_KINDS) and number, for reading legal actions by kind at once
        self._kind_code = np.array([FULL_KINDS.index(k) for k, _ in kinds], dtype=np.int64)
        self._kind_num = np.array([n for _, n in kinds], dtype=np.int64)

    def legal_of_kind(self, legal: list[int], kind: str) -> np.ndarray:
        """The numbers (job, tool, vehicle) of the legal full-net actions of ``kind``."""
        la = np.asarray(legal, dtype=np.int64)
        return self._kind_num[la[self._kind_code[la] == FULL_KINDS.index(kind)]]

    def _to_net(self, a: int) -> int | None:
        s = self.shop
        if self.decisions == "full":
            return self._env_to_net.get(a)
        if 0 <= a < self.max_jobs:
            return a if a < s.n_jobs else None
        a -= self.max_jobs
        if 0 <= a < self.max_agvs:
            return s.n_jobs + a if a < s.n_agvs else None
        a -= self.max_agvs
        if 0 <= a < self.max_tts:
            return s.n_jobs + s.n_agvs + a if a < s.n_tts else None
        return None

    def _from_net(self, a: int) -> int:
        s = self.shop
        if self.decisions == "full":
            return self._net_to_env[a]
        if a < s.n_jobs:
            return a
        if a < s.n_jobs + s.n_agvs:
            return self.max_jobs + a - s.n_jobs
        return self.max_jobs + self.max_agvs + a - s.n_jobs - s.n_agvs

    def _mask_net(self) -> list[bool]:
        return self.shop.action_mask()

    def _info(self, invalid: bool = False) -> dict[str, Any]:
        info = {"action_mask": self.action_masks(), "time": self.shop.now}
        if invalid:
            info["invalid_action"] = True
        return info

    # ------------------------------------------------------------------ features
    def _t(self) -> _Tables:
        inst = self.shop.instance
        if self._tables_for is not inst:
            tb = self._tables
            if tb is None or not tb.serves(inst):
                tb = _Tables(inst)
            self._tables, self._tables_for = tb, inst
        return self._tables

    def _scaled_tables(self, tb: _Tables) -> tuple[np.ndarray, np.ndarray]:
        """The job features read from the instance tables, scaled once per instance and padding: per (job,
        operation) its machine / max machines, duration / scale and remaining work / scale side by side, and its
        tool / max tools (the same divisions the observation made per decision)."""
        key = (tb, self.max_machines, self._scale, self.max_tools)
        if self._scaled is None or self._scaled[0] != key:
            sc = self._scale
            both = (np.stack([tb.mach / self.max_machines, tb.dur / sc, tb.suffix / sc], axis=-1),
                    tb.tool / max(1, self.max_tools))
            self._scaled = (key, both)
        return self._scaled[1]

    def _lower_bound(self) -> int:
        s = self.shop
        tb = self._t()
        now = s.now
        lb = max(now, s.makespan)
        # work not yet begun: on the full net a part can be dispatched ahead of its operation, so count from the
        # operations whose processing has started there (the paper's net starts an operation when it dispatches)
        k = np.asarray(s.started if isinstance(s, FullShop) else s.job_started_ops, dtype=np.int64)
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
        if self.decisions == "full":  # the decision's kinds from the action table (no kind lookup per action)
            codes, nums = self._kind_code[legal], self._kind_num[legal]
            open_ = np.zeros(len(FULL_KINDS), dtype=bool)
            open_[codes] = True
            job, agv, tt = open_[0], open_[1], open_[2]
            # the jobs whose dispatch is legal (a shop without AGVs has no job actions: its first actions are others)
            legal_jobs = nums[codes == 0].tolist() if job else []
        else:
            kinds = s.decision_kind() or ""
            job, agv, tt = "job" in kinds, "agv" in kinds, "tt" in kinds
        g = np.array((now / sc, sum(s.job_done_ops) / self._total_ops, job, agv, tt, inst.n_jobs / self.max_jobs,
                      inst.n_machines / self.max_machines), dtype=np.float32)
        req = s.awaiting_agv()

        k = np.asarray(s.job_started_ops, dtype=np.int64)
        at = [-1] * n  # each part's location, read into a list (a numpy item write per token costs several times more)
        for bucket in s.p_parts.buckets.values():
            for tok in bucket:
                c = tok.colour
                at[c[0]] = c[2]
        loc = np.array(at, dtype=np.int64)
        present = loc >= 0
        kk = np.minimum(k, tb.nops)  # tables are padded with zeros past the last operation
        J = np.zeros((self.max_jobs, len(JOB_FEATURES)), dtype=np.float64)
        Jn = J[:n]
        Jn[:, 0] = 1.0
        if self.decisions != "full":  # the paper net's first n actions dispatch the jobs
            legal_jobs = [a for a in legal if a < n]
        Jn[legal_jobs, 1] = 1.0
        Jn[:, 2] = present
        # the next operation's machine, duration and remaining work, and its tool, scaled (0 past the last operation:
        # the tables are padded with zeros there)
        scaled, scaled_tool = self._scaled_tables(tb)
        Jn[:, 3:6] = scaled[tb.rows, kk]
        Jn[:, 9] = scaled_tool[tb.rows, kk]
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
        count = [0] * (nm + 1)
        work = [0] * (nm + 1)
        dur = tb.dur_list
        for bucket in s.p_buffer.buckets.values():
            for tok in bucket:
                j, kop, m = tok.colour[:3]
                count[m] += 1
                work[m] += dur[j][kop]
        Mn[:, 3] = np.array(count[1:], dtype=np.int64) / inst.n_jobs
        Mn[:, 4] = np.array(work[1:], dtype=np.int64) / sc

        T = np.zeros((self.max_tools, len(TOOL_FEATURES)), dtype=np.float64)
        if inst.has_tools:
            nt = inst.n_tools
            T[:nt, 0] = 1.0
            T[:nt, 1] = np.asarray(s.tool_loc[1:nt + 1], dtype=np.float64) / mm
            if isinstance(s, FullShop):
                T[:nt, 2] = [s.tool_user[t] is None for t in range(1, nt + 1)]
            else:
                for tok in s.p_tool_free.tokens():
                    T[tok.colour[0] - 1, 2] = 1.0
        A = self._vehicles(self.max_agvs, s.n_agvs, s.agv_loc, s.agv_free_at, s.agv_work,
                           {c[0] for c in s.idle_agvs()}, inst.agv_travel, req[2] if req else None, now, sc, mm)
        treq = s.awaiting_transporter()
        R = self._vehicles(self.max_tts, s.n_tts, s.tt_loc, s.tt_free_at, s.tt_work,
                           {c[0] for c in s.idle_transporters()}, inst.tool_travel, treq[1] if treq else None,
                           now, sc, mm)
        parts = [g, J.astype(np.float32).ravel(), M.astype(np.float32).ravel(), T.astype(np.float32).ravel(),
                 A.ravel(), R.ravel()]
        if isinstance(s, FullShop):
            parts += self._full_features(s, codes, nums, loc, open_)  # (observed with decisions='full')
        obs = np.concatenate(parts)
        return np.clip(obs, -1.0, OBS_HIGH, out=obs)

    def _full_features(self, s: FullShop, codes: np.ndarray, nums: np.ndarray, loc: np.ndarray,
                       open_: np.ndarray) -> list[np.ndarray]:
        """The full net's decision points: which starts, tool take-ups and request choices are offered, where
        the parts and tools stand in their reservations. ``codes`` and ``nums``: the kind (indexed as
        :data:`FULL_KINDS`) and number of each legal action; ``loc``: each job's part location (-1: none or on a
        vehicle), as :meth:`_obs` read it; ``open_``: which kinds of action are legal, as :meth:`_obs` read them."""
        inst = self.instance
        empty = nums[:0]
        starts, tools, uses = (nums[codes == i] if open_[i] else empty for i in _START_TOOL_USE)
        g = open_[_FULL_G].astype(np.float32)
        J = np.zeros((self.max_jobs, len(FULL_JOB_FEATURES)), dtype=np.float32)
        J[starts, 0] = 1.0
        J[uses, 2] = 1.0
        chosen = s.tool_choice
        tb = self._t()
        n = inst.n_jobs
        rows = tb.rows
        k = np.asarray(s.started, dtype=np.int64)             # each job's next operation to start
        kk = np.minimum(k, tb.nops)
        buffered = np.zeros(n, dtype=bool)
        buffered[list(s.p_buffer.buckets)] = True  # the full net's buffer is keyed by job
        J[:n, 1] = buffered
        if chosen is not None:
            started = s.started
            J[[j for j, ks in s.treq[chosen].items() if ks[0] == started[j]], 3] = 1.0
        dispatched = np.asarray(s.job_started_ops, dtype=np.int64)
        done = np.asarray(s.job_done_ops, dtype=np.int64)
        J[:n, 4] = dispatched > done + 1
        # the part of each job's next operation is on its way (FullShop.part_on_its_way, for all jobs at once)
        prev_m = tb.mach[rows, np.maximum(kk - 1, 0)]
        m = tb.mach[rows, kk]
        if inst.has_agvs:
            on_way = buffered | (dispatched > k) | ((k > 0) & (prev_m == m))
        else:
            on_way = buffered | (k > 0) | (loc >= 0)
        on_way &= k < tb.nops
        due_count = [0] * (inst.n_tools + 1 if inst.has_tools else 1)
        if inst.has_tools:  # due tool requests (FullShop.due_tool_request), read from the pending requests
            # a request is due only for a job's next operation, so only that operation's tool is looked up (not
            # every pending request of every tool: hundreds on a 100-job shop). FullShop._candidate inlined: for
            # the job's next operation to start the reservation closes no circular wait (_safe is True at once),
            # so the request may be served where the tool is at its machine or a transporter is idle in service
            treq, nxt, tk = s.treq, k.tolist(), tb.tool[rows, kk]
            servable: dict[int, bool] = {}
            tkl, ml, tool_loc = tk.tolist(), m.tolist(), s.tool_loc
            carried = s._in_service("tt", s.p_tt_idle)
            due = []
            for j in np.flatnonzero(on_way & (tk > 0)).tolist():
                t = tkl[j]
                ks = treq[t].get(j)
                if not ks or ks[0] != nxt[j]:
                    continue
                ok = servable.get(t)
                if ok is None:
                    ok = servable[t] = s._servable(t)
                if ok and (carried or tool_loc[t] == ml[j]):
                    due.append(j)
                    due_count[t] += 1
            J[due, 5] = 1.0
        J[:n, 6] = self._start_estimates(s, tb, k, m, prev_m, buffered, done, loc) / self._scale
        T = np.zeros((self.max_tools, len(FULL_TOOL_FEATURES)), dtype=np.float32)
        if inst.has_tools:
            T[tools - 1, 0] = 1.0
            nt, nj = inst.n_tools, inst.n_jobs
            user, running, nxt_use, treq = s.tool_user, s.tool_running, s.tool_next, s.treq
            # column by column (numpy converts a flat list of numbers much faster than a list of rows)
            T[:nt, 1] = [u is not None for u in user[1:nt + 1]]
            T[:nt, 2] = running[1:nt + 1]
            T[:nt, 3] = [u is not None for u in nxt_use[1:nt + 1]]
            if chosen is not None and 1 <= chosen <= nt:
                T[chosen - 1, 4] = 1.0
            T[:nt, 5] = [len(q) / max(1, nj) for q in treq[1:nt + 1]]
            T[:nt, 6] = [c / nj for c in due_count[1:nt + 1]]
        return [g, J.ravel(), T.ravel()]

    @staticmethod
    def _start_estimates(s: FullShop, tb: "_Tables", k: np.ndarray, m: np.ndarray, prev_m: np.ndarray,
                         buffered: np.ndarray, done: np.ndarray, here: np.ndarray) -> np.ndarray:
        """Per job, the time from now until its next operation to start (``k``, on machine ``m``; ``prev_m`` the
        machine of the one before) could start: when the part can be there (buffered now; else free now at
        ``here`` or when its running operation ends, plus the AGV trip) and the machine is free. Vehicles and
        tools are not counted; 0 for a finished job."""
        inst, now = s.instance, s.now
        busy = np.asarray(s.machine_busy_until, dtype=np.int64)
        if inst.has_agvs:
            if tb.travel is None:
                tb.travel = np.asarray(inst.agv_travel, dtype=np.int64)
            travel = tb.travel
        free = done >= k
        if inst.has_agvs:  # (no travel within a location: the travel matrices' diagonals are 0)
            free_part = now + np.where(here >= 0, travel[np.maximum(here, 0), m], 0)
            run_part = np.maximum(now, busy[prev_m]) + travel[prev_m, m]
        else:
            free_part = np.full(tb.n, now, dtype=np.int64)
            run_part = np.maximum(now, busy[prev_m])
        part = np.where(buffered, now, np.where(free, free_part, run_part))
        est = np.maximum(part, busy[m]) - now  # part >= now in every case above
        return np.where(k < tb.nops, est, 0).astype(np.float64)

    @staticmethod
    def _vehicles(cap: int, n: int, loc: list[int], free_at: list[int], work: list[int], idle: set[int],
                  travel, target: int | None, now: int, sc: float, mm: int) -> np.ndarray:
        V = np.zeros((cap, len(AGV_FEATURES)), dtype=np.float32)
        if n:
            at = loc[:n]
            rows = V[:n]
            rows[:, 0] = 1.0
            rows[:, 1] = [v in idle for v in range(n)]
            rows[:, 2] = np.divide(at, mm)
            rows[:, 3] = np.maximum(0, np.subtract(free_at[:n], now)) / sc
            rows[:, 4] = np.divide(work[:n], sc)
            if target is not None:
                rows[:, 5] = [travel[x][target] / sc for x in at]
        return V
