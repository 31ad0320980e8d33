"""Running a shop from stop to stop: decisions and, optionally, idle-vehicle moments (for pre-positioning).

:meth:`Shop.act <fms_sim.shop.Shop.act>` runs the net from one decision to the next. Pre-positioning (the
lookahead of :mod:`fms_dispatch.rl.lookahead`) needs one more kind of stop: a moment when no decision is due
but an AGV or tool transporter stands idle with nothing assigned, so that it can be sent empty somewhere now.
:class:`Stepper` makes those moments explicit and deterministic, so that the offline lookahead, the shop node
(which publishes a state at each stop) and an agent's twin of the shop (which replays the applied labels)
all stop at exactly the same places:

* a **decision** stop: a controllable transition is enabled; answered by firing an action
  (:meth:`Stepper.decide`);
* an **idle** stop (only with ``idle_stops=True``): no decision is due, the run is not over, and some idle
  vehicle has not been *looked at* since the last decision; answered by a (possibly empty) list of moves
  (:meth:`Stepper.move`), after which every vehicle idle at this stop counts as looked at until the next
  decision. A vehicle is therefore offered at most once between two decisions, so stopping cannot cycle
  even where travel times are 0;
* **done**: every job is finished.

On the full-decision net (:class:`fms_sim.full_shop.FullShop`) something can nearly always be decided, so an
idle stop there comes *before* the decisions of the same moment, and a vehicle is offered once per idle period
(from the moment it turns idle until it is given work or moved) rather than once between two decisions: a plan
that moves a vehicle the moment it turns idle (replay, plan execution) can do so at exactly that moment.

Answers are written as labels, so they can travel in messages and histories: a decision is its action label
(``job:3``, ``agv:1``, ``tt:0``), an idle stop's answer is ``wait`` (no move) or
``reposition:agv:0:3,tt:1:5`` (AGV 0 to location 3 and transporter 1 to location 5, in that order).
"""

from __future__ import annotations

import re
from contextlib import contextmanager
from typing import Any, Iterator, Literal, NamedTuple, Sequence

from .instance import Operation
from .petri import InvalidAction
from .shop import Shop

__all__ = ["Stepper", "Move", "StopKind", "WAIT", "REPOSITION", "moves_label", "parse_moves"]

StopKind = Literal["decision", "idle", "done"]

WAIT = "wait"
REPOSITION = "reposition"
_KINDS = ("agv", "tt")
_NUMBER = re.compile(r"0|[1-9][0-9]*")  # a vehicle or location in a label, as moves_label writes it


class Move(NamedTuple):
    """Send idle vehicle ``vehicle`` of ``kind`` (``"agv"`` or ``"tt"``) empty to ``location``."""

    kind: str
    vehicle: int
    location: int


def moves_label(moves: list[Move] | list[tuple[str, int, int]]) -> str:
    """The label answering an idle stop: ``wait`` or ``reposition:agv:0:3,tt:1:5``."""
    if not moves:
        return WAIT
    return REPOSITION + ":" + ",".join(f"{k}:{v}:{loc}" for k, v, loc in moves)


def parse_moves(label: str) -> list[Move]:
    """Inverse of :func:`moves_label`; raises :class:`~fms_sim.petri.InvalidAction` on a malformed label. Only the
    labels :func:`moves_label` writes are read (``moves_label(parse_moves(x)) == x``), so an answer applied by the
    shop goes into the history exactly as a twin replays it."""
    if label == WAIT:
        return []
    head, sep, body = label.partition(":")
    if head != REPOSITION or not sep or not body:
        raise InvalidAction(f"malformed idle answer {label!r} (expected 'wait' or "
                            "'reposition:KIND:V:LOC[,KIND:V:LOC...]' with KIND agv or tt)")
    out = []
    for part in body.split(","):
        bits = part.split(":")
        # numbers in plain ASCII digits only, as moves_label writes them: int() also reads " 1", "+1", "0_1" and
        # "\u0661", and the shop put such a label as it came into the run's history, where a space broke the
        # history's separators (every later state failed its schema) and a twin could not replay it
        if len(bits) != 3 or bits[0] not in _KINDS or not all(_NUMBER.fullmatch(b) for b in bits[1:]):
            raise InvalidAction(f"malformed move {part!r} in {label!r} (expected KIND:V:LOC with KIND agv or "
                                "tt and V, LOC numbers in plain digits, as in reposition:agv:0:3)")
        out.append(Move(bits[0], int(bits[1]), int(bits[2])))
    return out


