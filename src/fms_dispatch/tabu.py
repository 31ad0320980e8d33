"""Tabu search over a schedule's resource orders: a fast improver of the guide's plans.

The list schedules (:func:`fms_dispatch.exact.greedy_schedule`) append every activity to the end of its resources
and pick a vehicle by a fixed rule, and their randomised restarts stall a few per cent above the best known
schedules (docs/benchmarks.md §9). This module searches a space that holds every semi-active schedule instead:
the order of the operations on each machine, of the loaded trips on each AGV, of the uses of each tool and of the
tool deliveries on each transporter (which vehicle carries what is part of the orders). Given the orders, the
earliest times follow in one pass over the *disjunctive graph*: job chains; machine orders; AGV routes, whose empty
legs run from one drop-off to the next pickup; tool orders, where a use on another machine than the tool's previous
use needs a delivery (after that use ended) and a use on the same machine needs none; transporter routes over the
deliveries. Its critical path says which changes can shorten the makespan:

* swap two adjacent operations of a machine (with their tool uses if they share a tool) that follow each other
  on the critical path;
* swap two adjacent trips of an AGV or a transporter that follow each other on it;
* move a critical trip that waits for its vehicle (any critical trip in a shop without tools and two AGVs) to
  another vehicle, next to the place its start time gives it there (a trip may not move again for a few
  iterations);
* swap two adjacent uses of a tool that follow each other on the critical path, move a critical use next to the
  nearest use of its tool on the same machine (no delivery between them), or move a use of a critical block of a
  tool's uses to the block's front or back; the deliveries this creates go to the transporter free earliest, those
  it makes unneeded are dropped.

Moves are ranked by an estimate of the makespan after them (the longest path through the nodes they change, from the
current heads and tails; a tool swap's ignores the transporters); tool insertions and block moves, and swaps of two
operations of one machine that also share a tool, are evaluated in full. Each iteration takes the best move not
forbidden by the tabu list (the reverse of a recent move, unless it beats the best schedule) whose orders have no
cycle, until the time budget, the iteration limit, the stall limit or the lower bound. The result is rebuilt as a
:class:`~fms_sim.schedule.Schedule` (empty trips leave as soon as the vehicle is free) that the validator accepts;
it is never worse than the start.

It improves residual plans too (re-planning from a running shop's state, :class:`~fms_sim.snapshot.Snapshot`):
the operations that have started are fixed, and the graph's sources are the state's instead of the depot at time
0: when each part is free to move (or at its machine, when its move is done or committed), each machine and tool
is free, where and when each vehicle is free (one standing idle leaves for its first load only once that load is
dispatched, ``Snapshot.held``), and a tool reserved for an operation serves it first without a delivery (a move that
puts another use before it is refused, as a cycle is).
"""

from __future__ import annotations

import numbers
import random
import time
from typing import Callable, Iterator, Sequence

from fms_sim.instance import Instance, require_instance
from fms_sim.schedule import AgvTrip, OperationRecord, Schedule, ToolTrip
from fms_sim.snapshot import Snapshot

from .progress import say

__all__ = ["tabu_plan", "solve_tabu", "residual_lower_bound"]

#: how many iterations a move's reverse stays forbidden: this many plus a random 0..TENURE_SPREAD-1
TENURE = 6
TENURE_SPREAD = 5


Orders = tuple[list[list[int]], list[list[int]], list[list[int]], list[list[int]]]
"""Machine orders (index = machine), AGV orders, tool orders (index = tool), transporter orders; entries are
operation numbers (a trip or delivery is named by the operation it serves)."""


