"""Events at one instant: in what order a schedule's tied operations and trips happen.

Operations of zero duration and trips over zero travel times can share an instant, and a schedule's times then
leave their order open. The validator (:mod:`fms_sim.validate`) and replay (:mod:`fms_sim.replay`) need one:

* each tool's uses in the order the tool serves them (:func:`tool_order`): by time, the uses at one instant in an
  order the tool can follow (each carried use's trip leaving from where the tool is, a job's operations in order);
* and all of those orders together with each part's operations and trips and each vehicle's recorded legs: some
  one sequence of the tied events must follow them all (:func:`settle`). A tool's order chosen on its own can
  contradict the others (two jobs at one instant, each needing the other's tool first), so where the orders so
  chosen close a cycle, the tools' orders at that instant are searched together (:func:`_search`); only where no
  order exists is the schedule's record contradictory (a transporter that records carrying a tool away from a
  machine before carrying it there).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace
from itertools import groupby

from .instance import Instance
from .schedule import Schedule

__all__ = ["tool_use_orders", "plan_orders", "has_ties"]

#: the most states :func:`_tied_order` visits for one tool at one instant before it gives up
_TIED_STATES = 100_000

#: the most states :func:`_search` visits at one instant before it gives up (the schedule is then refused, saying so)
_SEARCH_STATES = 100_000

#: the most operations and trips of one cycle a message names
_CYCLE_SHOWN = 8


class _GiveUp(Exception):
    """A search of tied orders (:func:`_tied_order`, :func:`_search`) visited too many states."""


def tool_order(us: list[tuple], trips: dict, origin: tuple[int, tuple[int, int] | None] = (0, None)) -> list[tuple]:
    """The uses of one tool (``(start, end, job, op, machine)``) in the order the tool serves them: by time; uses at
    the same instant (zero durations) in an order the tool can follow (:func:`_tied_order`), else, for the errors to
    name, one on the machine where the tool is before one it must be carried to, carried ones by their trip's start
    (job numbers do not decide: a trip may serve job 1 before job 0's use).

    ``origin``: where the tool stands when the schedule begins (the magazine, 0, for a whole schedule) and the use
    ``(job, op)`` it is held for then (None: none; a residual plan from a state, :func:`plan_orders`), which comes
    first."""
    out: list[tuple] = []
    loc, free = origin[0], 0  # where the tool is, and until when the uses so far hold it
    held = next((u for u in us if (u[2], u[3]) == origin[1]), None)
    if held is not None:  # the tool serves it before anything else, wherever the schedule's times put it
        us = [u for u in us if u is not held]
        out.append(held)
        loc, free = held[4], held[1]
    for _, group in groupby(sorted(us), key=lambda u: u[:2]):
        tied = list(group)
        found = _tied_order(tied, trips, loc, free) if len(tied) > 1 else None
        if found is not None:
            out += found
            loc, free = found[-1][4], max(free, found[0][1])  # the group's uses share their end
            continue
        while tied:  # no order the tool can follow: one for the checks to name what is wrong
            here = [u for u in tied if not trips.get((u[2], u[3])) and u[4] == loc]
            carried = sorted((u for u in tied if trips.get((u[2], u[3]))), key=lambda u: trips[u[2], u[3]][0].start)
            u = (here or carried or tied)[0]
            tied.remove(u)
            out.append(u)
            loc, free = u[4], max(free, u[1])
    return out


def _tied_order(tied: list[tuple], trips: dict, loc: int, free: int) -> list[tuple] | None:
    """An order of one tool's uses at one instant that the tool can follow from ``loc``, free from ``free`` on: each
    carried use's trip leaves from where the tool is and once it is free (a trip that left before the instant comes
    first), each other use is where the tool is, a job's operations in their order. None if there is none (the
    checks then name what is wrong) or the search gave up.

    An uncarried use where the tool is (its job's earlier uses done) is taken at once: it neither moves the tool
    nor can be needed later, so only the carried uses are choices: each in its transporter's route order (a
    transporter carries the tool in the order it drives), tried by trip start and the schedule's order of the trips,
    the dead ends remembered. So a group of dozens of uses is ordered at once."""
    def source(u: tuple) -> int:  # where the tool must be for the use (a carried one: where its trip leaves from)
        ts = trips.get((u[2], u[3]))
        return ts[0].from_ if ts else u[4]

    pos = {key: i for i, key in enumerate(trips)}  # the trips in the schedule's order (its routes' order)

    def rank(u: tuple) -> tuple:
        ts = trips.get((u[2], u[3]))
        return (1, ts[0].start, pos[u[2], u[3]], u[2], u[3]) if ts else (0, 0, 0, u[2], u[3])

    def first_of_job(u: tuple, rest: list[tuple]) -> bool:
        return not any(v[2] == u[2] and v[3] < u[3] for v in rest)

    def leg(u: tuple) -> tuple | None:  # a carried use's trip: its transporter and place on its route
        ts = trips.get((u[2], u[3]))
        return (ts[0].transporter, ts[0].start, ts[0].end, pos[u[2], u[3]]) if ts else None

    def next_on_route(u: tuple, rest: list[tuple]) -> bool:  # no trip of the tool before it on its transporter's route
        mine = leg(u)
        return mine is None or not any((o := leg(v)) is not None and o[0] == mine[0] and o < mine for v in rest)

    instant = tied[0][0]
    dead: set[tuple] = set()  # (uses left, where the tool is, free since) known to lead nowhere
    visits = 0

    def search(rest: list[tuple], at: int, since: int) -> list[tuple] | None:
        nonlocal visits
        taken: list[tuple] = []
        # a trip that left before the instant must be first: nothing is taken at once before it
        early = any(trips.get((u[2], u[3])) and trips[u[2], u[3]][0].start < max(since, instant) for u in rest)
        while not early:
            here = next((u for u in rest if not trips.get((u[2], u[3])) and u[4] == at and first_of_job(u, rest)),
                        None)
            if here is None:
                break
            rest = [u for u in rest if u is not here]
            taken.append(here)
            since = max(since, here[1])
        if not rest:
            return taken
        state = (frozenset(rest), at, since)
        if state in dead:
            return None
        visits += 1
        if visits > _TIED_STATES:
            raise _GiveUp
        for i, u in enumerate(rest):
            ts = trips.get((u[2], u[3]))
            if (source(u) != at or (ts and ts[0].start < since) or not first_of_job(u, rest)
                    or not next_on_route(u, rest)):
                continue
            tail = search(rest[:i] + rest[i + 1:], u[4], max(since, u[1]))
            if tail is not None:
                return taken + [u] + tail
        dead.add(state)
        return None

    try:
        return search(sorted(tied, key=rank), loc, free)
    except (_GiveUp, RecursionError):
        return None


def uses_by_tool(instance: Instance, ops: dict) -> dict[int, list[tuple]]:
    """Per tool, its uses ``(start, end, job, op, machine)`` by time, for the operations in ``ops`` (``(job, op)``
    -> ``(start, end)``)."""
    uses: dict[int, list[tuple]] = defaultdict(list)
    for j, job in enumerate(instance.jobs):
        for k, spec in enumerate(job):
            if spec.tool is not None and (j, k) in ops:
                uses[spec.tool].append((*ops[j, k], j, k, spec.machine))
    for us in uses.values():
        us.sort()
    return uses


def trips_by_op(moves: list) -> dict[tuple, list]:
    """One tool's loaded trips by the operation they serve, in the schedule's order (its routes' order)."""
    trips: dict[tuple, list] = {}
    for t in moves:
        trips.setdefault((t.job, t.op), []).append(t)
    return trips


def tool_use_orders(instance: Instance, schedule: Schedule) -> dict[int, list[tuple[int, int]]]:
    """Per tool, its uses ``(job, op)`` in the order the tool serves them, as the validator checks them (uses at one
    instant in an order the tool can follow, and that agrees with the parts' and vehicles' orders): what a replay
    of ``schedule`` must keep."""
    if not instance.has_tools:
        return {}
    orders, _ = settle(instance, schedule, {(r.job, r.op): (r.start, r.end) for r in schedule.operations})
    return {tool: [(u[2], u[3]) for u in us] for tool, us in orders.items()}


def has_ties(schedule: Schedule) -> bool:
    """Whether anything in ``schedule`` has zero length (an operation or a trip): only then can events tie in a way
    its times leave open, and a model whose precedences are inequalities (CP-SAT's) may order them impossibly."""
    return (any(r.start == r.end for r in schedule.operations) or any(t.start == t.end for t in schedule.agv_trips)
            or any(t.start == t.end for t in schedule.tool_trips))


def plan_orders(instance: Instance, schedule: Schedule,
                origin: dict[int, tuple[int, tuple[int, int] | None]] | None = None
                ) -> tuple[dict[int, list[tuple[int, int]]], dict[tuple[int, int], int]]:
    """What a replay of ``schedule`` must keep: per tool its uses ``(job, op)`` in the order the tool serves them (as
    :func:`tool_use_orders`), and per operation of zero duration its place in one sequence of all the tied events
    that follows every resource (a topological order of the graph :func:`settle` checks, the same graph: ties by
    time, trips before operations, then list order). A machine serves its operations at one instant in that order;
    by their list order instead, it could close a circular wait with a transporter's carries for them, and the replay
    of a valid schedule got stuck. Where the graph has a cycle (not a valid schedule) the events on it come last, in
    time and list order.

    ``origin`` (tool -> where it stands and the use ``(job, op)`` it is held for, or None) is the state a residual
    plan starts from (:meth:`fms_sim.replay.PlanPolicy.resume`); without it each tool starts in the magazine (0),
    held for nothing, as a whole schedule's do. A held use comes first in its tool's order and its carry, if the
    schedule records one, counts as made. Ordered from the magazine instead, the tied uses of a tool that stands
    elsewhere came out in an order the tool cannot follow, which the machines' orders (by the same ranks) and the
    transporters' routes contradicted, and the replay of the residual plan got stuck."""
    import heapq

    ops = {(r.job, r.op): (r.start, r.end) for r in schedule.operations}
    if origin:
        held = {(t, *op) for t, (_, op) in origin.items() if op is not None}
        if held:  # (its carry is made: the tool is on its way, or there)
            schedule = replace(schedule, tool_trips=[t for t in schedule.tool_trips
                                                      if not t.loaded or (t.tool, t.job, t.op) not in held])
    orders, _, when, succ = _settle(instance, schedule, ops, None, origin)
    tools = {tool: [(u[2], u[3]) for u in us] for tool, us in orders.items()}
    if not when:
        return tools, {}
    index = {("op", r.job, r.op): i for i, r in enumerate(schedule.operations)}

    def key(e: tuple) -> tuple:
        return (when[e], 1, index[e]) if e[0] == "op" else (when[e], 0, e[1])

    indeg = dict.fromkeys(when, 0)
    for a, bs in succ.items():
        for b in bs:
            indeg[b] += 1
    heap = [(key(e), e) for e, d in indeg.items() if not d]
    heapq.heapify(heap)
    seq: list[tuple] = []
    while heap:
        _, e = heapq.heappop(heap)
        seq.append(e)
        for b in succ.get(e, ()):
            indeg[b] -= 1
            if not indeg[b]:
                heapq.heappush(heap, (key(b), b))
    if len(seq) < len(when):  # a cycle
        done = set(seq)
        seq += sorted((e for e in when if e not in done), key=key)
    rank = {(e[1], e[2]): i for i, e in enumerate(e for e in seq if e[0] == "op")}
    return tools, rank


def settle(instance: Instance, schedule: Schedule, ops: dict,
           orders: dict[int, list[tuple]] | None = None) -> tuple[dict[int, list[tuple]], str | None]:
    """Each tool's uses in the order it serves them (:func:`tool_order`, or ``orders`` where the caller made them
    already, re-ordered in place at an instant where those orders contradict the parts' and vehicles' orders and
    some other order agrees with them all), and the contradiction that remains as an error message (None: some one
    sequence of the tied events follows them all).

    The events are the operations and trips of zero length (``ops``: ``(job, op) -> (start, end)``); what must
    precede what among them (a part's operations and trips, each vehicle's legs in the schedule's order, a tool's
    carries and uses) forms a graph. Between events at different times the validator's checks order them; every
    edge between two operations or trips leads from one's end to the other's start, so a cycle passes only through
    operations and trips of zero length at one instant, and the graph is built over those alone (none in most
    shops). Meant for a schedule that passed the validator's other checks."""
    orders, message, _, _ = _settle(instance, schedule, ops, orders)
    return orders, message


def _settle(instance: Instance, schedule: Schedule, ops: dict, orders: dict[int, list[tuple]] | None,
            origin: dict[int, tuple[int, tuple[int, int] | None]] | None = None
            ) -> tuple[dict[int, list[tuple]], str | None, dict[tuple, int], dict[tuple, list[tuple]]]:
    """:func:`settle`, also returning the tied events (event -> its instant) and the graph over them with the tools'
    orders as settled (empty where nothing is tied). ``origin``: where each tool starts and the use it is held for
    (:func:`plan_orders`; absent: the magazine, held for nothing)."""
    origin = origin or {}
    if orders is None:
        moves: dict[int, list] = defaultdict(list)
        for t in schedule.tool_trips:
            if t.loaded and t.tool is not None and t.job is not None and t.op is not None:
                moves[t.tool].append(t)
        orders = {tool: tool_order(us, trips_by_op(moves.get(tool, [])), origin.get(tool, (0, None)))
                  for tool, us in uses_by_tool(instance, ops).items()} if instance.has_tools else {}
    when: dict[tuple, int] = {("op", j, k): s for (j, k), (s, e) in ops.items() if s == e}
    when.update((("agv", i), t.start) for i, t in enumerate(schedule.agv_trips) if t.start == t.end)
    when.update((("tt", i), t.start) for i, t in enumerate(schedule.tool_trips) if t.start == t.end)
    if not when:
        return orders, None, when, {}
    carrier = {(t.tool, t.job, t.op): i for i, t in enumerate(schedule.tool_trips) if t.loaded}
    fixed = _fixed_edges(instance, schedule, when, carrier)
    searched: set[int] = set()
    while True:
        succ = _with_tools(fixed, orders, when, carrier)
        cycle = _find_cycle(succ)
        if cycle is None:
            return orders, None, when, succ
        instant = when[cycle[0]]
        try:
            found = None if instant in searched else _search(instant, fixed, orders, when, carrier, schedule,
                                                                 origin)
        except _GiveUp:
            return orders, (f"at time {instant} the order of the tied events could not be settled within "
                            f"{_SEARCH_STATES:,} states of the search (the tools' orders on their own close a cycle "
                            "with the parts' and routes' orders; a shop with fewer tied carries at one instant "
                            "is checked in full)"), when, succ
        searched.add(instant)
        if found is None:
            names = [_event(schedule, e) for e in cycle]
            shown = names[:_CYCLE_SHOWN] + (["..."] if len(names) > _CYCLE_SHOWN else [])
            return orders, (f"at time {instant} no order of the events follows every resource: "
                            f"{' -> '.join(shown + names[:1])} (each must come before the next; zero-length trips "
                            "or operations recorded in contradicting orders)"), when, succ
        for tool, seq in found.items():  # the tool's uses at the instant, in the order found
            us = orders[tool]
            at = [i for i, u in enumerate(us) if u[0] == u[1] == instant]
            for i, u in zip(at, seq):
                us[i] = u


def _fixed_edges(instance: Instance, schedule: Schedule, when: dict[tuple, int],
                 carrier: dict[tuple, int]) -> dict[tuple, list[tuple]]:
    """What must precede what among the tied events whatever the tools' orders: each part's operations and trips,
    each vehicle's legs (in the schedule's order, as the route check reads them), each tool carry before its use."""
    succ: dict[tuple, list[tuple]] = defaultdict(list)

    def before(a: tuple, b: tuple) -> None:
        t = when.get(a)
        if t is not None and when.get(b) == t:
            succ[a].append(b)

    routes: list[tuple[str, dict[int, list]]] = [("agv", defaultdict(list)), ("tt", defaultdict(list))]
    for i, a in enumerate(schedule.agv_trips):
        routes[0][1][a.agv].append((a.start, a.end, i))
    for i, r in enumerate(schedule.tool_trips):
        routes[1][1][r.transporter].append((r.start, r.end, i))
    for kind, legs in routes:
        for route in legs.values():
            route.sort(key=lambda leg: leg[:2])  # stable, as the route check orders them
            for a, b in zip(route, route[1:]):
                before((kind, a[2]), (kind, b[2]))
    carry = {(a.job, a.op): i for i, a in enumerate(schedule.agv_trips) if a.loaded}
    for j, job in enumerate(instance.jobs):
        for k in range(len(job)):
            c = carry.get((j, k)) if instance.has_agvs else None
            if c is None:
                if k:
                    before(("op", j, k - 1), ("op", j, k))
                continue
            if k:
                before(("op", j, k - 1), ("agv", c))
            before(("agv", c), ("op", j, k))
    for (tool, j, k), i in carrier.items():
        before(("tt", i), ("op", j, k))
    return succ


def _with_tools(fixed: dict[tuple, list[tuple]], orders: dict[int, list[tuple]], when: dict[tuple, int],
                carrier: dict[tuple, int]) -> dict[tuple, list[tuple]]:
    """``fixed`` and each tool's order: a use (or the carry that brings the tool to it) after the use before it."""
    succ = defaultdict(list, {a: list(bs) for a, bs in fixed.items()})
    for tool, us in orders.items():
        for p, u in zip(us, us[1:]):
            a = ("op", p[2], p[3])
            t = when.get(a)
            if t is None:
                continue
            i = carrier.get((tool, u[2], u[3]))
            b = ("tt", i) if i is not None else ("op", u[2], u[3])
            if when.get(b) == t:
                succ[a].append(b)
    return succ


def _search(t: int, fixed: dict[tuple, list[tuple]], orders: dict[int, list[tuple]], when: dict[tuple, int],
            carrier: dict[tuple, int], schedule: Schedule,
            origin: dict[int, tuple[int, tuple[int, int] | None]] | None = None) -> dict[int, list[tuple]] | None:
    """Orders of the tools' uses at instant ``t`` that agree with ``fixed`` (a sequence of all the tied events at
    ``t`` that each tool can follow), per tool the uses at ``t`` in order; None if there is none; raises
    :class:`_GiveUp` past :data:`_SEARCH_STATES`. An event without a tool, a use where its free tool is and the use
    a tool is held for are taken as soon as what precedes them is done (none moves or holds a tool, so taking it
    never blocks anything); the carries are the choices, searched depth-first, the dead ends remembered. A tool
    starts where ``origin`` says (else the magazine), held for the use it names there (:func:`plan_orders`)."""
    origin = origin or {}
    items = [e for e, w in when.items() if w == t]
    indeg0 = dict.fromkeys(items, 0)
    for a in items:
        for b in fixed.get(a, ()):
            if b in indeg0:
                indeg0[b] += 1
    group: dict[int, list[tuple]] = {}  # tool -> its uses at t
    start: dict[int, tuple[int, tuple | None, int]] = {}  # tool -> (where, the use it is held for, uses left)
    use_of: dict[tuple, tuple[int, int, bool]] = {}  # use event -> (tool, machine, carried)
    carry_of: dict[tuple, tuple[int, tuple, int, int]] = {}  # carry event -> (tool, use event, from, to)
    for tool, us in orders.items():
        at = [i for i, u in enumerate(us) if u[0] == u[1] == t]
        if not at:
            continue
        group[tool] = [us[i] for i in at]
        held = None
        for u in group[tool]:
            i = carrier.get((tool, u[2], u[3]))
            e = ("op", u[2], u[3])
            use_of[e] = (tool, u[4], i is not None)
            if i is not None and when.get(("tt", i)) != t:  # its carry left before the instant: it comes first
                held = e
        where = us[at[0] - 1][4] if at[0] else origin.get(tool, (0, None))[0]
        reserved = origin.get(tool, (0, None))[1]
        if not at[0] and held is None and reserved == us[0][2:4]:  # the tool's first use, the one it is held for
            held = ("op", *reserved)
        start[tool] = (where, held, len(at))
    for (tool, j, k), i in carrier.items():
        if tool in group and when.get(("tt", i)) == t:
            trip = schedule.tool_trips[i]
            carry_of["tt", i] = (tool, ("op", j, k), trip.from_, trip.to)
    dead: set[tuple] = set()
    visits = 0

    def go(done: frozenset, indeg: dict, state: dict, seq: list) -> list | None:
        nonlocal visits
        indeg = dict(indeg)
        done_l = set(done)
        state = dict(state)
        while True:  # what is no choice, as soon as it may happen: events without a tool, a use where its tool is
            fired = False  # (free) or of the use its tool is held for; neither moves or holds a tool
            for e in items:
                if e in done_l or indeg[e] or e in carry_of:
                    continue
                if e in use_of:
                    tool, machine, carried = use_of[e]
                    where, held, left = state[tool]
                    if held != e and (carried or held is not None or where != machine):
                        continue  # (a use the tool is held for goes, carried or not; another only where it is)
                    state[tool] = (machine, None, left - 1)
                done_l.add(e)
                seq = seq + [e]
                fired = True
                for b in fixed.get(e, ()):
                    if b in indeg:
                        indeg[b] -= 1
            if not fired:
                break
        if len(done_l) == len(items):
            return seq
        key = (frozenset(done_l), tuple(sorted(state.items())))
        if key in dead:
            return None
        visits += 1
        if visits > _SEARCH_STATES:
            raise _GiveUp
        for e in items:  # the choices: which carry next
            if e in done_l or indeg[e] or e not in carry_of:
                continue
            tool, use, src, dst = carry_of[e]
            where, held, left = state[tool]
            if held is not None or where != src or (use not in use_of and left):
                continue  # (a carry for a later use comes after the tool's uses at the instant)
            after: tuple[int, tuple | None, int] = (dst, use if use in use_of else None, left)
            nxt = dict(indeg)
            for b in fixed.get(e, ()):
                if b in nxt:
                    nxt[b] -= 1
            found = go(frozenset(done_l | {e}), nxt, {**state, tool: after}, seq + [e])
            if found is not None:
                return found
        dead.add(key)
        return None

    try:
        seq = go(frozenset(), indeg0, start, [])
    except RecursionError:  # (a carry per level: only a shop with hundreds of tied carries)
        raise _GiveUp from None
    if seq is None:
        return None
    place = {e: i for i, e in enumerate(seq)}
    return {tool: sorted(us, key=lambda u: place["op", u[2], u[3]]) for tool, us in group.items()}


def _find_cycle(succ: dict[tuple, list[tuple]]) -> list[tuple] | None:
    """One cycle of the graph ``succ`` (its nodes in order), or None if it has none."""
    state: dict[tuple, int] = {}  # 1: on the current path, 2: done
    for root in list(succ):
        if root in state:
            continue
        path, stack = [root], [iter(succ[root])]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(succ.get(nxt, ())))
    return None


def _event(schedule: Schedule, e: tuple) -> str:
    """A tied operation or trip in words."""
    if e[0] == "op":
        return f"op ({e[1]},{e[2]})"
    if e[0] == "agv":
        a = schedule.agv_trips[e[1]]
        return f"AGV {a.agv}'s trip {a.from_}->{a.to}" + (f" with op ({a.job},{a.op})'s part" if a.loaded else "")
    r = schedule.tool_trips[e[1]]
    return (f"transporter {r.transporter}'s trip {r.from_}->{r.to}"
            + (f" with tool {r.tool} for op ({r.job},{r.op})" if r.loaded else ""))