class Stepper:
    """Drives ``shop`` from stop to stop (see the module docstring).

    The shop must be fresh or at a decision (as :meth:`Shop.act` leaves it); call :meth:`advance` once to
    reach the first stop. ``kind`` is the current stop and ``idle`` (at an idle stop) the vehicles offered:
    ``(kind, vehicle, location)`` sorted, AGVs first.
    """

    def __init__(self, shop: Shop, idle_stops: bool = True) -> None:
        self.shop = shop
        self.idle_stops = idle_stops
        self.idle_first = getattr(shop, "decisions", "paper") == "full"
        self.looked: set[tuple[str, int]] = set()
        self.kind: StopKind | None = None
        self.idle: list[Move] = []
        self._trips = (len(shop.rec.agv), len(shop.rec.tt))  # trips recorded when the vehicles were last checked

    def _forget_workers(self, answered: set[tuple[str, int]] | frozenset = frozenset()) -> None:
        """A vehicle that made a trip since the last check is new again at the next idle stop, even if it never
        looked busy to a stop: a trip of travel time 0 starts and ends at one instant (a valid schedule's empty
        move after it was then never offered, and replay got stuck). The vehicles ``answered`` (moved at this idle
        stop: their trips are its answer) are not."""
        rec = self.shop.rec
        a0, t0 = self._trips
        if len(rec.agv) > a0 or len(rec.tt) > t0:
            self.looked -= ({("agv", t.agv) for t in rec.agv[a0:]}
                            | {("tt", t.transporter) for t in rec.tt[t0:]}) - answered
        self._trips = (len(rec.agv), len(rec.tt))

    def copy(self) -> "Stepper":
        """An independent twin at the same stop."""
        twin = Stepper(self.shop.copy(), self.idle_stops)
        twin.idle_first = self.idle_first
        twin.looked, twin.kind, twin.idle = set(self.looked), self.kind, list(self.idle)
        twin._trips = self._trips
        return twin

    @contextmanager
    def trial(self) -> Iterator["Stepper"]:
        """``with stepper.trial(): ...`` runs anything on this stepper (and its shop) and then puts both back
        as they were, even on errors (:meth:`Shop.trial <fms_sim.shop.Shop.trial>`): a twin without a copy."""
        state = self.shop.save_state()
        saved = (set(self.looked), self.kind, list(self.idle), self.idle_stops, self._trips)
        try:
            yield self
        finally:
            self.shop.restore_state(state)
            self.looked, self.kind, self.idle, self.idle_stops, self._trips = saved

    def mask(self) -> list[bool]:
        """The actions this stop offers: the shop's mask at a decision, none at an idle stop or the end (on the
        full net an idle stop can come while actions are enabled; they are offered at the next stop)."""
        if self.kind == "decision":
            return self.shop.action_mask()
        return [False] * self.shop.n_actions

    def idle_vehicles(self) -> list[Move]:
        shop = self.shop
        out = [Move("agv", v, loc) for v, loc in shop.idle_agvs()]
        out += [Move("tt", r, loc) for r, loc in shop.idle_transporters()]
        return sorted(out)

    def advance(self) -> StopKind:
        """Run the net to the next stop and return its kind (the same steps as :meth:`Net.advance`, one event
        time at a time when idle stops are on)."""
        shop, net = self.shop, self.shop.net
        self.idle = []
        if not self.idle_stops:
            net.advance()
            shop._check_progress()
            self.kind = "done" if shop.done else "decision"
            return self.kind
        while True:
            net.run_autonomous()
            self._forget_workers()
            if self.idle_first and not shop.done:
                vehicles = self.idle_vehicles()
                self.looked &= {(m.kind, m.vehicle) for m in vehicles}  # a vehicle that left idle is new again
                idle = [m for m in vehicles if (m.kind, m.vehicle) not in self.looked]
                if idle:
                    self.idle, self.kind = idle, "idle"
                    return self.kind
            if net.first_offered() is not None:
                self.kind = "decision"
                return self.kind
            if shop.done:
                self.kind = "done"
                return self.kind
            if not self.idle_first:  # (idle-first: the vehicles were offered above)
                idle = [m for m in self.idle_vehicles() if (m.kind, m.vehicle) not in self.looked]
                if idle:
                    self.idle, self.kind = idle, "idle"
                    return self.kind
            t = net.next_event_time()
            if t is None:
                shop._check_progress()  # raises Deadlock
                raise AssertionError("unreachable: a stuck net raises Deadlock")
            net.release_until(t)

    def decide(self, action: int) -> StopKind:
        """Fire controllable ``action`` at a decision stop and run to the next stop."""
        if self.kind != "decision":
            raise InvalidAction(f"no decision is due at time {self.shop.now} ({self._where()})")
        self.shop.fire_action(action)
        if not self.idle_first:
            self.looked.clear()
        return self.advance()

    def move(self, moves: list[Move] | list[tuple[str, int, int]]) -> StopKind:
        """Answer an idle stop: send each vehicle of ``moves`` (each one offered at this stop, at most once)
        empty to its location, in order, and run to the next stop. ``[]`` is *wait*.

        Raises :class:`InvalidAction` (and changes nothing) if this is not an idle stop, a vehicle is not
        offered here, appears twice, or a location does not exist."""
        shop = self.shop
        if self.kind != "idle":
            raise InvalidAction(f"no idle vehicle is offered at time {shop.now} ({self._where()})")
        offered = {(m.kind, m.vehicle) for m in self.idle}
        seen: set[tuple[str, int]] = set()
        for kind, v, loc in moves:  # every move is checked before any is made
            name = "AGV" if kind == "agv" else "tool transporter"
            if (kind, v) not in offered:
                raise InvalidAction(f"{name} {v} is not an idle vehicle offered at time {shop.now} "
                                    f"(offered: {moves_label(self.idle)[len(REPOSITION) + 1:] or 'none'})")
            if (kind, v) in seen:
                raise InvalidAction(f"{name} {v} is moved twice in one answer")
            shop.check_reposition(kind, v, loc)
            seen.add((kind, v))
        for kind, v, loc in moves:
            shop.reposition(kind, v, loc, advance=False)
        self._forget_workers()  # (trips before the moves stay news)
        # the moves' trips are recorded when their transitions fire: fired here, so that they are this stop's answer,
        # not news (counted before they fired, a moved vehicle was offered again before the next decision on the
        # paper's net, and moving it to and fro over travel times of 0 kept the clock from moving)
        shop.net.run_autonomous()
        self.looked.update(offered - seen if self.idle_first else offered)
        self._forget_workers(answered=seen)
        return self.advance()

    def add_jobs(self, jobs: Sequence[Sequence[Operation]]) -> list[int]:
        """Add a live order's jobs now (:meth:`Shop.add_jobs`) and run to the next stop; returns the new job
        numbers. Allowed at any stop before the end; the vehicles looked at so far stay looked at."""
        ids = self.shop.add_jobs(jobs, advance=False)
        self.advance()
        return ids

    def disrupt(self, d: Any) -> StopKind:
        """Report a breakdown or outage now (:meth:`FullShop.add_disruption <fms_sim.full_shop.FullShop.
        add_disruption>`, full net only) and run to the next stop."""
        add = getattr(self.shop, "add_disruption", None)
        if add is None:
            raise InvalidAction("disruptions need the full-decision net (decisions='full')")
        add(d)
        return self.advance()

    def apply(self, label: str) -> StopKind:
        """Apply an answer given as a label (an action label at a decision, ``wait``/``reposition:...`` at an
        idle stop) and run to the next stop; raises :class:`InvalidAction` if it does not fit the stop."""
        if self.kind == "idle":
            return self.move(parse_moves(label))
        if label == WAIT or label.startswith(REPOSITION + ":"):
            raise InvalidAction(f"{label!r} answers an idle stop, but {self._where()}")
        return self.decide(self.shop.action_index(label))

    def _where(self) -> str:
        return {"decision": "a decision is due", "idle": "idle vehicles are offered", "done": "the run is complete",
                None: "the stepper has not advanced yet"}[self.kind]
