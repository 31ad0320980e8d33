"""A guided model's plan search beside its run, on the machine's other core.

A guided model's solve searches the plan it acts out (:func:`~fms_dispatch.rl.guide.guide_plan`, within 1 s by
default) before its first decision. Where a second core is there for it (:func:`beside_possible`) and the search
can do little within its budget (:func:`worth_beside`: the large shops) the search runs on that core instead, in a
forked copy of the process (:class:`fms_dispatch.forked.Forked`), from the search's first plan (the earliest-start
list schedule, :func:`~fms_dispatch.rl.guide.first_plan`), while the run goes on with the first plan in force
(:func:`run_beside`). When the search ends:

* nothing it found ends earlier than the first plan: the run that went on is the run the solve makes with the
  search before it, and it goes on: the search's time is saved (on the large benchmark's 100-job shops with tools
  the search leaves the first plan as it is on 5 of 10 within its budget, docs/benchmarks.md §9);
* it found a plan that ends earlier: the run starts over with that plan, as it would have started after the
  search (the time of the run so far, made on this core while the search ran on the other, is lost).

Either way the schedule is the one the search before the run gives: the search is the same (the same steps, the
same budget counted from the same start); only, as before, a budget that cuts the search short makes its plan
depend on the machine's speed.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Callable

from fms_sim.full_shop import FullShop
from fms_sim.instance import Instance
from fms_sim.schedule import Schedule
from fms_sim.shop import Shop

from ..forked import FORK_AVAILABLE, Forked
from .guide import FirstPlan, PlanEffort, first_plan, search_from

__all__ = ["beside_possible", "worth_beside", "in_pool_worker", "SearchBeside", "run_beside", "ALLOWED",
           "BESIDE_LISTS"]

Choose = Callable[[Shop], int]

#: whether a plan search may run beside its run in this process (:func:`beside_possible`): a worker of a process
#: pool sets it False (:func:`in_pool_worker`), since the pool's other workers keep the machine's other cores busy
#: and a search sharing a core does less within its budget
ALLOWED = True


def in_pool_worker() -> None:
    """For a process pool's initializer: this process is one of several solving at once, so its plan searches run
    before their runs (:data:`ALLOWED`)."""
    global ALLOWED
    ALLOWED = False


#: where the control groups that may limit this process's CPU time are mounted (a container's own, as a rule)
CGROUP_ROOT = Path("/sys/fs/cgroup")


def _quota_cpus(root: Path) -> float | None:
    """The CPUs' worth of time a control group under ``root`` allows (cgroup v2 ``cpu.max``, or v1
    ``cpu/cpu.cfs_quota_us`` over ``cpu.cfs_period_us``: a container limited to 1.5 CPUs gives 1.5), None where
    there is no limit or nothing can be read."""
    try:
        quota, _, period = (root / "cpu.max").read_text().partition(" ")
        if quota.strip() == "max":
            return None
        return int(quota) / int(period)
    except (OSError, ValueError, ZeroDivisionError):
        pass
    try:
        quota_us = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period_us = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return quota_us / period_us if quota_us > 0 and period_us > 0 else None
    except (OSError, ValueError):
        return None


def _cpus() -> int:
    """The CPUs this process may run on (all of the machine's where the system cannot say), no more than the whole
    CPUs its control group's quota allows (a container given one CPU's time may still see every CPU in its
    affinity: the search and the run would share that one)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # (not on Linux; fork is not used there anyway)
        n = os.cpu_count() or 1
    quota = _quota_cpus(CGROUP_ROOT)
    return n if quota is None else max(1, min(n, int(quota)))


def beside_possible(effort: PlanEffort) -> bool:
    """Whether a plan search with ``effort`` runs beside the run here: this process is not one of a pool's workers
    (:data:`ALLOWED`) nor daemonic (a ``multiprocessing.Pool``'s worker, which may not start a process), a process
    can be forked (Linux), this process may use two CPUs or more (on one the search and the run would share it, and a
    budget cut short would end the search with a worse plan), and ``effort`` searches past the two list schedules
    (restarts, rule pairs or a tabu search) without CP-SAT's polish (OR-Tools' threads are not used in a forked
    child)."""
    import multiprocessing

    searches = effort.restarts > 0 or effort.rules or effort.tabu > 0
    # a daemonic process (a multiprocessing.Pool's worker) may not start a process, and is one of several solving
    daemonic = multiprocessing.current_process().daemon
    return ALLOWED and FORK_AVAILABLE and not daemonic and _cpus() >= 2 and searches and not effort.exact


#: the search runs beside the run only where its budget fits fewer list schedules of the shop than this
#: (:func:`worth_beside`)
BESIDE_LISTS = 16