class _Graph:
    """The fixed part of an instance's disjunctive graph. Operations are numbered job by job; node ``i`` is
    operation ``i``, node ``n + i`` its loaded AGV trip (when ``carried[i]``: ``pick[i] -> mach[i]``), node
    ``2n + i`` the delivery of its tool (when the tool comes from elsewhere)."""

    def __init__(self, inst: Instance, origin: Snapshot | None = None):
        self.inst = inst
        self.origin = origin
        self.key: list[tuple[int, int]] = []
        self.dur: list[int] = []
        self.mach: list[int] = []
        self.tool: list[int] = []
        self.jpred: list[int] = []
        self.jsucc: list[int] = []
        self.pick: list[int] = []
        tools = inst.has_tools
        first = origin.next_op if origin is not None else (0,) * inst.n_jobs  # each job's first operation to plan
        arrival = origin.arrival if origin is not None else {}
        ready = origin.ready if origin is not None else (0,) * inst.n_jobs
        live: list[int] = []
        head0: list[bool] = []  # the job's first operation to plan
        for j, job in enumerate(inst.jobs):
            for k, op in enumerate(job):
                i = len(self.key)
                self.key.append((j, k))
                self.dur.append(op.duration)
                self.mach.append(op.machine)
                self.tool.append(op.tool if tools and op.tool is not None else -1)
                self.jpred.append(i - 1 if k > first[j] else -1)
                self.jsucc.append(i + 1 if k + 1 < len(job) else -1)
                self.pick.append(job[k - 1].machine if k else 0)
                head0.append(k == first[j])
                if k >= first[j]:
                    live.append(i)
        n = self.n = len(self.key)
        #: the operations planned (all of them for a whole schedule; those not started for a residual plan)
        self.live = live
        self.index = {key: i for i, key in enumerate(self.key)}
        tr = self.travel = inst.agv_travel
        self.ttravel = inst.tool_travel
        # a part whose move to its machine is done or committed (``arrival``) needs no trip
        self.carried = [tr is not None and self.pick[i] != self.mach[i]
                        and not (head0[i] and self.key[i][0] in arrival) for i in range(n)]
        self.loaded = [tr[self.pick[i]][self.mach[i]] if self.carried[i] else 0 for i in range(n)]
        self.P2 = self.dur + self.loaded
        self.pick0 = [0] * n + self.pick  # node n + i picks up at pick[i] (nodes below n: operations, unused)
        self.n_tools = inst.n_tools if tools else 0
        self.n_vehicles = (inst.n_agvs, inst.n_tool_transporters if tools else 0)
        # where a plan starts from (all zero for a whole schedule: the depot at time 0): when each job's part is free
        # to move (or at its machine, where it needs no trip), each machine is free, each tool is free (and for a tool
        # reserved for an operation, when it is there: that use comes first and needs no delivery), each vehicle is
        # where and free when
        self.prel = [(arrival.get(self.key[i][0], ready[self.key[i][0]]) if head0[i] else 0) for i in range(n)]
        mfree = origin.machine_free if origin is not None else (0,) * (inst.n_machines + 1)
        self.mrel = [mfree[m] for m in self.mach]
        tfree = origin.tool_free if origin is not None and tools else (0,) * (self.n_tools + 1)
        self.tloc0 = list(origin.tool_loc) if origin is not None and tools else [0] * (self.n_tools + 1)
        self.reserved: dict[int, int] = {}
        self.trel = [tfree[t] if t >= 0 else 0 for t in self.tool]
        if origin is not None and tools:
            for t, (j, k, at) in origin.tool_reserved.items():
                i = self.index[j, k]
                self.reserved[t] = i
                self.trel[i] = max(self.trel[i], at)
        o = origin
        self.v0 = ((list(o.agv_loc), list(o.agv_free)) if o is not None else ([0] * inst.n_agvs, [0] * inst.n_agvs),
                   (list(o.tt_loc), list(o.tt_free)) if o is not None and tools
                   else ([0] * self.n_vehicles[1], [0] * self.n_vehicles[1]))
        self.base = o.makespan if o is not None else 0  # when the operations already started end
        # vehicles idle at the snapshot (Snapshot.held) leave for their first load only when it is dispatched: a part
        # once its previous operation has started, a tool once its previous use has (now: that has happened)
        held = o.held if o is not None else frozenset()
        self.held = ([("agv", v) in held for v in range(inst.n_agvs)],
                     [("tt", r) in held for r in range(self.n_vehicles[1])])
        self.now = o.now if o is not None else 0
        # the earliest start of every node from the start state alone (0 throughout for a whole schedule)
        self.rel = ([max(self.mrel[i], self.trel[i], 0 if self.carried[i] else self.prel[i]) for i in range(n)]
                    + [self.prel[i] if self.carried[i] else 0 for i in range(n)] + self.trel)

    def deliveries(self, tseq: Sequence[Sequence[int]]) -> tuple[list[int], list[int]]:
        """Per operation, the previous use of its tool (-1: none) and where its tool comes from (-1: no delivery,
        the tool is at the machine already or the operation needs none)."""
        n, mach, tloc0, reserved = self.n, self.mach, self.tloc0, self.reserved
        tpred = [-1] * n
        src = [-1] * n
        for t, seq in enumerate(tseq):
            prev = -1
            for i in seq:
                tpred[i] = prev
                here = mach[prev] if prev >= 0 else tloc0[t]
                if here != mach[i] and not (prev < 0 and reserved.get(t) == i):
                    src[i] = here
                prev = i
        return tpred, src

    def evaluate(self, o: Orders) -> "_Eval | None":
        """The semi-active schedule of these orders (earliest start of every node and the node whose end fixed
        it), or None if they form a cycle."""
        mseq, aseq, tseq, rseq = o
        n = self.n
        for t, i in self.reserved.items():  # a reserved tool serves its operation first
            if not tseq[t] or tseq[t][0] != i:
                return None
        mpred, msucc, vpred, vsucc = [-1] * n, [-1] * n, [-1] * (3 * n), [-1] * (3 * n)
        for seq in mseq:
            for a, b in zip(seq, seq[1:]):
                mpred[b] = a
                msucc[a] = b
        for seq in aseq:
            for a, b in zip(seq, seq[1:]):
                vpred[n + b] = n + a
                vsucc[n + a] = n + b
        for seq in rseq:
            for a, b in zip(seq, seq[1:]):
                vpred[2 * n + b] = 2 * n + a
                vsucc[2 * n + a] = 2 * n + b
        tpred, src = self.deliveries(tseq)
        tsucc = [-1] * n
        for i in range(n):
            if tpred[i] >= 0:
                tsucc[tpred[i]] = i
        carried, jpred, jsucc, mach, dur = self.carried, self.jpred, self.jsucc, self.mach, self.dur
        tr, ttr = self.travel, self.ttravel
        n2 = 2 * n
        # node durations: operations, loaded trips, deliveries (from where the tool order says)
        P = self.P2 + ([ttr[src[i]][mach[i]] if src[i] >= 0 else 0 for i in range(n)] if ttr is not None
                       else [0] * n)
        org = self.pick0 + src  # where each trip (node n + i) and delivery (node 2n + i) picks its load up
        # when each vehicle's first load can start: its empty trip from where it stands, once free; a held vehicle's
        # (vheld: that empty trip) also no earlier than the load's dispatch
        vstart: dict[int, int] = {}
        vheld: dict[int, int] = {}
        for seqs, base, mat, (loc0, free0), held in ((aseq, n, tr, self.v0[0], self.held[0]),
                                                     (rseq, n2, ttr, self.v0[1], self.held[1])):
            for v, seq in enumerate(seqs):
                if seq:
                    node = base + seq[0]
                    empty = mat[loc0[v]][org[node]]  # type: ignore[index]  # (a vehicle with carries: a matrix)
                    vstart[node] = free0[v] + empty
                    if held[v]:
                        vheld[node] = empty
        indeg = [0] * (3 * n)
        nodes = 0
        stack = []
        for i in self.live:
            d = (mpred[i] >= 0) + (carried[i] or jpred[i] >= 0) + (src[i] >= 0 or tpred[i] >= 0)
            indeg[i] = d
            if not d:
                stack.append(i)
            nodes += 1
            if carried[i]:
                d = (jpred[i] >= 0) + (vpred[n + i] >= 0)
                indeg[n + i] = d
                if not d:
                    stack.append(n + i)
                nodes += 1
            if src[i] >= 0:
                d = (tpred[i] >= 0) + (vpred[n2 + i] >= 0)
                indeg[n2 + i] = d
                if not d:
                    stack.append(n2 + i)
                nodes += 1
        start = list(self.rel)
        crit = [-1] * (3 * n)
        order: list[int] = []
        append, pop = stack.append, stack.pop
        # the hot loop of the search: each arc's relaxation is written out in place (a helper call per arc cost ~5 %)
        while stack:
            v = pop()
            order.append(v)
            if v < n:
                end = start[v] + dur[v]
                s = jsucc[v]
                if s >= 0:
                    w = n + s if carried[s] else s
                    if end > start[w] or (end == start[w] and crit[w] < 0):
                        start[w] = end
                        crit[w] = v
                    indeg[w] -= 1
                    if not indeg[w]:
                        append(w)
                w = msucc[v]
                if w >= 0:
                    if end > start[w] or (end == start[w] and crit[w] < 0):
                        start[w] = end
                        crit[w] = v
                    indeg[w] -= 1
                    if not indeg[w]:
                        append(w)
                s = tsucc[v]
                if s >= 0:
                    w = n2 + s if src[s] >= 0 else s
                    if end > start[w] or (end == start[w] and crit[w] < 0):
                        start[w] = end
                        crit[w] = v
                    indeg[w] -= 1
                    if not indeg[w]:
                        append(w)
                continue
            # an AGV trip or a tool delivery: its vehicle starts at location 0 at time 0, drives empty between loads
            if v < n2:
                i, mat = v - n, tr
            else:
                i, mat = v - n2, ttr
            if vpred[v] < 0:  # the vehicle's first load: the empty trip from where it stands
                e = vstart[v]
                if vheld and v in vheld:  # from the dispatch (its job's or tool's previous start: popped already)
                    y = jpred[i] if v < n2 else tpred[i]
                    d = (start[y] if y >= 0 else self.now) + vheld[v]
                    if d > e:
                        e = d
                if e > start[v]:
                    start[v], crit[v] = e, -1
            end = start[v] + P[v]
            w = vsucc[v]
            if w >= 0:
                t = end + mat[mach[i]][org[w]]
                if t > start[w] or (t == start[w] and crit[w] < 0):
                    start[w] = t
                    crit[w] = v
                indeg[w] -= 1
                if not indeg[w]:
                    append(w)
            if end > start[i] or (end == start[i] and crit[i] < 0):  # the operation the trip serves
                start[i] = end
                crit[i] = v
            indeg[i] -= 1
            if not indeg[i]:
                append(i)
        if len(order) != nodes:
            return None
        last = max(self.live, key=lambda i: start[i] + dur[i])
        return _Eval(max(start[last] + dur[last], self.base), start, crit, order, mpred, msucc, vpred, vsucc, tpred,
                     tsucc, src, org, P, last)

    def tails(self, ev: "_Eval") -> list[int]:
        """Per node, the longest path from its end to the end of the schedule (its tail)."""
        n = self.n
        q = [0] * (3 * n)
        P, src = ev.P, ev.src
        carried, jsucc, tr, ttr, mach = self.carried, self.jsucc, self.travel, self.ttravel, self.mach
        msucc, vsucc, tsucc = ev.msucc, ev.vsucc, ev.tsucc
        for v in reversed(ev.order):
            if v < n:
                t = 0
                s = jsucc[v]
                if s >= 0:
                    w = n + s if carried[s] else s
                    t = P[w] + q[w]
                s = msucc[v]
                if s >= 0 and P[s] + q[s] > t:
                    t = P[s] + q[s]
                s = tsucc[v]
                if s >= 0:
                    w = 2 * n + s if src[s] >= 0 else s
                    if P[w] + q[w] > t:
                        t = P[w] + q[w]
                q[v] = t
            else:
                i = v - n if v < 2 * n else v - 2 * n
                t = P[i] + q[i]
                w = vsucc[v]
                if w >= 0:
                    x = (tr if v < 2 * n else ttr)[mach[i]][ev.org[w]] + P[w] + q[w]
                    if x > t:
                        t = x
                q[v] = t
        return q

    def critical_path(self, ev: "_Eval") -> list[int]:
        """The nodes of one critical path, first to last (it ends at an operation that ends last)."""
        crit = ev.crit
        path = [ev.last]
        while crit[path[-1]] >= 0:
            path.append(crit[path[-1]])
        path.reverse()
        return path


