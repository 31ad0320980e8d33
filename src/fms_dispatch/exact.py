"""Exact CP-SAT model of the FMS scheduling problem, with a scalable fallback for large instances.

The model follows the project's semantics contract (see :mod:`fms_sim.validate`) for all four modes: plain
job shop, AGVs only, tools only and AGVs + tools. Every run starts from a feasible incumbent: the ``hint`` if
given, else the best of a few greedy list schedules (:func:`greedy_schedule`) and randomised restarts of them.

**Full model** (instances with at most :data:`FULL_MODEL_MAX_TASKS` transport tasks, i.e. loaded AGV tasks
plus tool uses, and every plain job shop):

* operations are fixed-size intervals with one ``NoOverlap`` per machine; heads and tails (own job's
  processing and loaded travel) bound the start variables, the incumbent's makespan bounds the objective;
* every operation whose pickup location differs from its machine is one *loaded AGV task* (fixed duration
  ``agv_travel[pickup][machine]``) that starts after the part is ready and ends before the operation starts;
* AGV routing is one multiple-circuit (vehicle-routing) constraint over all AGV tasks with a depot node
  (location 0 at time 0): arc ``i -> j`` means that one AGV does ``j`` right after ``i`` and implies
  ``end_i + gap(i, j) <= start_j`` (``gap`` = the shortest empty move from ``drop_i`` to ``pickup_j``, or for
  a later task of the same job the job's own lag if longer); at most ``n_agvs`` routes leave the depot. The
  AGVs are identical, so routes carry no vehicle index, which removes the vehicle symmetry altogether.
  Two redundant constraints make the proofs fast: a *fleet workload* cut ``n_agvs * makespan >= loaded
  time + gaps of the chosen arcs + the rest of each route's last job`` and a cumulative (capacity
  ``n_agvs``) over the intervals ``[start - before, end + after)`` whose slacks form a dual-feasible
  assignment of predecessors and successors (:func:`_agv_slacks`);
* every tool's uses are ordered by one circuit (node 0 = the magazine); the predecessor of a use fixes the
  origin of its *tool delivery* (none when the predecessor ran on the same machine: the delivery node then
  takes a self-loop in the transporter routing); a delivery starts after the previous use ended and ends
  before its use starts; transporters route deliveries with a second multiple-circuit constraint whose
  empty legs depend on the (variable) origin of the next delivery; tool uses also get a ``NoOverlap`` and
  deliveries a cumulative over the transporters;
* travel matrices need not satisfy the triangle inequality, and a vehicle may make an empty move as several
  empty trips through other places where that is quicker: every empty move (approach from the depot, between
  carries, and in every bound) is charged its shortest-path time (:class:`_EmptyMoves`), and a solution's
  schedule records it as those direct empty trips, one after the other; loaded trips are always the direct
  matrix entry (one loaded trip per carry).

On 2 workers this proves the Bilge–Ulusoy layout-2 optima EX12..EX102 in about 0.1–10 s each (see
``bench/cpsat_bu.py``), and the ra01..ra10 tools instances in seconds.

**Fallback** (more transport tasks; e.g. the 2000-operation benchmarks, where routing would need millions of
arc literals; measured on random 10–30-job instances, the full model's search stops paying off around 100
tasks, and above ~250 tasks CP-SAT's presolve alone eats the time limit):

* the lower bound comes from a *relaxation* solved by CP-SAT in 40 % of the remaining time: the job shop in
  which each loaded AGV trip is a minimum time lag between consecutive operations, plus one ``NoOverlap``
  per tool, release dates for tool uses (the tool must come from the magazine) and the AGV cumulative
  above; its proven bound is combined with :func:`simple_lower_bound` (machine/job/tool/fleet bounds);
* the schedule is the best of the incumbent, a list schedule guided by the relaxation's start times, and
  randomised list-scheduling restarts until the time is up (:func:`_improve_by_priorities`);
* the status is then ``"FEASIBLE"`` (or ``"OPTIMAL"`` when the schedule meets the bound).

Whatever the path, the result is never worse than the hint, ``lower_bound`` is always a valid bound, and
every schedule returned passes :func:`fms_sim.validate.validate`.
"""

from __future__ import annotations

import functools
import math
import numbers
import random
import threading
import time
import warnings
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np

if TYPE_CHECKING:
    from ortools.sat.python import cp_model

from fms_sim.instance import Instance, require_instance
from fms_sim.schedule import AgvTrip, OperationRecord, Schedule, ToolTrip, require_schedule
from fms_sim.snapshot import Snapshot
from fms_sim.ties import has_ties
from fms_sim.validate import validate

__all__ = [
    "ExactResult",
    "SearchInterrupted",
    "solve_exact",
    "cpsat",
    "greedy_schedule",
    "restart_list_plan",
    "polish_plan",
    "simple_lower_bound",
    "relaxation_bound",
    "FULL_MODEL_MAX_TASKS",
    "n_transport_tasks",
    "fits_full_model",
]

FULL_MODEL_MAX_TASKS = 100
"""Instances with at most this many transport tasks (AGV tasks + tool uses) get the full routing model."""

Progress = Callable[[int, int, float], None]


def _cp() -> ModuleType:
    """OR-Tools' CP-SAT module, imported when a model is first built: the list schedules, restarts and bounds of
    this module do not need it, and importing it takes about 0.25 s (a guided solve, the agent node's start)."""
    from ortools.sat.python import cp_model

    return cp_model


def cp_seed(seed: int) -> int:
    """``seed`` as CP-SAT's ``random_seed`` takes it (a 32-bit integer): unchanged within that range, else folded
    into it (``fms solve --seed 4294967296`` with a re-plan ended in a TypeError traceback at the first re-plan)."""
    return seed if -2 ** 31 <= seed < 2 ** 31 else seed % 2 ** 31


def run_solver(solver: Any, model: Any, callback: Any = None) -> Any:
    """``solver.solve(model, callback)``, stopped within a fraction of a second by Ctrl-C (or ``fms``'s SIGTERM).

    CP-SAT searches in C++ with the GIL released, and Python runs a signal handler only in the main thread, once
    that thread is back in Python: an interrupt during ``solve`` waited for the search's end (``fms solve sl00
    --solver cpsat --time-limit 60`` took 22 s to stop). So, called from the main thread, the search runs in a
    thread of its own while the main thread polls a flag the search thread sets (sleeping between polls: a wait on
    a lock or an event can be broken by a second signal, or leave a running thread taken as ended); an interrupt
    then asks the search to stop (``stop_search``) until it has ended (further interrupts do not end that wait; a
    stop asked before CP-SAT has started is lost, hence asking again each poll), and is raised again.
    Outside the main thread (a node's planning thread) no signal arrives: the search runs in place. The status is
    returned; an error of the search is raised here."""
    if threading.current_thread() is not threading.main_thread():
        return solver.solve(model, callback)
    done = threading.Event()
    out: dict[str, Any] = {}

    def search() -> None:
        try:
            out["status"] = solver.solve(model, callback)
        except BaseException as e:  # (raised in the caller's thread below)
            out["error"] = e
        finally:
            done.set()

    interrupted: BaseException | None = None
    thread: threading.Thread | None = None
    try:
        thread = threading.Thread(target=search, name="cp-sat", daemon=True)
        thread.start()
        while not done.is_set():
            time.sleep(0.05)
    except BaseException as exc:  # Ctrl-C, SIGTERM (or an error of the poll): stop the search, then raise
        interrupted = exc
    launched = time.monotonic() + 2.0  # (a thread never launched, the interrupt inside start(), sets nothing)
    while not done.is_set() and thread is not None and (thread.ident is not None or time.monotonic() < launched):
        try:  # further signals do not end the wait: the search must stop first
            solver.stop_search()
            time.sleep(0.02)
        except BaseException:
            continue
    if interrupted is not None:
        raise interrupted
    if "error" in out:
        raise out["error"]
    return out["status"]


def _proved(solver: Any, lb: int) -> int:
    """``lb`` raised to the lower bound a CP-SAT search proved (its best objective bound, rounded up)."""
    return max(lb, int(math.ceil(solver.best_objective_bound - 1e-6)))


class SearchInterrupted(KeyboardInterrupt):
    """An interrupt (Ctrl-C, or ``fms``'s SIGTERM) during :func:`solve_exact`, carrying the best schedule found
    before it (``best``: CP-SAT's best solution or the start schedule; its ``meta`` says so when it comes from
    :func:`cpsat`), the lower bound known then and the seconds spent. Every handler of KeyboardInterrupt takes it
    as one; ``fms solve`` keeps the schedule of a search it ran (cpsat, tabu, sos, rules: a long search stopped by
    hand is not lost). The tabu search, sos and the rule combinations raise it too (``lower_bound`` 0: none known;
    it is never above the best's makespan, which would claim more than was proved). ``start_makespan``: the
    makespan of the start schedule :func:`solve_exact` began its search from (None: interrupted before it had one,
    or another search)."""

    def __init__(self, best: Schedule, lower_bound: int, wall_time: float, start_makespan: int | None = None):
        super().__init__()
        self.best, self.lower_bound, self.wall_time = best, min(lower_bound, best.makespan), wall_time
        self.start_makespan = start_makespan

    @classmethod
    def of(cls, exc: KeyboardInterrupt, best: Schedule, lower_bound: int, wall_time: float) -> "SearchInterrupted":
        """What an interrupt ``exc`` caught around a search raises on: ``exc`` itself where it already carries the
        best of a search inside this one (which knows more), else one carrying ``best``."""
        return exc if isinstance(exc, cls) else cls(best, lower_bound, wall_time)

    def __reduce__(self) -> tuple:  # (a process pool's worker sends it to the parent: it failed to unpickle)
        return type(self), (self.best, self.lower_bound, self.wall_time, self.start_makespan)


@dataclass
class ExactResult:
    """What :func:`solve_exact` found: the best schedule (``None`` only if none was found), a valid lower
    bound on the optimal makespan, the status (``"OPTIMAL"``, ``"FEASIBLE"``, ``"INFEASIBLE"`` or
    ``"UNKNOWN"``), the wall time in seconds and the start schedule's makespan."""

    schedule: Schedule | None
    lower_bound: int
    status: str
    wall_time: float
    #: the makespan of the start schedule the search began from (the best list schedule or the hint), if any
    start_makespan: int | None = None


# ====================================================================================== instance facts
@dataclass(frozen=True)
class _Task:
    """A loaded AGV task: move the part of operation (job, op) from ``pickup`` to ``drop`` (its machine)."""

    job: int
    op: int
    pickup: int
    drop: int
    dur: int


