"""The shop simulator node's logic, without ROS: decoded messages in, messages to publish out.

:class:`ShopService` owns one run of the shop net (:class:`fms_sim.shop.Shop`). The ROS node
(:mod:`fms_sim.shop_node`) only moves text between topics and this class, so every rule below is tested without
rclpy:

* **States.** After every step the service publishes an ``fms/state/v1`` numbered ``seq`` (0, 1, ...) with the
  action labels, the mask and — unless disabled — the ``features`` that dispatching rules read (per job: entry,
  operation counts, next duration, remaining and total work, ready time; per vehicle: location, free time,
  work; the pending AGV / tool-transport request with every vehicle's empty travel to its pickup). An agent
  therefore decides from the message alone and needs no twin of the shop.
* **History** (opt-in, ``history=True``). States then also carry ``history``: the applied action labels (one
  space-separated string) and the accepted orders' jobs with the number of actions applied before each. An
  agent that needs the whole shop (the PPO policy) replays it into its own twin of the shop, started from the
  same instance; the net is deterministic, so the twin reaches the same state. The agent keeps no state of
  its own across restarts: the latched state is all it needs. With ``history_delta=True`` a state carries only
  what was applied since the state that the last applied command answered (``actions_from``, ``orders_from`` and
  ``disruptions_from`` say where that begins: normally the state before; a state superseded by an order before it
  was answered is covered by the next), so a state's size and cost stay the same all run long instead of growing
  with it (on a 100-job shop the whole history reaches about 120 KB); an agent that cannot follow (restarted, or
  it missed a state) asks for the current state again with the whole history: a replay request with
  ``what: "state"``.
* **Decisions** (``decisions="paper"`` by default, or ``"full"``): the net the shop runs and whose action
  labels the states carry (docs/semantics.md); every state names it in ``decisions``. On the full net idle
  stops come before the decisions of the same moment, once per idle period of a vehicle.
* **Idle stops** (opt-in, ``idle_stops=True``, for an agent that pre-positions vehicles: ``ppo+lookahead``).
  The run is driven by a :class:`~fms_sim.stepping.Stepper`, which also stops when no decision is due but an
  idle AGV or tool transporter has not been offered since the last decision. Such a state enables no action
  and lists the offered vehicles in ``idle``; it is answered with the command action ``wait`` or
  ``reposition:KIND:V:LOC[,...]`` (send those vehicles empty to those locations now). Every state of such a
  run carries ``idle`` (``[]`` at a decision); the answers are part of the history, so a twin replays them.
* **Commands.** A command is applied only if it names this run, answers the *current* state and picks an
  action that state enables; anything else (malformed JSON, wrong schema, unknown run, stale or unknown state
  number, unknown or masked action) is answered with an ``fms/error/v1`` and leaves the shop untouched.
* **Events.** The shop's records (operations, AGV trips, tool trips) become ``*_start``/``*_end`` events in
  time order; an event is published once the simulation clock has reached its time (all remaining ones when
  the run ends). ``*_end`` events carry ``start`` too, so the recorder can rebuild the schedule from events
  alone. Events are numbered per run and kept, so a replay request can re-publish them. ``run_start`` names the
  instance and this start of the run (``incarnation``, random): a shop restarted with the same ``run_id`` is told
  apart by it.
* **Orders.** A valid order joins the running net as new jobs (:meth:`Shop.add_jobs`) at the current time,
  is announced by an ``order_accepted`` event and a new state; an order id is accepted once. Invalid orders
  (unknown machine or tool, bad duration, finished run) are rejected with a ``bad_order`` (or schema) error.
* **Disruptions** (full net only). A valid ``fms/disruption/v1`` (a machine breakdown or a vehicle out of
  service, from now or a later time) joins the run's scenario (:meth:`FullShop.add_disruption`), is announced by
  a ``disruption_accepted`` event and a new state, and enters the history; a bad one (unknown machine or
  vehicle, overlapping window, repeated id, finished run, paper net) is rejected with ``bad_disruption``.
* **End.** When the last job is done the service publishes the remaining events, ``run_end``, a final state
  (``done``, ``makespan``) and the schedule (``fms/schedule/v1``) whose ``meta`` names the run, the agent,
  the number of decisions, the accepted orders, ``wall_time`` (seconds from the first state to the end,
  waiting for the agent included) and ``decision_time`` (from the first applied command to the end).
"""