class _Eval:
    """One evaluation of the orders: makespan, node starts, critical predecessors, a topological order, each
    node's resource neighbours, each use's previous and next use of its tool and its delivery origin (-1: none),
    where each trip or delivery node picks its load up (``org``), the node durations and the operation that ends
    last."""

    __slots__ = ("makespan", "start", "crit", "order", "mpred", "msucc", "vpred", "vsucc", "tpred", "tsucc", "src",
                 "org", "P", "last")

    def __init__(self, makespan: int, start: list[int], crit: list[int], order: list[int], mpred: list[int],
                 msucc: list[int], vpred: list[int], vsucc: list[int], tpred: list[int], tsucc: list[int],
                 src: list[int], org: list[int], P: list[int], last: int):
        self.makespan, self.start, self.crit, self.order, self.last = makespan, start, crit, order, last
        self.mpred, self.msucc, self.vpred, self.vsucc = mpred, msucc, vpred, vsucc
        self.tpred, self.tsucc, self.src, self.org, self.P = tpred, tsucc, src, org, P


_Move = tuple[int, tuple, tuple, str, tuple]


def _neighbours(g: _Graph, ev: _Eval, q: list[int], o: Orders, where: list[int]) -> list[_Move]:
    """The moves around the critical path: ``(estimate, attribute, reverse, kind, args)``; the estimate -1 means
    "evaluate in full"."""
    n = g.n
    start, P, dur = ev.start, ev.P, g.dur
    carried, jpred, jsucc, mach, tool = g.carried, g.jpred, g.jsucc, g.mach, g.tool
    mpred, msucc, vpred, vsucc, src = ev.mpred, ev.msucc, ev.vpred, ev.vsucc, ev.src
    tr, ttr = g.travel, g.ttravel

    tpred, tsucc = ev.tpred, ev.tsucc
    # where the plan starts from (zeros for a whole schedule): part, machine and tool release times, vehicles
    prel, mrel, trel, tloc0, v0 = g.prel, g.mrel, g.trel, g.tloc0, g.v0

    def head_part(x: int) -> int:  # when operation x's part is at its machine, from the job's side
        if carried[x]:
            return start[n + x] + P[n + x]
        y = jpred[x]
        return start[y] + dur[y] if y >= 0 else prel[x]

    def head_tool(x: int) -> int:  # when operation x's tool is at its machine (0: no tool)
        if src[x] >= 0:
            return start[2 * n + x] + P[2 * n + x]
        y = tpred[x]
        return start[y] + dur[y] if y >= 0 else trel[x]

    def head_machine(x: int) -> int:  # when operation x's machine is free, from the machine's side
        y = mpred[x]
        return start[y] + dur[y] if y >= 0 else mrel[x]

    def tail_job(x: int) -> int:  # the longest path after operation x along its job
        s = jsucc[x]
        if s < 0:
            return 0
        w = n + s if carried[s] else s
        return P[w] + q[w]

    def tail_tool(x: int) -> int:  # the longest path after operation x along its tool's uses
        s = tsucc[x]
        if s < 0:
            return 0
        w = 2 * n + s if src[s] >= 0 else s
        return P[w] + q[w]

    def move_tool(a: int, b: int) -> int:  # a delivery of operation b's tool from operation a's machine (a = -1:
        here = mach[a] if a >= 0 else tloc0[tool[b]]  # from where the tool starts)
        return ttr[here][mach[b]] if here != mach[b] else 0

    def ready(v: int) -> int:  # when trip or delivery v may start, from its load's side
        i = v - n if v < 2 * n else v - 2 * n
        if v < 2 * n:
            y = jpred[i]
            return start[y] + dur[y] if y >= 0 else prel[i]
        y = ev.tpred[i]
        return start[y] + dur[y] if y >= 0 else trel[i]

    org = ev.org

    def leg(a: int, b: int, veh: int) -> int:  # the empty leg of vehicle veh from the drop-off of a (-1: none: from
        agv = b < 2 * n  # where the vehicle starts) to the pickup of b
        mat = tr if agv else ttr
        return mat[mach[a - n if a < 2 * n else a - 2 * n] if a >= 0 else v0[0 if agv else 1][0][veh]][org[b]]

    def free(a: int, b: int, veh: int) -> int:  # when vehicle veh, whose last load was a (-1: none), can start b
        return (start[a] + P[a] if a >= 0 else v0[0 if b < 2 * n else 1][1][veh]) + leg(a, b, veh)

    def tool_swap(u: int, v: int) -> int:
        """The estimate for serving v before u (adjacent uses of a tool): deliveries as the new order needs them,
        without waiting for a transporter."""
        a, b = tpred[u], tsucc[v]
        ta = start[a] + dur[a] if a >= 0 else trel[u]
        rv = max(head_part(v), head_machine(v), ta + move_tool(a, v))
        ru = max(head_part(u), head_machine(u), rv + dur[v] + move_tool(v, u))
        qu = max(tail_job(u), P[msucc[u]] + q[msucc[u]] if msucc[u] >= 0 else 0,
                 move_tool(u, b) + dur[b] + q[b] if b >= 0 else 0)
        qv = max(tail_job(v), P[msucc[v]] + q[msucc[v]] if msucc[v] >= 0 else 0, move_tool(v, u) + dur[u] + qu)
        return max(rv + dur[v] + qv, ru + dur[u] + qu)

    moves: list[_Move] = []
    path = g.critical_path(ev)
    for u, v in zip(path, path[1:]):
        if u < n and v < n:
            if msucc[u] == v:
                b = msucc[v]
                joint = tsucc[u] == v
                if joint:
                    est = -1  # the tool's deliveries change too: evaluated in full
                else:
                    rv = max(head_part(v), head_tool(v), head_machine(u))
                    ru = max(head_part(u), head_tool(u), rv + dur[v])
                    qu = max(tail_job(u), tail_tool(u), P[b] + q[b] if b >= 0 else 0)
                    qv = max(tail_job(v), tail_tool(v), qu + dur[u])
                    est = max(rv + dur[v] + qv, ru + dur[u] + qu)
                moves.append((est, ("m", v, u), ("m", u, v), "m", (u, v, joint)))
            elif tsucc[u] == v:
                moves.append((tool_swap(u, v), ("t", v, u), ("t", u, v), "t", (u, v)))
        elif u < n and v >= 2 * n and tsucc[u] == v - 2 * n:
            w = v - 2 * n
            moves.append((tool_swap(u, w), ("t", w, u), ("t", u, w), "t", (u, w)))
        elif u >= n and v >= n and vsucc[u] == v:
            x, y = vpred[u], vsucc[v]
            veh = where[u]
            rb = max(ready(v), free(x, v, veh))
            ra = max(ready(u), rb + P[v] + leg(v, u, veh))
            iu, iv = (u - n, v - n) if u < 2 * n else (u - 2 * n, v - 2 * n)
            qa = max(P[iu] + q[iu], leg(u, y, veh) + P[y] + q[y] if y >= 0 else 0)
            qb = max(P[iv] + q[iv], leg(v, u, veh) + P[u] + qa)
            est = max(rb + P[v] + qb, ra + P[u] + qa)
            kind = "a" if u < 2 * n else "r"
            moves.append((est, (kind, iv, iu), (kind, iu, iv), kind, (iu, iv)))
    # critical blocks of a tool (its uses in a row on the critical path): move one of the last two uses to the
    # block's front or one of the first two to its back (as N7 does for machines), evaluated in full
    blocks: list[list[int]] = []
    for u in path:
        if u >= n or tool[u] < 0:
            continue
        if blocks and tsucc[blocks[-1][-1]] == u:
            blocks[-1].append(u)
        else:
            blocks.append([u])
    for blk in blocks:
        if len(blk) < 3:
            continue
        seq = o[2][tool[blk[0]]]
        first, last = seq.index(blk[0]), seq.index(blk[-1])
        for x in (blk[-1], blk[-2]):
            moves.append((-1, ("b", x), ("b", x), "i", (x, seq.index(x), first)))
        for x in (blk[0], blk[1]):
            moves.append((-1, ("b", x), ("b", x), "i", (x, seq.index(x), last)))
    for node in path:
        if node < n:
            t = tool[node]
            if t < 0:
                continue
            # the tool's nearest uses on the same machine before and after: serve this use next to them (no
            # delivery between them)
            seq = o[2][t]
            p = seq.index(node)
            m = mach[node]
            before = next((x for x in range(p - 1, -1, -1) if mach[seq[x]] == m), -1)
            after = next((x for x in range(p + 1, len(seq)) if mach[seq[x]] == m), -1)
            if before >= 0 and before < p - 1:
                moves.append((-1, ("i", node), ("i", node), "i", (node, p, before + 1)))
            if after > p + 1:
                moves.append((-1, ("i", node), ("i", node), "i", (node, p, after - 1)))
            continue
        agv = node < 2 * n
        i = node - n if agv else node - 2 * n
        fleet = o[1] if agv else o[3]
        if len(fleet) < 2:
            continue
        base = n if agv else 2 * n
        v = where[node]
        x, y = vpred[node], vsucc[node]
        # a trip that waits for its load is moved too where the fleet is two AGVs without tools (chosen on
        # validation shops: better on BU-size shops, where the search has time to spare, level elsewhere)
        waits_load = ev.crit[node] != x and not (x < 0 and ev.crit[node] < 0 and start[node] > 0)
        if waits_load and (len(fleet) > 2 or g.inst.has_tools):
            continue  # it waits for its load, not for its vehicle: another vehicle cannot start it earlier
        rest = max(ready(y), free(x, y, v)) + P[y] + q[y] if y >= 0 else 0
        ti = start[node]
        rdy = ready(node)
        for w in range(len(fleet)):
            if w == v:
                continue
            other = fleet[w]
            p = 0
            while p < len(other) and start[base + other[p]] <= ti:
                p += 1
            for pos in {max(0, p - 1), p, min(len(other), p + 1)}:
                before = base + other[pos - 1] if pos > 0 else -1
                after = base + other[pos] if pos < len(other) else -1
                ri = max(rdy, free(before, node, w))
                qi = P[i] + q[i]
                if after >= 0:
                    qi = max(qi, leg(node, after, w) + P[after] + q[after])
                est = max(ri + P[node] + qi, rest)
                kind = "v" if agv else "w"
                moves.append((est, (kind, i), (kind, i), kind, (i, v, w, pos)))  # the trip stays a while
    return moves


