"""``fms bench``: baseline tables and plots on the Bilge–Ulusoy (``bu``) and the large (``sl``) benchmarks.

A benchmark is a list of :class:`Task` s, one per (instance, variant, method). :func:`run_bench` solves them
(in a process pool when ``jobs > 1``), validates every schedule with :func:`fms_sim.validate.validate` and
appends each finished task at once as one JSON line to ``<results>/bench_cache.jsonl``. The cache key is
(benchmark, instance, variant, method, time_limit, seed), and for ``cpsat`` with ``--cpsat-workers`` given, its
threads too (the default follows ``--jobs``; a cached row of another thread count is reused then); a rerun skips
tasks already cached with a valid result (unless ``force``), so an interrupted run loses nothing. Tasks that failed
(solver error or invalid schedule) are cached too, so that the tables show them, but are tried again on the next
run. The outputs (Markdown, CSV, JSON, PNG) show this run's tasks, each from the cache (those run before included),
and are replaced by the next run's of the same benchmark and layout.

Each row records in ``digests`` what produced it (:func:`task_digests`): the cache format (:data:`CACHE_FORMAT`),
the SHA-256 of the solved instance's canonical JSON (``Instance.to_dict`` with sorted keys: its jobs, matrices and
fleet, not the data file's bytes, so a file reformatted only changes nothing), for ``ppo`` methods the SHA-256 of
the weights file the model resolves to (the default ``ppo`` per instance, by ``default_model_name``) and for
``plan:file:PATH`` the file's SHA-256. A cached row is reused only where its digests equal the task's: a row of an
instance whose data changed, of a retrained model or of an edited plan file is solved again, and the run says on
stderr how many were and what changed (the key alone reused such rows without a word, mixing results of different
inputs in one table). Rows cached before digests were recorded carry none: they are reused as they are (hours of
CP-SAT runs), and the run says on stderr how many it reused that way and that ``--force`` solves them again. The
digests are those of the inputs when the run starts, each computed once per run (no solver or torch is loaded).

Rows (plain dicts, as in the cache): ``benchmark, instance, variant, method, time_limit, seed, workers,
makespan, wall_time, valid, error, lower_bound, status, optimum, n_jobs, n_machines, digests``. ``error`` is
``None`` for a valid schedule; an invalid schedule or a solver failure gives ``valid = False`` and the reason, and
is never averaged into a table.

Gaps are relative to a reference makespan ``ref``: ``100 * (makespan - ref) / ref``. For ``bu`` the reference
is the known optimum (``instance.meta["optimal_makespan"]``), for ``sl`` the best lower bound any method
reported (``schedule.meta["lower_bound"]``, e.g. CP-SAT's). The "gap %" row is the mean of the per-instance
gaps (not the gap of the mean makespans).

CP-SAT threads: CP-SAT runs ``workers`` search threads. So that parallel tasks do not oversubscribe the CPU,
each ``cpsat`` task gets ``workers = max(1, min(2, cpus // parallel))``, where ``parallel`` is the number of
tasks that run at once (``min(jobs, tasks to run)``): 2 threads when run alone on a 2-core machine, 1 with
``--jobs 2``. ``--cpsat-workers`` overrides it; the value used is recorded per row. (The alternative, fewer
parallel jobs while cpsat runs, would leave cores idle beside the many fast rule tasks.)

``jobs > 1`` uses a process pool with *spawned* workers (forking a process that may hold CP-SAT or torch
threads can deadlock), so a script calling :func:`run_bench` needs the usual ``if __name__ == "__main__":``
guard; the ``fms`` command has it.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import sys
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

from fms_sim.benchmarks import SL_GROUPS, SL_PER_GROUP, builtin
from fms_sim.files import replacing, write_atomically
from fms_sim.instance import Instance

__all__ = [
    "Task", "run_bench", "run_task", "bu_tasks", "sl_tasks", "bu_table", "sl_table", "time_table", "summary",
    "best_rule_of", "failures", "parse_index_spec", "check_methods", "cpsat_threads", "default_jobs",
    "read_cache", "write_outputs", "render_markdown", "plot_bench", "add_bench_parser", "CACHE_NAME", "VARIANTS",
    "CACHE_FORMAT", "instance_digest", "task_digests",
]

CACHE_NAME = "bench_cache.jsonl"
#: The format of a cached row's ``digests`` (rows without them are of the format before: 1). A row of another
#: format is solved again, as one whose digests differ.
CACHE_FORMAT = 2
#: Instance variants: ``agvs`` = AGVs only (tools dropped), ``agvs+tools`` = the instance as built.
VARIANTS = ("agvs", "agvs+tools")
BU_SETS = range(1, 11)
EXIT_FAILED = 1


# ============================================================================================ tasks
@dataclass(frozen=True)
class Task:
    """One solve: built-in ``instance`` in ``variant`` by solver ``method`` (a name for ``solvers.solve``).

    ``time_limit`` is ``None`` for methods that take none (rules, ``first``, ``random``, ``list``, ``ppo``);
    ``workers`` is passed to ``cpsat`` only and is not part of the key (a cached row of another thread count is
    not reused where ``workers`` was given: :func:`run_bench`); ``seed`` is part of it (a run with another
    ``--seed`` reused the cached rows of seed 0 and printed their makespans).
    """

    benchmark: str
    instance: str
    variant: str
    method: str
    time_limit: float | None = None
    seed: int = 0
    workers: int | None = field(default=None, compare=False)

    @property
    def key(self) -> tuple[str, str, str, str, float | None, int]:
        return (self.benchmark, self.instance, self.variant, self.method, _tl(self.time_limit), int(self.seed))


def _tl(x: Any) -> float | None:
    return None if x is None else float(x)


def _row_key(row: dict[str, Any]) -> tuple[Any, ...]:
    return (row["benchmark"], row["instance"], row["variant"], row["method"], _tl(row.get("time_limit")),
            int(row.get("seed") or 0))


def searches(method: str) -> bool:
    """Whether a method takes a time limit (everything except rules, ``first``, ``random`` and ``list``)."""
    from .solvers import searches_time

    return searches_time(method)


def check_methods(methods: Sequence[str]) -> list[str]:
    """The methods, deduplicated in order; raises ``ValueError`` for an unknown solver name (before any work)."""
    from .solvers import get_solver

    if not methods:
        raise ValueError("no methods to run")
    out: list[str] = []
    for m in methods:
        get_solver(m)  # UnknownSolver is a ValueError with the list of names
        low = m.lower()
        if low.startswith("rule:") and m.count("+") >= 2:  # would fail every task, after the others have run
            raise ValueError(f"{m!r} names a tool rule: fms bench runs first, random and rule:JOB+VEHICLE through "
                             "the paper's net (the paper's table), which has none; rules:full runs the full net's "
                             f"rule combinations, and fms solve --solver {m} runs this one")
        if low.startswith("plan:file:"):  # a missing plan failed every task, after the others had run
            from .solvers import parse_plan_name

            plan = Path(parse_plan_name(m)[0][len("file:"):])
            if not plan.is_file():
                raise ValueError(f"{m!r}: no plan file {plan}")
        if low.startswith("ppo:"):  # an unknown model would fail every task, after the others have run
            from .rl.models import resolve_model

            resolve_model(m[4:].split("+", 1)[0].strip())
        if m not in out:
            out.append(m)
    return out


def _time_limit_for(method: str, time_limit: float | None, cpsat_time_limit: float | None) -> float | None:
    """The time limit a task of ``method`` runs with (and is cached under): None for a method without a search,
    the seconds a ``plan:SOLVER:SECONDS`` name gives, the CP-SAT limit for ``cpsat``, else ``time_limit``."""
    from .solvers import takes_time_limit

    if not searches(method) or not takes_time_limit(method):  # (ppo was cached under a limit it ignores)
        return None
    if method.lower().startswith("plan:"):
        from .solvers import parse_plan_name

        seconds = parse_plan_name(method)[1]
        if seconds is not None:
            return _tl(seconds)
    return _tl(cpsat_time_limit if method.lower() == "cpsat" else time_limit)


def bu_tasks(methods: Sequence[str], *, layout: int = 2, sets: Iterable[int] = BU_SETS,
             time_limit: float | None = 10.0, cpsat_time_limit: float | None = 60.0, seed: int = 0,
             cpsat_workers: int | None = None) -> list[Task]:
    """Tasks of the heuristic table: instances ``EX{set}{layout}`` (2 AGVs, no tools) x ``methods``."""
    if layout not in (1, 2, 3, 4):
        raise ValueError(f"layout must be 1, 2, 3 or 4, got {layout}")
    methods = check_methods(methods)
    sets = list(sets)
    for s in sets:
        if s not in BU_SETS:
            raise ValueError(f"BU job sets are 1-10, got {s}")
    return [Task("bu", f"EX{s}{layout}", "agvs", m, _time_limit_for(m, time_limit, cpsat_time_limit), seed,
                 cpsat_workers if m.lower() == "cpsat" else None)
            for s in sets for m in methods]


def sl_tasks(methods: Sequence[str], *, groups: Iterable[int], instances: Iterable[int] = range(SL_PER_GROUP),
             variants: Sequence[str] = VARIANTS, time_limit: float | None = 10.0,
             cpsat_time_limit: float | None = 10.0, seed: int = 0, cpsat_workers: int | None = None) -> list[Task]:
    """Tasks of the large benchmark: ``sl{g}{k}`` for the groups and instance indices, in each variant."""
    methods = check_methods(methods)
    for v in variants:
        if v not in VARIANTS:
            raise ValueError(f"unknown variant {v!r}; choose from {', '.join(VARIANTS)}")
    groups, instances = list(groups), list(instances)
    for g in groups:
        if not 0 <= g < len(SL_GROUPS):
            raise ValueError(f"sl groups are 0-{len(SL_GROUPS) - 1}, got {g}")
    for k in instances:
        if not 0 <= k < SL_PER_GROUP:
            raise ValueError(f"sl instances are 0-{SL_PER_GROUP - 1}, got {k}")
    return [Task("sl", f"sl{g}{k}", v, m, _time_limit_for(m, time_limit, cpsat_time_limit), seed,
                 cpsat_workers if m.lower() == "cpsat" else None)
            for g in groups for k in instances for v in variants for m in methods]


def parse_index_spec(spec: str, lo: int, hi: int, what: str = "index") -> list[int]:
    """``"3"``, ``"0..7"`` / ``"0-7"`` (inclusive) or ``"0,3,5"`` (parts may mix) -> sorted unique ints in
    ``lo..hi``; raises ``ValueError`` with the accepted syntax otherwise."""
    out: set[int] = set()
    syntax = f"use e.g. {lo}, {lo}..{hi} or {lo},{hi}"
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"empty {what} spec; {syntax}")
    for part in spec.split(","):
        part = part.strip()
        a, sep, b = part.partition("..")
        if not sep:
            a, sep, b = part.partition("-")
        try:
            first, last = (int(a), int(b)) if sep else (int(part), int(part))
        except ValueError:
            raise ValueError(f"bad {what} spec {spec!r}; {syntax}") from None
        if first > last:  # it said the sets are 1-10, which they were
            raise ValueError(f"bad {what} spec {spec!r}: the range {part} runs backwards; give {last}..{first}")
        if first < lo or last > hi:
            raise ValueError(f"bad {what} spec {spec!r}: {what}s are {lo}-{hi}; {syntax}")
        out.update(range(first, last + 1))
    return sorted(out)


# ============================================================================================ solving
def load_task_instance(task: Task) -> Instance:
    """The instance a task solves: the built-in, with tools dropped for variant ``agvs``."""
    inst = builtin(task.instance)
    if task.variant == "agvs":
        return inst.without_tools() if inst.has_tools else inst
    if task.variant == "agvs+tools":
        if not inst.has_tools:
            raise ValueError(f"{task.instance} has no tools; variant agvs+tools does not apply")
        return inst
    raise ValueError(f"unknown variant {task.variant!r}; choose from {', '.join(VARIANTS)}")


# ============================================================================================ digests
def instance_digest(inst: Instance) -> str:
    """The SHA-256 of ``inst``'s canonical JSON (:meth:`~fms_sim.instance.Instance.to_dict`, keys sorted, no
    spaces): what a solver reads of the instance (name, jobs, travel matrices, fleet and counts; not ``meta``), the
    same however the data file it came from is formatted."""
    text = json.dumps(inst.to_dict(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


class DigestMemo:
    """The digests of one run, each computed once: per (instance, variant), per model name and per file (a
    benchmark runs many methods on each instance, and each ``ppo`` method on many instances)."""

    def __init__(self) -> None:
        self.instances: dict[tuple[str, str], tuple[Instance | None, str | None]] = {}
        self.weights: dict[str, Path | None] = {}
        self.files: dict[str, str | None] = {}

    def instance(self, task: Task) -> tuple[Instance | None, str | None]:
        """The task's instance and its digest; ``(None, None)`` where it does not load (the task fails then)."""
        key = (task.instance, task.variant)
        if key not in self.instances:
            try:
                inst = load_task_instance(task)
                self.instances[key] = (inst, instance_digest(inst))
            except Exception:  # (the task's run records the error; its row is not reused)
                self.instances[key] = (None, None)
        return self.instances[key]

    def file(self, path: Path) -> str | None:
        """A file's SHA-256; None where it cannot be read."""
        key = str(path)
        if key not in self.files:
            from .rl.actors import file_sha256  # (what the actor exports record of their weights; no torch)

            try:
                self.files[key] = file_sha256(path)
            except OSError:
                self.files[key] = None
        return self.files[key]

    def model_weights(self, spec: str) -> str | None:
        """The SHA-256 of the weights file that model ``spec`` solves with; None where it does not resolve."""
        if spec not in self.weights:
            from .rl.models import resolve_model  # (no torch: the folder, its config and the weights' path)

            try:
                self.weights[spec] = resolve_model(spec).weights
            except Exception:  # (the task's run records the error; its row is not reused)
                self.weights[spec] = None
        path = self.weights[spec]
        return None if path is None else self.file(path)


