"""A general coloured-timed Petri net (CTPN) engine.

Concepts
--------
* :class:`Place` holds coloured tokens. A place may be *keyed*: tokens are bucketed by ``key(colour)`` so arcs
  can look up the tokens of one colour class (one job, one machine, one tool) in O(1).
* :class:`Token` carries a colour (any immutable value: a tuple, a dataclass) and is stored in arrival order.
* :class:`Arc` connects a place to a transition. ``kind`` is ``"in"`` (the token is consumed), ``"test"`` (a read
  arc: a token must be present, it stays) or ``"inhibit"`` (no matching token may be present). ``key`` restricts
  the candidate tokens to a bucket: a constant, or a function of the binding built so far (a colour join).
  ``first=True`` offers only the oldest candidate (FIFO queues).
* :class:`Transition` has arcs (evaluated in order, building a *binding* ``{var: colour}``), an optional
  ``guard(binding) -> bool``, outputs ``(place, expr(binding) -> colour | list | None, delay)`` and an optional
  ``on_fire(binding, now)`` hook. A non-zero ``delay`` makes the transition *timed*: its output tokens must
  sojourn ``delay`` time units before they are available. Transitions are *controllable* (fired by an agent;
  these are the actions) or *autonomous* (fired by the engine as soon as they are enabled).
* ``priority``: among autonomous transitions the lowest number fires first; among controllable ones only the
  lowest-numbered level that has an enabled transition is offered (a prioritised net: e.g. "choose the AGV for
  the job just selected" before "choose another job").

Time is event-driven: :meth:`Net.advance` fires autonomous transitions until none is enabled; if no
controllable transition is enabled either, it jumps straight to the next time a sojourning token becomes
available. It never ticks unit by unit.

Speed: every place knows which transitions read it, per key bucket where the arc key is a constant. A change
marks only those transitions dirty; test/inhibitor arcs that only count tokens (``count_only=True``) are woken
only when their bucket turns empty or non-empty. Masks are cached and only dirty transitions are re-evaluated.
Where one change wakes many choices of which a decider reads few (every job's dispatch when the last idle AGV
leaves, every candidate of a tool's request choice), the net need not evaluate them all: a module *defers* them
(:meth:`Net.defer`) or marks them *lazy* (:attr:`Transition.lazy`: behind a count-only read arc they are disabled
while the place is empty and get their bindings back when it fills), and :meth:`Net.first_offered` and
:meth:`Net.offers` evaluate them lowest action first only as far as the answer needs; :meth:`Net.enabled_actions`
(the full list, the mask) evaluates them all. The answers are the same either way.
"""

from __future__ import annotations

import heapq
import operator
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Iterator, Sequence

__all__ = ["Token", "Place", "Arc", "Output", "Transition", "Net", "NetState", "InvalidAction", "Deadlock", "ANY"]

Binding = dict[str, Any]


class InvalidAction(ValueError):
    """A controllable transition was fired while not enabled (its guard or arcs do not allow it)."""


