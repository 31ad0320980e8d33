"""The shop as a coloured-timed Petri net, built from modules over :mod:`fms_sim.petri`.

Modules (switching them gives the plain job shop, AGVs only, tools only, or AGVs + tools; the others do not
change):

* **jobs block** — place ``parts`` (colour ``(job, op, location)``: the part of ``job`` waits at ``location`` for
  operation ``op``) and one controllable *job-selection* transition per job. Firing it stamps the operation with
  the next dispatch number and emits a transport request ``(job, op, pickup, machine, stamp)``; with tools it
  also emits a tool request. The transport module adds its gate arcs to these transitions.
* **AGV block** (transport module) — ``agv_idle`` ``(agv, location)``; the job selection needs an idle AGV
  (read arc). The request waits in ``awaiting_agv`` for one controllable *AGV-selection* transition per AGV
  (offered before any other job is selected: a higher priority level). The AGV then makes a timed empty trip
  to the pickup and a timed loaded trip to the machine, and drops the part in the machine's buffer.
* **direct transfer** (transport module without AGVs) — the part moves instantly; a job is selectable only when
  its machine is idle with an empty buffer (classical non-delay dispatching of a job shop).
* **machines block** — ``buffer`` (keyed by machine), ``machine_idle``, ``busy``; an autonomous start per machine
  takes the buffered operation with the smallest dispatch stamp whose part is there (and, with tools, whose tool
  is at the machine), a timed transition holds it for its duration, the end returns the part to ``parts`` for
  its next operation at this machine's location (or to ``done``) and the tool to ``tool_free``.
* **tools block** — ``tool_requests`` (FIFO per tool by dispatch stamp), ``tool_free`` ``(tool, location)``; the
  head request of a free tool is served in place if the tool is at the machine, else it waits in
  ``awaiting_transporter`` for a controllable *tool-transporter selection*; the transporter makes a timed empty
  trip to the tool and a timed loaded trip to the machine, then the tool is ``tool_ready`` for that operation.

All resources serve operations in dispatch-stamp order (tools strictly, machines among ready operations), so
the net cannot deadlock. Action indices: jobs ``0..n-1``, then AGVs, then tool transporters; labels
``"job:J"``, ``"agv:V"``, ``"tt:R"``.
"""

from __future__ import annotations

import copy
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterator, Sequence

from .instance import Instance, InstanceError, Operation, require_instance
from .petri import Arc, Deadlock, InvalidAction, Net, NetState, Output, Place, Transition, index_arg
from .schedule import AgvTrip, OperationRecord, Schedule, ToolTrip

__all__ = ["Shop", "ShopState", "ActionKind", "run_policy"]


def _stamp_of(colour: tuple) -> int:
    return colour[3]

# priority levels: autonomous completions first, then allocation, then starts; decisions: vehicles before jobs
_P_DONE, _P_ALLOC, _P_START = 0, 1, 2
_P_VEHICLE, _P_JOB = 5, 10


class ActionKind:
    JOB = "job"
    AGV = "agv"
    TT = "tt"


#: the run's mutable state besides the net and the records (see :meth:`Shop.save_state`)
_LIST_STATE = ("job_started_ops", "job_done_ops", "job_ready_since", "job_entry", "agv_work", "tt_work", "agv_loc",
               "tt_loc", "agv_free_at", "tt_free_at", "machine_busy_until", "tool_loc")
_SCALAR_STATE = ("_stamp", "pending_job", "makespan")


@dataclass(frozen=True)
class ShopState:
    """A saved dynamic state of a :class:`Shop` (see :meth:`Shop.save_state`); opaque to callers."""

    net: NetState
    lists: dict[str, list]
    scalars: dict[str, Any]
    records: tuple[int, int, int]
    instance: Instance


@dataclass
class _Records:
    ops: list[OperationRecord] = field(default_factory=list)
    agv: list[AgvTrip] = field(default_factory=list)
    tt: list[ToolTrip] = field(default_factory=list)