def _with(seqs: list[list[int]], k: int, seq: list[int]) -> list[list[int]]:
    out = list(seqs)
    out[k] = seq
    return out


def _swap(seq: list[int], a: int, b: int) -> list[int]:
    """``seq`` with its adjacent entries ``a, b`` swapped."""
    out = list(seq)
    p = out.index(a)
    out[p], out[p + 1] = b, a
    return out


def _apply(kind: str, args: tuple, g: _Graph, o: Orders, ev: _Eval, where: list[int]) -> Orders:
    """The orders after a move (new lists where they change; the others shared)."""
    mseq, aseq, tseq, rseq = o
    n = g.n
    if kind == "m":
        u, v, joint = args
        mseq = _with(mseq, g.mach[u], _swap(mseq[g.mach[u]], u, v))
        if not joint:
            return mseq, aseq, tseq, rseq
        kind, args = "t", (u, v)
    if kind == "t":
        u, v = args
        tseq = _with(tseq, g.tool[u], _swap(tseq[g.tool[u]], u, v))
        return mseq, aseq, tseq, _fix_deliveries(g, tseq, rseq, ev)
    if kind == "i":
        u, p, q = args
        seq = list(tseq[g.tool[u]])
        del seq[p]
        seq.insert(q if q < p else q, u)
        tseq = _with(tseq, g.tool[u], seq)
        return mseq, aseq, tseq, _fix_deliveries(g, tseq, rseq, ev)
    if kind in ("a", "r"):
        a, b = args
        fleet, base = (aseq, n) if kind == "a" else (rseq, 2 * n)
        w = where[base + a]
        fleet = _with(fleet, w, _swap(fleet[w], a, b))
        return (mseq, fleet, tseq, rseq) if kind == "a" else (mseq, aseq, tseq, fleet)
    i, v, w, pos = args
    fleet = list(aseq if kind == "v" else rseq)
    fleet[v] = [x for x in fleet[v] if x != i]
    fleet[w] = fleet[w][:pos] + [i] + fleet[w][pos:]
    return (mseq, fleet, tseq, rseq) if kind == "v" else (mseq, aseq, tseq, fleet)