def task_digests(task: Task, memo: DigestMemo | None = None) -> dict[str, Any]:
    """What a task's row records of its inputs, and what a cached row must equal to be reused: ``format``
    (:data:`CACHE_FORMAT`), ``instance`` (:func:`instance_digest` of the instance it solves), for a ``ppo`` method
    ``weights`` (the SHA-256 of its model's solving weights; the default ``ppo`` takes the model
    :func:`~fms_dispatch.rl.models.default_model_name` gives for the instance) and for ``plan:file:PATH`` ``plan``
    (the file's SHA-256). A digest that cannot be computed (an instance or a model that does not load) is None: the
    task then fails, and a failed row is solved again anyway."""
    memo = memo or DigestMemo()
    inst, inst_digest = memo.instance(task)
    out: dict[str, Any] = {"format": CACHE_FORMAT, "instance": inst_digest}
    low = task.method.strip().lower()
    if low == "ppo" or low.startswith(("ppo:", "ppo+")):
        base = task.method.strip().partition("+")[0].strip()
        spec: str | None = base[4:].strip() if base.lower().startswith("ppo:") else None
        if spec is None and inst is not None:
            from .rl.models import default_model_name

            spec = default_model_name(inst)
        out["weights"] = None if spec is None else memo.model_weights(spec)
    elif low.startswith("plan:file:"):
        from .solvers import parse_plan_name

        try:
            path = Path(parse_plan_name(task.method)[0][len("file:"):])
        except ValueError:
            out["plan"] = None
        else:
            out["plan"] = memo.file(path)
    return out