class Shop:
    """A runnable shop net for one instance: decisions via :meth:`act`, time via the net's events.

    Typical loop::

        shop = Shop(instance)
        while not shop.done:
            shop.act(policy(shop.action_mask()))
        schedule = shop.schedule()

    A running shop is not picklable (its net's guards are closures over it): twin it with :meth:`copy` (or
    ``copy.deepcopy``), try runs with :meth:`save_state` / :meth:`restore_state`, and send another process its
    instance and the actions taken (``Instance`` and ``Schedule`` pickle).
    """

    decisions = "paper"
    """The decision space of this net (see :data:`fms_sim.full_shop.DECISIONS`)."""

    def __init__(self, instance: Instance, *, incremental: bool = True):
        self.instance = instance = require_instance(instance, type(self).__name__)
        self.net = Net(incremental=incremental)
        self._stamp = 0
        self.rec = _Records()
        self.n_jobs = instance.n_jobs
        self.n_agvs = instance.n_agvs if instance.has_agvs else 0
        self.n_tts = instance.n_tool_transporters if instance.has_tools else 0
        # statistics that rules and observations read
        self.job_started_ops = [0] * self.n_jobs          # operations dispatched per job
        self.job_done_ops = [0] * self.n_jobs             # operations finished per job
        self.job_ready_since = [0] * self.n_jobs          # time the job's part became ready
        self.job_entry = list(range(self.n_jobs))         # FIFO key: order of entry
        self.arrivals: dict[int, int] = {}                 # job of a live order -> when it arrived (add_jobs)
        self.agv_work = [0] * self.n_agvs                 # cumulative busy time per AGV
        self.tt_work = [0] * self.n_tts
        self.agv_loc = [0] * self.n_agvs                  # last known / destination location per vehicle
        self.tt_loc = [0] * self.n_tts
        self.agv_free_at = [0] * self.n_agvs
        self.tt_free_at = [0] * self.n_tts
        self.machine_busy_until = [0] * (instance.n_machines + 1)
        self.tool_loc = [0] * (instance.n_tools + 1)
        self.pending_job: int | None = None               # job selected, waiting for its AGV
        self.makespan = 0
        self._jobs = instance.jobs
        self._build()
        self.net.advance()
        self._check_progress()

    # ------------------------------------------------------------------ building
    def _build(self) -> None:
        inst, net = self.instance, self.net
        self.p_parts = net.add_place("parts", key=lambda c: c[0])
        self.p_done = net.add_place("done")
        self.p_buffer = net.add_place("buffer", key=lambda c: c[2])
        self.p_machine_idle = net.add_place("machine_idle", key=lambda c: c[0])
        self.p_busy = net.add_place("busy", key=lambda c: c[2])
        for j in range(inst.n_jobs):
            net.put(self.p_parts, (j, 0, 0))
        for m in range(1, inst.n_machines + 1):
            net.put(self.p_machine_idle, (m,))
        tool_arcs, tool_outputs = self._tools_block() if inst.has_tools else ([], [])
        gate_arcs, transport_out = self._agv_block() if inst.has_agvs else self._direct_block()
        self._jobs_block(gate_arcs, transport_out + tool_outputs)
        self._machines_block(tool_arcs)
        self._order_actions()

    def _jobs_block(self, gate_arcs: list[Arc], outputs: list[Output]) -> None:
        self._job_gate, self._job_outputs = gate_arcs, outputs
        for j in range(self.instance.n_jobs):
            self._add_job_transition(j)

    def _add_job_transition(self, j: int) -> None:
        self.net.add_transition(Transition(
            name=f"select_job[{j}]", label=f"job:{j}", controllable=True, priority=_P_JOB,
            arcs=[Arc(self.p_parts, "p", key=j)] + self._job_gate,
            outputs=self._job_outputs, on_fire=self._on_select_job,
        ))

    def _order_actions(self) -> None:
        kinds = {"job": 0, "agv": 1, "tt": 2}
        self.net.set_action_order(sorted(self.net.controllable, key=lambda t: (kinds[t.label.split(":")[0]],
                                                                                int(t.label.split(":")[1]))))

    def _on_select_job(self, b: dict, now: int) -> None:
        j, k, _ = b["p"]
        self._stamp += 1
        self.job_started_ops[j] += 1
        if self.instance.has_agvs:
            self.pending_job = j

    # transport modules ------------------------------------------------
    def _request(self, b: dict) -> tuple:
        j, k, loc = b["p"]
        return (j, k, loc, self._jobs[j][k].machine, self._stamp)

    def _direct_block(self) -> tuple[list[Arc], list[Output]]:
        gate = [Arc(self.p_machine_idle, kind="test", key=self._machine_of, count_only=True),
                Arc(self.p_buffer, kind="inhibit", key=self._machine_of, count_only=True)]
        return gate, [Output(self.p_buffer, self._direct_to_buffer)]

    def _machine_of(self, b: dict) -> int:
        j, k, _ = b["p"]
        return self._jobs[j][k].machine

    def _direct_to_buffer(self, b: dict) -> tuple:
        j, k, _ = b["p"]
        return (j, k, self._jobs[j][k].machine, self._stamp)

    def _agv_block(self) -> tuple[list[Arc], list[Output]]:
        net, inst = self.net, self.instance
        T = inst.agv_travel
        self.p_agv_empty, self.p_agv_loaded = self._agv_places("agv_empty_trip", "agv_loaded_trip")
        # a part already at its machine needs no AGV
        net.add_transition(Transition(
            name="stay", priority=_P_ALLOC, arcs=[Arc(self.p_awaiting_agv, "r")],
            guard=lambda b: b["r"][2] == b["r"][3],
            outputs=[Output(self.p_buffer, lambda b: (b["r"][0], b["r"][1], b["r"][3], b["r"][4]))],
            on_fire=self._on_stay,
        ))
        for v in range(inst.n_agvs):
            net.add_transition(Transition(
                name=f"select_agv[{v}]", label=f"agv:{v}", controllable=True, priority=_P_VEHICLE,
                arcs=[Arc(self.p_awaiting_agv, "r", first=True), Arc(self.p_agv_idle, "a", key=v)],
                guard=lambda b: b["r"][2] != b["r"][3],
                outputs=[Output(self.p_agv_empty, lambda b: (b["a"][0],) + b["r"],
                                delay=lambda b: T[b["a"][1]][b["r"][2]])],
                on_fire=self._on_select_agv,
            ))
            net.add_transition(Transition(
                name=f"agv_load[{v}]", priority=_P_DONE, arcs=[Arc(self.p_agv_empty, "e", key=v)],
                outputs=[Output(self.p_agv_loaded, lambda b: b["e"], delay=lambda b: T[b["e"][3]][b["e"][4]])],
            ))
            net.add_transition(Transition(
                name=f"agv_unload[{v}]", priority=_P_DONE, arcs=[Arc(self.p_agv_loaded, "l", key=v)],
                outputs=[Output(self.p_buffer, lambda b: (b["l"][1], b["l"][2], b["l"][4], b["l"][5])),
                         Output(self.p_agv_idle, lambda b: (b["l"][0], b["l"][4]))],
            ))
        self.p_agv_orders = self._reposition_block("agv", self.p_agv_idle, inst.n_agvs, T, self._on_agv_reposition)
        gate = [Arc(self.p_agv_idle, kind="test", count_only=True)]
        return gate, [Output(self.p_awaiting_agv, self._request)]

    def _agv_places(self, first_leg: str, second_leg: str) -> tuple[Place, Place]:
        """The AGV fleet's places (idle AGVs at L/U, the request waiting for its AGV) and the two places of a
        transport's legs, keyed by AGV, which the transport module names and returns."""
        net = self.net
        self.p_agv_idle = net.add_place("agv_idle", key=lambda c: c[0])
        self.p_awaiting_agv = net.add_place("awaiting_agv")
        legs = (net.add_place(first_leg, key=lambda c: c[0]), net.add_place(second_leg, key=lambda c: c[0]))
        for v in range(self.instance.n_agvs):
            net.put(self.p_agv_idle, (v, 0))
        return legs

    def _reposition_block(self, kind: str, idle: Place, n: int, travel, on_fire, delay=None) -> Place:
        """Pre-positioning module for one fleet: an order ``(vehicle, location)`` in the returned place sends
        that idle vehicle empty to the location (a timed trip); it is idle again on arrival. ``delay(binding)``
        replaces the travel matrix's time where trips take other times (a disrupted run)."""
        net = self.net
        if delay is None:
            delay = lambda b: travel[b["a"][1]][b["o"][1]]  # noqa: E731
        orders = net.add_place(f"{kind}_orders", key=lambda c: c[0])
        moving = net.add_place(f"{kind}_repositioning", key=lambda c: c[0])
        for v in range(n):
            net.add_transition(Transition(
                name=f"{kind}_reposition[{v}]", priority=_P_ALLOC,
                arcs=[Arc(orders, "o", key=v), Arc(idle, "a", key=v)],
                outputs=[Output(moving, lambda b: b["o"], delay=delay)],
                on_fire=on_fire,
            ))
            net.add_transition(Transition(
                name=f"{kind}_arrive[{v}]", priority=_P_DONE, arcs=[Arc(moving, "o", key=v)],
                outputs=[Output(idle, lambda b: b["o"])],
            ))
        return orders

    def _on_agv_reposition(self, b: dict, now: int) -> None:
        v, here = b["a"]
        self._record_reposition("agv", b, now, self.instance.agv_travel[here][b["o"][1]])

    def _record_reposition(self, kind: str, b: dict, now: int, t: int) -> None:
        """Record a pre-positioning trip of ``t`` time units that vehicle ``b["a"]`` of ``kind`` began now to
        ``b["o"]``'s location, and its statistics (work, destination, free time)."""
        v, here = b["a"]
        dest = b["o"][1]
        agv = kind == "agv"
        if here != dest:
            if agv:
                self.rec.agv.append(AgvTrip(v, None, None, here, dest, now, now + t, False))
            else:
                self.rec.tt.append(ToolTrip(v, None, None, None, here, dest, now, now + t, False))
        work, loc, free = ((self.agv_work, self.agv_loc, self.agv_free_at) if agv
                           else (self.tt_work, self.tt_loc, self.tt_free_at))
        work[v] += t
        loc[v] = dest
        free[v] = now + t

    def _on_stay(self, b: dict, now: int) -> None:
        self.pending_job = None

    def _on_select_agv(self, b: dict, now: int) -> None:
        v, here = b["a"]
        j, k, pickup, drop, _ = b["r"]
        T = self.instance.agv_travel
        t_empty, t_loaded = T[here][pickup], T[pickup][drop]
        if here != pickup:
            self.rec.agv.append(AgvTrip(v, None, None, here, pickup, now, now + t_empty, False))
        self.rec.agv.append(AgvTrip(v, j, k, pickup, drop, now + t_empty, now + t_empty + t_loaded, True))
        self.agv_work[v] += t_empty + t_loaded
        self.agv_loc[v] = drop
        self.agv_free_at[v] = now + t_empty + t_loaded
        self.pending_job = None

    # machines -----------------------------------------------------------
    def _machines_block(self, tool_arcs: list[Arc]) -> None:
        net, inst = self.net, self.instance
        tool_out = [Output(self.p_tool_free, self._released_tool)] if inst.has_tools else []
        for m in range(1, inst.n_machines + 1):
            net.add_transition(Transition(
                name=f"start[{m}]", priority=_P_START,
                arcs=[Arc(self.p_machine_idle, "mi", key=m), Arc(self.p_buffer, "q", key=m, order=_stamp_of)]
                + tool_arcs,
                outputs=[Output(self.p_busy, self._busy_token, delay=self._duration)],
                on_fire=self._on_start,
            ))
            net.add_transition(Transition(
                name=f"end[{m}]", priority=_P_DONE, arcs=[Arc(self.p_busy, "x", key=m)],
                outputs=[Output(self.p_machine_idle, lambda b: (b["x"][2],)),
                         Output(self.p_parts, self._next_part),
                         Output(self.p_done, self._finished_part)] + tool_out,
                on_fire=self._on_end,
            ))

    # output expressions read self._jobs (not a captured tuple): jobs may be added at run time and twins
    # made by deepcopy must read their own table
    def _busy_token(self, b: dict) -> tuple:
        j, k, m, _ = b["q"]
        return (j, k, m, self._jobs[j][k].tool if self.instance.has_tools else None)

    def _duration(self, b: dict) -> int:
        return self._jobs[b["q"][0]][b["q"][1]].duration

    def _next_part(self, b: dict) -> tuple | None:
        j, k, m, _ = b["x"]
        return (j, k + 1, m) if k + 1 < len(self._jobs[j]) else None

    def _finished_part(self, b: dict) -> int | None:
        j, k, _, _ = b["x"]
        return j if k + 1 == len(self._jobs[j]) else None

    @staticmethod
    def _released_tool(b: dict) -> tuple | None:
        return (b["x"][3], b["x"][2]) if b["x"][3] is not None else None

    def _on_start(self, b: dict, now: int) -> None:
        j, k, m, _ = b["q"]
        op = self.instance.jobs[j][k]
        tool = op.tool if self.instance.has_tools else None
        self.rec.ops.append(OperationRecord(j, k, m, tool, now, now + op.duration))
        self.machine_busy_until[m] = now + op.duration

    def _on_end(self, b: dict, now: int) -> None:
        j, k, m, _ = b["x"]
        self.job_done_ops[j] = k + 1
        self.job_ready_since[j] = now
        if now > self.makespan:
            self.makespan = now

    # tools --------------------------------------------------------------
    def _tools_block(self) -> tuple[list[Arc], list[Output]]:
        net, inst = self.net, self.instance
        TT = inst.tool_travel
        self.p_tool_requests = net.add_place("tool_requests", key=lambda c: c[0])
        self.p_tool_free = net.add_place("tool_free", key=lambda c: c[0])
        self.p_awaiting_tt = net.add_place("awaiting_transporter")
        self.p_tt_idle = net.add_place("tt_idle", key=lambda c: c[0])
        self.p_tt_empty = net.add_place("tt_empty_trip", key=lambda c: c[0])
        self.p_tt_loaded = net.add_place("tt_loaded_trip", key=lambda c: c[0])
        self.p_tool_ready = net.add_place("tool_ready", key=lambda c: (c[1], c[2]))
        for t in range(1, inst.n_tools + 1):
            net.put(self.p_tool_free, (t, 0))
        for r in range(inst.n_tool_transporters):
            net.put(self.p_tt_idle, (r, 0))
        for t in range(1, inst.n_tools + 1):
            net.add_transition(Transition(
                name=f"tool_here[{t}]", priority=_P_ALLOC,
                arcs=[Arc(self.p_tool_free, "f", key=t), Arc(self.p_tool_requests, "q", key=t, first=True)],
                guard=lambda b: b["f"][1] == b["q"][3],
                outputs=[Output(self.p_tool_ready, lambda b: b["q"][:4])],
            ))
            net.add_transition(Transition(
                name=f"tool_away[{t}]", priority=_P_ALLOC,
                arcs=[Arc(self.p_tool_free, "f", key=t), Arc(self.p_tool_requests, "q", key=t, first=True)],
                guard=lambda b: b["f"][1] != b["q"][3],
                outputs=[Output(self.p_awaiting_tt, lambda b: (b["f"][0], b["f"][1]) + b["q"][1:])],
            ))
        for r in range(inst.n_tool_transporters):
            net.add_transition(Transition(
                name=f"select_tt[{r}]", label=f"tt:{r}", controllable=True, priority=_P_VEHICLE,
                arcs=[Arc(self.p_awaiting_tt, "w", first=True), Arc(self.p_tt_idle, "a", key=r)],
                outputs=[Output(self.p_tt_empty, lambda b: (b["a"][0],) + b["w"],
                                delay=lambda b: TT[b["a"][1]][b["w"][1]])],
                on_fire=self._on_select_tt,
            ))
            # colour of trip tokens: (tt, tool, tool_loc, job, op, machine, stamp)
            net.add_transition(Transition(
                name=f"tt_load[{r}]", priority=_P_DONE, arcs=[Arc(self.p_tt_empty, "e", key=r)],
                outputs=[Output(self.p_tt_loaded, lambda b: b["e"], delay=lambda b: TT[b["e"][2]][b["e"][5]])],
            ))
            net.add_transition(Transition(
                name=f"tt_unload[{r}]", priority=_P_DONE, arcs=[Arc(self.p_tt_loaded, "l", key=r)],
                outputs=[Output(self.p_tool_ready, lambda b: (b["l"][1], b["l"][3], b["l"][4], b["l"][5])),
                         Output(self.p_tt_idle, lambda b: (b["l"][0], b["l"][5]))],
            ))

        self.p_tt_orders = self._reposition_block("tt", self.p_tt_idle, inst.n_tool_transporters, TT,
                                                  self._on_tt_reposition)
        outputs = [Output(self.p_tool_requests, self._tool_request), Output(self.p_tool_ready, self._no_tool)]
        arcs = [Arc(self.p_tool_ready, "tl", key=lambda b: (b["q"][0], b["q"][1]))]
        return arcs, outputs

    def _on_tt_reposition(self, b: dict, now: int) -> None:
        r, here = b["a"]
        self._record_reposition("tt", b, now, self.instance.tool_travel[here][b["o"][1]])

    def _no_tool(self, b: dict) -> tuple | None:
        j, k, _ = b["p"]
        op = self._jobs[j][k]
        return (None, j, k, op.machine) if op.tool is None else None

    def _tool_request(self, b: dict) -> tuple | None:
        # a method, not a closure: a deep-copied twin must read its own dispatch stamp
        j, k, _ = b["p"]
        op = self._jobs[j][k]
        return (op.tool, j, k, op.machine, self._stamp) if op.tool is not None else None

    def _on_select_tt(self, b: dict, now: int) -> None:
        r, here = b["a"]
        tool, tloc, j, k, m, _ = b["w"]
        TT = self.instance.tool_travel
        t_empty, t_loaded = TT[here][tloc], TT[tloc][m]
        if here != tloc:
            self.rec.tt.append(ToolTrip(r, None, None, None, here, tloc, now, now + t_empty, False))
        self.rec.tt.append(ToolTrip(r, tool, j, k, tloc, m, now + t_empty, now + t_empty + t_loaded, True))
        self.tt_work[r] += t_empty + t_loaded
        self.tt_loc[r] = m
        self.tt_free_at[r] = now + t_empty + t_loaded
        self.tool_loc[tool] = m

    # ------------------------------------------------------------------ running
    @property
    def now(self) -> int:
        return self.net.now

    @property
    def n_actions(self) -> int:
        return len(self.net.controllable)

    @property
    def done(self) -> bool:
        return self.p_done.count == self.n_jobs

    def action_labels(self) -> list[str]:
        return [t.label for t in self.net.controllable]

    def action_label(self, action: int) -> str:
        """The label of one action index (``action_labels()[action]`` without building the list: a decider that
        answers in labels calls it at every step). InvalidAction for no action's index."""
        action = index_arg(action)
        ctrl = self.net.controllable
        if not 0 <= action < len(ctrl):
            raise InvalidAction(f"action {action} is out of range (0..{len(ctrl) - 1})")
        return ctrl[action].label

    def action_kind(self, action: int) -> tuple[str, int]:
        """``("job", j)``, ``("agv", v)`` or ``("tt", r)`` for an action index (InvalidAction for no action's)."""
        action = index_arg(action)
        if not 0 <= action < self.n_jobs + self.n_agvs + self.n_tts:
            raise InvalidAction(f"action {action} is out of range (0..{self.n_jobs + self.n_agvs + self.n_tts - 1})")
        if action < self.n_jobs:
            return ActionKind.JOB, action
        if action < self.n_jobs + self.n_agvs:
            return ActionKind.AGV, action - self.n_jobs
        return ActionKind.TT, action - self.n_jobs - self.n_agvs

    def action_index(self, label: str) -> int:
        """Inverse of the labels: ``"job:3"`` -> 3, ``"agv:1"`` -> n_jobs + 1, ..."""
        parts = label.split(":") if isinstance(label, str) else []
        if len(parts) != 2 or not (parts[1].isascii() and parts[1].isdigit()):  # "job: 1", "job:+1" are no labels
            raise InvalidAction(f"malformed action label {label!r} (expected job:J, agv:V or tt:R)")
        kind, i = parts[0], int(parts[1])
        base, size = {"job": (0, self.n_jobs), "agv": (self.n_jobs, self.n_agvs),
                      "tt": (self.n_jobs + self.n_agvs, self.n_tts)}.get(kind, (0, -1))
        if not 0 <= i < size:
            raise InvalidAction(f"unknown action label {label!r}")
        return base + i

    def legal_actions(self) -> list[int]:
        return self.net.enabled_actions()

    def first_legal_action(self) -> int:
        """``legal_actions()[0]`` (the ``first`` solver's choice), without listing every legal action where the
        net can avoid it (:meth:`fms_sim.petri.Net.first_offered`); raises InvalidAction when none is legal."""
        a = self.net.first_offered()
        if a is None:
            raise InvalidAction(f"no action is legal at time {self.now}")
        return a

    def action_mask(self) -> list[bool]:
        return self.net.mask()

    def fire_action(self, action: int) -> None:
        """Fire one action without running on to the next decision (the caller steps the net)."""
        self.net.act(action)

    def act(self, action: int) -> None:
        """Fire the controllable transition ``action`` and run the net to the next decision (or the end)."""
        if self.done:
            raise InvalidAction("the run is complete; no action is enabled")
        self.net.act(action)
        self.net.advance()
        self._check_progress()

    def _check_progress(self) -> None:
        if not self.done and self.net.first_offered() is None and self.net.next_event_time() is None:
            raise Deadlock(f"the shop net is stuck at time {self.now} with {self.p_done.count}/{self.n_jobs} jobs done")

    def reposition_agv(self, agv: int, location: int) -> None:
        """Send idle AGV ``agv`` empty to ``location`` now (pre-positioning); it is busy until it arrives.

        Raises :class:`InvalidAction` if the AGV is not idle or the location does not exist. The net then
        runs on to the next decision, as after :meth:`act`.
        """
        self.reposition("agv", agv, location)

    def reposition_transporter(self, transporter: int, location: int) -> None:
        """Send idle tool transporter ``transporter`` empty to ``location`` now (see :meth:`reposition_agv`)."""
        self.reposition("tt", transporter, location)

    def reposition(self, kind: str, vehicle: int, location: int, advance: bool = True) -> None:
        """Send idle vehicle ``vehicle`` of ``kind`` (``"agv"`` or ``"tt"``) empty to ``location`` now; the net
        then runs on to the next decision unless ``advance`` is false (the caller steps it, as
        :class:`fms_sim.stepping.Stepper` does). Raises :class:`InvalidAction` (see
        :meth:`check_reposition`)."""
        self.check_reposition(kind, vehicle, location)
        vehicle, location = index_arg(vehicle), index_arg(location)  # a numpy integer: the token's colour an int
        self.net.put(self.p_agv_orders if kind == "agv" else self.p_tt_orders, (vehicle, location))
        if advance:
            self.net.advance()
            self._check_progress()

    def check_reposition(self, kind: str, vehicle: int, location: int) -> None:
        """Raise :class:`InvalidAction` unless :meth:`reposition` may send this vehicle there now."""
        if kind not in ("agv", "tt"):  # anything else moved a tool transporter
            raise InvalidAction(f"unknown vehicle kind {kind!r} (agv or tt)")
        agv = kind == "agv"
        what, n = ("AGV", self.n_agvs) if agv else ("tool transporter", self.n_tts)
        vehicle, location = index_arg(vehicle, f"the {what} number"), index_arg(location, "the location")
        idle = getattr(self, "p_agv_idle" if agv else "p_tt_idle", None)
        if self.done:
            raise InvalidAction("the run is complete; no vehicle can be repositioned")
        if not 0 <= vehicle < n or idle is None:
            raise InvalidAction(f"{what} {vehicle} does not exist")
        if not 0 <= location <= self.instance.n_machines:
            raise InvalidAction(f"location {location} does not exist (0..{self.instance.n_machines})")
        if not idle.tokens(vehicle):
            raise InvalidAction(f"{what} {vehicle} is not idle at time {self.now}")

    def add_jobs(self, jobs: Sequence[Sequence[Operation]], advance: bool = True) -> list[int]:
        """Add new jobs now (a live order): their parts enter at L/U at the current time.

        The operations are validated against this shop (machines and tools must exist). Returns the new job
        indices; the instance (``self.instance``) grows accordingly, so the final schedule validates against it.
        The net then runs on to the next decision, unless ``advance`` is false (the caller steps it, as
        :class:`fms_sim.stepping.Stepper` does).
        """
        if self.done:
            raise InvalidAction("the run is complete; start a new run for new jobs")
        inst = self.instance
        new = []
        for i, ops in enumerate(jobs):
            if not ops:
                raise InstanceError(f"new job {i} has no operations")
            row = []
            for k, op in enumerate(ops):
                if not isinstance(op, Operation):
                    raise InstanceError(f"new job {i} operation {k}: expected an Operation")
                if op.machine > inst.n_machines:
                    raise InstanceError(f"new job {i} operation {k}: machine {op.machine} does not exist "
                                        f"(1..{inst.n_machines})")
                if op.tool is not None and (not inst.has_tools or op.tool > inst.n_tools):
                    raise InstanceError(f"new job {i} operation {k}: tool {op.tool} does not exist in this shop")
                row.append(op)
            new.append(tuple(row))
        if not new:
            return []
        first = inst.n_jobs
        self.instance = inst = replace(inst, jobs=inst.jobs + tuple(new))
        self._jobs = inst.jobs
        ids = list(range(first, inst.n_jobs))
        for j in ids:
            self.job_started_ops.append(0)
            self.job_done_ops.append(0)
            self.job_ready_since.append(self.now)
            self.job_entry.append(j)
            self.arrivals[j] = self.now
            self._add_job_transition(j)
            self.net.put(self.p_parts, (j, 0, 0))
        self.n_jobs = inst.n_jobs
        self._order_actions()
        if advance:
            self.net.advance()
            self._check_progress()
        return ids

    def decision_kind(self) -> str | None:
        """What the next decision chooses: ``"job"``, ``"agv"``, ``"tt"`` or a mix ``"agv|tt"``."""
        kinds = sorted({self.action_kind(a)[0] for a in self.legal_actions()})
        return "|".join(kinds) if kinds else None

    def copy(self) -> "Shop":
        """An independent twin (for lookahead): same marking, clock and records."""
        return copy.deepcopy(self)

    def save_state(self) -> "ShopState":
        """The run's dynamic state (the net's marking and clock, the statistics, the records), for
        :meth:`restore_state`. Saving, running on and restoring is a trial run on this shop itself, far cheaper
        than :meth:`copy` (a deep copy rebuilds every transition and arc of the net). See :meth:`trial`."""
        return ShopState(self.net.save_state(), {name: list(getattr(self, name)) for name in _LIST_STATE},
                         {name: getattr(self, name) for name in _SCALAR_STATE},
                         (len(self.rec.ops), len(self.rec.agv), len(self.rec.tt)), self.instance)

    def restore_state(self, state: "ShopState") -> None:
        """Put back a state of :meth:`save_state`. Raises ValueError if jobs were added since (the net grew)."""
        if state.instance is not self.instance:
            raise ValueError("jobs were added since the state was saved; it cannot be restored")
        self.net.restore_state(state.net)
        for name, values in state.lists.items():
            setattr(self, name, list(values))
        for name, value in state.scalars.items():
            setattr(self, name, value)
        n_ops, n_agv, n_tt = state.records  # records are only ever appended
        del self.rec.ops[n_ops:], self.rec.agv[n_agv:], self.rec.tt[n_tt:]

    def state_key(self, quick: bool = False) -> int:
        """A hash of everything that decides how the run goes on from here: the net's
        :meth:`~fms_sim.petri.Net.state_key` (clock, marking, sojourning tokens) and the statistics
        (:data:`_LIST_STATE`, the dispatch count, the makespan so far); not the records of the past. Two shops
        of one instance with equal keys run on identically under the same deterministic policy. ``quick``: a
        cheap hash of the clock, the dispatch count and the busy-until times only; equal full keys imply equal
        quick keys. The lookahead uses these to stop a verifying rollout that has rejoined the plain run."""
        if quick:
            return hash((self.net.now, self._stamp, tuple(self.machine_busy_until), tuple(self.agv_free_at),
                         tuple(self.tt_free_at)))
        lists = tuple(tuple(getattr(self, name)) for name in _LIST_STATE)
        return hash((self.net.state_key(), lists, self._stamp, self.pending_job, self.makespan))

    @contextmanager
    def trial(self) -> Iterator["Shop"]:
        """``with shop.trial(): ...`` runs anything on this shop and then puts its state back (even on errors):
        a what-if run without a copy (the lookahead's twins)."""
        state = self.save_state()
        try:
            yield self
        finally:
            self.restore_state(state)

    # ------------------------------------------------------------------ introspection for rules / observations
    def next_op(self, job: int) -> int:
        """Index of the next operation to dispatch for ``job`` (== number of ops if finished)."""
        return self.job_started_ops[job]

    def part_location(self, job: int) -> int | None:
        toks = self.p_parts.tokens(job)
        return toks[0].colour[2] if toks else None

    def idle_agvs(self) -> list[tuple[int, int]]:
        return [t.colour for t in self.p_agv_idle.tokens()] if self.n_agvs else []

    def idle_transporters(self) -> list[tuple[int, int]]:
        return [t.colour for t in self.p_tt_idle.tokens()] if self.n_tts else []

    def awaiting_agv(self) -> tuple | None:
        """The request ``(job, op, pickup, machine, stamp)`` that the next AGV choice serves, if any."""
        if not self.n_agvs:
            return None
        toks = self.p_awaiting_agv.tokens()
        return toks[0].colour if toks else None

    def awaiting_transporter(self) -> tuple | None:
        """The tool transport ``(tool, tool_location, job, op, machine, stamp)`` a transporter choice serves."""
        if not self.n_tts:
            return None
        toks = self.p_awaiting_tt.tokens()
        return toks[0].colour if toks else None

    def idle_machines(self) -> int:
        return self.p_machine_idle.count

    # ------------------------------------------------------------------ result
    def schedule(self) -> Schedule:
        """The run's schedule (its instance with every job added); jobs of live orders are listed with the time they
        arrived in ``meta["arrivals"]`` (``[job, time]`` pairs), which the validator checks."""
        if not self.done:
            raise RuntimeError(f"the run is not complete ({self.p_done.count}/{self.n_jobs} jobs done)")
        inst = self.instance
        out = Schedule(
            instance=inst.name, makespan=self.makespan,
            n_agvs=self.n_agvs, n_tool_transporters=self.n_tts,
            operations=list(self.rec.ops), agv_trips=list(self.rec.agv), tool_trips=list(self.rec.tt),
        )
        if self.arrivals:  # the jobs of live orders: the validator checks that nothing of them came earlier
            out.meta["arrivals"] = [[j, t] for j, t in sorted(self.arrivals.items())]
        return out


def run_policy(instance: Instance, choose: Callable[[Shop], int]) -> Schedule:
    """Run the shop to completion, asking ``choose(shop)`` for the action at every decision."""
    shop = Shop(instance)
    while not shop.done:
        shop.act(choose(shop))
    return shop.schedule()