def _fix_deliveries(g: _Graph, tseq: list[list[int]], rseq: list[list[int]], ev: _Eval) -> list[list[int]]:
    """The transporter orders for the tool orders ``tseq``: deliveries no longer needed are dropped; a new one
    joins the transporter free earliest at the time its tool is free in ``ev`` (the schedule before the move)."""
    _, src = g.deliveries(tseq)
    need = {i for i in range(g.n) if src[i] >= 0}
    have = {i for seq in rseq for i in seq}
    if need == have:
        return rseq
    n2 = 2 * g.n
    start, P = ev.start, ev.P
    out = [[i for i in seq if i in need] for seq in rseq]
    free0 = g.v0[1][1]
    for i in sorted(need - have):
        y = ev.tpred[i]
        t = start[y] + g.dur[y] if y >= 0 else g.trel[i]
        best = None
        for r, seq in enumerate(out):
            p = 0
            while p < len(seq) and start[n2 + seq[p]] <= t:
                p += 1
            free = start[n2 + seq[p - 1]] + P[n2 + seq[p - 1]] if p else free0[r]
            if best is None or free < best[0]:
                best = (free, r, p)
        assert best is not None
        _, r, p = best
        out[r] = out[r][:p] + [i] + out[r][p:]
    return out


def _orders(g: _Graph, plan: Schedule) -> Orders:
    """Each resource's operations, trips or deliveries in ``plan``'s order of start times."""
    mseq: list[list[int]] = [[] for _ in range(g.inst.n_machines + 1)]
    tseq: list[list[int]] = [[] for _ in range(g.n_tools + 1)]
    for o in sorted(plan.operations, key=lambda o: (o.start, o.end)):
        i = g.index[o.job, o.op]
        mseq[o.machine].append(i)
        if g.tool[i] >= 0:
            tseq[g.tool[i]].append(i)
    aseq: list[list[int]] = [[] for _ in range(g.n_vehicles[0])]
    for t in sorted(plan.agv_trips, key=lambda t: (t.start, t.end)):
        if t.loaded:
            assert t.job is not None and t.op is not None
            aseq[t.agv].append(g.index[t.job, t.op])
    rseq: list[list[int]] = [[] for _ in range(g.n_vehicles[1])]
    for tt in sorted(plan.tool_trips, key=lambda t: (t.start, t.end)):
        if tt.loaded:
            assert tt.job is not None and tt.op is not None
            rseq[tt.transporter].append(g.index[tt.job, tt.op])
    return mseq, aseq, tseq, rseq