#: the names of a row's digests in the message on the rows solved again
_DIGEST_NAMES = {"format": "cache format", "instance": "instance data", "weights": "model weights",
                 "plan": "plan file"}


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _pool_worker() -> None:
    """A pool worker's start: the other workers keep the machine's other cores busy, so a guided model's plan
    search runs before its run here, not beside it (:func:`fms_dispatch.rl.beside.in_pool_worker`)."""
    from .rl.beside import in_pool_worker

    in_pool_worker()


def _blank_row(task: Task, error: str | None = None) -> dict[str, Any]:
    return {**asdict(task), "time_limit": _tl(task.time_limit), "makespan": None, "wall_time": None,
            "valid": False, "error": error, "lower_bound": None, "status": None, "optimum": None, "n_jobs": None,
            "n_machines": None}


def run_task(task: Task) -> dict[str, Any]:
    """Solve and validate one task; never raises for solver failures (they become an error row)."""
    from fms_sim.validate import validate

    from .solvers import solve

    row = _blank_row(task)
    t0 = time.perf_counter()
    try:
        inst = load_task_instance(task)
        row.update(optimum=inst.meta.get("optimal_makespan"), n_jobs=inst.n_jobs, n_machines=inst.n_machines)
        opts: dict[str, Any] = {"seed": task.seed}
        if task.time_limit is not None:
            opts["time_limit"] = task.time_limit
        if task.workers is not None and task.method.lower() == "cpsat":
            opts["workers"] = task.workers
        sched = solve(inst, task.method, **opts)
        row["wall_time"] = round(float(sched.meta.get("wall_time", time.perf_counter() - t0)), 4)
        row["makespan"] = int(sched.makespan)
        row["lower_bound"] = sched.meta.get("lower_bound")
        row["status"] = sched.meta.get("status")
        problems = validate(inst, sched)
        if problems:
            row["error"] = f"invalid schedule ({len(problems)} violation(s)): {problems[0]}"
        else:
            row["valid"] = True
    except Exception as exc:  # a solver bug or missing solver: record it, never lose the rest of the run
        row["error"] = _first_line(exc)
        if row["wall_time"] is None:
            row["wall_time"] = round(time.perf_counter() - t0, 4)
    return row


def read_cache(path: Path) -> dict[tuple[Any, ...], dict[str, Any]]:
    """The latest cached row per key; unreadable lines (a run killed mid-write) are skipped."""
    rows: dict[tuple[Any, ...], dict[str, Any]] = {}
    if not path.exists():
        return rows
    with path.open(encoding="utf-8", errors="replace") as fh:
        for line in fh:
            try:
                row = json.loads(line)
                if _row_ok(row):
                    rows[_row_key(row)] = row
            except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                continue
    return rows


def _row_ok(row: Any) -> bool:
    """Whether a cache line is a whole row: a valid one has an integer makespan and a number of seconds (a line
    that is JSON but not a row crashed the tables with a KeyError after the CSV had been replaced)."""
    if not isinstance(row, dict) or not isinstance(row.get("valid"), bool):
        return False
    if not row["valid"]:
        return True
    number = (int, float)
    return (isinstance(row.get("makespan"), int) and not isinstance(row["makespan"], bool)
            and isinstance(row.get("wall_time"), number) and not isinstance(row["wall_time"], bool))


