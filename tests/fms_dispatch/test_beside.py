"""A guided model's plan search beside its run: the same schedule as the search before the run, the run going on
where the first plan stands and starting over where the search found a better one; failures and interrupts."""

from __future__ import annotations

import json
import os

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.disruptions import Breakdown, Scenario
from fms_sim.full_shop import FullShop, make_shop
from fms_sim.validate import validate
from fms_dispatch.rl import beside
from fms_dispatch.rl.guide import PlanEffort, effort_from, first_plan, guide_plan, search_from
from fms_dispatch.rl.models import load_agent
from fms_dispatch.solvers import solve

#: a search that does not depend on the clock (8 restarts end far within the budget, no tabu search): its plan is
#: the same on any machine
SEARCH = effort_from(restarts=8, budget=30, tabu=0)

needs_fork = pytest.mark.skipif(not beside.FORK_AVAILABLE, reason="the search runs beside the run on Linux only")


@pytest.fixture
def two_cpus(monkeypatch):
    """The search may run beside the run whatever this machine's CPUs (CI has 2) and the shop's size (these are
    small shops, whose search runs in line by default); both checks are tested below."""
    monkeypatch.setattr(beside, "_cpus", lambda: 2)
    monkeypatch.setattr(beside, "BESIDE_LISTS", 10**9)


def _in_line(monkeypatch, inst, **kwargs):
    with monkeypatch.context() as m:
        m.setattr(beside, "FORK_AVAILABLE", False)
        sched = solve(inst, "ppo", guide_effort=SEARCH, **kwargs)
    assert sched.meta["guide_search_beside"] is None
    return sched


def test_the_search_from_its_first_plan_is_the_guides_plan():
    # guide_plan is first_plan and then search_from: the same plan; the search returns the first plan itself where
    # nothing ends earlier (EX12 with 8 restarts: 84 stands), a new plan where something does (EX22: 97 -> 82)
    assert SEARCH.budget == 30
    for name, kept in (("EX12", True), ("EX22", False)):
        inst = builtin(name)
        first = first_plan(FullShop(inst))
        searched = search_from(inst, first, SEARCH)
        assert (searched is first.plan) == kept
        whole = guide_plan(FullShop(inst), SEARCH)
        assert whole.makespan == searched.makespan and whole.operations == searched.operations


@needs_fork
@pytest.mark.parametrize("name,outcome", [("EX12", "kept"), ("EX22", "restarted"), ("sl00", "restarted")])
def test_the_search_beside_the_run_gives_the_schedule_of_the_search_before_it(monkeypatch, two_cpus, name, outcome):
    inst = builtin(name)
    before = _in_line(monkeypatch, inst)
    sched = solve(inst, "ppo", guide_effort=SEARCH)
    assert validate(inst, sched) == []
    assert sched.meta["guide_search_beside"] == outcome
    assert sched.operations == before.operations and sched.makespan == before.makespan
    assert sched.meta["guide_plan_makespan"] == before.meta["guide_plan_makespan"]
    assert 0 < sched.meta["guide_search_time"]


@needs_fork
def test_a_disrupted_run_with_its_re_plans_is_the_same_beside(monkeypatch, two_cpus):
    # the run that starts over gets a fresh shop and a fresh re-planner: its re-plans are those of the run alone
    inst = builtin("EX22")
    sc = Scenario((Breakdown(machine=2, start=20, duration=40),), (), 0.1, 5)
    before = _in_line(monkeypatch, inst, scenario=sc, guide_replan=True)
    sched = solve(inst, "ppo", guide_effort=SEARCH, scenario=sc, guide_replan=True)
    assert validate(inst, sched) == [] and sched.meta["guide_search_beside"] == "restarted"
    assert sched.operations == before.operations
    strip = [{k: v for k, v in e.items() if k != "wall_time"} for e in before.meta["replans"]]
    assert [{k: v for k, v in e.items() if k != "wall_time"} for e in sched.meta["replans"]] == strip


@needs_fork
def test_a_search_that_fails_in_its_process_is_made_in_line(monkeypatch, two_cpus):
    parent = os.getpid()
    real = beside.search_from

    def fails_in_the_child(inst, first, effort):
        if os.getpid() != parent:
            raise MemoryError("no memory in the child")
        return real(inst, first, effort)

    monkeypatch.setattr(beside, "search_from", fails_in_the_child)
    inst = builtin("EX22")
    search = beside.SearchBeside(FullShop(inst), SEARCH)
    plan = search.searched()
    assert search.failed == "no memory in the child"
    assert plan is not None and plan.operations == guide_plan(FullShop(inst), SEARCH).operations
    with pytest.raises(RuntimeError, match="read already"):
        search.searched()