def _agv_tasks(inst: Instance) -> list[_Task]:
    """Every loaded AGV task of an AGV instance (none when the pickup is the operation's own machine)."""
    tasks: list[_Task] = []
    if not inst.has_agvs:
        return tasks
    tr = inst.agv_travel
    assert tr is not None
    for j, job in enumerate(inst.jobs):
        for k, op in enumerate(job):
            pick = job[k - 1].machine if k else 0
            if pick != op.machine:
                tasks.append(_Task(j, k, pick, op.machine, tr[pick][op.machine]))
    return tasks


def _tool_uses(inst: Instance) -> dict[int, list[tuple[int, int]]]:
    """``tool -> [(job, op), ...]`` for the operations that need a tool (empty without tools)."""
    uses: dict[int, list[tuple[int, int]]] = {}
    if not inst.has_tools:
        return uses
    for j, job in enumerate(inst.jobs):
        for k, op in enumerate(job):
            if op.tool is not None:
                uses.setdefault(op.tool, []).append((j, k))
    return uses


def _shortest_paths(mat: Sequence[Sequence[int]]) -> list[list[int]]:
    """All-pairs shortest travel times (Floyd–Warshall); matrices need not satisfy the triangle inequality. One
    numpy step per intermediate place: the three Python loops took 36 s on a shop of 1,000 machines (every bound,
    so every search, starts with them), this takes well under a second. Exact in int64: a path has at most
    ``len(mat)`` legs of at most ``MAX_TIME``."""
    d = np.array(mat, dtype=np.int64).reshape(len(mat), len(mat))
    for k in range(len(d)):
        np.minimum(d, d[:, k:k + 1] + d[k:k + 1, :], out=d)
    return d.tolist()


class _EmptyMoves:
    """A vehicle's empty moves over ``travel``: the shortest time from one place to another and the direct trips
    (matrix entries) that make it up.

    Travel matrices need not satisfy the triangle inequality, and an empty vehicle may go through other places
    where that is quicker (the contract requires one *loaded* trip per carry, but an empty move is any sequence of
    empty trips): ``dist`` is the shortest-path closure, and :meth:`legs` a shortest path with the fewest trips,
    the direct trip wherever it is itself shortest."""

    def __init__(self, travel: Sequence[Sequence[int]]):
        self.travel = travel
        self.dist = _shortest_paths(travel)
        self._legs: dict[tuple[int, int], list[tuple[int, int, int]]] = {}

    def legs(self, a: int, b: int) -> list[tuple[int, int, int]]:
        """The direct trips ``(from, to, travel time)`` of a shortest move from ``a`` to ``b`` with the fewest
        trips (none when ``a == b``): a breadth-first search over the trips that stay on some shortest path."""
        key = (a, b)
        found = self._legs.get(key)
        if found is not None:
            return found
        travel, dist = self.travel, self.dist
        to_b = [row[b] for row in dist]
        prev: dict[int, int] = {a: a}
        frontier = [a]
        while b not in prev:  # (a shortest path exists: every place reaches every other one)
            assert frontier, f"no shortest move from {a} to {b}"
            nxt = []
            for u in frontier:
                row = travel[u]
                for v in range(len(row)):
                    if v not in prev and row[v] + to_b[v] == to_b[u]:
                        prev[v] = u
                        nxt.append(v)
            frontier = nxt
        path = [b]
        while path[-1] != a:
            path.append(prev[path[-1]])
        path.reverse()
        found = self._legs[key] = [(u, v, travel[u][v]) for u, v in zip(path, path[1:])]
        return found


def _loaded_time(inst: Instance, j: int, k: int) -> int:
    """The loaded AGV travel that must precede operation (j, k) (0 without AGVs or without a move)."""
    if not inst.has_agvs:
        return 0
    job = inst.jobs[j]
    pick = job[k - 1].machine if k else 0
    assert inst.agv_travel is not None
    return inst.agv_travel[pick][job[k].machine]


def _heads_tails(inst: Instance) -> tuple[dict[tuple[int, int], int], dict[tuple[int, int], int]]:
    """Earliest start (head) of each operation and minimum time from its end to the makespan (tail),
    counting processing and loaded travel of its own job only (plus the tool's trip from the magazine)."""
    heads: dict[tuple[int, int], int] = {}
    tails: dict[tuple[int, int], int] = {}
    sp_tool = _shortest_paths(inst.tool_travel) if inst.has_tools else None
    for j, job in enumerate(inst.jobs):
        t = 0
        for k, op in enumerate(job):
            t += _loaded_time(inst, j, k)
            if sp_tool is not None and op.tool is not None:
                t = max(t, sp_tool[0][op.machine])
            heads[j, k] = t
            t += op.duration
        t = 0
        for k in range(len(job) - 1, -1, -1):
            tails[j, k] = t
            t += job[k].duration + _loaded_time(inst, j, k)
    return heads, tails