def _end_line(path: Path) -> None:
    """End the cache's last line if a run killed mid-write left it cut (the next row was glued onto it and lost)."""
    try:
        with path.open("rb+") as fh:
            if fh.seek(0, os.SEEK_END) == 0:
                return
            fh.seek(-1, os.SEEK_END)
            if fh.read(1) != b"\n":
                fh.write(b"\n")
    except FileNotFoundError:
        pass


def _append(path: Path, row: dict[str, Any]) -> None:
    with path.open("a", encoding="utf-8") as fh:
        fh.write(json.dumps(row) + "\n")
        fh.flush()


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def default_jobs() -> int:
    """Default ``--jobs``: 2, or 1 on a single-core machine."""
    return max(1, min(2, _cpus()))


def cpsat_threads(parallel: int) -> int:
    """CP-SAT threads per task when ``parallel`` tasks run at once: at most 2 (the solver's default), and no
    more than the CPUs shared among the tasks."""
    return max(1, min(2, _cpus() // max(1, parallel)))


def run_bench(tasks: Sequence[Task], *, jobs: int = 1, force: bool = False, results_dir: str | Path = "results",
              progress: bool = False) -> list[dict[str, Any]]:
    """Run the tasks not yet cached (all with ``force``) and return one row per task, in task order.

    A cached valid row is reused where its ``digests`` equal the task's (:func:`task_digests`) or where it has
    none (a row cached before digests were recorded; the run says how many on stderr); a row whose digests differ
    is solved again (said on stderr, with what changed). Every finished task is appended to
    ``<results_dir>/bench_cache.jsonl`` immediately, with the digests its inputs had when the run started.
    ``jobs > 1`` runs tasks in a process pool (spawned workers: CP-SAT threads and fork do not mix); ``jobs == 1``
    runs them in this process.
    """
    if jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {jobs}")
    if not str(results_dir).strip():  # Path("") is the current folder: the tables and cache went there
        raise ValueError("--results-dir names no folder (an empty name); give one, e.g. --results-dir .")
    out_dir = Path(results_dir)
    from fms_sim.files import file_above, folder_problem

    blocker = out_dir if out_dir.exists() and not out_dir.is_dir() else file_above(out_dir)
    if blocker is not None:  # "File exists: afile" said nothing of the option
        raise ValueError(f"--results-dir {results_dir}: {blocker} is a file; name a folder")
    problem = folder_problem(out_dir)  # (a folder that cannot be made or written: "No such file or directory: /proc/x",
    if problem is not None:  # naming neither the option nor the cause, as fms experiment does)
        raise ValueError(f"--results-dir {results_dir}: {problem}")
    out_dir.mkdir(parents=True, exist_ok=True)
    cache_path = out_dir / CACHE_NAME
    _end_line(cache_path)
    cache = read_cache(cache_path)
    todo: list[Task] = []
    seen: set[tuple[Any, ...]] = set()
    memo = DigestMemo()
    digests: dict[tuple[Any, ...], dict[str, Any]] = {}
    changed: dict[str, int] = defaultdict(int)  # rows solved again, per input that changed
    n_changed = n_undigested = 0
    for t in tasks:
        if t.key in seen:
            continue
        seen.add(t.key)
        digests[t.key] = task_digests(t, memo)
        hit = cache.get(t.key)
        other_threads = t.workers is not None and hit is not None and hit.get("workers") != t.workers
        if force or hit is None or not hit.get("valid") or other_threads:
            todo.append(t)
            continue
        have = hit.get("digests")
        if have is None:  # cached before digests were recorded: reused (said below)
            n_undigested += 1
        elif have != digests[t.key]:
            todo.append(t)
            n_changed += 1
            have = have if isinstance(have, dict) else {}
            for name in _DIGEST_NAMES:
                if have.get(name) != digests[t.key].get(name):
                    changed[name] += 1
    if n_changed:
        what = ", ".join(f"{_DIGEST_NAMES[k]}: {n}" for k, n in changed.items())
        print(f"bench: {n_changed} cached row(s) solved again: their inputs changed since they were cached ({what})",
              file=sys.stderr)
    if n_undigested:
        print(f"bench: reused {n_undigested} cached row(s) that carry no digest of their instance data, model weights "
              "or plan file (cached before digests were recorded), so a change of those since goes unseen; --force "
              "solves them again and records their digests", file=sys.stderr)
    parallel = min(jobs, len(todo))  # tasks that really run at the same time
    todo = [Task(t.benchmark, t.instance, t.variant, t.method, t.time_limit, t.seed, cpsat_threads(parallel))
            if t.method.lower() == "cpsat" and t.workers is None else t for t in todo]

    done = 0
    try:
        for row in _execute(todo, jobs, progress):
            row["digests"] = digests[_row_key(row)]  # (of the inputs at the start: those the task was run from)
            _append(cache_path, row)
            cache[_row_key(row)] = row
            done += 1
    except KeyboardInterrupt:  # (only "fms: interrupted" was said: what was kept, and how to go on, was not)
        print(f"bench: interrupted after {done} of {len(todo)} task(s) to run; the finished ones are cached in "
              f"{cache_path} and the tables were not written: run the same command again to continue",
              file=sys.stderr)
        raise
    return [cache[k] for k in _ordered_keys(tasks)]


def _ordered_keys(tasks: Sequence[Task]) -> list[tuple[Any, ...]]:
    keys, seen = [], set()
    for t in tasks:
        if t.key not in seen:
            seen.add(t.key)
            keys.append(t.key)
    return keys


def _execute(todo: list[Task], jobs: int, progress: bool) -> Iterator[dict[str, Any]]:
    if not todo:
        return
    bar = _progress_bar(len(todo), progress)
    try:
        if jobs == 1 or len(todo) == 1:
            for t in todo:
                bar.set_postfix_str(f"{t.instance} {t.method}", refresh=False)
                row = run_task(t)
                bar.update(1)
                yield row
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(jobs, len(todo)), mp_context=ctx, initializer=_pool_worker) as pool:
            futures = {pool.submit(run_task, t): t for t in todo}
            try:
                for fut in as_completed(futures):
                    try:
                        row = fut.result()
                    except Exception as exc:  # the worker process died (crash, out of memory): an error row
                        row = _blank_row(futures[fut], f"worker failed: {_first_line(exc)}")
                    bar.set_postfix_str(f"{row['instance']} {row['method']}", refresh=False)
                    bar.update(1)
                    yield row
            except BaseException:  # interrupted: drop the queued tasks, finished ones are cached already
                # stop the running ones too: leaving the pool waited for them (a CP-SAT task's whole time limit), and
                # a SIGTERM left them running on without their parent (the executor's own list: it has no terminate;
                # read before the shutdown, which drops it)
                running = list((getattr(pool, "_processes", None) or {}).values())
                pool.shutdown(wait=False, cancel_futures=True)
                for proc in running:
                    proc.terminate()
                raise
    finally:
        bar.close()


class _NoBar:
    def update(self, n: int = 1) -> None: ...
    def set_postfix_str(self, s: str, refresh: bool = True) -> None: ...
    def close(self) -> None: ...


def _progress_bar(total: int, enabled: bool) -> Any:
    if not enabled:
        return _NoBar()
    try:
        from tqdm import tqdm
    except ImportError:  # tqdm is an optional extra ("rl"); benchmarks run without it
        return _NoBar()
    return tqdm(total=total, file=sys.stderr, unit="task", desc="bench", dynamic_ncols=True)


# ============================================================================================ tables
def _methods_of(rows: Sequence[dict[str, Any]]) -> list[str]:
    out: list[str] = []
    for r in rows:
        if r["method"] not in out:
            out.append(r["method"])
    return out


def _instances_of(rows: Sequence[dict[str, Any]]) -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    for r in rows:
        key = (r["instance"], r["variant"])
        if key not in out:
            out.append(key)
    return out


def gap_pct(makespan: float, ref: float) -> float:
    """Relative gap ``100 * (makespan - ref) / ref`` in percent."""
    return 100.0 * (makespan - ref) / ref


def _reference(rows: Sequence[dict[str, Any]]) -> int | None:
    """The known optimum of an instance's rows, else the best reported lower bound, else ``None``."""
    opt = next((r["optimum"] for r in rows if r.get("optimum") is not None), None)
    if opt is not None:
        return int(opt)
    bounds = [int(r["lower_bound"]) for r in rows if r.get("valid") and r.get("lower_bound") is not None]
    return max(bounds) if bounds else None


def best_rule_of(rows: Sequence[dict[str, Any]]) -> tuple[list[str], int] | None:
    """The rule pairs with the least makespan among one instance's valid rows, and that makespan."""
    ok = [r for r in rows if _is_rule(r["method"]) and r.get("valid")]
    if not ok:
        return None
    best = min(r["makespan"] for r in ok)
    return [r["method"] for r in ok if r["makespan"] == best], best


def _best_rule(rows: Sequence[dict[str, Any]]) -> str:
    found = best_rule_of(rows)
    if found is None:
        return "-"
    winners, best = found
    tie = f", {len(winners)} tied" if len(winners) > 1 else ""
    return f"{_label(winners[0])} ({best}{tie})"


def _cell(row: dict[str, Any] | None) -> str:
    if row is None:
        return "-"
    if not row.get("valid"):
        return "INVALID" if str(row.get("error", "")).startswith("invalid schedule") else "ERROR"
    return str(row["makespan"])


def _md(headers: Sequence[str], body: Sequence[Sequence[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in body)) if body else len(h) for i, h in enumerate(headers)]
    def line(cells: Sequence[str]) -> str:
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(headers), sep, *(line(r) for r in body)])