def _legs(g: _Graph, ev: _Eval, routes: list[list[int]], base: int, mat: Sequence[Sequence[int]],
          start: tuple[list[int], list[int]], held: list[bool]) -> Iterator[tuple[int, int | None, int, int, int, int]]:
    """Each vehicle's legs as ``(vehicle, operation or None for an empty leg, from, to, start, end)``: routes of the
    nodes ``base + i`` (AGV trips or deliveries) of vehicles that start where and when ``start`` says; empty legs
    leave as soon as the vehicle is free (a ``held`` vehicle's first one: once its load is dispatched)."""
    for v, seq in enumerate(routes):
        here, free = start[0][v], start[1][v]
        if held[v] and seq:
            y = g.jpred[seq[0]] if base == g.n else ev.tpred[seq[0]]
            free = max(free, ev.start[y] if y >= 0 else g.now)
        for i in seq:
            node = base + i
            origin = ev.org[node]
            if here != origin:
                yield v, None, here, origin, free, free + mat[here][origin]
            s = ev.start[node]
            yield v, i, origin, g.mach[i], s, s + ev.P[node]
            here, free = g.mach[i], s + ev.P[node]


def _schedule(g: _Graph, plan: Schedule, o: Orders, ev: _Eval) -> Schedule:
    inst, n, start, key = g.inst, g.n, ev.start, g.key
    ops = [OperationRecord(*key[i], g.mach[i], g.tool[i] if g.tool[i] >= 0 else None, start[i], start[i] + g.dur[i])
           for i in g.live]
    trips = [AgvTrip(v, None, None, a, b, s, e, False) if i is None else AgvTrip(v, *key[i], a, b, s, e, True)
             for v, i, a, b, s, e in _legs(g, ev, o[1], n, g.travel, g.v0[0], g.held[0])]
    deliveries = [ToolTrip(r, None, None, None, a, b, s, e, False) if i is None
                  else ToolTrip(r, g.tool[i], *key[i], a, b, s, e, True)
                  for r, i, a, b, s, e in _legs(g, ev, o[3], 2 * n, g.ttravel, g.v0[1], g.held[1])]
    meta: dict[str, object] = {"solver": "tabu", "improved": plan.meta.get("solver")}
    if g.origin is not None:
        meta["residual"] = g.origin.now
    return Schedule(instance=inst.name, makespan=ev.makespan, n_agvs=inst.n_agvs,
                    n_tool_transporters=inst.n_tool_transporters, operations=ops, agv_trips=trips,
                    tool_trips=deliveries, meta=meta)