from __future__ import annotations

import heapq
import itertools
import re
import time
import uuid
from typing import Any, Callable, NamedTuple

from fms_msgs_json import (
    TOPIC_ERRORS, TOPIC_EVENTS, TOPIC_SCHEDULE, TOPIC_STATE, MessageError, decode, error_reply, make_error,
    make_event, make_schedule, make_state,
)

from .instance import Instance, InstanceError, Operation
from .petri import InvalidAction
from .full_shop import make_shop
from .schedule import OperationRecord, Schedule
from .shop import Shop
from .stepping import Stepper, parse_moves

__all__ = ["Outgoing", "ShopService", "shop_features", "new_run_id"]

SOURCE = "fms_shop"


class Outgoing(NamedTuple):
    """One message to publish: the topic and the (already validated) message dict."""

    topic: str
    msg: dict[str, Any]


def new_run_id(instance_name: str) -> str:
    """A fresh run id: ``<instance>-<UTC time>-<6 hex digits>`` (unique enough for logs and databases)."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", instance_name) or "run"
    return f"{safe}-{time.strftime('%Y%m%dT%H%M%S', time.gmtime())}-{uuid.uuid4().hex[:6]}"


class _JobTable:
    """Per-job constants the features need (operation counts, total work, suffix sums), extended on orders."""

    def __init__(self) -> None:
        self.n_ops: list[int] = []
        self.total: list[int] = []
        self.suffix: list[list[int]] = []   # suffix[j][k] = sum of durations of operations k.. of job j

    def sync(self, jobs: tuple[tuple[Operation, ...], ...]) -> None:
        for ops in jobs[len(self.n_ops):]:
            suffix = [0] * (len(ops) + 1)
            for k in range(len(ops) - 1, -1, -1):
                suffix[k] = suffix[k + 1] + ops[k].duration
            self.n_ops.append(len(ops))
            self.total.append(suffix[0])
            self.suffix.append(suffix)


def shop_features(shop: Shop, table: _JobTable | None = None) -> dict[str, Any]:
    """The ``features`` object of a state message (see docs/ros.md): what dispatching rules read.

    ``table`` caches per-job constants between calls (pass the same one for the same shop).
    """
    inst = shop.instance
    if table is None:
        table = _JobTable()
    table.sync(inst.jobs)
    jobs = inst.jobs
    next_op = [shop.next_op(j) for j in range(shop.n_jobs)]
    jobs_cols = {
        "entry": list(shop.job_entry),
        "n_ops": list(table.n_ops),
        "next_op": next_op,
        "next_duration": [jobs[j][k].duration if k < table.n_ops[j] else 0 for j, k in enumerate(next_op)],
        "remaining_work": [table.suffix[j][k] for j, k in enumerate(next_op)],
        "total_work": list(table.total),
        "ready_since": list(shop.job_ready_since),
    }
    out: dict[str, Any] = {
        "jobs": jobs_cols,
        "agvs": {"loc": list(shop.agv_loc), "free_at": list(shop.agv_free_at), "work": list(shop.agv_work)},
        "transporters": {"loc": list(shop.tt_loc), "free_at": list(shop.tt_free_at), "work": list(shop.tt_work)},
        "agv_request": None,
        "tt_request": None,
    }
    req = shop.awaiting_agv()
    if req is not None:
        j, k, pickup, machine = req[:4]
        travel = inst.agv_travel
        out["agv_request"] = {"job": j, "op": k, "pickup": pickup, "to": machine,
                              "empty_travel": [travel[loc][pickup] for loc in shop.agv_loc]}
    treq = shop.awaiting_transporter()
    if treq is not None:
        tool, tloc, j, k, machine = treq[:5]
        travel = inst.tool_travel
        out["tt_request"] = {"tool": tool, "job": j, "op": k, "pickup": tloc, "to": machine,
                             "empty_travel": [travel[loc][tloc] for loc in shop.tt_loc]}
    return out


def _op_data(r: OperationRecord) -> dict[str, Any]:
    """An operation's event data (its end event adds ``start``)."""
    return {"job": r.job, "op": r.op, "machine": r.machine, "tool": r.tool}