def _fmt(x: float | None, digits: int) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def summary(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per method: instances run, failures, mean makespan, mean gap % to the reference (optimum or best lower
    bound, over instances that have one), optimum/bound hits, mean and max wall time."""
    by_inst: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_inst[(r["instance"], r["variant"])].append(r)
    refs = {k: _reference(v) for k, v in by_inst.items()}
    out: dict[str, dict[str, Any]] = {}
    for m in _methods_of(rows):
        mine = [r for r in rows if r["method"] == m]
        ok = [r for r in mine if r.get("valid")]
        gaps = [gap_pct(r["makespan"], refs[(r["instance"], r["variant"])]) for r in ok
                if refs[(r["instance"], r["variant"])]]
        hits = [r for r in ok if refs[(r["instance"], r["variant"])] is not None
                and r["makespan"] <= refs[(r["instance"], r["variant"])]]
        times = [r["wall_time"] for r in mine if r.get("wall_time") is not None]
        out[m] = {
            "n": len(mine), "n_failed": len(mine) - len(ok),
            "mean_makespan": round(sum(r["makespan"] for r in ok) / len(ok), 3) if ok else None,
            "mean_gap_pct": round(sum(gaps) / len(gaps), 3) if gaps else None,
            "n_with_reference": len(gaps), "n_at_reference": len(hits),
            "mean_time": round(sum(times) / len(times), 4) if times else None,
            "max_time": round(max(times), 4) if times else None,
        }
    return out


def _makespan_table(rows: Sequence[dict[str, Any]], ref_label: str, show_variant: bool,
                    unproven: frozenset[str] = frozenset()) -> str:
    methods = _methods_of(rows)
    insts = _instances_of(rows)
    cell: dict[tuple[str, str, str], dict[str, Any]] = {(r["instance"], r["variant"], r["method"]): r for r in rows}
    has_rules = any(_is_rule(m) for m in methods)
    headers = ["instance"] + (["variant"] if show_variant else []) + [ref_label] + [_label(m) for m in methods]
    headers += ["best rule"] if has_rules else []
    body: list[list[str]] = []
    refs: list[int | None] = []
    for inst, var in insts:
        mine = [cell[(inst, var, m)] for m in methods if (inst, var, m) in cell]
        ref = _reference(mine)
        refs.append(ref)
        line = [inst] + ([var] if show_variant else []) + ["-" if ref is None else
                                                           str(ref) + ("†" if inst in unproven else "")]
        line += [_cell(cell.get((inst, var, m))) for m in methods]
        line += [_best_rule(mine)] if has_rules else []
        body.append(line)
    stats = summary(rows)
    n = len(insts)
    known = [r for r in refs if r is not None]
    pad = [""] if show_variant else []
    tail = [""] if has_rules else []

    def mean_cell(m: str) -> str:
        s = stats[m]
        if s["mean_makespan"] is None:
            return "-"
        return f"{s['mean_makespan']:.1f}" + ("*" if s["n"] - s["n_failed"] < n else "")

    body.append(["average"] + pad + [_fmt(sum(known) / len(known), 1) if known else "-"]
                + [mean_cell(m) for m in methods] + tail)
    body.append(["gap %"] + pad + ["0.00" if known else "-"]
                + [_fmt(stats[m]["mean_gap_pct"], 2) for m in methods] + tail)
    body.append([f"at {ref_label}"] + pad + [f"{len(known)}/{n}"]
                + [f"{stats[m]['n_at_reference']}/{stats[m]['n_with_reference']}" for m in methods] + tail)
    text = _md(headers, body)
    if any(inst in unproven for inst, _ in insts):
        text += f"\n\n† the literature's {ref_label}, not proven by this project's CP-SAT runs."
    if any(s["n_failed"] for s in stats.values()):
        text += "\n\n\\* mean over the instances without errors; ERROR/INVALID cells are listed below the table."
    return text


def bu_table(rows: Sequence[dict[str, Any]]) -> str:
    """The heuristic table (Markdown): one row per instance with the known optimum, each method's makespan
    and the best rule pair, then the average makespan, the average gap % to the optimum and the number of
    instances solved to the optimum. Wall times are in :func:`time_table` (so that tables of repeated runs
    compare equal)."""
    from fms_sim.benchmarks import BU_LITERATURE_OPTIMA

    return _makespan_table(rows, "opt", show_variant=False, unproven=BU_LITERATURE_OPTIMA)


def sl_table(rows: Sequence[dict[str, Any]]) -> str:
    """The large-benchmark table (Markdown), one section per variant: makespans per instance and method, the
    best lower bound (``LB``) reported by any method, the best rule pair, the means and gaps to ``LB``."""
    parts = []
    for var in VARIANTS:
        mine = [r for r in rows if r["variant"] == var]
        if mine:
            title = "AGVs only" if var == "agvs" else "AGVs + tools"
            parts.append(f"### {title} ({var})\n\n" + _makespan_table(mine, "LB", show_variant=False))
    return "\n\n".join(parts)


def time_table(rows: Sequence[dict[str, Any]]) -> str:
    """Mean and max wall time (seconds) per method and variant (Markdown)."""
    body = []
    for var in [v for v in VARIANTS if any(r["variant"] == v for r in rows)]:
        for m, s in summary([r for r in rows if r["variant"] == var]).items():
            body.append([m, var, str(s["n"]), _fmt(s["mean_time"], 3), _fmt(s["max_time"], 3)])
    return _md(["method", "variant", "runs", "mean s", "max s"], body)


def failures(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The error rows (solver failures and invalid schedules)."""
    return [r for r in rows if not r.get("valid")]


# ============================================================================================ outputs
CSV_FIELDS = ("benchmark", "instance", "variant", "method", "time_limit", "makespan", "optimum", "lower_bound",
              "reference", "gap_pct", "status", "wall_time", "valid", "error", "seed", "workers", "n_jobs",
              "n_machines")


def _with_gaps(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    by_inst: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_inst[(r["instance"], r["variant"])].append(r)
    out = []
    for r in rows:
        ref = _reference(by_inst[(r["instance"], r["variant"])])
        gap = round(gap_pct(r["makespan"], ref), 3) if ref and r.get("valid") else None
        out.append({**r, "reference": ref, "gap_pct": gap})
    return out


def write_outputs(rows: Sequence[dict[str, Any]], results_dir: str | Path, stem: str, *, title: str,
                  meta: dict[str, Any] | None = None) -> dict[str, Path]:
    """Write ``<stem>.csv`` (one line per task), ``<stem>.json`` (rows + per-method summary), ``<stem>.md``
    (the tables) and ``<stem>.png`` (the plot) under ``results_dir``; returns the paths by kind."""
    out = Path(results_dir)
    out.mkdir(parents=True, exist_ok=True)
    full = _with_gaps(rows)
    paths = {k: out / f"{stem}.{k}" for k in ("csv", "json", "md", "png")}
    # each file replaced only by a complete one (an interrupt while writing left half a chart over the last run's)
    with replacing(paths["csv"]) as tmp, tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in full:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in CSV_FIELDS})
    doc = {"title": title, **(meta or {}), "methods": _methods_of(rows), "summary": summary(rows),
           "best_rule": {f"{i}/{v}": _best_rule_json([r for r in rows if (r["instance"], r["variant"]) == (i, v)])
                         for i, v in _instances_of(rows)},
           "rows": full}
    write_atomically(paths["json"], json.dumps(doc, indent=1) + "\n")
    write_atomically(paths["md"], render_markdown(rows, title) + "\n")
    plot_bench(rows, paths["png"], title=title)
    return paths