def index_arg(value: Any, what: str = "action") -> int:
    """``value`` as an index (an int or a numpy integer), else :class:`InvalidAction` naming ``what``: a float or a
    string was taken by list indexing far from the call (a TypeError there), or compared equal to an index; a bool
    (True ran action 1) is no index either."""
    if type(value) is bool:
        raise InvalidAction(f"{what} must be an integer, got {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise InvalidAction(f"{what} must be an integer, got {value!r}") from None


class Deadlock(RuntimeError):
    """Nothing is enabled and nothing is in flight, but the net is not in a final marking."""


class _Any:
    """Singleton sentinel; stays the same object through copy, deepcopy and pickle (twins of a net)."""

    def __repr__(self) -> str:
        return "ANY"

    def __copy__(self) -> "_Any":
        return self

    def __deepcopy__(self, memo: dict) -> "_Any":
        return self

    def __reduce__(self) -> str:
        return "ANY"


ANY: Any = _Any()
"""Arc key meaning: every token of the place is a candidate."""


class Token:
    __slots__ = ("colour", "key", "ready")

    def __init__(self, colour: Any, key: Hashable, ready: int):
        self.colour = colour
        self.key = key
        self.ready = ready

    def __repr__(self) -> str:
        return f"Token({self.colour!r}, ready={self.ready})"

    def __deepcopy__(self, memo: dict) -> "Token":
        # colours and keys are immutable values (tuples of ints): a twin's token shares them (fast twins)
        return Token(self.colour, self.key, self.ready)


class Place:
    """A place; ``key`` (colour -> hashable) buckets its tokens for O(1) coloured lookups."""

    __slots__ = ("name", "key_fn", "buckets", "count", "in_flight", "index",
                 "_all_listeners", "_key_listeners", "_count_listeners", "_count_key_listeners", "_count_lazy",
                 "_count_lazy_ids", "_gate")

    def __init__(self, name: str, key: Callable[[Any], Hashable] | None = None):
        self.name = name
        self.key_fn = key
        self.buckets: dict[Hashable, list[Token]] = {}
        self.count = 0
        self.in_flight = 0  # tokens produced by timed transitions, still sojourning
        self.index = -1
        self._all_listeners: list[Transition] = []
        self._key_listeners: dict[Hashable, list[Transition]] = {}
        self._count_listeners: list[Transition] = []
        self._count_lazy: list[Transition] = []  # lazy controllable count listeners: deferred on a flip, as a group
        self._count_lazy_ids: tuple[int, int, set[int]] | None = None  # (action order version, priority, indices)
        # while the place is empty (its lazy listeners all disabled): the bindings they had before it emptied, and
        # those of them whose binding is unknown (woken since, or never evaluated with the place non-empty)
        self._gate: tuple[dict[int, Any], set[int]] | None = None
        self._count_key_listeners: dict[Hashable, list[Transition]] = {}

    def tokens(self, key: Hashable = ANY) -> Sequence[Token]:
        if key is ANY:
            if len(self.buckets) == 1:
                return next(iter(self.buckets.values()))
            return [t for b in self.buckets.values() for t in b]
        return self.buckets.get(key, ())

    def colours(self, key: Hashable = ANY) -> list[Any]:
        return [t.colour for t in self.tokens(key)]

    def __len__(self) -> int:
        return self.count

    def __repr__(self) -> str:
        return f"Place({self.name!r}, {self.count} tokens)"


@dataclass(frozen=True)
class Arc:
    """Place -> transition arc. ``kind``: ``"in"`` consumes, ``"test"`` reads, ``"inhibit"`` forbids."""

    place: Place
    var: str | None = None
    kind: str = "in"
    key: Any = ANY
    first: bool = False
    order: Callable[[Any], Any] | None = None
    """Sort candidates by ``order(colour)`` (e.g. a dispatch stamp) before trying them."""
    count_only: bool = False
    """For test/inhibit arcs whose token the guard never reads: wake the transition only on empty<->non-empty."""

    def __post_init__(self) -> None:
        if self.kind not in ("in", "test", "inhibit"):
            raise ValueError(f"arc kind must be in/test/inhibit, got {self.kind!r}")
        if self.kind == "in" and self.var is None:
            raise ValueError("an input arc needs a variable name")


@dataclass(frozen=True)
class Output:
    """Transition -> place arc: ``expr(binding)`` gives a colour, a list of colours, or None (no token)."""

    place: Place
    expr: Callable[[Binding], Any]
    delay: int | Callable[[Binding], int] = 0


@dataclass(eq=False)
class Transition:
    name: str
    arcs: Sequence[Arc]
    outputs: Sequence[Output] = ()
    guard: Callable[[Binding], bool] | None = None
    controllable: bool = False
    priority: int = 0
    on_fire: Callable[[Binding, int], None] | None = None
    label: str = ""
    index: int = -1
    _compiled: tuple = ()
    action: int = -1
    """Position among the controllable transitions (the action index), -1 for autonomous ones."""
    lazy: bool = False
    """A controllable transition whose count-only arcs (key ANY) defer it (:meth:`Net.defer`) instead of marking it
    dirty: many transitions woken together by one place turning empty or non-empty (every job's dispatch when the
    last idle AGV leaves) are then evaluated only as far as a question about the offered actions needs."""
    _gate: Any = None
    """The place of a lazy transition's count-only test arc (set by :meth:`Net.add_transition`)."""

    def __hash__(self) -> int:
        return id(self)


def _release_order(entry: tuple) -> tuple[int, int]:
    return entry[0], entry[1]  # (ready, sequence number) of a sojourning token: the order of release


@dataclass(frozen=True)
class NetState:
    """A saved dynamic state of a :class:`Net` (see :meth:`Net.save_state`); opaque to callers."""

    n_transitions: int
    n_controllable: int
    places: list[tuple[dict[Hashable, list[Token]], int, int]]
    now: int
    pending: list[tuple[int, int, Place, Token]]
    seq: int
    dirty_auto: list[tuple[int, int, Transition]]
    auto_marked: set[int]
    enabled: dict[int, Binding | None]
    levels: dict[int, set[int]]
    dirty_ctrl: set[int]
    offered: list[int] | None
    fired: int
    acted: int
    deferred: dict[int, set[int]] = field(default_factory=dict)
    gates: list[tuple[dict[int, Any], set[int]] | None] = field(default_factory=list)


@dataclass
class _Level:
    transitions: list[Transition] = field(default_factory=list)


class Net:
    """The net: places, transitions, a clock and the marking; fires transitions and advances time."""

    def __init__(self, incremental: bool = True) -> None:
        self.incremental = incremental
        """False re-evaluates every transition at every step (the naive engine; a benchmark baseline)."""
        self.places: list[Place] = []
        self.transitions: list[Transition] = []
        self.controllable: list[Transition] = []
        self.now = 0
        self._pending: list[tuple[int, int, Place, Token]] = []  # (ready, seq, place, token)
        self._seq = 0
        self._dirty_auto: list[tuple[int, int, Transition]] = []  # heap (priority, index, t)
        self._auto_marked: set[int] = set()
        self._enabled: dict[int, Binding | None] = {}  # controllable index -> binding (cache)
        self._levels: dict[int, set[int]] = {}  # priority -> enabled controllable indices (kept with the cache)
        self._dirty_ctrl: set[int] = set()
        self._offered: list[int] | None = None
        self._deferred: dict[int, set[int]] = {}  # priority -> controllable indices to evaluate only when asked
        self._dheap: dict[int, list[int]] = {}  # priority -> a heap over (at least) its deferred indices, for order
        self._gated: list[Place] = []  # places with lazy count-only listeners (Transition.lazy)
        self._order_version = 0  # set_action_order renumbers the actions: cached index sets are rebuilt
        self.fired = 0
        self.acted = 0
        """Controllable transitions fired so far (the number of decisions taken)."""

    # ------------------------------------------------------------------ construction
    def add_place(self, name: str, key: Callable[[Any], Hashable] | None = None) -> Place:
        p = Place(name, key)
        p.index = len(self.places)
        self.places.append(p)
        return p

    def add_transition(self, t: Transition) -> Transition:
        kinds = {"in": 0, "test": 1, "inhibit": 2}
        t._compiled = tuple(
            (a.place, None if (a.kind != "in" and a.var is None) else a.var, kinds[a.kind], a.key,
             a.key is not ANY and callable(a.key), a.first, a.order)
            for a in t.arcs)
        t.index = len(self.transitions)
        self.transitions.append(t)
        if t.controllable:
            t.action = len(self.controllable)
            self.controllable.append(t)
            self._dirty_ctrl.add(t.action)
            self._offered = None
        else:
            self._mark_auto(t)
        for a in t.arcs:
            p = a.place
            if a.count_only and a.kind != "in":
                if a.key is ANY and t.lazy and t.controllable and a.kind == "test":
                    if t._gate is not None and t._gate is not p:
                        raise ValueError(f"lazy transition {t.name!r} has count-only test arcs on two places")
                    if p._count_lazy and p._count_lazy[0].priority != t.priority:  # (found mid-run, as a ValueError
                        # when the place first emptied or filled)
                        raise ValueError(f"lazy transition {t.name!r} has priority {t.priority}, but the lazy "
                                         f"transitions reading place {p.name!r} must share one "
                                         f"({p._count_lazy[0].priority})")
                    t._gate = p
                    if not p._count_lazy:
                        self._gated.append(p)
                    p._count_lazy.append(t)
                    p._count_lazy_ids = None
                    if p.count == 0:  # disabled now; its binding is unknown until the place fills
                        self._dirty_ctrl.discard(t.action)
                        if p._gate is None:
                            p._gate = ({}, set())
                        p._gate[1].add(t.action)
                elif a.key is ANY:
                    p._count_listeners.append(t)
                elif callable(a.key):
                    p._all_listeners.append(t)
                else:
                    p._count_key_listeners.setdefault(a.key, []).append(t)
            elif a.key is ANY or callable(a.key):
                p._all_listeners.append(t)
            else:
                p._key_listeners.setdefault(a.key, []).append(t)
        return t

    def set_action_order(self, order: Sequence[Transition]) -> None:
        """Renumber the actions: ``order`` must list every controllable transition exactly once."""
        if sorted(t.index for t in order) != sorted(t.index for t in self.controllable):
            raise ValueError("set_action_order needs every controllable transition exactly once")
        self.controllable = list(order)
        for i, t in enumerate(self.controllable):
            t.action = i
        self._enabled = {}
        self._levels = {}
        self._dirty_ctrl = set(range(len(self.controllable)))
        self._deferred = {}
        self._dheap = {}
        self._order_version += 1
        for p in self._gated:  # renumbered: what a closed gate remembers is unknown again
            p._count_lazy_ids = None
            if p.count == 0:
                p._gate = ({}, {t.action for t in p._count_lazy})
                self._dirty_ctrl -= p._gate[1]
        self._offered = None

    # ------------------------------------------------------------------ marking changes
    def put(self, place: Place, colour: Any, delay: int = 0) -> None:
        """Add a token now, or after ``delay`` time units of sojourn."""
        key = place.key_fn(colour) if place.key_fn is not None else None
        if delay:
            tok = Token(colour, key, self.now + delay)
            self._seq += 1
            heapq.heappush(self._pending, (tok.ready, self._seq, place, tok))
            place.in_flight += 1
        else:
            self._insert(place, Token(colour, key, self.now))

    def _insert(self, place: Place, tok: Token) -> None:
        bucket = place.buckets.get(tok.key)
        if bucket is None:
            bucket = place.buckets[tok.key] = []
        bucket.append(tok)
        place.count += 1
        self._touch(place, tok.key, len(bucket) == 1, place.count == 1)

    def _remove(self, place: Place, tok: Token) -> None:
        bucket = place.buckets[tok.key]
        if bucket[0] is tok:
            del bucket[0]
        else:
            bucket.remove(tok)
        if not bucket:
            del place.buckets[tok.key]
        place.count -= 1
        self._touch(place, tok.key, not bucket, place.count == 0)

    def _touch(self, place: Place, key: Hashable, bucket_flip: bool, place_flip: bool) -> None:
        for t in place._all_listeners:
            self._mark(t)
        ls = place._key_listeners.get(key)
        if ls:
            for t in ls:
                self._mark(t)
        if place_flip:
            for t in place._count_listeners:
                self._mark(t)
            if place._count_lazy:
                if place.count:
                    self._open_gate(place)
                else:
                    self._close_gate(place)
        if bucket_flip:
            ls = place._count_key_listeners.get(key)
            if ls:
                for t in ls:
                    self._mark(t)

    def touch(self, t: Transition) -> None:
        """Mark ``t`` for re-evaluation. Arcs wake their transitions by themselves; a module whose guards read
        state kept outside the marking (counters, reservations) calls this when that state changes."""
        self._mark(t)

    def wake_on_change(self, place: Place, t: Transition) -> None:
        """Wake ``t`` whenever any token enters or leaves ``place`` (a guard that reads the place's tokens)."""
        place._all_listeners.append(t)

    def wake_on_count(self, place: Place, t: Transition) -> None:
        """Wake ``t`` whenever ``place`` turns empty or non-empty (for a guard that reads only its count)."""
        place._count_listeners.append(t)

    def postpone(self, place: Place, key: Hashable, delta: int) -> int:
        """Delay every sojourning token of ``place`` in bucket ``key`` by ``delta`` (a timed activity that is
        suspended, e.g. an operation on a machine that breaks down); returns how many were delayed."""
        hit = 0
        entries = []
        for ready, seq, p, tok in self._pending:
            if p is place and tok.key == key:
                tok = Token(tok.colour, tok.key, ready + delta)
                ready += delta
                hit += 1
            entries.append((ready, seq, p, tok))
        if hit:
            heapq.heapify(entries)
            self._pending = entries
        return hit

    def sojourning(self, place: Place) -> list[tuple[int, Any]]:
        """``(ready time, colour)`` of the tokens on their way into ``place`` (timed activities under way)."""
        return [(ready, tok.colour) for ready, _, p, tok in self._pending if p is place]

    def discard_pending(self, place: Place, drop: Callable[[Any], bool]) -> int:
        """Remove the sojourning tokens of ``place`` whose colour ``drop`` selects (events that a what-if copy
        of a run must not see, e.g. disruptions not known yet); returns how many were removed."""
        keep = [e for e in self._pending if not (e[2] is place and drop(e[3].colour))]
        gone = len(self._pending) - len(keep)
        if gone:
            heapq.heapify(keep)
            self._pending = keep
            place.in_flight -= gone
        return gone

    def take(self, place: Place, key: Hashable) -> Any:
        """Remove and return the colour of the oldest available token of ``place`` in bucket ``key`` (a
        module's on_fire hook moving a token that no arc of the fired transition names); KeyError if none."""
        bucket = place.buckets.get(key)
        if not bucket:
            raise KeyError(f"place {place.name!r} has no token with key {key!r}")
        tok = bucket[0]
        self._remove(place, tok)
        return tok.colour

    def _mark(self, t: Transition) -> None:
        if t.action >= 0:
            gate = t._gate
            if gate is not None and gate.count == 0 and gate._gate is not None:
                # disabled while its place is empty: re-evaluated when the place fills (its remembered binding is
                # no longer known)
                gate._gate[0].pop(t.action, None)
                gate._gate[1].add(t.action)
                return
            self._dirty_ctrl.add(t.action)
            self._offered = None
        else:
            self._mark_auto(t)

    def _mark_auto(self, t: Transition) -> None:
        if t.index not in self._auto_marked:
            self._auto_marked.add(t.index)
            heapq.heappush(self._dirty_auto, (t.priority, t.index, t))

    # ------------------------------------------------------------------ enabling
    def binding(self, t: Transition) -> Binding | None:
        """The first binding (in arc order, tokens oldest first) that enables ``t`` now, or None."""
        if not t._compiled:  # a pure guard (state kept by the module, woken by touch)
            if t.guard is None or t.guard({}):
                return {"__tokens__": [], "__places__": []}
            return None
        toks: list[Token] = []
        places: list[Place] = []
        b: Binding = {}
        if self._bind(t._compiled, 0, t.guard, b, toks, places):
            b["__tokens__"] = toks
            b["__places__"] = places
            return b
        return None

    def _bind(self, arcs: tuple, i: int, guard: Callable[[Binding], bool] | None, b: Binding,
              toks: list[Token], places: list[Place]) -> bool:
        # hot path: arcs are pre-compiled tuples (place, var, kind, key, key_is_fn, first, order)
        n = len(arcs)
        while i < n:
            place, var, kind, key, key_fn, first, order = arcs[i]
            buckets = place.buckets
            if key_fn:
                cands = buckets.get(key(b), ())
            elif key is ANY:
                if not buckets:
                    cands = ()
                elif len(buckets) == 1:
                    cands = next(iter(buckets.values()))
                else:
                    cands = [tk for bk in buckets.values() for tk in bk]
            else:
                cands = buckets.get(key, ())
            if kind == 2:  # inhibitor
                if cands:
                    return False
                i += 1
                continue
            if not cands:
                return False
            if var is None:  # read arc that only needs presence
                i += 1
                continue
            if order is not None and len(cands) > 1:
                cands = sorted(cands, key=lambda tk: order(tk.colour))
            if first or len(cands) == 1:
                tok = cands[0]
                if kind == 0:
                    if tok in toks:
                        return False
                    toks.append(tok)
                    places.append(place)
                b[var] = tok.colour
                i += 1
                continue
            # several candidates: backtrack over them
            for tok in cands:
                if kind == 0:
                    if tok in toks:
                        continue
                    toks.append(tok)
                    places.append(place)
                b[var] = tok.colour
                if self._bind(arcs, i + 1, guard, b, toks, places):
                    return True
                if kind == 0:
                    toks.pop()
                    places.pop()
            return False
        return guard is None or guard(b)

    def is_enabled(self, t: Transition) -> bool:
        return self.binding(t) is not None

    def _evaluate(self, i: int) -> Binding | None:
        """Re-evaluate controllable transition ``i`` and keep its binding and level up to date."""
        t = self.controllable[i]
        b = self.binding(t)
        enabled = self._enabled
        was = enabled.get(i)
        enabled[i] = b
        if (b is None) != (was is None):
            level = self._levels.get(t.priority)
            if level is None:
                level = self._levels[t.priority] = set()
            if b is None:
                level.discard(i)
            else:
                level.add(i)
        return b

    def _refresh_ctrl(self, lazy: bool = False) -> None:
        """Re-evaluate the dirty controllable transitions, and (unless ``lazy``) the deferred ones too."""
        if self._dirty_ctrl:
            evaluate = self._evaluate
            for i in self._dirty_ctrl:
                evaluate(i)
            self._dirty_ctrl.clear()
        if not lazy and self._deferred:
            for ids in self._deferred.values():
                for i in sorted(ids):
                    self._evaluate(i)
            self._deferred = {}
            self._dheap = {}

    # ------------------------------------------------------------------ deferred evaluation
    def defer(self, transitions: Sequence[Transition]) -> None:
        """Mark controllable ``transitions`` for re-evaluation, like :meth:`touch`, but evaluate them only when a
        question about the offered actions needs them: :meth:`enabled_actions` and :meth:`mask` evaluate them
        all; :meth:`first_offered`, :meth:`offers` and :meth:`act` only as many as the answer depends on, lowest
        action first. For a module that wakes many choices at once of which a decider usually reads few (the
        requests a tool could serve): the answers are those of :meth:`touch`, since a binding depends only on the
        state when it is evaluated, and every change of that state marks or defers the transition again."""
        transitions = self._past_closed_gates(transitions)
        if not transitions:
            return
        priorities = {t.priority for t in transitions}
        if len(priorities) == 1:
            ids = {t.action for t in transitions}
            if -1 in ids:
                raise ValueError("defer takes controllable transitions, not autonomous ones")
            self._defer_ids(priorities.pop(), ids)
            return
        for p in priorities:
            self.defer([t for t in transitions if t.priority == p])

    def _past_closed_gates(self, transitions: Sequence[Transition]) -> Sequence[Transition]:
        """``transitions`` but the lazy ones whose gate place is empty (disabled now, re-evaluated when it fills):
        those are marked as :meth:`touch` marks them, so that the binding their gate remembers is forgotten. (Deferred
        or disabled as others, the remembered binding came back when the place filled, whatever had changed.)"""
        if not self._gated:
            return transitions
        out = []
        for t in transitions:
            gate = t._gate
            if gate is not None and gate.count == 0 and gate._gate is not None:
                self._mark(t)
            else:
                out.append(t)
        return out

    def _group(self, place: Place) -> tuple[int, set[int]]:
        """``(priority, action indices)`` of the lazy count-only listeners of ``place`` (cached per action order; they
        share one priority, :meth:`add_transition` refuses another)."""
        cached = place._count_lazy_ids
        if cached is None or cached[0] != self._order_version:
            group = place._count_lazy
            cached = place._count_lazy_ids = (self._order_version, group[0].priority, {t.action for t in group})
        return cached[1], cached[2]

    def _close_gate(self, place: Place) -> None:
        """``place`` turned empty: its lazy listeners are disabled (their test arc fails) without evaluating them;
        the bindings of those enabled are remembered for when it fills again, unless they are woken meanwhile."""
        priority, ids = self._group(place)
        enabled = self._enabled
        level = self._levels.get(priority)
        on = level & ids if level else set()
        unknown: set[int] = set()
        d = self._deferred.get(priority)
        if d:
            unknown |= d & ids
            d -= unknown
            if not d:
                self._dheap.pop(priority, None)
        if self._dirty_ctrl:
            dirty = self._dirty_ctrl & ids
            if dirty:
                unknown |= dirty
                self._dirty_ctrl -= dirty
        saved = {i: enabled[i] for i in on if i not in unknown}
        for i in on:
            enabled[i] = None
        if on and level is not None:
            level -= on
        place._gate = (saved, unknown)
        self._offered = None

    def _open_gate(self, place: Place) -> None:
        """``place`` filled again: its lazy listeners get back the bindings they had (nothing they read but the
        place changed, or they would have been woken), and the ones woken meanwhile are deferred."""
        priority, ids = self._group(place)
        gate, place._gate = place._gate, None
        if gate is None:  # (nothing remembered: all unknown)
            self._defer_ids(priority, ids)
            return
        saved, unknown = gate
        if saved:
            level = self._levels.get(priority)
            if level is None:
                level = self._levels[priority] = set()
            self._enabled.update(saved)
            level.update(saved)
        if unknown:
            self._defer_ids(priority, unknown)
        self._offered = None

    def _defer_ids(self, priority: int, ids: set[int]) -> None:
        level = self._levels.get(priority)
        if level:
            stale = level & ids  # unknown until evaluated: no cached binding may answer for them
            if stale:
                enabled = self._enabled
                for i in stale:
                    enabled[i] = None
                level -= stale
        if self._dirty_ctrl:
            self._dirty_ctrl -= ids
        d = self._deferred.get(priority)
        heap = self._dheap.get(priority)
        if not d or heap is None:
            self._deferred[priority] = d = set(ids) if not d else d | ids
            self._dheap[priority] = sorted(d)  # (a sorted list is a heap)
        else:
            new = ids - d
            if new:
                d |= new
                if len(new) < 8:
                    for i in new:
                        heapq.heappush(heap, i)
                else:
                    heap.extend(new)
                    heapq.heapify(heap)
        self._offered = None

    def disable(self, transitions: Sequence[Transition]) -> None:
        """Record that controllable ``transitions`` are not enabled now, without evaluating them: for a module
        whose state change just closed all of them at once (a choice made: every candidate's guard is now false;
        the caller guarantees it). Cheaper than :meth:`touch` and a re-evaluation of each."""
        transitions = self._past_closed_gates(transitions)
        if not transitions:
            return
        priorities = {t.priority for t in transitions}
        if len(priorities) > 1:
            for p in priorities:
                self.disable([t for t in transitions if t.priority == p])
            return
        p = priorities.pop()
        ids = {t.action for t in transitions}
        level = self._levels.get(p)
        if level:
            on = level & ids
            if on:
                enabled = self._enabled
                for i in on:
                    enabled[i] = None
                level -= on
        d = self._deferred.get(p)
        if d:
            d -= ids
            if not d:
                self._dheap.pop(p, None)
        if self._dirty_ctrl:
            self._dirty_ctrl -= ids
        self._offered = None

    def _deferred_enabled(self, priority: int, below: int | None = None) -> int | None:
        """The lowest deferred action of level ``priority`` that is enabled, evaluating the level's deferred
        actions in order (only those below ``below``, when given), or None; the ones evaluated leave the list."""
        d = self._deferred.get(priority)
        if not d:
            return None
        heap = self._dheap[priority]
        pop = heapq.heappop
        while heap:
            i = heap[0]
            if i not in d:  # (evaluated or disabled since it was deferred)
                pop(heap)
                continue
            if below is not None and i >= below:
                return None
            pop(heap)
            d.discard(i)
            if self._evaluate(i) is not None:
                return i
        return None

    def first_offered(self) -> int | None:
        """The lowest action offered now (``enabled_actions()[0]``, None if none), evaluating deferred
        transitions only as far as the answer needs, and without sorting the offered ones."""
        if not self.incremental:
            offered = self.enabled_actions()
            return offered[0] if offered else None
        if self._offered is not None:
            return self._offered[0] if self._offered else None
        if self._dirty_ctrl:
            self._refresh_ctrl(lazy=True)
        levels, deferred = self._levels, self._deferred
        for p in sorted({p for p, level in levels.items() if level} | {p for p, d in deferred.items() if d}):
            level = levels.get(p)
            low = min(level) if level else None
            hit = self._deferred_enabled(p, low)
            if hit is not None:
                return hit
            if low is not None:
                return low
        return None

    def offers(self, action: int) -> bool:
        """Whether ``action`` is offered now (``action in enabled_actions()``), evaluating deferred transitions
        only as far as the answer needs, and without listing the offered ones."""
        if not self.incremental:
            return action in self.enabled_actions()
        if self._dirty_ctrl:
            self._refresh_ctrl(lazy=True)
        p = self.controllable[action].priority
        deferred = self._deferred
        if deferred:
            d = deferred.get(p)
            if d and action in d:
                d.discard(action)
                self._evaluate(action)
        if self._enabled.get(action) is None:
            return False
        for q, level in self._levels.items():
            if level and q < p:
                return False
        if deferred:
            for q in sorted(q for q, d in deferred.items() if d and q < p):
                if self._deferred_enabled(q) is not None:
                    return False
        return True

    def enabled_actions(self) -> list[int]:
        """Indices of the controllable transitions offered now (only the most urgent priority level)."""
        if not self.incremental:
            self._dirty_ctrl.update(range(len(self.controllable)))
            self._offered = None
        if self._offered is not None:
            return list(self._offered)
        self._refresh_ctrl()
        out: list[int] = []
        best = None
        for p, level in self._levels.items():
            if level and (best is None or p < best):
                best = p
        if best is not None:
            out = sorted(self._levels[best])
        self._offered = out
        return list(out)

    def mask(self) -> list[bool]:
        m = [False] * len(self.controllable)
        for i in self.enabled_actions():
            m[i] = True
        return m

    # ------------------------------------------------------------------ firing
    def fire(self, t: Transition, binding: Binding | None = None) -> Binding:
        """Fire ``t`` with ``binding`` (found if None); raises :class:`InvalidAction` if not enabled."""
        if binding is None:
            binding = self.binding(t)
            if binding is None:
                raise InvalidAction(f"transition {t.name!r} is not enabled at time {self.now}")
        toks = binding.pop("__tokens__")
        places = binding.pop("__places__", [])
        for p, tok in zip(places, toks):
            self._remove(p, tok)
        now = self.now
        for o in t.outputs:
            val = o.expr(binding)
            if val is None:
                continue
            d = o.delay
            if callable(d):
                d = d(binding)
            if isinstance(val, list):
                for c in val:
                    self.put(o.place, c, d)
            else:
                self.put(o.place, val, d)
        self.fired += 1
        if t.on_fire is not None:
            t.on_fire(binding, now)
        return binding

    def act(self, action: int) -> Binding:
        """Fire the controllable transition with this action index (must be offered now)."""
        action = index_arg(action)
        if not (0 <= action < len(self.controllable)):
            raise InvalidAction(f"action {action} is out of range (0..{len(self.controllable) - 1})")
        t = self.controllable[action]
        offered = self.offers(action)  # (evaluates the action if it was dirty or deferred)
        b = self._enabled.get(action)
        if b is None:
            raise InvalidAction(f"action {action} ({t.label or t.name}) is not enabled at time {self.now}")
        if not offered:
            raise InvalidAction(f"action {action} ({t.label or t.name}) is enabled but a more urgent decision "
                                f"is due at time {self.now}")
        self._dirty_ctrl.add(action)
        self._offered = None
        self.acted += 1
        # the cached binding is consumed; copy so that the cache never aliases a fired binding
        return self.fire(t, dict(b, __tokens__=list(b["__tokens__"]), __places__=list(b.get("__places__", []))))

    def run_autonomous(self) -> int:
        """Fire enabled autonomous transitions (by priority) until none is enabled; returns how many fired."""
        n = 0
        heap = self._dirty_auto
        marked = self._auto_marked
        if not self.incremental:
            for t in self.transitions:
                if t.action < 0:
                    self._mark_auto(t)
        while heap:
            _, idx, t = heapq.heappop(heap)
            marked.discard(idx)
            b = self.binding(t)
            if b is not None:
                self.fire(t, b)
                self._mark_auto(t)  # it may be enabled again with other tokens
                n += 1
                if not self.incremental:
                    for u in self.transitions:
                        if u.action < 0:
                            self._mark_auto(u)
        return n

    def next_event_time(self) -> int | None:
        return self._pending[0][0] if self._pending else None

    def release_until(self, time: int) -> None:
        """Move the clock to ``time`` and make available every token whose sojourn ends by then."""
        self.now = time
        pend = self._pending
        while pend and pend[0][0] <= time:
            _, _, place, tok = heapq.heappop(pend)
            place.in_flight -= 1
            self._insert(place, tok)

    def advance(self) -> bool:
        """Run until a controllable decision is due (True) or nothing more can happen (False)."""
        while True:
            self.run_autonomous()
            if self.first_offered() is not None:
                return True
            t = self.next_event_time()
            if t is None:
                return False
            self.release_until(t)

    # ------------------------------------------------------------------ saving and restoring the marking
    def save_state(self) -> "NetState":
        """The dynamic state (marking, sojourning tokens, clock, caches), to be put back by
        :meth:`restore_state`: a trial run on the net itself instead of on a deep copy (lookahead twins).

        Tokens are never changed once made, so the state shares them; only the containers are copied.
        The structure (places, transitions, action order) must not change in between (e.g. no new jobs).
        """
        return NetState(
            len(self.transitions), len(self.controllable),
            [({k: list(b) for k, b in p.buckets.items()}, p.count, p.in_flight) for p in self.places],
            self.now, list(self._pending), self._seq, list(self._dirty_auto), set(self._auto_marked),
            dict(self._enabled), {p: set(v) for p, v in self._levels.items()}, set(self._dirty_ctrl), self._offered,
            self.fired, self.acted, {p: set(d) for p, d in self._deferred.items()},
            [None if p._gate is None else (dict(p._gate[0]), set(p._gate[1])) for p in self._gated])

    def restore_state(self, state: "NetState") -> None:
        """Put back a state of :meth:`save_state` (raises ValueError if the net's structure changed since)."""
        if (state.n_transitions, state.n_controllable) != (len(self.transitions), len(self.controllable)):
            raise ValueError("the net's structure changed since the state was saved; it cannot be restored")
        for p, (buckets, count, in_flight) in zip(self.places, state.places):
            p.buckets = {k: list(b) for k, b in buckets.items()}
            p.count, p.in_flight = count, in_flight
        self.now, self._seq, self.fired, self.acted = state.now, state.seq, state.fired, state.acted
        self._pending = list(state.pending)
        self._dirty_auto = list(state.dirty_auto)
        self._auto_marked = set(state.auto_marked)
        self._enabled = dict(state.enabled)
        self._levels = {p: set(v) for p, v in state.levels.items()}
        self._dirty_ctrl = set(state.dirty_ctrl)
        self._deferred = {p: set(d) for p, d in state.deferred.items() if d}
        self._dheap = {p: sorted(d) for p, d in self._deferred.items()}
        for p, gate in zip(self._gated, state.gates):
            p._gate = None if gate is None else (dict(gate[0]), set(gate[1]))
        self._offered = state.offered

    def state_key(self) -> int:
        """A hash of the clock, the marking (each place's tokens by colour, in their order, which FIFO arcs
        read) and the sojourning tokens in the order they will be released; not the structure, the token
        ready times of the past or the counters. Equal keys: the net fires the same way from here."""
        marking = tuple(tuple((k, tuple(t.colour for t in b)) for k, b in p.buckets.items()) for p in self.places)
        pending = tuple((ready, p.index, t.colour) for ready, _, p, t in sorted(self._pending, key=_release_order))
        return hash((self.now, marking, pending))

    def marking(self) -> dict[str, int]:
        """Token counts per place (sojourning tokens counted under ``name + "~"``)."""
        out = {p.name: p.count for p in self.places}
        for p in self.places:
            if p.in_flight:
                out[p.name + "~"] = p.in_flight
        return out

    def iter_tokens(self) -> Iterator[tuple[Place, Token]]:
        for p in self.places:
            for b in p.buckets.values():
                for tok in b:
                    yield p, tok