class _EventQueue:
    """Turns the shop's growing records into time-ordered start/end events.

    Records are appended by the shop when an operation starts or a vehicle is dispatched; their end (and for
    a loaded trip after an empty one, their start) lies in the future. Events wait in a heap until the clock
    reaches them. At one time, ends of earlier-started activities come first, then starts, then the ends of
    zero-length activities (so every end follows its own start).

    A breakdown lengthens the operation running on its machine (the shop replaces its record): its end event,
    queued at the old end, is then queued again at the new one and the old one dropped (it was published at the
    old end, and the schedule rebuilt from the events differed from the shop's).
    """

    def __init__(self) -> None:
        self._heap: list[tuple[int, int, int, str, dict[str, Any]]] = []
        self._count = itertools.count()
        self._seen = [0, 0, 0]  # records of rec.ops, rec.agv, rec.tt already queued
        self._op_ends: dict[int, tuple[int, int]] = {}  # rec.ops index -> (queued end, its heap entry's number)
        self._dropped: set[int] = set()  # heap entry numbers of end events queued again later

    def _push(self, start: int, end: int, kind: str, data: dict[str, Any]) -> int:
        """Queue the start and end events of one record; returns the end event's entry number."""
        heapq.heappush(self._heap, (start, 1, next(self._count), f"{kind}_start", data))
        return self._push_end(start, end, kind, data)

    def _push_end(self, start: int, end: int, kind: str, data: dict[str, Any]) -> int:
        number = next(self._count)
        heapq.heappush(self._heap, (end, 0 if end > start else 2, number, f"{kind}_end", dict(data, start=start)))
        return number

    def collect(self, shop: Shop) -> None:
        """Queue the start and end events of every record the shop added since the last call, and again the end
        of each operation whose end has moved since it was queued."""
        rec = shop.rec
        for i, (end, number) in list(self._op_ends.items()):
            r = rec.ops[i]
            if r.end != end:
                self._dropped.add(number)
                self._op_ends[i] = (r.end, self._push_end(r.start, r.end, "op", _op_data(r)))
        for i, r in enumerate(rec.ops[self._seen[0]:], start=self._seen[0]):
            self._op_ends[i] = (r.end, self._push(r.start, r.end, "op", _op_data(r)))
        for t in rec.agv[self._seen[1]:]:
            self._push(t.start, t.end, "agv_trip", {"agv": t.agv, "job": t.job, "op": t.op, "from": t.from_,
                                                    "to": t.to, "loaded": t.loaded})
        for t in rec.tt[self._seen[2]:]:
            self._push(t.start, t.end, "tool_trip", {"transporter": t.transporter, "tool": t.tool, "job": t.job,
                                                     "op": t.op, "from": t.from_, "to": t.to, "loaded": t.loaded})
        self._seen = [len(rec.ops), len(rec.agv), len(rec.tt)]

    def due(self, until: int | None) -> list[tuple[int, str, dict[str, Any]]]:
        """Pop the events with time ``<= until`` (all of them if ``until`` is None), in order."""
        out = []
        heap = self._heap
        while heap and (until is None or heap[0][0] <= until):
            t, _, number, kind, data = heapq.heappop(heap)
            if number in self._dropped:  # an operation's old end (a breakdown lengthened it)
                self._dropped.discard(number)
                continue
            out.append((t, kind, data))
        # the operations whose end is still to come (a breakdown can move only those)
        self._op_ends = {} if until is None else {i: v for i, v in self._op_ends.items() if v[0] > until}
        return out