def worth_beside(first: FirstPlan, effort: PlanEffort) -> bool:
    """Whether the search from ``first`` is worth running beside the run: its budget fits fewer than
    :data:`BESIDE_LISTS` list schedules of the shop (``first.seconds`` each), so that its restarts and tabu search get
    little done and the first plan may well stand (on the large benchmark it stood on 5 of the 10 100-job shops with
    tools, where 3-4 list schedules fit in the 1 s budget, and on no shop of up to 40 jobs). On smaller shops the
    search improves the first plan nearly always, so a run beside it would start over and pay for the fork and the
    plan's transfer for nothing (about 10 ms a solve on Bilge-Ulusoy's shops, a seventh of it). A search without a
    budget is not run beside."""
    return effort.budget is not None and first.seconds * BESIDE_LISTS > effort.budget


def _search(inst: Instance, first: FirstPlan, effort: PlanEffort) -> tuple[Schedule | None, float]:
    """The forked child's work: the search from ``first`` (:func:`~fms_dispatch.rl.guide.search_from`); its plan,
    None where that is the first plan itself, and when it ended (``time.monotonic()``, one clock for both
    processes)."""
    best = search_from(inst, first, effort)
    return (None if best is first.plan else best), time.monotonic()


class SearchBeside:
    """The guide's plan search for ``shop`` (at its run's start) with ``effort``, running in a forked process from
    the moment this is made; :attr:`first` is its first plan (``first``, :func:`~fms_dispatch.rl.guide.first_plan`
    of ``shop``, or computed here), for the run to go on with. Raises OSError where no process can be forked now (the
    caller then searches in line)."""

    def __init__(self, shop: FullShop, effort: PlanEffort, first: FirstPlan | None = None) -> None:
        self.effort = effort
        self.instance = shop.instance
        self.first: FirstPlan = first_plan(shop) if first is None else first
        #: the search's length in seconds from its start (the first plan included), once it has ended
        self.seconds: float | None = None
        #: why the forked search failed (it was then made again in line), or None
        self.failed: str | None = None
        self._job: Forked | None = Forked(_search, (self.instance, self.first, effort), name="fms-plan-search")

    def ready(self) -> bool:
        """Whether the search has ended (:meth:`searched` would not wait)."""
        return self._job is None or self._job.ready()

    def searched(self) -> Schedule | None:
        """The searched plan if it ends earlier than the first plan, None where the first plan stands; waits for
        the search. A search that failed in its process (killed, out of memory) is made again here, with its whole
        budget."""
        job, self._job = self._job, None
        if job is None:
            raise RuntimeError("the plan search's result was read already")
        try:
            plan, end = job.result()
        except RuntimeError as exc:
            self.failed = str(exc)
            first = dataclasses.replace(self.first, t0=time.monotonic())
            plan, end = _search(self.instance, first, self.effort)
        except BaseException:  # interrupted while it waited (Ctrl-C): the search ends with the solve, not its budget
            job.cancel()
            raise
        self.seconds = end - self.first.t0
        return plan

    def cancel(self) -> None:
        """End the search if it still runs (a run interrupted or failed)."""
        if self._job is not None:
            self._job.cancel()
            self._job = None


def run_beside(search: SearchBeside, shop: Shop, choose: Choose, again: Callable[[Schedule], tuple[Shop, Choose]],
               progress: Callable[[str], None] | None = None, every_s: float = 2.0) -> tuple[Schedule, Shop, bool]:
    """Run ``shop`` (its guide: ``search.first``'s plan) to completion with ``choose`` while ``search`` runs; where
    the search ends with a plan that ends earlier, the run starts over with that plan: ``again(plan)`` gives the
    fresh shop (its guide: ``plan``) and its ``choose``. Returns the schedule, the shop that made it and whether the
    run started over.
    ``progress`` gets a line at most every ``every_s`` seconds, and one where the run starts over. The search is
    ended if the run fails or is interrupted."""
    from .lookahead import progress_line, run_agent

    t0 = last = time.perf_counter()
    better = None
    pending, n = True, 0
    try:
        while not shop.done:
            shop.act(choose(shop))
            n += 1
            if pending and not n & 15 and search.ready():  # (a poll of the pipe every 16 decisions)
                pending = False
                better = search.searched()
                if better is not None:
                    break
            if progress is not None and time.perf_counter() - last >= every_s:
                last = time.perf_counter()
                progress(progress_line(shop, last - t0, ", the plan search beside it" if pending else ""))
        if pending:  # the run ended first
            pending = False
            better = search.searched()
    finally:
        if pending:
            search.cancel()
    if better is None:
        return shop.schedule(), shop, False
    if progress is not None:
        progress(f"  the plan search found a plan ending at {better.makespan} (its first plan: "
                 f"{search.first.plan.makespan}): the run starts over with it")
    shop, choose = again(better)
    return run_agent(shop, choose, progress=progress, every_s=every_s), shop, True