@needs_fork
def test_an_interrupted_run_ends_the_search(two_cpus):
    inst = builtin("sl00")
    agent = load_agent("guided-dagger")
    agent.use_guide_effort(effort_from(restarts=64, budget=30, tabu=0))  # a search that would run for 30 s
    shop = make_shop(inst, agent.decisions)
    search = beside.SearchBeside(shop, agent.guide_effort)
    agent.adopt_replan(shop, search.first.plan, None, None)
    job = search._job
    n = 0

    def interrupted(s):
        nonlocal n
        n += 1
        if n == 40:
            raise KeyboardInterrupt
        return agent.act(s)

    with pytest.raises(KeyboardInterrupt):
        beside.run_beside(search, shop, interrupted, lambda plan: pytest.fail("no second run"))
    assert not job.process.is_alive() and job.process.exitcode is not None


def test_the_search_runs_beside_only_where_it_can_and_searches(monkeypatch):
    monkeypatch.setattr(beside, "FORK_AVAILABLE", True)
    monkeypatch.setattr(beside, "_cpus", lambda: 2)
    assert beside.beside_possible(SEARCH)
    assert beside.beside_possible(effort_from(restarts=0, tabu=0.001))
    assert not beside.beside_possible(PlanEffort())  # the list schedules only: nothing to search beside
    assert not beside.beside_possible(effort_from(exact=1.0))  # CP-SAT's polish stays in line
    monkeypatch.setattr(beside, "_cpus", lambda: 1)  # one CPU: the search would share it with the run
    assert not beside.beside_possible(SEARCH)
    monkeypatch.setattr(beside, "_cpus", lambda: 2)
    monkeypatch.setattr(beside, "FORK_AVAILABLE", False)
    assert not beside.beside_possible(SEARCH)


def test_only_a_search_that_its_budget_cuts_short_runs_beside(monkeypatch):
    # beside only where the budget fits fewer than BESIDE_LISTS list schedules (the 100-job shops): elsewhere the
    # search nearly always improves the first plan, and the run would start over after a fork for nothing
    import dataclasses

    monkeypatch.setattr(beside, "_cpus", lambda: 2)
    first = first_plan(FullShop(builtin("EX12")))
    one_s = effort_from(budget=1.0)
    assert not beside.worth_beside(dataclasses.replace(first, seconds=0.01), one_s)  # 16 x 0.01 s fit in 1 s
    assert beside.worth_beside(dataclasses.replace(first, seconds=0.1), one_s)  # (sl70: 0.15 s each)
    assert not beside.worth_beside(dataclasses.replace(first, seconds=0.1), effort_from(budget=0))  # no budget
    sched = solve(builtin("EX12"), "ppo")  # the default search on a small shop: before the run
    assert sched.meta["guide_search_beside"] is None and validate(builtin("EX12"), sched) == []


def test_lookahead_runs_search_before_the_run(monkeypatch, two_cpus):
    # the lookahead's twins read the guide too: a run with the lookahead plans first, as before
    sched = solve(builtin("EX12"), "ppo+lookahead-fast", guide_effort=SEARCH)
    assert validate(builtin("EX12"), sched) == [] and sched.meta["guide_search_beside"] is None


def test_a_pool_worker_searches_before_its_run(monkeypatch):
    # fms bench / fms experiment --jobs N: N workers solve at once, so a search beside a run would share a core
    from fms_dispatch.benchmark import _pool_worker

    monkeypatch.setattr(beside, "FORK_AVAILABLE", True)
    monkeypatch.setattr(beside, "_cpus", lambda: 2)
    monkeypatch.setattr(beside, "ALLOWED", True)
    assert beside.beside_possible(SEARCH)
    _pool_worker()
    assert not beside.ALLOWED and not beside.beside_possible(SEARCH)


def test_where_no_process_can_be_forked_the_search_runs_before_the_run(monkeypatch, two_cpus):
    def no_fork(*args, **kwargs):
        raise OSError("Resource temporarily unavailable")

    monkeypatch.setattr(beside, "Forked", no_fork)
    inst = builtin("EX22")
    sched = solve(inst, "ppo", guide_effort=SEARCH)
    assert validate(inst, sched) == [] and sched.meta["guide_search_beside"] is None
    assert sched.operations == _in_line(monkeypatch, inst).operations and sched.meta["guide_search_time"] > 0