class ShopService:
    """One run of the shop simulator, driven by decoded messages (see the module docstring).

    Every ``handle_*`` method takes the raw text of a received message and returns the :class:`Outgoing`
    messages to publish, in order. Nothing here raises on bad input: failures become ``fms/error/v1``
    messages on ``fms/errors``.
    """

    def __init__(self, instance: Instance, *, run_id: str | None = None, source: str = SOURCE,
                 features: bool = True, history: bool = False, idle_stops: bool = False,
                 clock: Callable[[], float] = time.perf_counter, decisions: str = "paper",
                 scenario: Any = None, history_delta: bool = False) -> None:
        if history_delta and not history:
            raise ValueError("history_delta needs history: the deltas are of the history")
        self.shop = make_shop(instance, decisions, scenario)
        # the run's scenario as given at the start, for twins that mirror the shop (with history)
        self._scenario_doc = scenario.to_dict() if scenario is not None and not scenario.empty else None
        self.stepper = Stepper(self.shop, idle_stops=idle_stops)
        self.stepper.advance()
        self.run_id = run_id or new_run_id(instance.name)
        # this start of the run, in its run_start event: a shop restarted with the same run_id (a respawn with fixed
        # parameters) published the very same events again, and the recorder could not tell the two runs apart
        self.incarnation = uuid.uuid4().hex[:12]
        self.source = source
        self.with_features = features
        self.with_history = history
        self.history_delta = history_delta
        self._applied: list[str] = []                     # applied action labels, in order (for history)
        self._applied_text = ""                           # the same, space-separated (whole histories only)
        # a delta starts where the history stood when the state that the last applied command answered was published
        # (what the agent that answered it has seen: a state superseded by an order before anyone answered it is
        # covered by the next one); counts of (labels, orders, disruptions)
        self._history_base = (0, 0, 0)
        self._history_at_state = (0, 0, 0)                # the counts when the current state was published
        self._order_history: list[dict[str, Any]] = []    # accepted orders: {"at": n actions before, "jobs"}
        self._disruption_history: list[dict[str, Any]] = []  # {"at", "orders_before", "disruption"}
        self.disruptions: dict[str, dict[str, Any]] = {}  # accepted disruption id -> its message body
        self._clock = clock
        self._table = _JobTable()
        self._queue = _EventQueue()
        self.events: list[dict[str, Any]] = []          # every event of the run, by seq
        self.state: dict[str, Any] | None = None         # the latest published state
        self.state_seq = -1
        self.decisions = 0                                # applied decisions (actions of the net)
        self.idle_answers = 0                             # applied answers to idle stops (wait / reposition)
        self.orders: dict[str, list[int]] = {}            # accepted order id -> its job numbers
        self.agents: list[str] = []                       # agent names seen in applied commands, in order
        self.final_schedule: Schedule | None = None
        self._schedule_msg: dict[str, Any] | None = None
        self._started_at: float | None = None
        self._first_command_at: float | None = None
        self.wall_time: float | None = None
        self.decision_time: float | None = None

    # ------------------------------------------------------------------ properties
    @property
    def instance(self) -> Instance:
        """The instance as it is now (it grows when orders are accepted)."""
        return self.shop.instance

    @property
    def done(self) -> bool:
        return self.shop.done

    # ------------------------------------------------------------------ entry points
    def start(self) -> list[Outgoing]:
        """The opening messages of the run: ``run_start``, any events at time 0, and state 0."""
        if self.state is not None:
            raise RuntimeError("the run has already started")
        self._started_at = self._clock()
        # (machines: the recorder's chart has a row for each, an idle one too; the schedule names only those used)
        out = [self._event(0, "run_start", {"instance": self.instance.name, "incarnation": self.incarnation,
                                            "machines": self.instance.n_machines})]
        return out + self._after_step()

    def handle_command(self, text: str) -> list[Outgoing]:
        """Apply a command if it answers the current state with an enabled action; else an error."""
        try:
            msg = decode(text, expect="command")
        except MessageError as exc:
            return [self._error_reply(exc, text)]
        if msg["run_id"] != self.run_id:
            return [self._error("unknown_run", f"command names run {msg['run_id']!r} but this shop runs "
                                               f"{self.run_id!r}", text)]
        seq, label = msg["state_seq"], msg["action"]
        if self.done:
            return [self._error("stale_state", f"command answers state {seq} but the run is complete (final "
                                               f"state {self.state_seq}); no command is accepted", text)]
        if seq < self.state_seq:  # with the current state again: an agent that lost it (a state overwritten in a
            # subscriber's queue of depth 1 by another shop's on the same domain) re-sent its last command for ever
            assert self.state is not None  # (a state newer than seq was published)
            return [self._error("stale_state", f"command answers state {seq} but the current state is "
                                               f"{self.state_seq}", text), Outgoing(TOPIC_STATE, self.state)]
        if seq > self.state_seq:  # with the current state again: an agent of this run's earlier incarnation (the
            # shop restarted with the same run_id) re-sent its command for ever, ignoring state 0 as an old state
            assert self.state is not None
            return [self._error("stale_state", f"command answers state {seq}, which was never published "
                                               f"(the current state is {self.state_seq})", text),
                    Outgoing(TOPIC_STATE, self.state)]
        assert self.state is not None
        if self._first_command_at is None:
            self._first_command_at = self._clock()
        if self.stepper.kind == "idle":
            try:
                self.stepper.move(parse_moves(label))
            except InvalidAction as exc:
                return [self._error("forbidden_action", f"state {seq} is an idle stop: {exc}", text)]
            self.idle_answers += 1
        else:
            problem = self._decide(seq, label)
            if problem is not None:
                return [self._error("forbidden_action", problem, text)]
            self.decisions += 1
        if self.with_history:
            self._history_base = self._history_at_state
            self._applied.append(label)
            if not self.history_delta:  # (a delta shop joins the labels only when asked for the whole history)
                self._applied_text = f"{self._applied_text} {label}" if self._applied_text else label
        agent = msg.get("agent")
        if agent and (not self.agents or self.agents[-1] != agent):
            self.agents.append(agent)
        return self._after_step()

    def _decide(self, seq: int, label: str) -> str | None:
        """Fire ``label`` at the current decision; None, or why it is refused (nothing changed then)."""
        assert self.state is not None
        actions, mask = self.state["actions"], self.state["mask"]
        try:
            index = actions.index(label)
        except ValueError:
            return f"action {label!r} is not an action of state {seq} (labels: {_short_list(actions)})"
        if not mask[index]:
            enabled = [a for a, m in zip(actions, mask) if m]
            return f"action {label!r} is not enabled in state {seq} (enabled: {_short_list(enabled)})"
        self.stepper.decide(index)  # enabled by the mask: cannot be refused
        return None

    def handle_order(self, text: str) -> list[Outgoing]:
        """Add an order's jobs to the running net now; reject invalid, duplicate or late orders."""
        try:
            msg = decode(text, expect="order")
        except MessageError as exc:
            return [self._error_reply(exc, text)]
        oid = msg["order_id"]
        target = msg.get("run_id")
        if target is not None and target != self.run_id:
            return [self._error("unknown_run", f"order {oid!r} is for run {target!r} but this shop runs "
                                               f"{self.run_id!r}", text)]
        if oid in self.orders:
            return [self._error("bad_order", f"order {oid!r} was already accepted (jobs "
                                             f"{_short_list(self.orders[oid])}); an order id is accepted once", text)]
        if self.done:
            return [self._error("bad_order", f"order {oid!r} arrived after run {self.run_id!r} completed; "
                                             "start a new run for it", text)]
        try:
            jobs = [[Operation(op["machine"], op.get("tool"), op["duration"]) for op in ops] for ops in msg["jobs"]]
            ids = self.stepper.add_jobs(jobs)
        except (InstanceError, InvalidAction) as exc:
            return [self._error("bad_order", f"order {oid!r} rejected: {exc}", text)]
        self.orders[oid] = ids
        if self.with_history:
            self._order_history.append({"at": len(self._applied), "jobs": [
                [{"machine": o.machine, "tool": o.tool, "duration": o.duration} for o in ops] for ops in jobs]})
        out = [self._event(self.shop.now, "order_accepted", {"order_id": oid, "jobs": ids})]
        return out + self._after_step()

    def handle_disruption(self, text: str) -> list[Outgoing]:
        """Accept a breakdown or outage reported now (full net only); reject bad, repeated or late ones."""
        from .disruptions import Breakdown, Outage, ScenarioError

        try:
            msg = decode(text, expect="disruption")
        except MessageError as exc:
            return [self._error_reply(exc, text)]
        did = msg["disruption_id"]
        target = msg.get("run_id")
        if target is not None and target != self.run_id:
            return [self._error("unknown_run", f"disruption {did!r} is for run {target!r} but this shop runs "
                                               f"{self.run_id!r}", text)]
        if did in self.disruptions:
            return [self._error("bad_disruption", f"disruption {did!r} was already accepted; an id is accepted "
                                                  "once", text)]
        if self.done:
            return [self._error("bad_disruption", f"disruption {did!r} arrived after run {self.run_id!r} "
                                                  "completed", text)]
        if self.shop.decisions != "full":
            return [self._error("bad_disruption", f"disruption {did!r} rejected: disruptions need a shop on the "
                                                  "full-decision net (decisions:=full)", text)]
        now = self.shop.now
        start = max(now, msg.get("start") or now)
        body = {k: msg[k] for k in ("disruption_id", "kind", "machine", "vehicle_kind", "vehicle", "duration")
                if msg.get(k) is not None}
        body["start"] = start
        d = (Breakdown(msg["machine"], start, msg["duration"]) if msg["kind"] == "breakdown"
             else Outage(msg["vehicle_kind"], msg["vehicle"], start, msg["duration"]))
        try:
            self.stepper.disrupt(d)
        except (ScenarioError, InvalidAction) as exc:
            return [self._error("bad_disruption", f"disruption {did!r} rejected: {exc}", text)]
        self.disruptions[did] = body
        if self.with_history:
            self._disruption_history.append({"at": len(self._applied), "orders_before": len(self._order_history),
                                             "disruption": body})
        data = {"disruption_id": did, "disruption": msg["kind"], "start": start, "duration": msg["duration"]}
        for key in ("machine", "vehicle_kind", "vehicle"):
            if msg.get(key) is not None:
                data[key] = msg[key]
        out = [self._event(now, "disruption_accepted", data)]
        return out + self._after_step()

    def handle_replay(self, text: str) -> list[Outgoing]:
        """Re-publish this run's events from ``from_seq`` on (and the schedule if the run is complete); with
        ``what: "state"``, the current state instead, with the run's whole history (an agent of a
        ``history_delta`` shop that cannot follow the deltas asks for it)."""
        try:
            msg = decode(text, expect="replay_request")
        except MessageError as exc:
            return [self._error_reply(exc, text)]
        if msg["run_id"] not in ("*", self.run_id):
            return [self._error("unknown_run", f"replay requested for run {msg['run_id']!r} but this shop runs "
                                               f"{self.run_id!r}", text)]
        if msg.get("what") == "state":
            state = self.state
            if state is not None and "history" in state:
                state = dict(state, history=self._history(whole=True))
            return [] if state is None else [Outgoing(TOPIC_STATE, state)]
        out = [Outgoing(TOPIC_EVENTS, e) for e in self.events[msg["from_seq"]:]]
        if self._schedule_msg is not None:
            out.append(Outgoing(TOPIC_SCHEDULE, self._schedule_msg))
        return out

    def delay_end(self, seconds: float) -> None:
        """The end of the run is published ``seconds`` after it was reached (a shop kept to a clock,
        :mod:`fms_sim.pacing`): count them in the final schedule's ``wall_time`` and ``decision_time`` (in the
        schedule message too, whether or not it was sent yet)."""
        if self.final_schedule is None or self.wall_time is None or self.decision_time is None or seconds <= 0:
            return
        self.wall_time += seconds
        self.decision_time += seconds
        for meta in (self.final_schedule.meta, *([self._schedule_msg["schedule"]["meta"]] if self._schedule_msg
                                                 else [])):
            meta.update(wall_time=round(self.wall_time, 4), decision_time=round(self.decision_time, 4))

    def handle_bad_text(self, text: str, exc: BaseException) -> list[Outgoing]:
        """An error for a failure outside the handlers (the node calls this if a handler crashed)."""
        return [self._error_reply(exc, text)]

    # ------------------------------------------------------------------ internals
    def _event(self, t: int, kind: str, data: dict[str, Any]) -> Outgoing:
        msg = make_event(self.run_id, len(self.events), t, kind, data, incarnation=self.incarnation)
        self.events.append(msg)
        return Outgoing(TOPIC_EVENTS, msg)

    def _after_step(self) -> list[Outgoing]:
        """The new state, then the events that became due (at the end: the final state, the remaining events,
        run_end and the schedule). The state goes first: it is what the agent waits for, and DDS keeps no
        order between topics anyway."""
        shop = self.shop
        self._queue.collect(shop)
        done = shop.done
        events = [self._event(t, kind, data) for t, kind, data in self._queue.due(None if done else shop.now)]
        if done:
            end_time = max(shop.makespan, self.events[-1]["time"])
            events.append(self._event(end_time, "run_end", {"makespan": shop.makespan}))
        out = [Outgoing(TOPIC_STATE, self._new_state())] + events
        if done:
            end = self._clock()
            self.wall_time = end - (self._started_at or end)
            self.decision_time = end - (self._first_command_at or end)
            sched = shop.schedule()
            sched.meta.update(run_id=self.run_id, decisions=self.decisions, orders=dict(self.orders),
                              wall_time=round(self.wall_time, 4), decision_time=round(self.decision_time, 4))
            if self.stepper.idle_stops:
                sched.meta["idle_answers"] = self.idle_answers
            if self.agents:
                sched.meta["solver"] = self.agents[-1] if len(self.agents) == 1 else "+".join(self.agents)
            self.final_schedule = sched
            self._schedule_msg = make_schedule(self.run_id, sched)
            out.append(Outgoing(TOPIC_SCHEDULE, self._schedule_msg))
        return out

    def _new_state(self) -> dict[str, Any]:
        shop = self.shop
        self.state_seq += 1
        done = shop.done
        features = shop_features(shop, self._table) if self.with_features and not done else None
        self.state = make_state(self.run_id, self.state_seq, shop.now, shop.net.marking(), shop.action_labels(),
                                self.stepper.mask(), done,
                                instance=shop.instance.name, makespan=shop.makespan if done else None,
                                features=features, idle=self._idle_offer())
        if self.with_history and not done:  # added after make_state's check; the schema (history) allows it
            self.state["history"] = self._history(whole=not self.history_delta)
            self._history_at_state = (len(self._applied), len(self._order_history), len(self._disruption_history))
        self.state["decisions"] = shop.decisions  # an extra field (allowed): the net the labels belong to
        # an extra field too: this start of the run, so that an agent tells an old state of this start delivered late
        # (reordered, duplicated) from a shop restarted with the same run_id, which numbers its states from 0 again
        self.state["incarnation"] = self.incarnation
        return self.state

    def _history(self, whole: bool) -> dict[str, Any]:
        """The state's ``history``: the whole run's, or (``whole=False``) what was applied since the state that the
        last applied command answered was published, with where that begins."""
        p, q, r = (0, 0, 0) if whole else self._history_base
        if whole:
            text = " ".join(self._applied) if self.history_delta else self._applied_text
        else:
            text = " ".join(self._applied[p:])
        history: dict[str, Any] = {"actions": text, "orders": self._order_history[q:]}
        if self._disruption_history:
            history["disruptions"] = self._disruption_history[r:]
        if self._scenario_doc is not None:
            history["scenario"] = self._scenario_doc
        if self.history_delta:
            history.update(actions_from=p, orders_from=q, disruptions_from=r)
        return history

    def _idle_offer(self) -> list[dict[str, Any]] | None:
        """The state's ``idle`` field: None without idle stops, else the vehicles offered now."""
        if not self.stepper.idle_stops or self.shop.done:
            return None
        return [{"kind": k, "vehicle": v, "location": loc} for k, v, loc in self.stepper.idle]

    def _error(self, code: str, message: str, received: str | None) -> Outgoing:
        return Outgoing(TOPIC_ERRORS, make_error(self.source, code, message, run_id=self.run_id, received=received))

    def _error_reply(self, exc: BaseException, received: str | None) -> Outgoing:
        return Outgoing(TOPIC_ERRORS, error_reply(self.source, exc, received=received, run_id=self.run_id))


def _short_list(items: list[Any], limit: int = 12) -> str:
    """``a, b, c`` (at most ``limit`` items, then ``... (N in all)``) for one-line error messages."""
    shown = ", ".join(str(x) for x in items[:limit])
    if len(items) > limit:
        shown += f", ... ({len(items)} in all)"
    return shown or "none"
