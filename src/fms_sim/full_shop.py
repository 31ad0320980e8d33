"""The full-decision shop net: every valid schedule is reachable through its decisions.

The paper's net (:class:`fms_sim.shop.Shop`, ``decisions="paper"``) decides only which job goes next and which
vehicle carries it; tools serve their requests FIFO by dispatch stamp, machines start the smallest stamp, a job
is dispatched only when its part is ready, and time passes only when nothing can be done. On tool-sharing shops
that decision space is the limit of every method that decides through it. :class:`FullShop`
(``decisions="full"``) keeps the same jobs, AGV, tools and machines blocks but makes the remaining choices
controllable, each a transition whose guard gives its mask:

* **dispatch ahead** — ``job:J`` hands job J's next transport to an AGV (``agv:V`` follows at once) as soon as
  the operation before it has *started*; the AGV deadheads to the pickup and waits there for the part. A part
  whose next machine is the one it is on goes to that machine's buffer by itself when it is ready;
* **machine sequencing** — ``start:J`` starts job J's buffered operation when its machine is idle and (with
  tools) its tool is at the machine. Nothing starts by itself, so a machine may be kept for a later part;
* **tool-request selection** — ``tool:T`` takes up tool T, then ``use:J`` names the job whose next unserved
  operation on T it serves (then ``tt:R`` the transporter when the tool must travel). T may be taken up when it
  is free, or while a running operation uses it (the transporter then waits at the tool for that operation to
  end). Requests exist from the start, so a tool can be brought before its part has arrived (pre-fetch);
* **hold** — ``hold`` lets time pass to the next event instead of acting; offered only while something is in
  flight and no vehicle choice is pending, so it can never stall the run.

Deadlock: an AGV or transporter only ever waits for an operation that is running, so the only circular wait a
decider could build is among tools reserved for operations whose jobs still need other reserved tools first.
``use:J`` is masked out when serving that request would close such a cycle (a depth-first search over the
reserved operations; nearly always a trivial check), so every reachable state can finish. Every valid schedule
keeps its reservations acyclic, so none is excluded.

Action layout (indices in this order): ``job:0..n-1 | agv:0..A-1 | tt:0..R-1 | start:0..n-1 | tool:1..T |
use:0..n-1 | hold``; the first three blocks are the paper net's. Labels as shown.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from functools import partial
from .disruptions import Breakdown, Outage, Scenario, ScenarioError
from .instance import Instance, require_instance
from .petri import Arc, InvalidAction, Output, Place, Transition, index_arg
from .schedule import AgvTrip, OperationRecord, Schedule, ToolTrip
from .shop import _P_ALLOC, _P_DONE, _P_JOB, _P_VEHICLE, Shop, ShopState

__all__ = ["FullShop", "DECISIONS", "make_shop", "HOLD"]

#: the nets a decider can run on: the paper's (FIFO tools, ready-only dispatch, stamp-order starts) and ours
DECISIONS = ("full", "paper")
HOLD = "hold"
_P_DISRUPT = -1  # disruptions take effect before anything else happens at their time
_P_USE = 4  # after tool:T, the request it serves comes before anything else (then the transporter, at 5)
_KIND_ORDER = {"job": 0, "agv": 1, "tt": 2, "start": 3, "tool": 4, "use": 5}

#: state kept beside the marking (copied by save_state, hashed by state_key)
_FULL_STATE = ("disp_next", "started", "m_idle", "buf_at", "tool_ready_for", "tool_user", "tool_running",
               "tool_next", "treq", "treq_at", "tool_choice", "tt_waiting", "_use_cands", "m_down", "out", "_trips",
               "_running_rec")


def make_shop(instance: Instance, decisions: str = "full", scenario: Scenario | None = None) -> Shop:
    """A runnable shop net for ``instance`` with the paper's decisions or the full ones (see :data:`DECISIONS`);
    ``scenario`` (breakdowns, outages, noise) needs the full one."""
    if decisions == "full":
        return FullShop(instance, scenario=scenario)
    if decisions == "paper":
        if scenario is not None and not scenario.empty:
            raise ValueError("disruptions (a scenario or noise) run on the full-decision net only")
        return Shop(instance)
    raise ValueError(f"unknown decisions {decisions!r}; choose from {', '.join(DECISIONS)}")


class FullShop(Shop):
    """The shop net with every decision controllable (module docstring); the API of :class:`Shop` plus the
    ``hold`` action (the last index)."""

    decisions = "full"

    def __init__(self, instance: Instance, *, incremental: bool = True, scenario: Scenario | None = None):
        if scenario is not None and not isinstance(scenario, Scenario):
            raise TypeError(f"scenario must be a Scenario (Scenario.from_dict reads a dict), got "
                            f"{type(scenario).__name__}")
        if scenario is not None:
            scenario.check(require_instance(instance, "FullShop"))
        self.scenario = scenario if scenario is not None and not scenario.empty else None
        self._kinds: list[tuple[str, int]] = []  # action_kind per controllable transition, parsed once
        super().__init__(instance, incremental=incremental)

    # ------------------------------------------------------------------ building
    def _build(self) -> None:
        inst, net = self.instance, self.net
        n, M = inst.n_jobs, inst.n_machines
        self.p_parts = net.add_place("parts", key=lambda c: c[0])
        self.p_done = net.add_place("done")
        self.p_buffer = net.add_place("buffer", key=lambda c: c[0])
        self.p_busy = net.add_place("busy", key=lambda c: c[2])
        for j in range(n):
            net.put(self.p_parts, (j, 0, 0))
        self.disp_next = [self._next_transport(j, 0) for j in range(n)]
        self.started = [0] * n
        self.m_idle = [True] * (M + 1)
        self.buf_at: list[set[int]] = [set() for _ in range(M + 1)]
        self.tool_ready_for: set[tuple[int, int]] = set()
        nt = inst.n_tools + 1
        self.tool_user: list[tuple[int, int] | None] = [None] * nt
        self.tool_running = [False] * nt
        self.tool_next: list[tuple[int, int] | None] = [None] * nt
        self.treq: list[dict[int, list[int]]] = [{} for _ in range(nt)]
        self.treq_at: list[dict[int, set[int]]] = [{} for _ in range(nt)]  # tool -> machine -> jobs next there
        self.tool_choice: int | None = None
        self.tt_waiting: list[int | None] = [None] * nt
        self._use_cands: list[int] = []
        self.m_down = [False] * (M + 1)                      # machines broken down now
        self.out = {"agv": [False] * self.n_agvs, "tt": [False] * self.n_tts}  # vehicles out of service now
        self._trips = {"agv": [0] * self.n_agvs, "tt": [0] * self.n_tts}      # legs driven (noise draws)
        self._last_leg: dict[tuple[str, int], int] = {}      # the time of the leg a vehicle just began
        self._running_rec: list[int] = [-1] * (M + 1)          # rec.ops index of the operation on each machine
        self.t_select: dict[tuple[str, int], Transition] = {}
        self._tool_ops: list[list[tuple[int, int]]] = []  # per job: (op, tool) of its operations with a tool
        self._danger_cache: dict[int, set[tuple[int, int]]] = {}  # see _danger
        self._wait_graph: tuple[dict, dict] | None = None  # see _wait_for
        self.t_job: list[Transition] = []
        self.t_start: list[Transition] = []
        self.t_use: list[Transition] = []
        self.t_tool: list[Transition] = []
        self.t_tt_load: list[Transition] = []
        self.t_agv_load: list[Transition] = []
        if inst.has_tools:
            self._tools_block_full()
        if inst.has_agvs:
            self._agv_block_full()
        for j in range(n):
            self._add_job(j)
        self._machines_block_full()
        self._disruptions_block()
        self._order_actions()

    def _next_transport(self, j: int, k: int) -> int:
        """The first operation index >= k of job j that needs an AGV (its part is elsewhere), or len(job)."""
        ops = self._jobs[j]
        if self.instance.has_agvs:
            while k < len(ops) and k > 0 and ops[k - 1].machine == ops[k].machine:
                k += 1
        return k

    def _add_job(self, j: int) -> None:
        """Per-job transitions (dispatch, part flow, start, request selection) and the job's tool requests."""
        net, inst = self.net, self.instance
        self._tool_ops.append([])
        for k, op in enumerate(self._jobs[j]):
            if inst.has_tools and op.tool is not None:
                if j not in self.treq[op.tool]:
                    self.treq_at[op.tool].setdefault(op.machine, set()).add(j)
                self.treq[op.tool].setdefault(j, []).append(k)
                self._tool_ops[j].append((k, op.tool))
        if inst.has_agvs:
            t = net.add_transition(Transition(
                name=f"select_job[{j}]", label=f"job:{j}", controllable=True, priority=_P_JOB, lazy=True,
                arcs=[Arc(self.p_agv_idle, kind="test", count_only=True)],
                guard=partial(self._job_ok, j), outputs=[Output(self.p_awaiting_agv, partial(self._request_of, j))],
                on_fire=partial(self._on_job, j)))
            self.t_job.append(t)
            if self.scenario is not None and any(o.kind == "agv" for o in self.scenario.outages):
                self._watch_outages("agv", [t])
            net.add_transition(Transition(
                name=f"stay[{j}]", priority=_P_ALLOC, arcs=[Arc(self.p_parts, "p", key=j)],
                guard=self._stays, outputs=[Output(self.p_buffer, self._to_buffer)], on_fire=self._on_buffered))
        else:
            net.add_transition(Transition(
                name=f"direct[{j}]", priority=_P_ALLOC, arcs=[Arc(self.p_parts, "p", key=j)],
                outputs=[Output(self.p_buffer, self._to_buffer)], on_fire=self._on_buffered))
        self.t_start.append(net.add_transition(Transition(
            name=f"start_job[{j}]", label=f"start:{j}", controllable=True, priority=_P_JOB,
            arcs=[Arc(self.p_buffer, "q", key=j)], guard=self._start_ok,
            outputs=[Output(self.p_busy, self._busy_token, delay=self._duration)], on_fire=self._on_start)))
        if inst.has_tools:
            self.t_use.append(net.add_transition(Transition(
                name=f"use_job[{j}]", label=f"use:{j}", controllable=True, priority=_P_USE, arcs=[],
                guard=partial(self._use_ok, j), on_fire=partial(self._on_use, j))))

    def _order_actions(self) -> None:
        def key(t: Transition) -> tuple[int, int]:
            kind, num = t.label.split(":")
            return _KIND_ORDER[kind], int(num)

        self.net.set_action_order(sorted(self.net.controllable, key=key))
        self._label_index = {t.label: i for i, t in enumerate(self.net.controllable)}
        self._label_index[HOLD] = len(self.net.controllable)

    # jobs and AGVs -------------------------------------------------------
    def _agv_block_full(self) -> None:
        net, inst = self.net, self.instance
        T = inst.agv_travel
        self.p_agv_pick, self.p_agv_drop = self._agv_places("agv_to_pickup", "agv_loaded_trip")
        for v in range(inst.n_agvs):
            # colour of trip tokens: (agv, job, op, pickup, machine)
            self._vehicle_choice("agv", v, self.p_awaiting_agv, self.p_agv_idle, self.p_agv_pick, T, 2,
                                 self._on_select_agv_full)
            self.t_agv_load.append(net.add_transition(Transition(
                name=f"agv_load[{v}]", priority=_P_DONE,
                arcs=[Arc(self.p_agv_pick, "e", key=v), Arc(self.p_parts, "p", key=lambda b: b["e"][1])],
                guard=self._agv_load_ok,
                outputs=[Output(self.p_agv_drop, lambda b: b["e"], delay=partial(self._loaded_leg, "agv", 3, 4))],
                on_fire=self._on_agv_load)))
            net.add_transition(Transition(
                name=f"agv_unload[{v}]", priority=_P_DONE, arcs=[Arc(self.p_agv_drop, "l", key=v)],
                outputs=[Output(self.p_buffer, lambda b: (b["l"][1], b["l"][2], b["l"][4])),
                         Output(self.p_agv_idle, lambda b: (b["l"][0], b["l"][4]))],
                on_fire=self._on_agv_unload))
        self.p_agv_orders = self._reposition_block("agv", self.p_agv_idle, inst.n_agvs, T,
                                                   partial(self._on_reposition_full, "agv"),
                                                   partial(self._reposition_leg, "agv"))

    def _vehicle_choice(self, kind: str, v: int, waiting: Place, idle: Place, to_pickup: Place, travel,
                        origin: int, on_fire) -> Transition:
        """The controllable choice ``KIND:V`` of an idle vehicle for the request waiting in ``waiting``: it
        deadheads from where it is to the request's field ``origin`` (a timed token in ``to_pickup``)."""
        t = self.net.add_transition(Transition(
            name=f"select_{kind}[{v}]", label=f"{kind}:{v}", controllable=True, priority=_P_VEHICLE,
            arcs=[Arc(waiting, "r", first=True), Arc(idle, "a", key=v)], guard=partial(self._serving, kind, v),
            outputs=[Output(to_pickup, lambda b: (b["a"][0],) + b["r"],
                            delay=partial(self._leg_to, kind, origin))],
            on_fire=on_fire))
        self.t_select[kind, v] = t
        return t

    def _serving(self, kind: str, v: int, b: dict) -> bool:
        return not self.out[kind][v]

    def _leg(self, kind: str, v: int, a: int, z: int) -> int:
        """The time of the leg ``a -> z`` that vehicle ``v`` of ``kind`` begins now (noise drawn per leg)."""
        travel = self.instance.agv_travel if kind == "agv" else self.instance.tool_travel
        t = travel[a][z]
        if a != z and self.scenario is not None:
            n = self._trips[kind][v]
            self._trips[kind][v] = n + 1
            t = self.scenario.trip_time(kind, v, n, t)
        self._last_leg[kind, v] = t
        return t

    def _leg_to(self, kind: str, origin: int, b: dict) -> int:
        return self._leg(kind, b["a"][0], b["a"][1], b["r"][origin])

    def _loaded_leg(self, kind: str, a: int, z: int, b: dict) -> int:
        e = b["e"]
        return self._leg(kind, e[0], e[a], e[z])

    def _reposition_leg(self, kind: str, b: dict) -> int:
        return self._leg(kind, b["a"][0], b["a"][1], b["o"][1])

    def _job_ok(self, j: int, b: dict) -> bool:
        k = self.disp_next[j]
        return k < len(self._jobs[j]) and self.started[j] >= k and self._in_service("agv", self.p_agv_idle)

    def _in_service(self, kind: str, idle: Place) -> bool:
        """Some vehicle of ``kind`` is idle and not out of service."""
        if not self.scenario:
            return idle.count > 0
        out = self.out[kind]
        return any(not out[c[0]] for c in idle.colours())

    def _request_of(self, j: int, b: dict) -> tuple:
        k = self.disp_next[j]
        return (j, k, self._jobs[j][k - 1].machine if k else 0, self._jobs[j][k].machine)

    def _on_job(self, j: int, b: dict, now: int) -> None:
        k = self.disp_next[j]
        self._stamp += 1
        self.job_started_ops[j] = k + 1
        self.disp_next[j] = self._next_transport(j, k + 1)
        self.pending_job = j
        self.net.touch(self.t_job[j])

    def _agv_load_ok(self, b: dict) -> bool:
        return b["p"][1] == b["e"][2] and not self.out["agv"][b["e"][0]]

    def _on_reposition_full(self, kind: str, b: dict, now: int) -> None:
        self._record_reposition(kind, b, now, self._last_leg[kind, b["a"][0]])  # the leg's drawn time

    def _on_select_agv_full(self, b: dict, now: int) -> None:
        v, here = b["a"]
        pickup = b["r"][2]
        t = self._last_leg["agv", v]
        if here != pickup:
            self.rec.agv.append(AgvTrip(v, None, None, here, pickup, now, now + t, False))
        self.agv_work[v] += t
        self.agv_loc[v] = pickup
        self.agv_free_at[v] = now + t  # at the pickup; the loaded trip starts when the part is ready
        self.pending_job = None

    def _on_agv_load(self, b: dict, now: int) -> None:
        v, j, k, pickup, m = b["e"]
        t = self._last_leg["agv", v]
        self.rec.agv.append(AgvTrip(v, j, k, pickup, m, now, now + t, True))
        self.agv_work[v] += t
        self.agv_loc[v] = m
        self.agv_free_at[v] = now + t

    def _on_agv_unload(self, b: dict, now: int) -> None:
        _, j, _, _, m = b["l"]
        self._buffered(j, m)

    def _stays(self, b: dict) -> bool:
        j, k, loc = b["p"]
        return k > 0 and self._jobs[j][k].machine == loc

    def _to_buffer(self, b: dict) -> tuple:
        j, k, _ = b["p"]
        return (j, k, self._jobs[j][k].machine)

    def _on_buffered(self, b: dict, now: int) -> None:
        j, k, _ = b["p"]
        if not self.instance.has_agvs:
            self.job_started_ops[j] = k + 1
        self._buffered(j, self._jobs[j][k].machine)

    def _buffered(self, j: int, m: int) -> None:
        self.buf_at[m].add(j)

    # machines -----------------------------------------------------------
    def _machines_block_full(self) -> None:
        net, inst = self.net, self.instance
        for m in range(1, inst.n_machines + 1):
            net.add_transition(Transition(
                name=f"end[{m}]", priority=_P_DONE, arcs=[Arc(self.p_busy, "x", key=m)],
                outputs=[Output(self.p_parts, self._next_part), Output(self.p_done, self._finished_part)],
                on_fire=self._on_end_full))

    def _busy_token(self, b: dict) -> tuple:
        j, k, m = b["q"]
        return (j, k, m, self._jobs[j][k].tool if self.instance.has_tools else None)

    def _duration(self, b: dict) -> int:
        j, k, _ = b["q"]
        nominal = self._jobs[j][k].duration
        return self.scenario.op_duration(j, k, nominal) if self.scenario is not None else nominal

    def _start_ok(self, b: dict) -> bool:
        j, k, m = b["q"]
        if not self.m_idle[m] or self.m_down[m]:
            return False
        return not self.instance.has_tools or self._jobs[j][k].tool is None or (j, k) in self.tool_ready_for

    def _on_start(self, b: dict, now: int) -> None:
        j, k, m = b["q"]
        op = self._jobs[j][k]
        tool = op.tool if self.instance.has_tools else None
        d = self._duration(b)
        self._running_rec[m] = len(self.rec.ops)
        self.rec.ops.append(OperationRecord(j, k, m, tool, now, now + d))
        self.machine_busy_until[m] = now + d
        self.m_idle[m] = False
        self.buf_at[m].discard(j)
        if self.buf_at[m]:  # the machine is busy: every start on it is off, known without evaluating each
            t_start = self.t_start
            self.net.disable([t_start[i] for i in self.buf_at[m]])
        self.started[j] = k + 1
        if self.t_job:
            self.net.touch(self.t_job[j])
        if tool is not None:
            self.tool_running[tool] = True
            self.tool_ready_for.discard((j, k))
            self._touch_tools()

    def _on_end_full(self, b: dict, now: int) -> None:
        j, k, m, tool = b["x"]
        self._running_rec[m] = -1
        self.job_done_ops[j] = k + 1
        self.job_ready_since[j] = now
        if now > self.makespan:
            self.makespan = now
        self.m_idle[m] = True
        self._touch_starts(m)
        if tool is not None:
            self.tool_running[tool] = False
            nxt = self.tool_next[tool]
            self.tool_user[tool], self.tool_next[tool] = nxt, None
            if nxt is not None:
                if self._jobs[nxt[0]][nxt[1]].machine == self.tool_loc[tool]:
                    self._tool_ready(nxt)
                elif self.tt_waiting[tool] is not None:
                    self.net.touch(self.t_tt_load[self.tt_waiting[tool]])
            self._touch_tools()

    # disruptions ---------------------------------------------------------
    def _disruptions_block(self) -> None:
        """Breakdowns and outages of the scenario as timed tokens: each takes effect when its time comes (no
        decider knows of it before) and a second token ends it."""
        net = self.net
        self.p_disrupt = net.add_place("disruptions")
        # before anything else of the same moment: a vehicle out from t starts no trip at t
        net.add_transition(Transition(name="disruption", priority=_P_DISRUPT, arcs=[Arc(self.p_disrupt, "d")],
                                      on_fire=self._on_disruption))
        if self.scenario is None:
            return
        if any(o.kind == "tt" for o in self.scenario.outages):
            self._watch_outages("tt", self.t_tool)  # (job transitions: in _add_job)
        for b in self.scenario.breakdowns:
            net.put(self.p_disrupt, ("down", b.machine, b.duration), delay=b.start)
        for o in self.scenario.outages:
            net.put(self.p_disrupt, ("out", o.kind, o.vehicle, o.duration), delay=o.start)

    def _watch_outages(self, kind: str, transitions: list[Transition]) -> None:
        """With vehicles of ``kind`` out of service, "an idle vehicle in service" can change without the idle
        count turning empty: the guards that ask for one (``transitions``) read every change of the idle place."""
        idle = self.p_agv_idle if kind == "agv" else self.p_tt_idle
        for t in transitions:
            self.net.wake_on_change(idle, t)

    def add_disruption(self, d: Breakdown | Outage) -> None:
        """A breakdown or outage reported during the run (``d.start`` >= now; it takes effect then). Raises
        :class:`~fms_sim.disruptions.ScenarioError` (nothing changed) for an unknown machine or vehicle, a past
        start, or a window that overlaps a known one of the same machine or vehicle."""
        if d.start < self.now:
            raise ScenarioError(f"the disruption starts at {d.start}, before the shop's time {self.now}")
        base = self.scenario or Scenario()
        new = base.adding(d)
        new.check(self.instance)
        if isinstance(d, Outage) and not any(o.kind == d.kind for o in base.outages):
            self._watch_outages(d.kind, self.t_job if d.kind == "agv" else self.t_tool)
        self.scenario = new
        if isinstance(d, Breakdown):
            self.net.put(self.p_disrupt, ("down", d.machine, d.duration), delay=d.start - self.now)
        else:
            self.net.put(self.p_disrupt, ("out", d.kind, d.vehicle, d.duration), delay=d.start - self.now)

    def _on_disruption(self, b: dict, now: int) -> None:
        d = b["d"]
        if d[0] == "down":
            _, m, dur = d
            self.m_down[m] = True
            i = self._running_rec[m]
            if i >= 0 and self.rec.ops[i].end > now:  # the operation on the machine is suspended until the repair
                rec = self.rec.ops[i]
                self.rec.ops[i] = replace(rec, end=rec.end + dur)
                self.machine_busy_until[m] += dur
                self.net.postpone(self.p_busy, m, dur)
            self.net.put(self.p_disrupt, ("up", m), delay=dur)
            self._touch_starts(m)
        elif d[0] == "up":  # unless a window that starts at this repair is already under way (back to back)
            sc = self.scenario
            self.m_down[d[1]] = sc is not None and any(w.start <= now < w.end for w in sc.windows(d[1]))
            self._touch_starts(d[1])
        else:
            kind, v = d[1], d[2]
            sc = self.scenario
            self.out[kind][v] = d[0] == "out" or (sc is not None and any(
                o.kind == kind and o.vehicle == v and o.start <= now < o.end for o in sc.outages))
            if d[0] == "out":
                self.net.put(self.p_disrupt, ("back", kind, v), delay=d[3])
            touch = self.net.touch
            touch(self.t_select[kind, v])
            touch((self.t_agv_load if kind == "agv" else self.t_tt_load)[v])  # a committed vehicle waiting to load
            if kind == "agv":
                for t in self.t_job:
                    touch(t)
            else:
                self._touch_tools()
                if self.tool_choice is not None:  # an open request choice: a use that needs a transporter may change
                    self.net.defer([self.t_use[j] for j in self._use_cands])

    def _touch_starts(self, m: int) -> None:
        """The machine's state changed: the starts of the parts in its buffer are re-evaluated when asked (a
        congested machine holds many; Net.defer)."""
        buf = self.buf_at[m]
        if len(buf) > 4:
            t_start = self.t_start
            self.net.defer([t_start[j] for j in buf])
        else:  # (a few: evaluated at once, cheaper than deferring)
            t_start, touch = self.t_start, self.net.touch
            for j in buf:
                touch(t_start[j])

    # tools --------------------------------------------------------------
    def _tools_block_full(self) -> None:
        net, inst = self.net, self.instance
        TT = inst.tool_travel
        self.p_awaiting_tt = net.add_place("awaiting_transporter")
        self.p_tt_idle = net.add_place("tt_idle", key=lambda c: c[0])
        self.p_tt_pick = net.add_place("tt_to_tool", key=lambda c: c[0])
        self.p_tt_drop = net.add_place("tt_loaded_trip", key=lambda c: c[0])
        for r in range(inst.n_tool_transporters):
            net.put(self.p_tt_idle, (r, 0))
        for t in range(1, inst.n_tools + 1):
            tr = net.add_transition(Transition(
                name=f"take_tool[{t}]", label=f"tool:{t}", controllable=True, priority=_P_JOB, arcs=[],
                guard=partial(self._tool_ok, t), on_fire=partial(self._on_tool, t)))
            self.t_tool.append(tr)
            net.wake_on_count(self.p_tt_idle, tr)  # requests that need a trip need an idle transporter
        # colour of trip tokens: (transporter, tool, tool_location, job, op, machine)
        for r in range(inst.n_tool_transporters):
            self._vehicle_choice("tt", r, self.p_awaiting_tt, self.p_tt_idle, self.p_tt_pick, TT, 1,
                                 self._on_select_tt_full)
            self.t_tt_load.append(net.add_transition(Transition(
                name=f"tt_load[{r}]", priority=_P_DONE, arcs=[Arc(self.p_tt_pick, "e", key=r)],
                guard=self._tt_load_ok,
                outputs=[Output(self.p_tt_drop, lambda b: b["e"], delay=partial(self._loaded_leg, "tt", 2, 5))],
                on_fire=self._on_tt_load)))
            net.add_transition(Transition(
                name=f"tt_unload[{r}]", priority=_P_DONE, arcs=[Arc(self.p_tt_drop, "l", key=r)],
                outputs=[Output(self.p_tt_idle, lambda b: (b["l"][0], b["l"][5]))], on_fire=self._on_tt_unload))
        self.p_tt_orders = self._reposition_block("tt", self.p_tt_idle, inst.n_tool_transporters, TT,
                                                  partial(self._on_reposition_full, "tt"),
                                                  partial(self._reposition_leg, "tt"))

    def _servable(self, t: int) -> bool:
        """Tool t may take up a new request: it is free, or in use by a running operation with none queued."""
        user = self.tool_user[t]
        return user is None or (self.tool_running[t] and self.tool_next[t] is None)

    def _candidate(self, t: int, j: int) -> bool:
        """Job j's next unserved operation on tool t may be served now (a transporter is idle when the tool must
        travel, and the reservation closes no circular wait)."""
        ks = self.treq[t].get(j)
        if not ks:
            return False
        k = ks[0]
        if self.tool_loc[t] != self._jobs[j][k].machine and not self._in_service("tt", self.p_tt_idle):
            return False
        return self._safe(t, (j, k))

    def _tool_ok(self, t: int, b: dict) -> bool:
        """Tool t may take up a request now: some candidate (:meth:`_candidate`) among its pending requests."""
        treq = self.treq[t]
        if self.tool_choice is not None or not treq or not self._servable(t):
            return False
        # without an idle transporter only requests on the machine where the tool is can be served
        carried = self._in_service("tt", self.p_tt_idle)
        loc = self.tool_loc[t]
        cands = treq if carried else self.treq_at[t].get(loc, ())
        # any(self._candidate(t, j) for j in cands), the cheap case first: a request for its job's next operation to
        # start closes no circular wait (_safe is True at once), so the wait-for graph (_danger, rebuilt after every
        # change of the tools) is walked only where no such request is a candidate (this guard is re-evaluated for
        # every tool at each of those changes)
        started, jobs = self.started, self._jobs
        later = []
        for j in cands:
            ks = treq.get(j)
            if not ks:
                continue
            k = ks[0]
            if not carried and loc != jobs[j][k].machine:
                continue
            if k == started[j]:
                return True
            later.append((j, k))
        return any(self._safe(t, op) for op in later)

    def _use_ok(self, j: int, b: dict) -> bool:
        t = self.tool_choice
        return t is not None and self._candidate(t, j)

    def reserved_op(self, t: int) -> tuple[int, int] | None:
        """The operation tool t is reserved for that has not started (None: the tool is free, or only busy with a
        running operation that will end by itself): the one an unserved request on it would have to wait for, and
        the one a plan from this state must let it serve first."""
        return self.tool_next[t] if self.tool_running[t] else self.tool_user[t]

    _waiter = reserved_op  # (its name in the wait-for graph's checks)

    def _safe(self, tool: int, op: tuple[int, int]) -> bool:
        """Would reserving ``tool`` for ``op`` keep the wait-for graph of reserved operations acyclic?

        A reserved operation (i, z) waits for the operation that holds the next reservation of each tool needed by
        an earlier, unstarted operation (i, y < z) of its job. ``op`` would wait for the holders of the tools its
        own earlier operations need; a cycle closes if one of them leads back, through reserved operations, to
        one that needs ``tool`` before its own turn (see :meth:`_danger`)."""
        j, z = op
        s = self.started[j]
        if z == s:
            return True  # nothing of the job comes before it: it waits for no reservation
        waiter = self._waiter
        danger = None
        for y, need in self._tool_ops[j]:
            if y >= z:
                break
            if y < s:
                continue
            if need == tool:
                return False  # the job needs the tool for an earlier operation first
            w = waiter(need)
            if w is None or w == (j, y):
                continue
            if danger is None:
                danger = self._danger(tool)
            if w in danger:
                return False
        return True

    def _danger(self, tool: int) -> set[tuple[int, int]]:
        """Reserved operations from which the wait-for graph reaches one whose job needs ``tool`` for an earlier,
        unstarted operation (cached until reservations or starts change)."""
        cached = self._danger_cache.get(tool)
        if cached is not None:
            return cached
        into, needs = self._wait_for()
        frontier = [node for node, tools in needs.items() if tool in tools]
        danger = set(frontier)
        while frontier:
            for prev in into.get(frontier.pop(), ()):
                if prev not in danger:
                    danger.add(prev)
                    frontier.append(prev)
        self._danger_cache[tool] = danger
        return danger

    def _wait_for(self) -> tuple[dict[tuple[int, int], list[tuple[int, int]]], dict[tuple[int, int], set[int]]]:
        """The wait-for graph of the reserved operations, for every tool's :meth:`_danger` (cached with them):
        ``into[w]``, the reserved operations that wait for ``w`` (``w`` holds the next reservation of a tool that an
        earlier, unstarted operation of their job needs), and ``needs[node]``, the tools those earlier operations of
        each reserved operation's job need. (An edge through the tool whose danger is asked only leads back into an
        operation that needs it, one that is in its danger set anyway, so one graph serves every tool.)"""
        graph = self._wait_graph
        if graph is not None:
            return graph
        waiter, started = self._waiter, self.started
        into: dict[tuple[int, int], list[tuple[int, int]]] = {}
        needs: dict[tuple[int, int], set[int]] = {}
        for node in {w for w in map(waiter, range(1, len(self.tool_user))) if w is not None}:
            i, z = node
            before = needs[node] = set()
            for y, need in self._tool_ops[i]:
                if y >= z:
                    break
                if y < started[i]:
                    continue
                before.add(need)
                w = waiter(need)
                if w is not None and w != (i, y):
                    into.setdefault(w, []).append(node)
        self._wait_graph = graph = (into, needs)
        return graph

    def _forget_waits(self) -> None:
        """Reservations or starts changed: the wait-for graph and every tool's danger set are recomputed when next
        asked."""
        self._danger_cache.clear()
        self._wait_graph = None

    def _touch_tools(self) -> None:
        self._forget_waits()
        touch = self.net.touch
        for tr in self.t_tool:
            touch(tr)

    def _on_tool(self, t: int, b: dict, now: int) -> None:
        self.tool_choice = t
        self._use_cands = list(self.treq[t])
        # every job with a request on t may be a candidate; a decider often reads only the first (first, replay):
        # evaluated when asked (Net.defer), not all of them at every tool choice (quadratic on large shops)
        self.net.defer([self.t_use[j] for j in self._use_cands])
        # a choice is open: every take_tool guard is false until it closes (_tool_ok), known without evaluating each
        # (the reservations are as they were: the wait-for graph the use: guards walk stands)
        self.net.disable(self.t_tool)

    def _on_use(self, j: int, b: dict, now: int) -> None:
        t = self.tool_choice
        assert t is not None
        ks = self.treq[t][j]
        k = ks.pop(0)
        at = self.treq_at[t]
        at[self._jobs[j][k].machine].discard(j)
        if ks:
            at.setdefault(self._jobs[j][ks[0]].machine, set()).add(j)
        else:
            del self.treq[t][j]
        op = (j, k)
        m = self._jobs[j][k].machine
        if self.tool_user[t] is None:
            self.tool_user[t] = op
            if self.tool_loc[t] == m:
                self._tool_ready(op)
        else:
            self.tool_next[t] = op
        if self.tool_loc[t] != m:
            self.net.put(self.p_awaiting_tt, (t, self.tool_loc[t], j, k, m))
        self.tool_choice = None
        self.net.disable([self.t_use[i] for i in self._use_cands])  # no choice open: every use: guard is false
        self._use_cands = []
        self._touch_tools()

    def _tool_ready(self, op: tuple[int, int]) -> None:
        self.tool_ready_for.add(op)
        self.net.touch(self.t_start[op[0]])

    def _on_select_tt_full(self, b: dict, now: int) -> None:
        r, here = b["a"]
        tool, tloc, _, _, _ = b["r"]
        t = self._last_leg["tt", r]
        if here != tloc:
            self.rec.tt.append(ToolTrip(r, None, None, None, here, tloc, now, now + t, False))
        self.tt_work[r] += t
        self.tt_loc[r] = tloc
        self.tt_free_at[r] = now + t
        self.tt_waiting[tool] = r

    def _tt_load_ok(self, b: dict) -> bool:
        r, tool, _, j, k, _ = b["e"]
        return self.tool_user[tool] == (j, k) and not self.tool_running[tool] and not self.out["tt"][r]

    def _on_tt_load(self, b: dict, now: int) -> None:
        r, tool, src, j, k, m = b["e"]
        t = self._last_leg["tt", r]
        self.rec.tt.append(ToolTrip(r, tool, j, k, src, m, now, now + t, True))
        self.tt_work[r] += t
        self.tt_loc[r] = m
        self.tt_free_at[r] = now + t
        self.tt_waiting[tool] = None

    def _on_tt_unload(self, b: dict, now: int) -> None:
        _, tool, _, j, k, m = b["l"]
        self.tool_loc[tool] = m
        self._tool_ready((j, k))

    # ------------------------------------------------------------------ running
    @property
    def n_actions(self) -> int:
        return len(self.net.controllable) + 1

    @property
    def hold_action(self) -> int:
        return len(self.net.controllable)

    def action_labels(self) -> list[str]:
        return [t.label for t in self.net.controllable] + [HOLD]

    def action_label(self, action: int) -> str:
        """The label of one action index, ``hold`` included (:meth:`Shop.action_label`)."""
        action = index_arg(action)
        ctrl = self.net.controllable
        if action == len(ctrl):
            return HOLD
        if not 0 <= action < len(ctrl):
            raise InvalidAction(f"action {action} is out of range (0..{len(ctrl)})")
        return ctrl[action].label

    def action_kind(self, action: int) -> tuple[str, int]:
        """``(kind, number)`` for an action index: kinds job, agv, tt, start, tool, use; ``("hold", 0)``."""
        ctrl = self.net.controllable
        action = index_arg(action)
        if action == len(ctrl):
            return HOLD, 0
        if not 0 <= action < len(ctrl):  # a negative index read the list from its end
            raise InvalidAction(f"action {action} is out of range (0..{len(ctrl)})")
        kinds = self._kinds
        if len(kinds) != len(ctrl):  # parsed once per layout (a live order adds transitions)
            kinds = self._kinds = [(k, int(n)) for k, n in (t.label.split(":") for t in ctrl)]
        return kinds[action]

    def action_index(self, label: str) -> int:
        try:
            return self._label_index[label]
        except (KeyError, TypeError):  # TypeError: a label that is no string (a list)
            raise InvalidAction(f"unknown action label {label!r} (full net: job:J, agv:V, tt:R, start:J, tool:T, "
                                "use:J or hold)") from None

    def idle_machines(self) -> int:
        """How many machines process nothing now (a broken-down machine without an operation included): what the
        paper's ``idle`` reward counts, as on the paper's net (:meth:`Shop.idle_machines`)."""
        return sum(self.m_idle) - 1  # index 0 is no machine

    def hold_allowed(self) -> bool:
        """Hold is offered at a decision among the base choices while some event is still to come."""
        net = self.net
        first = net.first_offered()
        return first is not None and net.controllable[first].priority == _P_JOB and net.next_event_time() is not None

    def legal_actions(self) -> list[int]:
        out = self.net.enabled_actions()
        if out and self.net.controllable[out[0]].priority == _P_JOB and self.net.next_event_time() is not None:
            out.append(len(self.net.controllable))
        return out

    def action_mask(self) -> list[bool]:
        m = self.net.mask()
        m.append(self.hold_allowed())
        return m

    def fire_action(self, action: int) -> None:
        """Fire one action without running on (``hold`` moves the clock to the next event)."""
        action = index_arg(action)
        if action == self.hold_action:
            if not self.hold_allowed():
                raise InvalidAction(f"hold is not allowed at time {self.now} (a vehicle choice is due or nothing "
                                    "is in flight)")
            self.net.release_until(self.net.next_event_time())
            self.net.acted += 1
        else:
            self.net.act(action)

    def act(self, action: int) -> None:
        if self.done:
            raise InvalidAction("the run is complete; no action is enabled")
        self.fire_action(action)
        self.net.advance()
        self._check_progress()

    def _add_job_transition(self, j: int) -> None:
        """A live order's job joins the net (called by :meth:`Shop.add_jobs` for each new job)."""
        self.disp_next.append(self._next_transport(j, 0))
        self.started.append(0)
        self._add_job(j)
        if self.tool_choice is not None:  # a tool's user is being chosen: the new job may be one, and its use:
            self._use_cands.append(j)     # transition must be re-checked when the choice closes, like the others'
            self.net.touch(self.t_use[j])
        self._touch_tools()  # new requests for the tools

    # ------------------------------------------------------------------ introspection
    def idle_agvs(self) -> list[tuple[int, int]]:
        """Idle AGVs in service (out-of-service ones cannot be sent anywhere)."""
        return [c for c in super().idle_agvs() if not self.out["agv"][c[0]]]

    def idle_transporters(self) -> list[tuple[int, int]]:
        return [c for c in super().idle_transporters() if not self.out["tt"][c[0]]]

    def check_reposition(self, kind: str, vehicle: int, location: int) -> None:
        super().check_reposition(kind, vehicle, location)
        if self.out[kind][vehicle]:
            what = "AGV" if kind == "agv" else "tool transporter"
            raise InvalidAction(f"{what} {vehicle} is out of service at time {self.now}")

    def schedule(self) -> Schedule:
        """The schedule; a disrupted run records its scenario in ``meta["scenario"]``, which the validator
        checks the realised times against."""
        out = super().schedule()
        if self.scenario is not None:
            out.meta["scenario"] = self.scenario.to_dict()
        return out

    def next_op(self, job: int) -> int:
        """Index of the next operation of ``job`` that needs a dispatch decision (== number of ops if none)."""
        return self.disp_next[job]

    def buffered_op(self, job: int) -> tuple[int, int] | None:
        """``(op, machine)`` of the job's part waiting in a machine buffer, if any."""
        toks = self.p_buffer.tokens(job)
        return (toks[0].colour[1], toks[0].colour[2]) if toks else None

    def request_of(self, tool: int, job: int) -> int | None:
        """The operation of ``job`` that ``use:job`` would serve with ``tool`` (its next unserved one)."""
        ks = self.treq[tool].get(job)
        return ks[0] if ks else None

    def part_on_its_way(self, j: int, k: int | None) -> bool:
        """Operation ``(j, k)`` is the job's next to start and its part is on its way: buffered, carried
        (dispatched), or finishing the previous operation where no AGV is needed. This is when a tool for it is
        *due*: taking it up earlier reserves the tool for an operation that may start much later."""
        if k is None or k != self.started[j]:
            return False
        if self.buffered_op(j) is not None:
            return True
        inst = self.instance
        if inst.has_agvs:
            if self.job_started_ops[j] > k:
                return True
            return k > 0 and inst.jobs[j][k - 1].machine == inst.jobs[j][k].machine
        return k > 0 or self.p_parts.tokens(j) != ()

    def due_tool_request(self, j: int) -> int | None:
        """The tool that job ``j``'s next operation to start needs, when that request is pending, due
        (:meth:`part_on_its_way`) and may be served now (the tool may take up a request and this one is a
        candidate); else None."""
        k = self.started[j]
        jobs = self.instance.jobs
        if k >= len(jobs[j]):
            return None
        t = jobs[j][k].tool
        if t is None or self.request_of(t, j) != k or not self.part_on_its_way(j, k):
            return None
        return t if self._servable(t) and self._candidate(t, j) else None

    # ------------------------------------------------------------------ saving
    def save_state(self) -> ShopState:
        """As :meth:`Shop.save_state`, with the full net's own state, and the records of the operations running
        now: a breakdown lengthens one in place (records are otherwise only appended), and a trial run across a
        breakdown's start left it lengthened, so that the real run lengthened it again (a schedule the validator
        refuses)."""
        base = super().save_state()
        extra = copy.deepcopy({name: getattr(self, name) for name in _FULL_STATE})
        running = {i: self.rec.ops[i] for i in self._running_rec if i >= 0}
        return ShopState(base.net, base.lists, {**base.scalars, "__full__": extra, "__running__": running},
                         base.records, base.instance)

    def restore_state(self, state: ShopState) -> None:
        scalars = dict(state.scalars)
        extra = scalars.pop("__full__")
        running = scalars.pop("__running__")
        super().restore_state(ShopState(state.net, state.lists, scalars, state.records, state.instance))
        for i, record in running.items():
            self.rec.ops[i] = record
        for name, value in copy.deepcopy(extra).items():
            setattr(self, name, value)
        self._forget_waits()

    def state_key(self, quick: bool = False) -> int:
        base = super().state_key(quick)
        if quick:
            return base
        extra = (tuple(self.disp_next), tuple(self.started), tuple(sorted(self.tool_ready_for)),
                 tuple(self.tool_user), tuple(self.tool_running), tuple(self.tool_next), self.tool_choice,
                 tuple(tuple(sorted((j, tuple(ks)) for j, ks in d.items())) for d in self.treq))
        return hash((base, extra))