def _best_rule_json(rows: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    found = best_rule_of(rows)
    return None if found is None else {"methods": found[0], "makespan": found[1]}


def render_markdown(rows: Sequence[dict[str, Any]], title: str) -> str:
    """Title, makespan table(s), time table and the list of failures, as printed by ``fms bench``."""
    bench = rows[0]["benchmark"] if rows else "bu"
    table = bu_table(rows) if bench == "bu" else sl_table(rows)
    note = "\n\nRule pairs are shown as JOB+vehicle (solver `rule:JOB+vehicle`)." if any(
        _is_rule(r["method"]) for r in rows) else ""
    settings = _settings(rows)
    text = (f"## {title}\n\n" + (f"{settings}\n\n" if settings else "") + f"{table}{note}\n\n"
            f"### Computation time (s)\n\n{time_table(rows)}")
    bad = failures(rows)
    if bad:
        text += "\n\n### Failures\n\n" + "\n".join(
            f"- {r['instance']} ({r['variant']}) {r['method']}: {r['error']}" for r in bad)
    return text


def _settings(rows: Sequence[dict[str, Any]]) -> str:
    """What the rows were run with, in one line: each searching method's time limit, CP-SAT's threads and the seed
    (the tables named the methods only; the limits were in the JSON)."""
    limits: dict[str, set[float]] = defaultdict(set)
    threads: set[int] = set()
    seeds = {int(r.get("seed") or 0) for r in rows}
    for r in rows:
        if r.get("time_limit") is not None:
            limits[r["method"]].add(float(r["time_limit"]))
        if r["method"].lower() == "cpsat" and r.get("workers"):
            threads.add(int(r["workers"]))
    parts = [f"{_label(m)} {', '.join(f'{x:g}' for x in sorted(v))} s" for m, v in limits.items()]
    out = ("Time limits: " + "; ".join(parts) + ". ") if parts else ""
    if threads:
        out += f"CP-SAT threads: {', '.join(map(str, sorted(threads)))}. "
    if seeds != {0}:
        out += f"Seed: {', '.join(map(str, sorted(seeds)))}."
    return out.strip()


_STRONG = ("#d62728", "#1f3fbf", "#2ca02c", "#8c2d9c", "#ff7f0e", "#17becf")


def _is_rule(method: str) -> bool:
    return method.lower().startswith("rule:")


def _label(method: str) -> str:
    """Display name: rule pairs without the ``rule:`` prefix (tables and legends get narrow enough)."""
    return method[5:] if _is_rule(method) else method


def plot_bench(rows: Sequence[dict[str, Any]], path: str | Path, *, title: str = "") -> Path:
    """Two panels like the paper's figures: makespan per instance per method (lines with markers, the
    reference as a dashed black line) and computation time on a log axis. Headless (Agg canvas)."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    methods = _methods_of(rows)
    # x positions: instances grouped by variant, one empty slot between variant blocks (lines break there)
    found = _instances_of(rows)
    variants = [v for v in VARIANTS if any(b == v for _, b in found)] + \
        sorted({b for _, b in found} - set(VARIANTS))
    slots: list[tuple[str, str] | None] = []
    for v in variants:
        if slots:
            slots.append(None)
        slots.extend(k for k in found if k[1] == v)
    multi_variant = len(variants) > 1
    x = list(range(len(slots)))
    labels = ["" if k is None else k[0] for k in slots]
    cell = {(r["instance"], r["variant"], r["method"]): r for r in rows}
    ncol = 1 if len(methods) <= 16 else 2
    left_in, plot_in, legend_in = 0.9, max(5.0, 0.45 * len(slots)), 0.3 + 1.9 * ncol
    fig_w = left_in + plot_in + legend_in
    fig = Figure(figsize=(fig_w, 7.5), dpi=100)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    cmap = colormaps["tab20"]
    markers = "os^vD<>phX*P"
    n_rule = n_other = 0
    for m in methods:
        if _is_rule(m):  # many thin, light lines; the searching methods stand out in strong colours
            style = {"color": cmap(n_rule % 20), "marker": markers[n_rule % len(markers)], "markersize": 3,
                     "linewidth": 0.8, "alpha": 0.75}
            n_rule += 1
        else:
            style = {"color": _STRONG[n_other % len(_STRONG)], "marker": "os^D"[n_other % 4], "markersize": 6,
                     "linewidth": 2.2, "zorder": 3}
            n_other += 1
        got = [None if k is None else cell.get((k[0], k[1], m)) for k in slots]
        ms = [r["makespan"] if r and r.get("valid") else math.nan for r in got]
        ts = [max(1e-4, r["wall_time"]) if r and r.get("wall_time") is not None else math.nan for r in got]
        ax1.plot(x, ms, label=_label(m), **style)
        ax2.plot(x, ts, label=_label(m), **style)
    refs = [None if k is None else _reference([cell[(k[0], k[1], m)] for m in methods if (k[0], k[1], m) in cell])
            for k in slots]
    if any(r is not None for r in refs):
        bench = rows[0]["benchmark"] if rows else ""
        ax1.plot(x, [math.nan if r is None else r for r in refs], "k--", linewidth=1.5, zorder=1.5,
                 label="optimum" if bench == "bu" else "lower bound")
    ax1.set_ylabel("makespan")
    ax1.set_title(title)
    ax1.grid(True, alpha=0.3)
    ax2.set_yscale("log")
    ax2.set_ylabel("computation time (s)")
    ax2.grid(True, which="both", alpha=0.3)
    ax2.set_xticks(x)
    ax2.set_xticklabels(labels, rotation=90 if len(slots) > 12 else 0, fontsize=8)
    if multi_variant:  # name each block under the axis, separate blocks by a vertical line
        start = 0
        for v in variants:
            n = sum(1 for k in slots if k is not None and k[1] == v)
            mid = start + (n - 1) / 2
            ax2.annotate(v, xy=(mid, 0), xycoords=("data", "axes fraction"), xytext=(0, -34 if len(slots) <= 12
                         else -48), textcoords="offset points", ha="center", va="top", fontsize=9)
            if start:
                for ax in (ax1, ax2):
                    ax.axvline(start - 1, color="grey", linewidth=0.8)
            start += n + 1
    ax1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, ncol=ncol, frameon=False)
    bottom = 0.9 if len(slots) > 12 else 0.5
    fig.subplots_adjust(left=left_in / fig_w, right=(left_in + plot_in) / fig_w, top=0.94,
                        bottom=(bottom + (0.3 if multi_variant else 0.0)) / 7.5, hspace=0.08)
    path = Path(path)
    with replacing(path, suffix=".tmp" + path.suffix) as tmp:  # (a temporary matplotlib reads the format from)
        fig.savefig(tmp)
    return path


# ============================================================================================ CLI
def _split_methods(values: Sequence[str] | None, default: Sequence[str], nearest: bool) -> list[str]:
    from .rules import all_rule_pairs

    if not values:
        return list(default)
    out: list[str] = []
    for v in values:
        for name in (p.strip() for p in v.split(",")):
            if not name:
                continue
            out.extend(all_rule_pairs(include_nearest=nearest) if name.lower() == "rules" else [name])
    return out


def _positive(name: str, x: float | None) -> None:
    if x is not None and not (0 < x < float("inf")):  # NaN and inf too: they would reach the caches as non-JSON
        raise ValueError(f"{name} must be a positive number, got {x:g}")


def _finish(rows: list[dict[str, Any]], results_dir: str, stem: str, title: str, meta: dict[str, Any]) -> int:
    paths = write_outputs(rows, results_dir, stem, title=title, meta=meta)
    print(render_markdown(rows, title))
    print("\n" + "\n".join(f"{k}: {p}" for k, p in paths.items()), file=sys.stderr)
    bad = failures(rows)
    if bad:
        print(f"fms: {len(bad)} task(s) failed or gave an invalid schedule (see Failures)", file=sys.stderr)
        return EXIT_FAILED
    return 0


def _check_numbers(a: argparse.Namespace) -> None:
    _positive("--time-limit", a.time_limit)
    _positive("--cpsat-time-limit", a.cpsat_time_limit)
    _positive("--cpsat-workers", a.cpsat_workers)
    _positive("--jobs", a.jobs)
    if a.seed < 0:  # the searches took its absolute value (sos, tabu) and cached the rows under the negative seed
        raise ValueError(f"--seed must be an integer >= 0, got {a.seed}")


def cmd_bench_bu(a: argparse.Namespace) -> int:
    from .rules import all_rule_pairs

    _check_numbers(a)
    default = all_rule_pairs(include_nearest=a.nearest) + ["sos", "cpsat"]
    methods = check_methods(_split_methods(a.methods, default, a.nearest))
    sets = parse_index_spec(a.instances, 1, 10, "BU job set")
    tasks = bu_tasks(methods, layout=a.layout, sets=sets, time_limit=a.time_limit,
                     cpsat_time_limit=a.cpsat_time_limit, seed=a.seed, cpsat_workers=a.cpsat_workers)
    rows = run_bench(tasks, jobs=a.jobs, force=a.force, results_dir=a.results_dir, progress=not a.quiet)
    title = f"Bilge-Ulusoy layout {a.layout}, 2 AGVs: makespan per method"
    return _finish(rows, a.results_dir, f"bench_bu_L{a.layout}", title,
                   {"benchmark": "bu", "layout": a.layout, "time_limit": a.time_limit,
                    "cpsat_time_limit": a.cpsat_time_limit})


def cmd_bench_sl(a: argparse.Namespace) -> int:
    from .rules import all_rule_pairs

    _check_numbers(a)
    default = all_rule_pairs(include_nearest=True) + ["cpsat"]
    methods = check_methods(_split_methods(a.methods, default, True))
    groups = parse_index_spec(a.group, 0, len(SL_GROUPS) - 1, "sl group")
    insts = parse_index_spec(a.instances, 0, SL_PER_GROUP - 1, "sl instance")
    variants = {"both": VARIANTS, "no": ("agvs",), "yes": ("agvs+tools",)}[a.tool_variants]
    tasks = sl_tasks(methods, groups=groups, instances=insts, variants=variants, time_limit=a.time_limit,
                     cpsat_time_limit=a.cpsat_time_limit, seed=a.seed, cpsat_workers=a.cpsat_workers)
    rows = run_bench(tasks, jobs=a.jobs, force=a.force, results_dir=a.results_dir, progress=not a.quiet)
    title = "Large benchmark (10 AGVs, 5 tool transporters): makespan per method"
    return _finish(rows, a.results_dir, "bench_sl", title,
                   {"benchmark": "sl", "groups": groups, "instances": insts, "time_limit": a.time_limit,
                    "cpsat_time_limit": a.cpsat_time_limit})


def _common(p: argparse.ArgumentParser, cpsat_default: float) -> None:
    p.add_argument("--methods", nargs="+", metavar="NAME",
                   help="solver names (space- or comma-separated; 'rules' = every rule pair), e.g. "
                        "rule:MTWR+first sos cpsat; first, random and rule: run through the paper's net (fms "
                        "solve's default is the full net), rules:full and list through the full net")
    p.add_argument("--time-limit", type=float, default=10.0, metavar="S",
                   help="time limit of searching methods other than cpsat, e.g. sos (default 10)")
    p.add_argument("--cpsat-time-limit", type=float, default=cpsat_default, metavar="S",
                   help=f"time limit of cpsat (default {cpsat_default:g})")
    p.add_argument("--cpsat-workers", type=int, metavar="N",
                   help="CP-SAT threads per task (default: min(2, cpus // tasks running at once), the tasks at "
                        "once being min(--jobs, tasks to run)); given, a cached cpsat row of other threads is "
                        "solved again (by default any cached row serves)")
    p.add_argument("--seed", type=int, default=0, help="seed (>= 0) of the methods that search or draw at random (default 0)")
    p.add_argument("--jobs", type=int, default=default_jobs(), metavar="N",
                   help=f"parallel tasks (process pool; default {default_jobs()})")
    p.add_argument("--force", action="store_true",
                   help="re-solve tasks that are already in the cache (without it, a cached row is solved again "
                        "only where it failed, ran other --cpsat-workers than given, or where its instance data, ppo "
                        "model weights or plan:file file changed since; rows cached before those digests were "
                        "recorded are reused)")
    p.add_argument("--results-dir", default="results", help="where the cache, CSV, JSON, Markdown and PNG go")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def add_bench_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``fms bench bu|sl`` to the CLI's subparsers; each sets ``fn`` to a command returning an exit code."""
    p = subparsers.add_parser("bench", help="baseline tables and plots (bu: Bilge-Ulusoy, sl: large benchmark)",
                              description="Run methods on a benchmark; resumable (results/bench_cache.jsonl: a "
                                          "cached row is reused while its instance data, ppo model weights and "
                                          "plan:file file are unchanged, as their SHA-256 digests say).")
    sub = p.add_subparsers(dest="bench_cmd", required=True)
    s = sub.add_parser("bu", help="the heuristic table on EX1L..EX10L (2 AGVs, no tools) with gaps to the optimum")
    s.add_argument("--layout", type=int, default=2, choices=(1, 2, 3, 4), help="BU layout (default 2)")
    s.add_argument("--instances", default="1..10", metavar="SETS", help="job sets, e.g. 1..10, 1,2 (default all)")
    s.add_argument("--nearest", action="store_true", help="also the rule pairs with the nearest-vehicle rule")
    _common(s, 60.0)
    s.set_defaults(fn=cmd_bench_bu)
    s = sub.add_parser("sl", help="makespan and time on the large benchmark sl{g}{k}, AGVs only and with tools")
    s.add_argument("--group", default="0", metavar="G", help="groups 0-7: 0, 0..7 or 0,3 (default 0)")
    s.add_argument("--instances", default="0..9", metavar="K", help="instances 0-9 per group: 0..9, 0-4, 0,3")
    s.add_argument("--tools", dest="tool_variants", choices=("both", "yes", "no"), default="both",
                   help="with tools (yes), AGVs only (no) or both (default)")
    _common(s, 10.0)
    s.set_defaults(fn=cmd_bench_sl)
    return p