def residual_lower_bound(origin: Snapshot) -> int:
    """A lower bound on the makespan of any run continued from ``origin``: what has started ends as it says, each
    job's remaining operations follow one another from when its part is free, each machine's remaining work follows
    when it is free."""
    inst = origin.instance
    bound = origin.makespan
    load = [0] * (inst.n_machines + 1)
    for j, job in enumerate(inst.jobs):
        rest = job[origin.next_op[j]:]
        if rest:
            bound = max(bound, origin.ready[j] + sum(op.duration for op in rest))
        for op in rest:
            load[op.machine] += op.duration
    for m in range(1, inst.n_machines + 1):
        if load[m]:
            bound = max(bound, origin.machine_free[m] + load[m])
    return bound


def solve_tabu(instance: Instance, *, time_limit: float | None = 10.0, seed: int = 0, progress: bool = False,
               **_: object) -> Schedule:
    """The ``tabu`` solver: the best of the four list schedules (earliest start or completion, earliest or nearest
    vehicle; :func:`fms_dispatch.exact.greedy_schedule`; the first always, each other one while it fits the time
    limit), improved by :func:`tabu_plan` for the rest of
    ``time_limit`` seconds (None: 10 s), stopping at the simple lower bound. ``progress`` prints the start and the
    result."""
    from .exact import greedy_schedule, simple_lower_bound

    require_instance(instance, "solve_tabu")
    t0 = time.monotonic()
    limit = 10.0 if time_limit is None else time_limit
    if not (isinstance(limit, numbers.Real) and not isinstance(limit, bool) and 0 < limit < float("inf")):
        # inf: "tabu_plan needs a time budget", a function it was not given; "1": a TypeError from the comparison
        raise ValueError(f"time_limit must be a positive, finite number of seconds, got {time_limit!r}")
    # the first list schedule always; each further one while another fits the limit (on 100-job shops the four took
    # two seconds of a one-second limit before the search began)
    plans = [greedy_schedule(instance)]
    one = time.monotonic() - t0
    for rule, vehicle in (("est", "nearest"), ("ect", "earliest"), ("ect", "nearest")):
        if time.monotonic() - t0 + one > limit:
            break
        plans.append(greedy_schedule(instance, rule=rule, vehicle=vehicle))
    start = min(plans, key=lambda p: p.makespan)
    bound = simple_lower_bound(instance)  # (before the start is reported: an interrupt from then on keeps it)
    shown = [time.monotonic()]

    def report(makespan: int, iteration: int, seconds: float) -> None:
        if time.monotonic() - shown[0] >= 1.0:  # at most one line a second
            shown[0] = time.monotonic()
            say(f"  tabu: makespan {makespan} at iteration {iteration}, {seconds:.1f} s")

    if progress:
        say(f"  tabu: list schedule {start.makespan}")
    try:
        best = tabu_plan(instance, start, budget=max(0.0, limit - (time.monotonic() - t0)), seed=seed,
                         bound=bound, progress=report if progress else None)
    except KeyboardInterrupt as exc:  # the best so far (the start schedule before the search), for fms solve to keep
        from .exact import SearchInterrupted

        kept = SearchInterrupted.of(exc, start, bound, time.monotonic() - t0)
        kept.best.meta = {"solver": "tabu", "status": "INTERRUPTED", "wall_time": round(time.monotonic() - t0, 3)}
        raise kept from None
    if progress:
        say(f"  tabu: makespan {best.makespan} after {best.meta.get('iterations', 0)} iterations")
    best.meta["solver"] = "tabu"
    return best