def simple_lower_bound(inst: Instance) -> int:
    """A cheap valid lower bound on the makespan: the maximum of job bounds (processing plus loaded
    travel), machine bounds (smallest head + total load + smallest tail), tool bounds (likewise over the
    uses of a tool) and, with AGVs, a fleet bound (loaded plus minimum empty travel spread over the AGVs)."""
    heads, tails = _heads_tails(inst)
    lb = max(heads[j, len(job) - 1] + job[-1].duration for j, job in enumerate(inst.jobs))
    groups: dict[tuple[str, int], list[tuple[int, int]]] = {}
    for j, job in enumerate(inst.jobs):
        for k, op in enumerate(job):
            groups.setdefault(("m", op.machine), []).append((j, k))
            if inst.has_tools and op.tool is not None:
                groups.setdefault(("t", op.tool), []).append((j, k))
    for keys in groups.values():
        load = sum(inst.jobs[j][k].duration for j, k in keys)
        lb = max(lb, min(heads[x] for x in keys) + load + min(tails[x] for x in keys))
    tasks = _agv_tasks(inst)
    if tasks:
        before, after = _agv_slacks(inst, tasks, tails)
        n = inst.n_agvs
        total = sum(t.dur + x for t, x in zip(tasks, before))
        tail_after = min(inst.jobs[t.job][t.op].duration + tails[t.job, t.op] for t in tasks)
        lb = max(lb, -(-total // n) + tail_after, -(-(total + sum(after)) // n))
    return lb


JobSums = tuple[list[list[int]], list[list[int]]]
"""Per job, the processing and the loaded AGV travel of its operations before each one, summed (entry ``k``: of
operations ``0 .. k-1``; one more entry than the job has operations): :func:`_job_sums`."""


def _job_sums(inst: Instance) -> JobSums:
    """The :data:`JobSums` of ``inst``: any stretch of a job's processing or loaded travel in O(1) (a 100 x 20 shop
    has 38,000 pairs of tasks of one job)."""
    dsum, lsum = [], []
    for j, job in enumerate(inst.jobs):
        d, lt = [0], [0]
        for k, op in enumerate(job):
            d.append(d[-1] + op.duration)
            lt.append(lt[-1] + _loaded_time(inst, j, k))
        dsum.append(d)
        lsum.append(lt)
    return dsum, lsum


def _same_job_lag(sums: JobSums, a: _Task, b: _Task) -> int:
    """Minimum time from the end of task ``a`` to the start of the later task ``b`` of the same job: the
    operations from ``a.op`` to ``b.op - 1`` and the loaded trips between them must run in between (``sums``: the
    instance's :func:`_job_sums`)."""
    d, lt = sums[0][a.job], sums[1][a.job]
    return d[b.op] - d[a.op] + lt[b.op] - lt[a.op + 1]


def _agv_gap(a: _Task, b: _Task, sums: JobSums, empty: Sequence[Sequence[int]]) -> int:
    """Minimum time between the end of ``a`` and the start of ``b`` when one AGV does ``b`` right after
    ``a``: the empty move, or (for a later task of the same job) the job's own lag if longer (``sums``: the
    instance's :func:`_job_sums`; ``empty``: the shortest empty moves, :func:`_shortest_paths` of the AGV matrix,
    since the AGV may go through other places where that is quicker)."""
    gap = empty[a.drop][b.pickup]
    if a.job == b.job and a.op < b.op:
        gap = max(gap, _same_job_lag(sums, a, b))
    return gap


def _agv_slacks(inst: Instance, tasks: Sequence[_Task], tails: dict[tuple[int, int], int]) -> tuple[list[int], list[int]]:
    """Per AGV task, ``before`` and ``after`` amounts such that one AGV's intervals
    ``[start - before, end + after)`` never overlap, start at >= 0 and end at <= makespan.

    They form a feasible dual of the assignment of each task to a predecessor (depot or task) and a
    successor (task or the end): ``after_i + before_j <= gap(i, j)``, ``before_j <= empty(0, pickup_j)``
    and ``after_i <= processing + tail after i``, with ``empty`` the shortest empty move (an AGV may go through
    other places). Computed in O(tasks x locations), fine for 2000 tasks.
    """
    assert inst.agv_travel is not None
    tr = _shortest_paths(inst.agv_travel)
    locs = range(len(tr))
    by_job: dict[int, list[int]] = {}
    drop_jobs: dict[int, set[int]] = {}
    for i, t in enumerate(tasks):
        by_job.setdefault(t.job, []).append(i)
        drop_jobs.setdefault(t.drop, set()).add(t.job)
    sums = _job_sums(inst)
    # the drop-off places of each job's tasks, for 'a task of another job ends here'
    only_job = {loc: next(iter(js)) if len(js) == 1 else None for loc, js in drop_jobs.items()}
    before = []
    for i, t in enumerate(tasks):
        best = tr[0][t.pickup]
        for loc, j1 in only_job.items():
            if j1 != t.job:  # some job other than t's drops a part here
                best = min(best, tr[loc][t.pickup])
        for i2 in by_job[t.job]:
            if tasks[i2].op < t.op:
                best = min(best, _agv_gap(tasks[i2], t, sums, tr))
        before.append(best)
    # per pickup location: the two smallest `before` values from different jobs
    INF = 1 << 60
    best2: dict[int, list[tuple[int, int]]] = {}
    for i, t in enumerate(tasks):
        cur = best2.setdefault(t.pickup, [])
        cur.append((before[i], t.job))
        cur.sort()
        if len(cur) > 2:
            # keep the best and the best of another job
            first = cur[0]
            other = next((x for x in cur[1:] if x[1] != first[1]), None)
            best2[t.pickup] = [first] + ([other] if other else [])
    # per place: the smallest 'before' there, its job, and the smallest of another job (INF: none)
    lead = {loc: (c[0][0], c[0][1], next((b for b, job in c[1:] if job != c[0][1]), INF))
            for loc, c in best2.items() if c}
    after = []
    for i, t in enumerate(tasks):
        best = inst.jobs[t.job][t.op].duration + tails[t.job, t.op]
        here = tr[t.drop]
        for loc in locs:
            c = lead.get(loc)
            if c is None:
                continue
            bj = c[0] if c[1] != t.job else c[2]
            if bj < INF:
                best = min(best, here[loc] - bj)
        for i2 in by_job[t.job]:
            if tasks[i2].op > t.op:
                best = min(best, _agv_gap(t, tasks[i2], sums, tr) - before[i2])
        after.append(max(0, best))
    return before, after


# ====================================================================================== greedy
def _earliest_vehicle(locs: Sequence[int], free: Sequence[int], travel: Sequence[Sequence[int]], src: int,
                      ready: int, nearest: bool = False, held: Sequence[bool] | None = None,
                      dispatch: int = 0) -> tuple[int, int]:
    """``(vehicle, start)``: the vehicle (AGV or transporter) that can start the loaded trip from ``src``
    earliest, not before ``ready`` (ties: the shorter empty trip, then the lowest number); ``(-1, 0)`` if
    there is none. A vehicle marked in ``held`` (idle at a snapshot, :attr:`fms_sim.snapshot.Snapshot.held`)
    leaves for the carry no earlier than its ``dispatch``."""
    # compared field by field rather than as (start, empty trip) tuples: this runs for every job a vehicle's move
    # touches, and is most of a list schedule's time on 100-job shops
    best_v, start, empty = -1, 0, 0
    for v, loc in enumerate(locs):
        e = travel[loc][src]
        s = free[v]
        if held is not None and held[v] and s < dispatch:
            s = dispatch
        s += e
        if s < ready:
            s = ready
        if best_v < 0:
            best_v, start, empty = v, s, e
        elif nearest:
            if e < empty or (e == empty and s < start):
                best_v, start, empty = v, s, e
        elif s < start or (s == start and e < empty):
            best_v, start, empty = v, s, e
    return best_v, start


#: the list schedule memoises its fleets' answers on shops of at least this many jobs (see greedy_schedule)
_MEMO_JOBS = 40


def _earliest_and_lowest(locs: Sequence[int], free: Sequence[int], travel: Sequence[Sequence[int]], src: int,
                         ready: int) -> tuple[int, int, int, tuple[int, int, int] | None]:
    """``(vehicle, start, empty trip, lowest)``: :func:`_earliest_vehicle`'s answer (earliest start; ``(-1, 0, 0,
    None)`` without vehicles) and, in the same pass, ``lowest = (earliest arrival at src, its empty trip,
    vehicle)``, the least over the fleet (ties: the shorter empty trip, then the lowest number), which is the answer
    for every ``ready`` up to that arrival."""
    best_v, start, empty = -1, 0, 0
    low_f = low_e = low_v = -1
    for v, loc in enumerate(locs):
        e = travel[loc][src]
        f = free[v] + e
        if low_v < 0 or f < low_f or (f == low_f and e < low_e):
            low_f, low_e, low_v = f, e, v
        s = f if f > ready else ready
        if best_v < 0 or s < start or (s == start and e < empty):
            best_v, start, empty = v, s, e
    return best_v, start, empty, ((low_f, low_e, low_v) if low_v >= 0 else None)


def greedy_schedule(
    inst: Instance,
    *,
    rule: str = "est",
    rng: random.Random | None = None,
    priority: dict[tuple[int, int], float] | None = None,
    noise: dict[tuple[int, int], float] | None = None,
    origin: Snapshot | None = None,
    vehicle: str = "earliest",
) -> Schedule:
    """A feasible schedule by list scheduling, appending every activity to the end of its resources.

    At each step every job's next operation is planned: the AGV that delivers the part earliest, the
    transporter that brings the tool earliest, the machine; then one is committed: the one with the
    earliest start (``rule="est"``) or completion (``"ect"``), ties broken by the most remaining work (or
    randomly when ``rng`` is given), or the smallest ``priority`` value (``rule="guided"``); ``noise`` adds a
    per-operation offset to the start times compared by ``"est"`` (randomised restarts). Empty trips
    start as soon as the vehicle is free (one idle at ``origin``: once its carry is dispatched, ``Snapshot.held``);
    vehicles then wait for the part or tool. Each carry goes to the
    vehicle that can start it earliest (``vehicle="earliest"``; ties: the shorter empty trip) or to the one with
    the shortest empty trip (``"nearest"``, as the nearest-vehicle rules do; ties: the earliest start). Always
    valid, never optimal in general; it gives the solver its first upper bound and the fallback its schedule.

    ``origin`` (a :class:`fms_sim.snapshot.Snapshot` of a running shop) plans only what has not started, from
    that state: committed moves and tool reservations are kept (they get no trip record), a reserved tool serves
    its reserved operation first, and the result holds the remaining operations and the new trips only, with
    ``makespan`` the predicted end of the whole run (``meta["residual"]``: the time it starts from). Such a
    *residual plan* is not a schedule of the instance (the validator would miss the past); re-planning executes
    it with :meth:`fms_sim.replay.PlanPolicy.resume`.
    """
    require_instance(inst, "greedy_schedule")  # a name was an AttributeError (every list and tabu solver)
    if rule not in ("est", "ect", "guided"):
        raise ValueError(f"unknown greedy rule {rule!r}; use 'est', 'ect' or 'guided'")
    if vehicle not in ("earliest", "nearest"):
        raise ValueError(f"unknown vehicle choice {vehicle!r}; use 'earliest' or 'nearest'")
    near = vehicle == "nearest"
    if rule == "guided" and priority is None:
        raise ValueError("greedy rule 'guided' needs a priority for every operation")
    if origin is not None:
        origin.check_of(inst)
    o = origin if origin is not None else Snapshot.initial(inst)
    for name, given in (("priority", priority if rule == "guided" else None), ("noise", noise)):
        if given is not None:  # (a KeyError naming only an operation came from deep inside the loop)
            missing = next(((j, k) for j, job in enumerate(inst.jobs) for k in range(o.next_op[j], len(job))
                            if (j, k) not in given), None)
            if missing is not None:
                raise ValueError(f"the {name} of the list schedule has no entry for operation {missing} of "
                                 f"{inst.name}; give one for every (job, op) to plan")
    jobs = inst.jobs
    nj = len(jobs)
    atr, ttr = inst.agv_travel, inst.tool_travel
    nxt = list(o.next_op)
    ready = list(o.ready)
    remaining = [sum(op.duration for op in job[nxt[j]:]) for j, job in enumerate(jobs)]
    mach_free = list(o.machine_free)
    # vehicles idle at the snapshot leave for their first carry only when it is dispatched (Snapshot.held): a
    # part's once its previous operation has started, a tool's once its previous use has; None: no vehicle held
    agv_flags = [("agv", v) in o.held for v in range(inst.n_agvs)]
    tr_flags = [("tt", r) in o.held for r in range(inst.n_tool_transporters)]
    agv_held: list[bool] | None = agv_flags if any(agv_flags) else None
    tr_held: list[bool] | None = tr_flags if any(tr_flags) else None
    last_start = [o.now] * nj  # when each job's last planned operation starts (now: started before the state)
    tool_last = [o.now] * (inst.n_tools + 1)  # when each tool's last planned use starts
    agv_loc, agv_free = list(o.agv_loc), list(o.agv_free)
    tr_loc, tr_free = list(o.tt_loc), list(o.tt_free)
    tool_loc, tool_free = list(o.tool_loc), list(o.tool_free)
    arrival = dict(o.arrival)          # job -> when its next part is at the machine (move done or committed)
    reserved = dict(o.tool_reserved)   # tool -> (job, op, when the tool is there) served before any other use
    ops: list[OperationRecord] = []
    agv_trips: list[AgvTrip] = []
    tool_trips: list[ToolTrip] = []
    # per job, the earliest vehicle for its next carry (part / tool) as (start, empty travel, vehicle, from, not
    # before): the minimum over the fleet, kept up to date as one vehicle changes per step (None: recompute)
    agv_best: list[tuple[int, int, int, int, int] | None] = [None] * nj
    tt_best: list[tuple[int, int, int, int, int] | None] = [None] * nj

    # per fleet (the AGVs' cache list or the transporters'), answers of _earliest_vehicle while no vehicle of the
    # fleet moves: by (from, not before), and the least arrival at each place (every "not before" up to it has
    # that answer): many jobs ask the same (a tool's requests; parts waiting for the AGVs on a congested shop). Only
    # on shops of many jobs: on a few it costs more than it saves (the guide's plan search runs thousands of these)
    memoise = nj >= _MEMO_JOBS
    agv_memo: tuple[dict, dict] | None = ({}, {}) if memoise else None
    tt_memo: tuple[dict, dict] | None = ({}, {}) if memoise else None

    def earliest(cache: list, memo: tuple[dict, dict] | None, j: int, locs: list[int], free: list[int],
                 travel: Sequence[Sequence[int]], src: int, rdy: int, held: list[bool] | None = None,
                 dispatch: int = 0) -> tuple[int, int]:
        c = cache[j]
        if c is None and (memo is None or held is not None):  # (held vehicles: answers differ by job, no memo)
            v, st = _earliest_vehicle(locs, free, travel, src, rdy, near, held, dispatch)
            e = travel[locs[v]][src] if v >= 0 else 0
            c = cache[j] = ((e, st) if near else (st, e)) + (v, src, rdy, st)
        elif c is None:
            assert memo is not None
            answers, lowest = memo
            low = lowest.get(src) if not near else None
            if low is not None and rdy <= low[0]:
                st, e, v = low
            else:
                got = answers.get((src, rdy))
                if got is None:
                    if near:
                        v, st = _earliest_vehicle(locs, free, travel, src, rdy, True)
                        got = (v, st, travel[locs[v]][src] if v >= 0 else 0)
                    else:
                        v, st, e, low = _earliest_and_lowest(locs, free, travel, src, rdy)
                        got = (v, st, e)
                        if low is not None:
                            lowest[src] = low
                    answers[src, rdy] = got
                v, st, e = got
            c = cache[j] = ((e, st) if near else (st, e)) + (v, src, rdy, st)
        return c[2], c[5]

    def moved(cache: list, memo: tuple[dict, dict] | None, v: int, locs: list[int], free: list[int],
              travel: Sequence[Sequence[int]]) -> None:
        """Vehicle ``v`` got a new place and time: update every job's earliest vehicle (and its plan)."""
        if memo is not None:
            memo[0].clear()
            memo[1].clear()
        here, fv = travel[locs[v]], free[v]
        for i, c in enumerate(cache):
            if c is None:
                continue
            if c[2] == v:
                cache[i] = planned[i] = None
                continue
            src, rdy = c[3], c[4]
            e = here[src]
            st = fv + e
            if st < rdy:
                st = rdy
            # (e, st, v) if near else (st, e, v), against the cached key c[:3], without building either
            a, b = (e, st) if near else (st, e)
            if a < c[0] or (a == c[0] and (b < c[1] or (b == c[1] and v < c[2]))):
                cache[i] = (a, b, v, src, rdy, st)
                planned[i] = None

    # per job, plan(j) as of the current state; None: recompute (a job's plan changes only with its machine, its
    # tool, its earliest vehicles or itself)
    planned: list[tuple[tuple[int, int, int, int, int, int] | None] | None] = [None] * nj

    def plan(j: int) -> tuple[int, int, int, int, int, int] | None:
        """(start, agv, loaded start, transporter, tool loaded start, end) for the next operation of j; None
        while its tool is reserved for another operation."""
        k = nxt[j]
        op = jobs[j][k]
        m = op.machine
        arrive, best_a, ls = ready[j], -1, 0
        if arrival and j in arrival:
            arrive = arrival[j]
        elif atr is not None:
            pick = jobs[j][k - 1].machine if k else 0
            if pick != m:
                best_a, ls = earliest(agv_best, agv_memo, j, agv_loc, agv_free, atr, pick, ready[j], agv_held,
                                      last_start[j])
                arrive = ls + atr[pick][m]
        tool_at, best_r, tls = 0, -1, 0
        if ttr is not None and op.tool is not None:
            t = op.tool
            res = reserved.get(t) if reserved else None
            if res is not None:
                if res[0] != j or res[1] != k:
                    return None
                tool_at = res[2]
            elif tool_loc[t] == m:
                tool_at = tool_free[t]
            else:
                src = tool_loc[t]
                best_r, tls = earliest(tt_best, tt_memo, j, tr_loc, tr_free, ttr, src, tool_free[t], tr_held,
                                       tool_last[t])
                tool_at = tls + ttr[src][m]
        start = max(mach_free[m], arrive, tool_at)
        return start, best_a, ls, best_r, tls, start + op.duration

    n_ops = [len(job) for job in jobs]
    ect, guided = rule == "ect", rule == "guided"
    # the jobs whose next operation is on each machine, and (with tools) needs each tool: the plans a step changes
    on_machine: list[set[int]] = [set() for _ in range(inst.n_machines + 1)]
    on_tool: dict[int, set[int]] = {}

    def enter(j: int) -> None:
        if nxt[j] < n_ops[j]:
            nop = jobs[j][nxt[j]]
            on_machine[nop.machine].add(j)
            if ttr is not None and nop.tool is not None:
                on_tool.setdefault(nop.tool, set()).add(j)

    for j in range(nj):
        enter(j)
    # the keys are compared field by field, as the tuples (start or end [+ noise], tie) and, guided, (priority,
    # start, tie) would be, without building them: this loop runs over every job at every step
    for _ in range(o.remaining):
        best_j, best_plan = -1, None
        b0 = b1 = b2 = 0.0
        for j in range(nj):
            k = nxt[j]
            if k >= n_ops[j]:
                continue
            cached = planned[j]
            if cached is None:
                cached = planned[j] = (plan(j),)
            p = cached[0]
            if p is None:
                continue
            tie = rng.random() if rng is not None else -remaining[j]
            if guided:
                assert priority is not None
                k0, k1 = priority[j, k], p[0]
                if best_j < 0 or k0 < b0 or (k0 == b0 and (k1 < b1 or (k1 == b1 and tie < b2))):
                    b0, b1, b2, best_j, best_plan = k0, k1, tie, j, p
                continue
            k0 = p[5] if ect else (p[0] + noise[j, k] if noise is not None else p[0])
            if best_j < 0 or k0 < b0 or (k0 == b0 and tie < b1):
                b0, b1, best_j, best_plan = k0, tie, j, p
        if best_plan is None:  # every next operation waits for a reservation: the snapshot had a circular wait
            raise ValueError(f"no operation of {inst.name} can be planned: the tool reservations wait on each other")
        j, k = best_j, nxt[best_j]
        op = jobs[j][k]
        m = op.machine
        start, a, ls, r, tls, end = best_plan
        if a >= 0:
            assert atr is not None
            pick = jobs[j][k - 1].machine if k else 0
            if agv_loc[a] != pick:
                e0 = agv_free[a]
                if agv_held is not None and agv_held[a]:  # it leaves when the carry is dispatched
                    e0 = max(e0, last_start[j])
                agv_trips.append(AgvTrip(a, None, None, agv_loc[a], pick, e0, e0 + atr[agv_loc[a]][pick], False))
            agv_trips.append(AgvTrip(a, j, k, pick, m, ls, ls + atr[pick][m], True))
            agv_loc[a], agv_free[a] = m, ls + atr[pick][m]
            if agv_held is not None and agv_held[a]:  # (before moved(): its answers are a free vehicle's now)
                agv_held[a] = False
                if not any(agv_held):
                    agv_held = None
            moved(agv_best, agv_memo, a, agv_loc, agv_free, atr)
        if r >= 0:
            assert ttr is not None and op.tool is not None
            src = tool_loc[op.tool]
            if tr_loc[r] != src:
                e0 = tr_free[r]
                if tr_held is not None and tr_held[r]:
                    e0 = max(e0, tool_last[op.tool])
                tool_trips.append(ToolTrip(r, None, None, None, tr_loc[r], src, e0, e0 + ttr[tr_loc[r]][src], False))
            tool_trips.append(ToolTrip(r, op.tool, j, k, src, m, tls, tls + ttr[src][m], True))
            tr_loc[r], tr_free[r] = m, tls + ttr[src][m]
            if tr_held is not None and tr_held[r]:
                tr_held[r] = False
                if not any(tr_held):
                    tr_held = None
            moved(tt_best, tt_memo, r, tr_loc, tr_free, ttr)
        if ttr is not None and op.tool is not None:
            tool_loc[op.tool], tool_free[op.tool] = m, end
            tool_last[op.tool] = start
            if reserved:
                reserved.pop(op.tool, None)
        tool = op.tool if ttr is not None else None
        for i in on_machine[m]:  # the machine is free later
            planned[i] = None
        if tool is not None:  # the tool's next carry starts elsewhere, later
            for i in on_tool[tool]:
                tt_best[i] = planned[i] = None
            on_tool[tool].discard(j)
        on_machine[m].discard(j)
        agv_best[j] = tt_best[j] = planned[j] = None  # j's next operation: another carry
        if arrival:
            arrival.pop(j, None)
        mach_free[m] = end
        ready[j] = end
        last_start[j] = start
        remaining[j] -= op.duration
        nxt[j] += 1
        enter(j)
        ops.append(OperationRecord(j, k, m, op.tool if inst.has_tools else None, start, end))
    meta: dict[str, object] = {"solver": "greedy", "rule": rule}
    if origin is not None:
        meta["residual"] = origin.now
    return Schedule(
        instance=inst.name,
        makespan=max([r.end for r in ops] + [o.makespan]),
        n_agvs=inst.n_agvs,
        n_tool_transporters=inst.n_tool_transporters,
        operations=ops,
        agv_trips=agv_trips,
        tool_trips=tool_trips,
        meta=meta,
    )


def _best_greedy(inst: Instance, budget: float, seed: int, max_runs: int = 64) -> Schedule:
    """The best of the deterministic greedy rules and randomised-tie restarts within ``budget`` seconds."""
    t0 = time.monotonic()
    best = greedy_schedule(inst, rule="est")
    one_run = time.monotonic() - t0
    rng = random.Random(seed)
    candidates = [("ect", None)] + [("est", rng)] * max_runs
    try:
        for rule, r in candidates:
            if time.monotonic() - t0 + one_run > budget:
                break
            s = greedy_schedule(inst, rule=rule, rng=r)
            if s.makespan < best.makespan:
                best = s
    except KeyboardInterrupt:  # the best start schedule so far goes with the interrupt (up to 10 s on large shops)
        raise SearchInterrupted(best, simple_lower_bound(inst), time.monotonic() - t0) from None
    return best


# ====================================================================================== full model
class _FullModel:
    """The exact CP-SAT model (see the module docstring); ``extract`` turns a solution into a Schedule."""

    def __init__(self, inst: Instance, lb: int, ub: int):
        cp_model = _cp()
        self.inst = inst
        self.model = m = cp_model.CpModel()
        self.ub = ub
        jobs = inst.jobs
        heads, tails = _heads_tails(inst)
        self.heads, self.tails = heads, tails
        # ---- operations
        self.s: dict[tuple[int, int], cp_model.IntVar] = {}
        self.itv: dict[tuple[int, int], cp_model.IntervalVar] = {}
        by_machine: dict[int, list[cp_model.IntervalVar]] = {}
        for j, job in enumerate(jobs):
            for k, op in enumerate(job):
                hi = ub - tails[j, k] - op.duration
                s = m.new_int_var(heads[j, k], max(hi, heads[j, k]), f"s{j}_{k}")
                self.s[j, k] = s
                self.itv[j, k] = iv = m.new_fixed_size_interval_var(s, op.duration, f"op{j}_{k}")
                by_machine.setdefault(op.machine, []).append(iv)
        for ivs in by_machine.values():
            if len(ivs) > 1:
                m.add_no_overlap(ivs)
        self.mk = m.new_int_var(lb, ub, "makespan")
        for j, job in enumerate(jobs):
            m.add(self.mk >= self.s[j, len(job) - 1] + job[-1].duration)
        m.minimize(self.mk)
        self._build_parts()
        self._build_tools()

    # ------------------------------------------------------------------ parts and AGVs
    def _build_parts(self) -> None:
        inst, m = self.inst, self.model
        jobs = inst.jobs
        self.tasks = _agv_tasks(inst)
        self.ts: list[cp_model.IntVar] = []
        self.agv_arcs: list[tuple[int, int, cp_model.IntVar]] = []
        task_of = {(t.job, t.op): i for i, t in enumerate(self.tasks)}
        for j, job in enumerate(jobs):
            for k in range(len(job)):
                ready = self.s[j, k - 1] + job[k - 1].duration if k else 0
                if (j, k) not in task_of:
                    if k:
                        m.add(self.s[j, k] >= ready)
                    continue
                t = self.tasks[task_of[j, k]]
                lo = self.heads[j, k - 1] + job[k - 1].duration if k else 0
                hi = max(lo, self.ub - self.tails[j, k] - job[k].duration - t.dur)
                ts = m.new_int_var(lo, hi, f"ts{j}_{k}")
                self.ts.append(ts)
                if k:
                    m.add(ts >= ready)
                m.add(self.s[j, k] >= ts + t.dur)
        if not self.tasks:
            return
        assert inst.agv_travel is not None
        self.agv_moves = _EmptyMoves(inst.agv_travel)
        sp = self.agv_moves.dist  # empty moves may go through other places
        tasks, ts = self.tasks, self.ts
        out_of_depot = []
        gap: dict[tuple[int, int], int] = {}
        sums = _job_sums(inst)
        for i, t in enumerate(tasks):
            gap[0, i + 1] = sp[0][t.pickup]
            lit = m.new_bool_var(f"a0_{i}")
            m.add(ts[i] >= sp[0][t.pickup]).only_enforce_if(lit)
            self.agv_arcs.append((0, i + 1, lit))
            out_of_depot.append(lit)
            self.agv_arcs.append((i + 1, 0, m.new_bool_var(f"a{i}_0")))
        for i, a in enumerate(tasks):
            for jj, b in enumerate(tasks):
                if i == jj or (a.job == b.job and b.op < a.op):
                    continue  # a later task of the same job never comes first
                lit = m.new_bool_var(f"a{i}_{jj}")
                gap[i + 1, jj + 1] = g = _agv_gap(a, b, sums, sp)
                m.add(ts[jj] >= ts[i] + a.dur + g).only_enforce_if(lit)
                self.agv_arcs.append((i + 1, jj + 1, lit))
        m.add_multiple_circuit(self.agv_arcs)
        m.add(sum(out_of_depot) <= inst.n_agvs)
        # redundant "fleet workload" cut: each used AGV's last task ends after all its loaded and empty
        # legs (or waits for its own part), and the makespan follows that task's operation and its job's
        # tail, so summed over the AGVs:
        # n_agvs * makespan >= sum(loaded) + sum(gaps of the arcs chosen) + sum(tail after each route's end).
        work = []
        for a, b, lit in self.agv_arcs:
            if b:
                if gap[a, b]:
                    work.append(gap[a, b] * lit)
            else:
                ta = tasks[a - 1]
                rest = inst.jobs[ta.job][ta.op].duration + self.tails[ta.job, ta.op]
                if rest:
                    work.append(rest * lit)
        m.add(inst.n_agvs * self.mk >= sum(t.dur for t in tasks) + sum(work))
        # redundant: one AGV's intervals [start - before, end + after) never overlap (see _agv_slacks)
        before, after = _agv_slacks(inst, tasks, self.tails)
        ivs = [m.new_interval_var(ts[i] - before[i], t.dur + before[i] + after[i], ts[i] + t.dur + after[i],
                                  f"agv{i}") for i, t in enumerate(tasks)]
        if inst.n_agvs == 1:
            m.add_no_overlap(ivs)
        else:
            m.add_cumulative(ivs, [1] * len(ivs), inst.n_agvs)

    # ------------------------------------------------------------------ tools and transporters
    def _build_tools(self) -> None:
        inst, m = self.inst, self.model
        self.uses = _tool_uses(inst)
        self.tool_arcs: dict[int, list[tuple[int, int, cp_model.IntVar]]] = {}
        self.deliveries: list[tuple[int, int, int]] = []  # (tool, job, op)
        self.tr_arcs: list[tuple[int, int, cp_model.IntVar]] = []
        if not self.uses:
            return
        tt = inst.tool_travel
        assert tt is not None
        self.tool_moves = _EmptyMoves(tt)
        sp = self.tool_moves.dist  # loaded trips are direct (tt), empty moves may go through other places (sp)
        jobs = inst.jobs
        # delivery variables per use: start, duration (a linear expression of the predecessor arcs), absent
        self.dts: dict[tuple[int, int], cp_model.IntVar] = {}
        self.dd_de: dict[tuple[int, int], tuple[cp_model.IntVar, cp_model.IntVar]] = {}  # duration, end
        self.pred_arcs: dict[tuple[int, int], list[tuple[int, cp_model.IntVar]]] = {}  # use -> [(origin, lit)]
        dur_expr: dict[tuple[int, int], cp_model.LinearExprT] = {}
        absent: dict[tuple[int, int], cp_model.IntVar] = {}
        for tool, us in sorted(self.uses.items()):
            arcs: list[tuple[int, int, cp_model.IntVar]] = []
            for w in us:
                self.pred_arcs[w] = []
                self.dts[w] = m.new_int_var(0, self.ub, f"dts{w[0]}_{w[1]}")
            for wi, w in enumerate(us):
                lit = m.new_bool_var(f"t{tool}_0_{wi}")
                arcs.append((0, wi + 1, lit))
                self.pred_arcs[w].append((0, lit))
                arcs.append((wi + 1, 0, m.new_bool_var(f"t{tool}_{wi}_0")))
            for ui, u in enumerate(us):
                end_u = self.s[u] + jobs[u[0]][u[1]].duration
                for wi, w in enumerate(us):
                    if ui == wi or (u[0] == w[0] and w[1] < u[1]):
                        continue  # a later operation of the same job never uses the tool first
                    lit = m.new_bool_var(f"t{tool}_{ui}_{wi}")
                    arcs.append((ui + 1, wi + 1, lit))
                    self.pred_arcs[w].append((jobs[u[0]][u[1]].machine, lit))
                    # the tool leaves u's machine (the delivery for w starts) only after u ended
                    m.add(self.dts[w] >= end_u).only_enforce_if(lit)
                    m.add(self.s[w] >= end_u).only_enforce_if(lit)
            m.add_circuit(arcs)
            self.tool_arcs[tool] = arcs
            if len(us) > 1:
                m.add_no_overlap([self.itv[u] for u in us])
            for w in us:
                mw = jobs[w[0]][w[1]].machine
                preds = self.pred_arcs[w]
                dur_expr[w] = sum(tt[o][mw] * lit for o, lit in preds)
                ab = m.new_bool_var(f"absent{w[0]}_{w[1]}")
                m.add(ab == sum(lit for o, lit in preds if o == mw))  # the tool is already there
                absent[w] = ab
                m.add(self.s[w] >= self.dts[w] + dur_expr[w])  # the delivery ends before w starts
                self.deliveries.append((tool, w[0], w[1]))
        # transporter routing over deliveries (absent deliveries take a self-loop)
        n = len(self.deliveries)
        starts = []
        for i, (_, j, k) in enumerate(self.deliveries):
            w = (j, k)
            self.tr_arcs.append((i + 1, i + 1, absent[w]))
            lit = m.new_bool_var(f"r0_{i}")
            self.tr_arcs.append((0, i + 1, lit))
            starts.append(lit)
            m.add(self.dts[w] >= sum(sp[0][o] * p for o, p in self.pred_arcs[w])).only_enforce_if(lit)
            self.tr_arcs.append((i + 1, 0, m.new_bool_var(f"r{i}_0")))
        for vi, (_, jv, kv) in enumerate(self.deliveries):
            mv = jobs[jv][kv].machine
            v = (jv, kv)
            for wi, (_, jw, kw) in enumerate(self.deliveries):
                if vi == wi:
                    continue
                w = (jw, kw)
                lit = m.new_bool_var(f"r{vi}_{wi}")
                self.tr_arcs.append((vi + 1, wi + 1, lit))
                empty = sum(sp[mv][o] * p for o, p in self.pred_arcs[w])
                m.add(self.dts[w] >= self.dts[v] + dur_expr[v] + empty).only_enforce_if(lit)
        m.add_multiple_circuit(self.tr_arcs)
        m.add(sum(starts) <= inst.n_tool_transporters)
        self._tool_workload_cuts(dur_expr)
        # redundant: present deliveries share n_tool_transporters vehicles
        ivs, demands = [], []
        for i, (_, j, k) in enumerate(self.deliveries):
            w = (j, k)
            d = m.new_int_var(0, max(max(r) for r in tt), f"dd{j}_{k}")
            m.add(d == dur_expr[w])
            end = m.new_int_var(0, self.ub, f"de{j}_{k}")
            m.add(end == self.dts[w] + d)
            self.dd_de[w] = (d, end)
            ivs.append(m.new_optional_interval_var(self.dts[w], d, end, ~absent[w], f"del{j}_{k}"))
            demands.append(1)
        if inst.n_tool_transporters == 1:
            m.add_no_overlap(ivs)
        elif n > inst.n_tool_transporters:
            m.add_cumulative(ivs, demands, inst.n_tool_transporters)

    def _tool_workload_cuts(self, dur_expr: dict[tuple[int, int], cp_model.LinearExprT]) -> None:
        """Redundant linear cuts. Per tool: its deliveries and uses run one after the other, and the job of
        its last use still has its tail to do. Over the transporters: each one's last delivery ends after
        all its loaded legs and empty moves (at least the shortest approach to any possible origin, through other
        places where that is quicker), and the delivered operation and its job's tail follow."""
        inst, m, jobs = self.inst, self.model, self.inst.jobs
        sp = self.tool_moves.dist
        for tool, us in self.uses.items():
            rest = [self.tails[us[a - 1]] * lit for (a, b, lit) in self.tool_arcs[tool] if b == 0 and a != 0]
            m.add(self.mk >= sum(jobs[j][k].duration for j, k in us) + sum(dur_expr[w] for w in us) + sum(rest))
        origins = {w: {o for o, _ in preds if o != jobs[w[0]][w[1]].machine} for w, preds in self.pred_arcs.items()}
        work = [dur_expr[(j, k)] for _, j, k in self.deliveries]
        for a, b, lit in self.tr_arcs:
            if a == b:
                continue
            if b == 0:
                j, k = self.deliveries[a - 1][1:]
                work.append((jobs[j][k].duration + self.tails[j, k]) * lit)
                continue
            w = self.deliveries[b - 1][1:]
            here = 0 if a == 0 else jobs[self.deliveries[a - 1][1]][self.deliveries[a - 1][2]].machine
            if origins[w]:
                empty = min(sp[here][o] for o in origins[w])
                if empty:
                    work.append(empty * lit)
        m.add(inst.n_tool_transporters * self.mk >= sum(work))

    # ------------------------------------------------------------------ hints
    def add_hint(self, sch: Schedule) -> None:
        """Hint every variable from a feasible schedule (complete hints let CP-SAT start from it)."""
        m, inst = self.model, self.inst
        start = {(o.job, o.op): o.start for o in sch.operations}
        end = {(o.job, o.op): o.end for o in sch.operations}
        for key, var in self.s.items():
            m.add_hint(var, start[key])
        m.add_hint(self.mk, sch.makespan)
        if self.tasks:
            loaded = {(t.job, t.op): t for t in sch.agv_trips if t.loaded}
            for i, t in enumerate(self.tasks):
                m.add_hint(self.ts[i], loaded[t.job, t.op].start)
            idx = {(t.job, t.op): i + 1 for i, t in enumerate(self.tasks)}
            seqs = []
            for a in range(inst.n_agvs):
                seq = sorted((t.start, idx[t.job, t.op]) for t in sch.agv_trips
                             if t.agv == a and t.loaded and (t.job, t.op) in idx)
                if seq:
                    seqs.append([n for _, n in seq])
            true_arcs = set()
            for seq in seqs:
                nodes = [0] + seq + [0]
                true_arcs.update(zip(nodes, nodes[1:]))
            for a, b, lit in self.agv_arcs:
                m.add_hint(lit, (a, b) in true_arcs)
        if self.uses:
            tool_loaded = {(t.job, t.op): t for t in sch.tool_trips if t.loaded and t.from_ != t.to}
            true_t = set()
            prev_of: dict[tuple[int, int], tuple[int, int] | None] = {}
            for tool, us in self.uses.items():
                order = sorted(range(len(us)), key=lambda i: (start[us[i]], end[us[i]], us[i]))
                nodes = [0] + [i + 1 for i in order] + [0]
                true_t.update((tool, a, b) for a, b in zip(nodes, nodes[1:]))
                prev: tuple[int, int] | None = None
                for i in order:
                    prev_of[us[i]] = prev
                    prev = us[i]
                for a, b, lit in self.tool_arcs[tool]:
                    m.add_hint(lit, (tool, a, b) in true_t)
            for w, var in self.dts.items():
                if w in tool_loaded:
                    st, dur = tool_loaded[w].start, tool_loaded[w].end - tool_loaded[w].start
                else:
                    p = prev_of[w]
                    st, dur = (end[p] if p is not None else 0), 0
                m.add_hint(var, st)
                if w in self.dd_de:
                    m.add_hint(self.dd_de[w][0], dur)
                    m.add_hint(self.dd_de[w][1], st + dur)
            didx = {(j, k): i + 1 for i, (_, j, k) in enumerate(self.deliveries)}
            true_r = set()
            for r in range(inst.n_tool_transporters):
                seq = sorted((t.start, didx[t.job, t.op]) for t in sch.tool_trips
                             if t.transporter == r and t.loaded and t.from_ != t.to)
                nodes = [0] + [n for _, n in seq] + [0]
                if len(nodes) > 2:
                    true_r.update(zip(nodes, nodes[1:]))
            present = {didx[w] for w in tool_loaded}
            for a, b, lit in self.tr_arcs:
                if a == b:
                    m.add_hint(lit, a not in present)
                else:
                    m.add_hint(lit, (a, b) in true_r)

    # ------------------------------------------------------------------ solution -> schedule
    def extract(self, value: Callable[[cp_model.IntVar], int], bool_value: Callable[[cp_model.IntVar], bool]) -> Schedule:
        """The schedule of a solution: operations, each route's loaded trips, and the empty move from the
        vehicle's previous drop to the next pickup as the consecutive direct empty trips of a shortest path
        (:class:`_EmptyMoves`), leaving as soon as the previous trip ended (the arc constraints, which charge the
        shortest move, guarantee it arrives before the loaded trip starts)."""
        inst = self.inst
        jobs = inst.jobs
        ops = [OperationRecord(j, k, op.machine, op.tool if inst.has_tools else None,
                               value(self.s[j, k]), value(self.s[j, k]) + op.duration)
               for j, job in enumerate(jobs) for k, op in enumerate(job)]
        agv_trips: list[AgvTrip] = []
        if self.tasks:
            routes = _routes(self.agv_arcs, bool_value)
            for a, route in enumerate(routes):
                for n, src, dst, st, end in _route_legs(
                        route, lambda n: value(self.ts[n - 1]), lambda n: self.tasks[n - 1].dur,
                        lambda n: (self.tasks[n - 1].pickup, self.tasks[n - 1].drop), self.agv_moves,
                        lambda n: ((self.tasks[n - 1].job, self.tasks[n - 1].op),)):
                    t = self.tasks[n - 1] if n is not None else None
                    agv_trips.append(AgvTrip(a, t.job if t else None, t.op if t else None, src, dst, st, end,
                                             t is not None))
        tool_trips: list[ToolTrip] = []
        if self.uses:
            tt = inst.tool_travel
            assert tt is not None
            origin: dict[tuple[int, int], int] = {}
            for w, preds in self.pred_arcs.items():
                origin[w] = next(o for o, lit in preds if bool_value(lit))
            rank: dict[tuple[int, int], int] = {}  # each use's place in its tool's sequence
            for tool, us in self.uses.items():
                for route in _routes(self.tool_arcs[tool], bool_value):
                    rank.update((us[n - 1], i) for i, n in enumerate(route))
            routes = _routes([a for a in self.tr_arcs if a[0] != a[1]], bool_value)

            def ends(n: int) -> tuple[int, int]:  # a delivery's pickup (where its tool is) and drop
                _, j, k = self.deliveries[n - 1]
                return origin[j, k], jobs[j][k].machine

            for r, route in enumerate(routes):
                for n, src, dst, st, end in _route_legs(
                        route, lambda n: value(self.dts[self.deliveries[n - 1][1:]]),
                        lambda n: tt[ends(n)[0]][ends(n)[1]], ends, self.tool_moves,
                        lambda n: ((("tool", self.deliveries[n - 1][0]), rank[self.deliveries[n - 1][1:]]),
                                   (self.deliveries[n - 1][1], self.deliveries[n - 1][2]))):
                    d = self.deliveries[n - 1] if n is not None else (None, None, None)
                    tool_trips.append(ToolTrip(r, d[0], d[1], d[2], src, dst, st, end, n is not None))
        return Schedule(instance=inst.name, makespan=max(o.end for o in ops), n_agvs=inst.n_agvs,
                        n_tool_transporters=inst.n_tool_transporters, operations=ops, agv_trips=agv_trips,
                        tool_trips=tool_trips)


#: the most partial orders :func:`_tie_order` tries for one instant of one route
_TIE_TRIES = 10_000


def _route_legs(route: list[int], start: Callable[[int], int], length: Callable[[int], int],
                ends: Callable[[int], tuple[int, int]], moves: _EmptyMoves,
                keys: Callable[[int], tuple[tuple[Any, int], ...]]) -> list[tuple[int | None, int, int, int, int]]:
    """A vehicle's legs along ``route`` (its nodes' loaded trips: ``start``, ``length``, ``ends`` pickup and drop),
    each ``(node, from, to, start, end)``, ``node`` None for an empty leg. The empty move to each pickup is the
    direct trips of a shortest path (``moves``), one after the other from the end of the previous trip. Nodes that
    start at one instant are re-sequenced for their owners (:func:`_tie_order`, ``keys``) where the vehicle can keep
    to the new order; else the route's own order (which the model's arcs make reachable)."""
    def legs(order: list[int], check: bool) -> list[tuple[int | None, int, int, int, int]] | None:
        out: list[tuple[int | None, int, int, int, int]] = []
        here, free = 0, 0
        for n in order:
            (src, dst), st = ends(n), start(n)
            if check and free + moves.dist[here][src] > st:
                return None
            for a, b, d in moves.legs(here, src):
                out.append((None, a, b, free, free + d))
                free += d
            out.append((n, src, dst, st, st + length(n)))
            here, free = dst, st + length(n)
        return out

    tied = _tie_order(route, start, length, ends, moves, keys)
    found = legs(tied, True) if tied != route else None
    return found if found is not None else legs(route, False) or []


def _tie_order(route: list[int], start: Callable[[int], int], length: Callable[[int], int],
               ends: Callable[[int], tuple[int, int]], moves: _EmptyMoves,
               keys: Callable[[int], tuple[tuple[Any, int], ...]]) -> list[int]:
    """``route`` with the nodes that start at one instant re-sequenced so that the nodes of one owner follow the
    owner's order: each node's ``keys`` are ``(owner, rank)`` pairs (a part and its operation; a tool and the
    use's place in its sequence), and a node comes after every node at the instant with the same owner and a lower
    rank. The vehicle must still reach each node's pickup in time (``ends``: pickup and drop, ``length``: the
    loaded trip's duration, ``moves``: the empty moves' shortest times), before and after the instant.

    The model's precedences are inequalities, so where zero-length trips tie at one instant a solution may route a
    vehicle through them in an order their part or tool cannot follow (a tool carried away from a machine before it
    is carried there); the times stay right, only the recorded order of the tied trips changes. The first order
    found (depth-first, the solution's order first) is taken; the solution's own where none is found."""
    out = list(route)
    i = 0
    while i < len(out):
        e = i
        while e + 1 < len(out) and start(out[e + 1]) == start(out[i]):
            e += 1
        if e > i:
            before = out[i - 1] if i else None
            after = out[e + 1] if e + 1 < len(out) else None
            found = _tie_group(out[i:e + 1], before, after, start, length, ends, moves, keys)
            if found is not None:
                out[i:e + 1] = found
        i = e + 1
    return out


def _tie_group(group: list[int], before: int | None, after: int | None, start: Callable[[int], int],
               length: Callable[[int], int], ends: Callable[[int], tuple[int, int]], moves: _EmptyMoves,
               keys: Callable[[int], tuple[tuple[Any, int], ...]]) -> list[int] | None:
    """An order of ``group`` (nodes at one instant, between ``before`` and ``after`` on the route) for
    :func:`_tie_order`, or None."""
    def reaches(p: int | None, n: int) -> bool:  # from p's drop, free when p's trip ends, to n's pickup in time
        here, free = (ends(p)[1], start(p) + length(p)) if p is not None else (0, 0)
        return free + moves.dist[here][ends(n)[0]] <= start(n)

    dead: set[tuple] = set()
    tries = 0

    def go(rest: tuple[int, ...], last: int | None) -> list[int] | None:
        nonlocal tries
        if not rest:
            return [] if after is None or reaches(last, after) else None
        if (rest, last) in dead or tries > _TIE_TRIES:
            return None
        tries += 1
        low: dict[Any, int] = {}
        for m in rest:
            for o, r in keys(m):
                low[o] = min(r, low.get(o, r))
        for n in rest:
            if all(low[o] == r for o, r in keys(n)) and reaches(last, n):
                tail = go(tuple(m for m in rest if m != n), n)
                if tail is not None:
                    return [n] + tail
        dead.add((rest, last))
        return None

    return go(tuple(group), before)


def _routes(arcs: Sequence[tuple[int, int, cp_model.IntVar]], bool_value: Callable[[cp_model.IntVar], bool]) -> list[list[int]]:
    """The vehicle routes (lists of nodes, depot 0 excluded) of a solved multiple-circuit constraint."""
    succ: dict[int, list[int]] = {}
    for a, b, lit in arcs:
        if a != b and bool_value(lit):
            succ.setdefault(a, []).append(b)
    routes = []
    for first in succ.get(0, []):
        route, node = [], first
        while node != 0:
            route.append(node)
            node = succ[node][0]
        routes.append(route)
    return routes


@functools.lru_cache(maxsize=1)
def _callback_class() -> type:
    """The solution callback's class (it subclasses CP-SAT's, so it is made once CP-SAT is imported)."""

    class _Callback(_cp().CpSolverSolutionCallback):
        """Keeps the latest (best) solution as a Schedule and reports progress."""

        def __init__(self, fm: _FullModel, progress: Progress | None, t0: float):
            super().__init__()
            self.fm, self.progress, self.t0 = fm, progress, t0
            self.best: Schedule | None = None

        def on_solution_callback(self) -> None:
            sch = self.fm.extract(self.value, self.boolean_value)
            if has_ties(sch) and validate(self.fm.inst, sch):
                # zero-length trips and operations tied in orders no shop can follow (the model's precedences are
                # inequalities: a tool's order at one instant against a job's, a route's against a tool's, where the
                # routes' re-sequencing found none): not a schedule. A list schedule that follows its start times
                # is; kept if it is the best so far
                sch = greedy_schedule(self.fm.inst, rule="guided", priority={(o.job, o.op): o.start
                                                                             for o in sch.operations})
                if validate(self.fm.inst, sch):
                    return
            if self.best is not None and sch.makespan >= self.best.makespan:
                return  # (a stand-in may be better than CP-SAT's next solutions)
            self.best = sch
            if self.progress is not None:
                self.progress(sch.makespan, int(self.best_objective_bound), time.monotonic() - self.t0)

    return _Callback


# ====================================================================================== relaxation
def _relaxation_model(inst: Instance, ub: int) -> tuple[cp_model.CpModel, dict[tuple[int, int], cp_model.IntVar]]:
    """Job shop with loaded-travel lags, tool no-overlaps, tool release dates and an AGV cumulative: every
    feasible schedule satisfies it, so its optimum (or proven bound) bounds the true makespan from below."""
    cp_model = _cp()
    m = cp_model.CpModel()
    heads, tails = _heads_tails(inst)
    jobs = inst.jobs
    s: dict[tuple[int, int], cp_model.IntVar] = {}
    by_res: dict[tuple[str, int], list[cp_model.IntervalVar]] = {}
    mk = m.new_int_var(0, ub, "makespan")
    for j, job in enumerate(jobs):
        for k, op in enumerate(job):
            s[j, k] = v = m.new_int_var(heads[j, k], max(heads[j, k], ub - tails[j, k] - op.duration), f"s{j}_{k}")
            iv = m.new_fixed_size_interval_var(v, op.duration, f"i{j}_{k}")
            by_res.setdefault(("m", op.machine), []).append(iv)
            if inst.has_tools and op.tool is not None:
                by_res.setdefault(("t", op.tool), []).append(iv)
            if k:
                m.add(v >= s[j, k - 1] + job[k - 1].duration + _loaded_time(inst, j, k))
        m.add(mk >= s[j, len(job) - 1] + job[-1].duration)
    for ivs in by_res.values():
        if len(ivs) > 1:
            m.add_no_overlap(ivs)
    tasks = _agv_tasks(inst)
    if tasks and len(tasks) > inst.n_agvs:
        before, after = _agv_slacks(inst, tasks, tails)
        ivs = []
        for i, t in enumerate(tasks):
            ts = m.new_int_var(0, ub, f"ts{i}")
            m.add(s[t.job, t.op] >= ts + t.dur)
            if t.op:
                m.add(ts >= s[t.job, t.op - 1] + inst.jobs[t.job][t.op - 1].duration)
            ivs.append(m.new_interval_var(ts - before[i], t.dur + before[i] + after[i], ts + t.dur + after[i],
                                          f"a{i}"))
        if inst.n_agvs == 1:
            m.add_no_overlap(ivs)
        else:
            m.add_cumulative(ivs, [1] * len(ivs), inst.n_agvs)
    m.minimize(mk)
    return m, s


def _check_seconds(time_limit: Any, zero: bool = False) -> None:
    """Refuse a ``time_limit`` that is no number, negative (zero too unless ``zero``), NaN or infinite: CP-SAT ran
    NaN as a fraction of a second and infinity without end, where :func:`fms_dispatch.solvers.solve` refuses both."""
    if isinstance(time_limit, bool) or not isinstance(time_limit, numbers.Real):
        raise TypeError(f"time_limit must be a number of seconds, got {time_limit!r}")
    seconds = float(time_limit)
    if not (0 <= seconds if zero else 0 < seconds) or not math.isfinite(seconds):
        raise ValueError(f"time_limit must be a {'non-negative' if zero else 'positive'}, finite number of seconds, "
                         f"got {time_limit!r}")


def relaxation_bound(inst: Instance, *, time_limit: float = 10.0, workers: int = 2, seed: int = 0,
                     ub: int | None = None) -> tuple[int, dict[tuple[int, int], int] | None]:
    """A valid lower bound from the relaxation (see :func:`_relaxation_model`) solved within ``time_limit``
    seconds, at least :func:`simple_lower_bound`; also the relaxed start times (``None`` if none found)."""
    _check_seconds(time_limit, zero=True)
    lb = simple_lower_bound(inst)
    if ub is None:
        ub = greedy_schedule(inst).makespan
    if time_limit == 0 or lb >= ub:
        return lb, None
    model, s = _relaxation_model(inst, ub)
    cp_model = _cp()
    solver = cp_model.CpSolver()
    solver.parameters.max_time_in_seconds = time_limit
    solver.parameters.num_workers = max(1, workers)
    solver.parameters.random_seed = cp_seed(seed)
    solver.parameters.catch_sigint_signal = False  # see _solve_full
    status = run_solver(solver, model)
    starts = None
    if status in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        starts = {key: solver.value(v) for key, v in s.items()}
    if status == cp_model.INFEASIBLE:
        lb = max(lb, ub)  # no relaxed schedule within ub: ub itself is a bound (ub is feasible)
    else:
        lb = _proved(solver, lb)
    return min(lb, ub), starts


# ====================================================================================== entry points
def n_transport_tasks(inst: Instance) -> int:
    """AGV carries plus tool uses of ``inst``: the size that decides between the full and the relaxed model."""
    return len(_agv_tasks(inst)) + sum(len(u) for u in _tool_uses(inst).values())


def fits_full_model(inst: Instance) -> bool:
    """Whether ``solve_exact(model="auto")`` and :func:`polish_plan` use the full model on ``inst``: a plain job
    shop, or at most :data:`FULL_MODEL_MAX_TASKS` transport tasks."""
    return inst.mode == "jobshop" or n_transport_tasks(inst) <= FULL_MODEL_MAX_TASKS


def solve_exact(
    instance: Instance,
    *,
    time_limit: float = 60.0,
    workers: int = 2,
    seed: int = 0,
    hint: Schedule | None = None,
    log: bool = False,
    progress: Progress | None = None,
    model: str = "auto",
    cp_params: Mapping[str, object] | None = None,
) -> ExactResult:
    """Minimise the makespan of ``instance`` with CP-SAT within ``time_limit`` seconds on ``workers`` threads.

    ``hint`` (a feasible schedule) seeds the search and is the fallback incumbent; ``progress(objective,
    bound, seconds)`` is called on each improved solution; ``model`` is ``"auto"`` (full model up to
    :data:`FULL_MODEL_MAX_TASKS` transport tasks, plain job shops always), ``"full"`` or ``"relaxed"``;
    ``cp_params`` sets extra CP-SAT parameters of the full model (e.g. ``{"use_objective_lb_search": True}``).
    """
    t0 = time.monotonic()
    _check_seconds(time_limit)
    if not isinstance(workers, numbers.Integral) or isinstance(workers, bool) or workers < 1:  # "2": a TypeError
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if model not in ("auto", "full", "relaxed"):
        raise ValueError(f"unknown model {model!r}; use 'auto', 'full' or 'relaxed'")
    if hint is not None:
        problems = validate(instance, hint)
        if problems:
            raise ValueError(f"the hint is not a feasible schedule for {instance.name}: {problems[0]}")
    full = model == "full" or (model == "auto" and fits_full_model(instance))
    greedy_budget = min(2.0, 0.05 * time_limit) if full else min(10.0, 0.15 * time_limit)
    incumbent = _best_greedy(instance, greedy_budget, seed)
    if hint is not None and hint.makespan <= incumbent.makespan:
        incumbent = _copy_schedule(hint)
    lb = simple_lower_bound(instance)
    start = incumbent.makespan
    try:  # (an interrupt before this point, in the start schedule's search, has no start schedule to report)
        if full:
            incumbent = _improve_by_priorities(instance, incumbent, None, lb, t0 + 0.1 * time_limit, seed, None, t0,
                                               max_stall=300)
            res = _solve_full(instance, incumbent, lb, t0, time_limit, workers, seed, log, progress, cp_params)
        else:
            res = _solve_fallback(instance, incumbent, lb, t0, time_limit, workers, seed, progress)
        res.start_makespan = start
        return res
    except KeyboardInterrupt as exc:  # before CP-SAT's search (or in the fallback's): the best start schedule
        stopped = SearchInterrupted.of(exc, incumbent, lb, time.monotonic() - t0)
        stopped.start_makespan = start
        raise stopped from None


def _copy_schedule(s: Schedule) -> Schedule:
    return Schedule(s.instance, s.makespan, s.n_agvs, s.n_tool_transporters, list(s.operations),
                    list(s.agv_trips), list(s.tool_trips), dict(s.meta))


def _solve_full(inst: Instance, incumbent: Schedule, lb: int, t0: float, time_limit: float, workers: int,
                seed: int, log: bool, progress: Progress | None,
                cp_params: Mapping[str, object] | None, min_time: float = 0.1) -> ExactResult:
    ub = incumbent.makespan
    if lb >= ub:
        if progress is not None:
            progress(ub, ub, time.monotonic() - t0)
        return ExactResult(incumbent, ub, "OPTIMAL", time.monotonic() - t0)
    fm = _FullModel(inst, lb, ub)
    fm.add_hint(incumbent)
    cp_model = _cp()
    solver = cp_model.CpSolver()
    p = solver.parameters
    p.max_time_in_seconds = max(min_time, time_limit - (time.monotonic() - t0), 1e-3)
    p.num_workers = workers
    p.random_seed = cp_seed(seed)
    # CP-SAT's own SIGINT handler would outlive the solve: a node that planned with it then dies of the SIGINT
    # that should stop it cleanly (the agent node running plan:cpsat); the caller's handler stays in charge
    p.catch_sigint_signal = False
    p.log_search_progress = log
    for key, val in (cp_params or {}).items():
        if not hasattr(p, key):
            raise ValueError(f"unknown CP-SAT parameter {key!r}")
        if isinstance(val, (list, tuple)):
            getattr(p, key).extend(val)
        else:
            setattr(p, key, val)
    cb = _callback_class()(fm, progress, t0)
    try:
        status = run_solver(solver, fm.model, cb)
    except KeyboardInterrupt:  # the search stopped (run_solver): its best solution, with the bound it had proved
        best = cb.best if cb.best is not None and cb.best.makespan <= incumbent.makespan else incumbent
        try:
            lb = _proved(solver, lb)
        except Exception:  # (no response to read: the search had not begun)
            pass
        raise SearchInterrupted(best, lb, time.monotonic() - t0) from None
    bound = _proved(solver, lb) if status != cp_model.INFEASIBLE else lb
    best = incumbent
    if cb.best is not None and cb.best.makespan <= best.makespan:
        best = cb.best
    wall = time.monotonic() - t0
    if status == cp_model.OPTIMAL and best.makespan <= bound:  # (the model's optimum may have been skipped as
        name = "OPTIMAL"                                        # contradictory: its bound still holds)
        bound = best.makespan
    elif status == cp_model.INFEASIBLE:
        # cannot happen: the incumbent satisfies the model; keep it with the simple bound, but say so
        warnings.warn(f"CP-SAT called the model of {inst.name} infeasible although the incumbent "
                      f"(makespan {ub}) satisfies it; returning the incumbent", RuntimeWarning, stacklevel=3)
        name = "FEASIBLE"
    else:
        name = "OPTIMAL" if bound >= best.makespan else "FEASIBLE"
    bound = min(bound, best.makespan)
    return ExactResult(best, bound, name, wall)


def _solve_fallback(inst: Instance, incumbent: Schedule, lb: int, t0: float, time_limit: float, workers: int,
                    seed: int, progress: Progress | None) -> ExactResult:
    """Relaxation bound, then iterated guided list scheduling until the time is up (see module docstring)."""
    deadline = t0 + 0.97 * time_limit
    left = deadline - time.monotonic()
    bound, starts = relaxation_bound(inst, time_limit=max(0.0, 0.4 * left), workers=workers, seed=seed,
                                     ub=incumbent.makespan)
    bound = max(bound, lb)
    best = incumbent
    if progress is not None:
        progress(best.makespan, min(bound, best.makespan), time.monotonic() - t0)
    best = _improve_by_priorities(inst, best, starts, bound, deadline, seed, progress, t0)
    bound = min(bound, best.makespan)
    status = "OPTIMAL" if bound >= best.makespan else "FEASIBLE"
    return ExactResult(best, bound, status, time.monotonic() - t0)


def _improve_by_priorities(inst: Instance, best: Schedule, starts: dict[tuple[int, int], int] | None, bound: int,
                           deadline: float, seed: int, progress: Progress | None, t0: float,
                           max_stall: int | None = None, origin: Snapshot | None = None,
                           max_tries: int | None = None) -> Schedule:
    """Randomised greedy restarts, keeping the best schedule, until ``deadline`` (or ``max_stall`` attempts
    in a row without improvement, or ``max_tries`` attempts in all): first a schedule guided by the
    relaxation's start times (if given), then earliest-start list schedules whose start times are perturbed by
    random offsets (two in three attempts) and schedules guided by the best schedule's start times plus noise.
    With ``origin`` every schedule is a residual plan from that snapshot (see :func:`greedy_schedule`)."""
    rng = random.Random(seed)
    first = origin.next_op if origin is not None else (0,) * inst.n_jobs
    keys = [(j, k) for j, job in enumerate(inst.jobs) for k in range(first[j], len(job))]
    if not keys:
        return best
    mean_p = max(1.0, sum(inst.jobs[j][k].duration for j, k in keys) / len(keys))
    it = stall = 0
    try:
        while (best.makespan > bound and (max_stall is None or stall < max_stall)
               and (max_tries is None or it < max_tries)):
            t1 = time.monotonic()
            scale = mean_p * rng.choice((0.05, 0.2, 0.5))
            if it == 0 and starts is not None:
                cand = greedy_schedule(inst, rule="guided", priority=dict(starts), origin=origin)
            elif rng.random() < 2 / 3:
                cand = greedy_schedule(inst, rule="est", noise={key: scale * rng.random() for key in keys},
                                       origin=origin)
            else:
                prio = {(o.job, o.op): o.start + 4 * scale * rng.random() for o in best.operations}
                cand = greedy_schedule(inst, rule="guided", priority=prio, origin=origin)
            stall += 1
            if cand.makespan < best.makespan:
                best, stall = cand, 0
                if progress is not None:
                    progress(best.makespan, bound, time.monotonic() - t0)
            it += 1
            now = time.monotonic()
            if now + (now - t1) > deadline:
                break
    except KeyboardInterrupt as exc:  # the best found so far goes with the interrupt (solve_exact's large shops)
        raise SearchInterrupted.of(exc, best, bound, time.monotonic() - t0) from None
    return best


def check_plan_of(inst: Instance, plan: Schedule, origin: Snapshot | None, who: str) -> None:
    """Refuse (TypeError, ValueError) what ``who`` cannot improve: ``plan`` must be a whole schedule of ``inst``
    that the validator accepts (``origin`` None), or a residual plan from the snapshot ``origin`` of ``inst``
    (``meta["residual"]`` its time). Another shop's plan came back as this one's best, or failed deep inside."""
    require_instance(inst, who)
    require_schedule(plan, who)
    if origin is None and "residual" in plan.meta:
        raise ValueError(f"{who} improves a residual plan (meta['residual']) only with the snapshot it starts from "
                         "(origin)")
    if origin is not None and plan.meta.get("residual") != origin.now:
        raise ValueError(f"the plan does not start from the snapshot at time {origin.now} (its meta['residual']: "
                         f"{plan.meta.get('residual')!r})")
    if origin is not None:
        origin.check_of(inst)
        return
    problems = validate(inst, plan)
    if problems:
        raise ValueError(f"the plan is not a valid schedule of {inst.name}: {problems[0]}"
                         + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else ""))


def restart_list_plan(inst: Instance, plan: Schedule, *, tries: int, budget: float | None = None, seed: int = 0,
                      origin: Snapshot | None = None) -> Schedule:
    """``plan`` or a better list schedule found by at most ``tries`` randomised restarts of it within ``budget``
    seconds (None: no time limit): perturbed earliest-start schedules and schedules guided by the best one's
    start times (:func:`_improve_by_priorities`). Deterministic for a given ``seed`` while the time limit does
    not cut the restarts short. With ``origin`` every schedule is a residual plan from that snapshot."""
    check_plan_of(inst, plan, origin, "restart_list_plan")
    if not isinstance(tries, numbers.Integral) or isinstance(tries, bool) or tries < 0:  # (NaN made no restart)
        raise ValueError(f"tries must be an integer >= 0, got {tries!r}")
    if budget is not None and not (isinstance(budget, numbers.Real) and not isinstance(budget, bool) and budget >= 0):
        raise ValueError(f"budget must be >= 0 seconds (None: no time limit), got {budget!r}")  # (NaN: no limit)
    if tries == 0 or budget == 0:
        return plan
    t0 = time.monotonic()
    deadline = math.inf if budget is None else t0 + budget
    return _improve_by_priorities(inst, plan, None, 0, deadline, seed, None, t0, origin=origin, max_tries=tries)


def polish_plan(inst: Instance, plan: Schedule, *, time_limit: float, workers: int = 2, seed: int = 0) -> Schedule:
    """``plan`` or a better schedule that CP-SAT's full model finds from it within ``time_limit`` seconds (``plan``
    as its hint and upper bound; model building counted): a short exact polish of a heuristic plan on small
    shops, where a tenth of a second of CP-SAT from a good hint closes most of a list schedule's gap
    (docs/benchmarks.md §9). ``plan`` comes back unchanged when the shop is beyond the full model (more than
    :data:`FULL_MODEL_MAX_TASKS` transport tasks), when it meets the simple lower bound, or when nothing better is
    found in time. ``plan`` must be a whole schedule of ``inst`` (not a residual plan). Not reproducible in
    general: CP-SAT's parallel search depends on timing."""
    _check_seconds(time_limit, zero=True)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if "residual" in plan.meta:
        raise ValueError("polish_plan needs a whole schedule; a residual plan (meta['residual']) cannot be polished")
    if time_limit == 0 or not fits_full_model(inst):
        return plan
    t0 = time.monotonic()
    res = _solve_full(inst, plan, simple_lower_bound(inst), t0, time_limit, workers, seed, False, None, None,
                      min_time=0.0)
    if res.schedule is None or res.schedule.makespan >= plan.makespan:
        return plan
    best = res.schedule
    best.meta = {"solver": "cpsat", "polished": plan.meta.get("solver"), "wall_time": round(res.wall_time, 3)}
    return best


def cpsat(instance: Instance, *, time_limit: float = 60.0, workers: int = 2, **kw: object) -> Schedule:
    """The best schedule :func:`solve_exact` finds, with ``meta`` = solver, status, lower bound, wall time and the
    makespan of the start schedule the search began from (``start_makespan``).

    Raises ``RuntimeError`` if no feasible schedule was found within the time limit.
    """
    try:
        res = solve_exact(instance, time_limit=time_limit, workers=workers, **kw)  # type: ignore[arg-type]
    except SearchInterrupted as exc:
        exc.best.meta = {"solver": "cpsat", "status": "INTERRUPTED", "lower_bound": exc.lower_bound,
                         "wall_time": round(exc.wall_time, 3), "start_makespan": exc.start_makespan}
        raise
    if res.schedule is None:
        raise RuntimeError(f"cpsat found no feasible schedule for {instance.name} within {time_limit:g} s "
                           f"(status {res.status})")
    sch = res.schedule
    sch.meta = {"solver": "cpsat", "status": res.status, "lower_bound": res.lower_bound,
                "wall_time": round(res.wall_time, 3), "start_makespan": res.start_makespan}
    return sch