@needs_fork
def test_an_interrupt_while_the_solve_waits_for_the_search_ends_it(two_cpus):
    # the run ended first and the solve waits for the search; a Ctrl-C there (KeyboardInterrupt) left the search
    # running in its process to the end of its budget (30 s here), at full CPU, in a process that went on
    import signal

    search = beside.SearchBeside(FullShop(builtin("EX22")), effort_from(restarts=10**6, budget=30, tabu=0))
    job = search._job

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, interrupt)
    signal.setitimer(signal.ITIMER_REAL, 0.3)
    try:
        with pytest.raises(KeyboardInterrupt):
            search.searched()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    job.process.join(timeout=5)  # (a process still searching would not end within 5 s)
    assert not job.process.is_alive() and job.process.exitcode is not None


@needs_fork
def test_an_interrupt_before_the_run_ends_the_search(monkeypatch, two_cpus):
    # a Ctrl-C after the search began and before the run did (while the first plan was put in force) left the
    # search running to the end of its budget
    from fms_dispatch.rl.agent import Agent

    started = []

    class Recorded(beside.Forked):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            started.append(self)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(beside, "Forked", Recorded)
    monkeypatch.setattr(Agent, "adopt_replan", interrupted)
    with pytest.raises(KeyboardInterrupt):
        solve(builtin("EX22"), "ppo", guide_effort=effort_from(restarts=10**6, budget=30, tabu=0))
    assert len(started) == 1
    started[0].process.join(timeout=5)
    assert not started[0].process.is_alive()


@needs_fork
def test_a_daemonic_process_searches_before_its_run(monkeypatch, two_cpus):
    # a multiprocessing.Pool's worker is daemonic, and a daemonic process may not start one: solve(sl70, "ppo") in
    # one failed with "AssertionError: daemonic processes are not allowed to have children"
    import multiprocessing

    monkeypatch.setitem(multiprocessing.current_process()._config, "daemon", True)
    assert not beside.beside_possible(SEARCH)
    inst = builtin("EX22")
    sched = solve(inst, "ppo", guide_effort=SEARCH)
    assert validate(inst, sched) == [] and sched.meta["guide_search_beside"] is None
    with pytest.raises(OSError, match="daemonic"):  # (the agent node's re-plans and the search fall back on it)
        beside.Forked(len, ((),))


def test_a_cpu_quota_below_two_cpus_keeps_the_search_before_the_run(tmp_path, monkeypatch):
    # a container given 1.5 CPUs' time may see every CPU in its affinity: the search and the run would share one
    monkeypatch.setattr(beside.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    monkeypatch.setattr(beside, "CGROUP_ROOT", tmp_path)
    assert beside._cpus() == 4  # nothing to read: no limit
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert beside._cpus() == 4
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert beside._cpus() == 1
    (tmp_path / "cpu.max").write_text("300000 100000\n")
    assert beside._cpus() == 3
    (tmp_path / "cpu.max").unlink()
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("100000\n")  # cgroup v1
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert beside._cpus() == 1
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")  # v1: no limit
    assert beside._cpus() == 4


def test_no_guide_beside_searches_before_the_run(monkeypatch, two_cpus, tmp_path, capsys):
    # a second CPU that another job keeps busy would give the search beside the run less time: the user can say so
    from fms_dispatch import cli

    inst = builtin("EX22")
    sched = solve(inst, "ppo", guide_effort=SEARCH, guide_beside=False)
    assert sched.meta["guide_search_beside"] is None
    assert sched.operations == solve(inst, "ppo", guide_effort=SEARCH).operations
    out = tmp_path / "s.json"
    assert cli.main(["solve", "EX22", "--solver", "ppo", "--guide-budget", "30", "--guide-tabu", "0",
                     "--guide-restarts", "8", "--out", str(out), "-q"]) == 0
    assert json.loads(out.read_text())["meta"]["guide_search_beside"] == "restarted"
    assert cli.main(["solve", "EX22", "--solver", "ppo", "--guide-budget", "30", "--guide-tabu", "0",
                     "--guide-restarts", "8", "--no-guide-beside", "--out", str(out), "-q"]) == 0
    assert json.loads(out.read_text())["meta"]["guide_search_beside"] is None
    capsys.readouterr()
    assert cli.main(["solve", "EX22", "--solver", "list", "--no-guide-beside"]) == 2
    assert "--[no-]guide-beside applies to the ppo solver only" in capsys.readouterr().err
    assert cli.main(["solve", "EX22", "--solver", "ppo:full", "--no-guide-beside"]) == 2
    assert "reads no plan guide, so it takes no --[no-]guide-beside" in capsys.readouterr().err