def tabu_plan(inst: Instance, plan: Schedule, *, budget: float | None = 0.05, max_iters: int | None = None,
              max_stall: int | None = None, seed: int = 0, bound: int = 0,
              progress: Callable[[int, int, float], None] | None = None, origin: Snapshot | None = None) -> Schedule:
    """``plan`` or a better schedule of ``inst`` found by tabu search over its resource orders within ``budget``
    seconds (None: no time limit), ``max_iters`` iterations and ``max_stall`` iterations without a better schedule
    (None: no limit; a budget or an iteration limit must be set), stopping at ``bound`` (pass
    :func:`fms_dispatch.exact.simple_lower_bound`, or :func:`residual_lower_bound` for a residual plan).
    Reproducible for a given ``seed`` while the time limit does not cut it short. ``progress(makespan, iteration,
    seconds)`` is called at every better schedule.

    ``plan`` is a whole schedule of ``inst`` (ValueError if the validator refuses it for ``inst``), or, with
    ``origin`` (the :class:`~fms_sim.snapshot.Snapshot` of a running shop), a residual plan from that state
    (:func:`fms_dispatch.exact.greedy_schedule` with ``origin``):
    then only the operations not started are searched over, each part, machine, tool and vehicle starts where and
    when the snapshot says (a tool reserved for an operation serves it first, without a delivery), and the result
    is a residual plan from the same state."""
    from .exact import check_plan_of

    # the instance and the plan first (None was an AttributeError; another shop's plan came back as this one's
    # best, or failed deep inside with a KeyError)
    check_plan_of(inst, plan, origin, "tabu_plan")
    if budget == float("inf"):
        budget = None  # no time limit, as None says: an iteration limit must then be set (it ran without an end)
    if budget is None and max_iters is None:
        raise ValueError("tabu_plan needs a time budget or an iteration limit")
    if budget is not None and not (isinstance(budget, numbers.Real) and not isinstance(budget, bool) and budget >= 0):
        raise ValueError(f"budget must be >= 0 seconds (None: no time limit), got {budget!r}")  # NaN passed
    for name, v in (("max_iters", max_iters), ("max_stall", max_stall)):  # (NaN or -1: no limit; 1.5 ran 2)
        if v is not None and (not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < 0):
            raise ValueError(f"{name} must be an integer >= 0 (None: no limit), got {v!r}")
    if budget == 0 or max_iters == 0 or plan.makespan <= bound or (origin is not None and not origin.remaining):
        return plan
    t0 = time.monotonic()
    deadline = None if budget is None else t0 + budget
    g = _Graph(inst, origin)
    n = g.n
    rng = random.Random(seed)
    o = _orders(g, plan)
    if sorted(i for seq in o[0] for i in seq) != g.live:
        return plan  # the plan does not hold exactly the operations to plan (a residual plan of another state)
    _, src = g.deliveries(o[2])
    if {i for i in range(n) if src[i] >= 0} != {i for seq in o[3] for i in seq}:
        return plan  # a delivery the tool order does not need (a trip to where the tool is): not this search's form
    cur = g.evaluate(o)
    if cur is None:  # cannot happen for a valid plan: its start times order every resource
        return plan
    best_val = cur.makespan
    best = (o, cur)
    tabu: dict[tuple, int] = {}
    it = last = 0
    where = [-1] * (3 * n)  # the vehicle of each trip and delivery node
    interrupted = False
    try:
        while (max_iters is None or it < max_iters) and (deadline is None or time.monotonic() < deadline):
            if max_stall is not None and it - last >= max_stall:
                break
            it += 1
            for v, seq in enumerate(o[1]):
                for i in seq:
                    where[n + i] = v
            for v, seq in enumerate(o[3]):
                for i in seq:
                    where[2 * n + i] = v
            q = g.tails(cur)
            moves = _neighbours(g, cur, q, o, where)
            # full evaluations first for the moves without an estimate, then the estimates in order
            exact: list[tuple[int, float, tuple, tuple, Orders, _Eval]] = []
            ranked: list[tuple[int, float, _Move]] = []
            for mv in moves:
                if deadline is not None and time.monotonic() > deadline:
                    break
                if mv[0] >= 0:
                    ranked.append((mv[0], rng.random(), mv))
                    continue
                o2 = _apply(mv[3], mv[4], g, o, cur, where)
                res = g.evaluate(o2)
                if res is None or (tabu.get(mv[1], 0) >= it and res.makespan >= best_val):
                    continue
                exact.append((res.makespan, rng.random(), mv[1], mv[2], o2, res))
            ranked.sort(key=lambda r: (r[0], r[1]))
            chosen = min(exact, key=lambda e: (e[0], e[1])) if exact else None
            for est, _, (_, attr, reverse, kind, args) in ranked:
                if chosen is not None and est >= chosen[0]:
                    break
                if tabu.get(attr, 0) >= it and est >= best_val:
                    continue
                o2 = _apply(kind, args, g, o, cur, where)
                res = g.evaluate(o2)
                if res is None or (tabu.get(attr, 0) >= it and res.makespan >= best_val):
                    continue
                if chosen is None or res.makespan < chosen[0]:
                    chosen = (res.makespan, 0.0, attr, reverse, o2, res)
                break
            if chosen is None:
                if not tabu or not moves:
                    break  # no move at all, or only moves into cycles
                tabu.clear()  # every move is forbidden: forget them
                continue
            _, _, _, reverse, o, cur = chosen
            tabu[reverse] = it + TENURE + rng.randrange(TENURE_SPREAD)
            if cur.makespan < best_val:
                best_val, last = cur.makespan, it
                best = (o, cur)
                if progress is not None:
                    progress(best_val, it, time.monotonic() - t0)
                if best_val <= bound:
                    break
    except KeyboardInterrupt:  # the best found so far goes with the interrupt (fms solve --solver tabu keeps it)
        interrupted = True
    if interrupted:
        from .exact import SearchInterrupted

        out = plan if best[1].makespan >= plan.makespan else _schedule(g, plan, *best)
        raise SearchInterrupted(out, bound, time.monotonic() - t0)
    if best_val >= plan.makespan:
        return plan
    out = _schedule(g, plan, *best)
    out.meta["wall_time"] = round(time.monotonic() - t0, 3)
    out.meta["iterations"] = it
    out.meta["best_at"] = last
    return out
