"""``fms up INSTANCE``: run the shop, the agent and the recorder as ROS 2 node processes, end to end.

The launcher checks the instance and the solver first (bad input: one line, exit code 2), starts the three
nodes (``python -m fms_sim.recorder_node``, ``fms_sim.shop_node``, ``fms_dispatch.agent_node``) in their own
process groups, waits until the shop has written the final schedule and the recorder has stored the run and
rendered its Gantt chart, validates the schedule against the final instance (including accepted orders),
writes it to ``--out``, and stops the nodes with SIGINT (SIGKILL after :data:`STOP_GRACE_S`). A node that
fails to stop cleanly after the run was delivered and validated is reported as a warning (its log is kept),
not as a failed run: nothing is lost by then. It imports no rclpy itself: the nodes do.

``--solver best`` simulates every rule pair, the list schedule and the shipped PPO model (with and without
lookahead) on the instance in-process first and runs the winner over the topics: PPO if its makespan is strictly
smaller than the best rule pair's and the list schedule's, else the better of those (:func:`best_solver`; it says
which; in a disrupted run ``plan:rules`` takes their place). A ``ppo`` solver makes the launcher
start the shop with ``history:=true`` and ``history_delta:=true`` (each state carries what was applied since the
one before; and ``features:=false``) and give the agent the instance file, so that the agent can replay the run
into its twin of the shop; a lookahead solver also sets ``idle_stops:=true``, and
a plan solver (``plan:cpsat:10``: the agent plans at the first state, then executes the plan) runs the shop on
the full-decision net (``decisions:=full``) with history and idle stops. ROS settings: ``ROS_DOMAIN_ID`` is taken from the
environment or ``--domain-id``, else a random one in 1..101 (so two ``fms up`` runs never talk to each
other); ``ROS_AUTOMATIC_DISCOVERY_RANGE`` defaults to ``LOCALHOST``. The node logs go to ``--log-dir`` (by
default a temporary folder, kept and printed only when something fails). While the run goes on, a line every
:data:`PROGRESS_S` seconds says how far it is (operations ended and the shop's clock, from the recorder's database);
a run that makes no progress (no operation ended, the shop's clock still) for ``--timeout`` seconds fails with that
progress named; a long run that keeps moving does not time out. A simulated shop without a clock
(``--time-scale 0``, the default) waits for each re-plan of a ``plan:`` solver or a guided model
(``replan_wait:=true``; ``--no-replan-wait`` lets it run on meanwhile), so that its run is the offline one and does
not depend on how fast this machine searches; a shop kept to a clock runs on, as a real shop would.

Exit codes: 0 done and valid; 1 the run failed (a node died before the run was delivered, timeout, invalid
schedule); 2 bad input.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Callable, Sequence

from fms_sim.files import drop_instance_beside, instance_beside
from fms_sim.instance import Instance, InstanceError
from fms_sim.recorder_store import DEFAULT_DB, MAX_RUN_NAME, gantt_path, safe_run_name
from fms_sim.schedule import Schedule, ScheduleError
from fms_sim.shop_service import new_run_id

from .agent_logic import UnavailableSolver, make_decider, needs_full_net, needs_idle_stops, needs_twin

__all__ = ["add_up_parser", "cmd_up", "main", "UpError", "best_rule", "best_solver", "NodeProcess", "node_command",
           "stop_all"]

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_INTERRUPTED = 130  # Ctrl-C, SIGTERM, SIGHUP: as the CLI and shells say it

#: seconds the nodes get to stop after SIGINT before SIGKILL (a node bounds its own teardown at
#: ``fms_sim.shop_node.STOP_STALL_S``, which is shorter)
STOP_GRACE_S = 10.0

#: seconds between the progress lines of a run that goes on (operations done and the shop's clock, read from the
#: recorder's database); --quiet prints none
PROGRESS_S = 5.0


class UpError(ValueError):
    """Bad input for ``fms up`` (exit code 2)."""


def add_up_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``up`` subcommand to an ``argparse`` subparsers object; it sets ``fn=cmd_up``."""
    p = subparsers.add_parser(
        "up", help="run the shop, agent and recorder ROS 2 nodes on an instance and write the schedule",
        description="Start the shop simulator, the dispatcher agent and the recorder as ROS 2 node processes, "
                    "wait for the schedule, write it, and stop them.")
    _add_arguments(p)
    p.set_defaults(fn=cmd_up)
    return p


def _add_arguments(p: argparse.ArgumentParser) -> None:
    from .cli import DEFAULT_DISRUPTED_SOLVER, add_guide_args, add_instance_args  # late: cli imports this module

    add_instance_args(p)
    p.add_argument("--solver", default=DEFAULT_DISRUPTED_SOLVER,
                   help="agent solver: first | random | rule:<JOB>[+<first|least-work|nearest>] | ppo | ppo:<model> | "
                        "ppo[:<model>]+lookahead | ppo[:<model>]+lookahead-fast | ppo[:<model>]+lookahead-guide | "
                        "lookahead (ppo+lookahead) | plan:<SOLVER>[:SECONDS] (e.g. plan:cpsat:10: plan at the first "
                        "state, then execute the plan) | plan:file:PATH (execute a schedule made beforehand) | "
                        "best (the shipped PPO model, with or without lookahead, if "
                        "it beats the best rule pair and the list schedule in simulation, else the better of those; "
                        "with --scenario/--noise plan:rules instead of them) "
                        f"(default: {DEFAULT_DISRUPTED_SOLVER}: the earliest-start list schedule, planned at the first "
                        "state and executed live, re-planned when late)")
    p.add_argument("--seed", type=int, default=None, help="seed (>= 0) of the random and plan: solvers (default 0) and of "
                   "the noise (--noise, or the --scenario file's: this seed replaces the file's); refused for a "
                   "solver that draws nothing in a run without noise")
    p.add_argument("--scenario", metavar="FILE", help="disruptions of the run (fms/scenario/v1: breakdowns, "
                   "outages, noise; docs/semantics.md); the shop runs the full net: plan:, first, random or a "
                   "full-net ppo model")
    p.add_argument("--noise", type=float, metavar="SPREAD", help="lognormal noise on every processing and travel "
                   "time (sigma from 0 to 1), seeded by --seed (with --scenario it replaces the "
                   "file's noise and its seed: --seed, default 0)")
    p.add_argument("--replan", type=float, default=None, metavar="SECONDS",
                   help="plan: solvers: seconds per re-plan when an order arrives or the shop departs from the plan "
                        "(default 2; 0: never re-plan)")
    p.add_argument("--replan-wait", action=argparse.BooleanOptionalAction, default=None,
                   help="plan: solvers and guided ppo models: the shop waits for each re-plan (as offline "
                        "re-planning does) instead of running on under the plan in force meanwhile (default: wait "
                        "where the shop keeps no clock, --time-scale 0, so that how fast this machine searches "
                        "does not enter the simulated run; not with --time-scale)")
    add_guide_args(p)
    p.add_argument("--out", help="write the schedule JSON here (default: <instance>.schedule.json)")
    p.add_argument("--db", default=DEFAULT_DB, help=f"recorder SQLite database (default: {DEFAULT_DB})")
    p.add_argument("--gantt-dir", help="folder for the Gantt PNG (default: the database's folder)")
    p.add_argument("--run-id", help="run id (default: <instance>-<time>-<random>)")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID for the nodes (default: $ROS_DOMAIN_ID, "
                                                 "else a random one in 1..101)")
    p.add_argument("--time-scale", type=float, default=0.0, metavar="SECONDS",
                   help="the simulated shop keeps to a clock: wall seconds per unit of shop time (e.g. 0.01: a "
                        "makespan of 3000 takes 30 s; default 0: as fast as the agent answers)")
    p.add_argument("--timeout", type=float, default=120.0,
                   help="give up when the run has made no progress (no operation ended, the shop's clock still, as "
                        "the recorder stores them) for this many seconds (default 120)")
    p.add_argument("--log-dir", help="keep the node logs here (default: a temporary folder, kept on failure)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the result lines")


def best_rule(instance: Instance) -> tuple[str, int]:
    """The rule pair (``rule:JOB+veh``, including ``nearest``) with the smallest makespan on ``instance``,
    found by simulating each in-process; ties go to the first in ``all_rule_pairs`` order."""
    from .rules import all_rule_pairs, solve_rule

    best: tuple[int, str] | None = None
    for name in all_rule_pairs(include_nearest=True):
        job, veh = name.split(":", 1)[1].split("+")
        span = solve_rule(instance, job, veh).makespan
        if best is None or span < best[0]:
            best = (span, name)
    assert best is not None
    return best[1], best[0]


def best_solver(instance: Instance, guide_effort: Any = None, disrupted: bool = False) -> tuple[str, int, str]:
    """The solver ``fms up --solver best`` runs: ``(name, simulated makespan, one-line reason)``; a guided model
    plans with ``guide_effort`` (None: its default).

    The shipped PPO model (the default one for the instance, plain or with lookahead) is preferred when its
    simulated makespan is strictly smaller than both the best rule pair's and the list schedule's (``plan:list``,
    the default solver, which on shops with tools ends far below every rule pair); else the better of those two
    (the pair on a tie). If the model cannot run on this instance (larger than the model allows) or here (its
    dependencies are missing), the better of those two is used and the reason says why. A shipped model that is not installed is an error (:class:`UpError`, naming the places searched), never
    a quiet fall-back to a rule. For a ``disrupted`` run (a scenario or noise: the shop runs the full net, where
    the paper net's rule pairs cannot decide) the model is compared with ``plan:rules`` instead (the best
    full-net rule or list schedule, executed as a plan and re-planned); the simulations are nominal, since the
    disruptions are not known in advance."""
    from .rl.models import ModelNotFoundError  # numpy only: importable without the rl extra

    if disrupted:
        from .full_rules import solve_best_rules

        rule, rule_span, what = "plan:rules", solve_best_rules(instance, decisions="full").makespan, \
            "best full-net rule"
    else:
        from .full_rules import solve_list

        (rule, rule_span), what = best_rule(instance), "best rule pair"
        list_span = solve_list(instance).makespan  # plan:list executes it: nominally the same run
        if list_span < rule_span:
            rule, rule_span, what = "plan:list", list_span, "list schedule"
    try:
        from .rl import ppo_solver

        solve = ppo_solver("ppo")
        kw = {} if guide_effort is None else {"guide_effort": guide_effort}
        plain = solve(instance, **kw)
        ahead = solve(instance, lookahead=True, **kw)
    except ModelNotFoundError as exc:
        raise UpError(f"--solver best needs the shipped PPO models: {exc}") from None
    except (ImportError, ValueError, OSError) as exc:
        return rule, rule_span, (f"{what} on {instance.name}: {rule} (makespan {rule_span} in simulation; "
                                 f"PPO not available: {str(exc).splitlines()[0]})")
    sched = ahead if ahead.makespan < plain.makespan else plain
    ppo = str(sched.meta["solver"])
    if sched.makespan < rule_span:
        return ppo, sched.makespan, (f"best on {instance.name}: {ppo} (makespan {sched.makespan} in simulation; "
                                     f"{what} {rule}: {rule_span})")
    return rule, rule_span, (f"best on {instance.name}: {rule} (makespan {rule_span} in simulation; "
                             f"{ppo}: {sched.makespan})")


def node_command(module: str, params: dict[str, Any], python: str | None = None) -> list[str]:
    """The command line that starts the node in ``module`` with ROS parameters ``params``."""
    cmd = [python or sys.executable, "-m", module, "--ros-args"]
    for key, value in params.items():
        if isinstance(value, bool):
            value = "true" if value else "false"
        cmd += ["-p", f"{key}:={value}"]
    return cmd


@dataclass
class NodeProcess:
    """A node started in its own process group, its output going to a log file."""

    name: str
    cmd: list[str]
    log_path: Path
    env: dict[str, str]
    proc: subprocess.Popen | None = None
    _log: IO[bytes] | None = field(default=None, repr=False)
    _interrupted: bool = field(default=False, repr=False)

    def start(self) -> "NodeProcess":
        self._log = open(self.log_path, "wb")
        self._interrupted = False
        self.proc = subprocess.Popen(self.cmd, stdout=self._log, stderr=subprocess.STDOUT, env=self.env,
                                     stdin=subprocess.DEVNULL, start_new_session=True,
                                     preexec_fn=_stop_with(os.getpid()) if sys.platform.startswith("linux") else None)
        return self

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def interrupt(self) -> None:
        """Ask the node to stop: SIGINT to its process group (rclpy shuts down cleanly, exit code 0). Sent
        once: a second SIGINT could reach the node while its interpreter finalises."""
        if self.proc is not None and self.proc.poll() is None and not self._interrupted:
            self._interrupted = True
            _signal_group(self.proc.pid, signal.SIGINT)

    def stop(self, grace: float = 5.0) -> int | None:
        """SIGINT the process group (if still running), wait up to ``grace`` s, then SIGKILL; returns the
        exit code."""
        if self.proc is None:
            return None
        self.interrupt()
        try:
            self.proc.wait(max(grace, 0.0))
        except subprocess.TimeoutExpired:
            _signal_group(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        if self._log is not None:
            self._log.close()
            self._log = None
        return self.proc.returncode

    def tail(self, lines: int = 15) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(f"    {line}" for line in text[-lines:])

    def first_error(self) -> str | None:
        """The first error the node logged (an ``[ERROR]`` or ``[FATAL]`` line of ROS 2's logger, or the last line of
        a Python traceback: an exception in a callback), or None; read from its log."""
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return None
        for i, line in enumerate(text):
            if line.startswith(("[ERROR]", "[FATAL]")):
                return line.strip()
            if line.startswith("Traceback (most recent call last):"):
                last = next((x for x in text[i + 1:] if x.strip() and not x.startswith((" ", "\t"))), None)
                if last is not None:
                    return last.strip()
        return None


def stop_all(nodes: Sequence[NodeProcess], grace: float = 5.0) -> dict[str, int | None]:
    """Interrupt every node at once, then wait for each (SIGKILL after ``grace`` s in all)."""
    for n in nodes:
        n.interrupt()
    deadline = time.monotonic() + grace
    return {n.name: n.stop(deadline - time.monotonic()) for n in nodes}


def _stop_shielded(nodes: Sequence[NodeProcess]) -> dict[str, int | None]:
    """:func:`stop_all`, with fms up's stop signals ignored meanwhile: a second Ctrl-C escaped the stop and left
    a node running (its SIGKILL fallback skipped); the stop is bounded by :data:`STOP_GRACE_S` anyway."""
    old: dict[int, Any] = {}
    try:
        for sig in (signal.SIGINT, *STOP_SIGNALS):
            old[sig] = signal.signal(sig, signal.SIG_IGN)
    except ValueError:  # not the main thread: signals reach only the main thread
        pass
    try:
        return stop_all(nodes, STOP_GRACE_S)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _print_logs(nodes: Sequence[NodeProcess]) -> None:
    """The path and the last lines of each node's log, on stderr."""
    for n in nodes:
        print(f"  {n.name} log ({n.log_path}):\n{n.tail()}", file=sys.stderr)


def _signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def _load(a: argparse.Namespace) -> Instance:
    from fms_sim.formats import load_instance

    return load_instance(a.instance, layout=a.layout, agvs=a.agvs, tool_transporters=a.tool_transporters,
                         no_tools=a.no_tools, no_agvs=a.no_agvs)


def rclpy_missing() -> str | None:
    """Why a command that talks ROS 2 cannot run here (rclpy is not installed), else None; found without importing
    rclpy (``fms up`` and ``fms send`` check before they start anything)."""
    if importlib.util.find_spec("rclpy") is None:
        return "ROS 2 (rclpy) is not installed; `pip install 'fms[ros]'` or source a ROS 2 installation"
    return None


def cmd_up(a: argparse.Namespace) -> int:
    """Run ``fms up`` for parsed arguments (see the module docstring); returns the exit code."""
    from fms_sim.validate import validate

    say = (lambda *args: None) if a.quiet else (lambda *args: print(*args, file=sys.stderr, flush=True))
    t0 = time.perf_counter()
    missing = rclpy_missing()
    if missing:
        raise UpError(missing)
    inst = _load(a)
    solver = a.solver
    if a.seed is not None and a.seed < 0:  # (as fms solve: -3 ran as 3)
        raise UpError(f"--seed must be an integer >= 0, got {a.seed}")
    from .cli import guide_effort_from_args

    try:
        effort = guide_effort_from_args(a)
    except ValueError as exc:
        raise UpError(str(exc)) from None
    if a.scenario is not None and not a.scenario.strip():  # ran undisrupted
        raise UpError("--scenario names no file (an empty name); leave it out for an undisrupted run")
    disrupted = bool(a.scenario) or bool(a.noise)
    if solver.lower() == "best":
        solver, _, reason = best_solver(inst, effort, disrupted)
        say(reason + (" (nominal simulations: the disruptions are not known in advance)" if disrupted else ""))
    else:
        from .cli import moot_choice

        moot = moot_choice(solver, inst, effort)
        if moot:
            raise UpError(moot)
    from .cli import DEFAULT_DISRUPTED_SOLVER, GUIDE_OPTIONS

    named = f"{solver!r}" + (" (the default solver)" if solver == DEFAULT_DISRUPTED_SOLVER else "")
    if a.guide_replan is not None and not needs_twin(solver):
        raise UpError(f"--[no-]guide-replan applies to ppo solvers only, not to {named}")
    if effort is not None and not needs_twin(solver):  # (the agent's own check names its parameters, not these)
        raise UpError(f"a plan search option ({GUIDE_OPTIONS}) applies to ppo solvers only, not to {named}")
    if a.replan is not None and not needs_full_net(solver):
        raise UpError(f"--replan applies to plan: solvers only, not to {named}")
    try:
        decider, _ = make_decider(solver, a.seed or 0, inst, guide_effort=effort)
    except UnavailableSolver as exc:
        msg = str(exc)
        raise UpError(msg + ("; fms up also takes best" if msg.startswith("unknown solver") else "")) from None
    guide_replans = hasattr(getattr(decider, "choose", None), "trigger") and a.guide_replan is not False
    if a.replan_wait and not (needs_full_net(solver) or guide_replans):
        raise UpError(f"--replan-wait applies to plan: solvers and to guided ppo models that re-plan their guide, "
                      f"not to {solver!r}" + (" with --no-guide-replan" if a.guide_replan is False else ""))
    # a full-net PPO model (ppo:full) decides on the full net too: the shop must run it
    full_model = needs_twin(solver) and getattr(decider, "decisions", "paper") == "full"
    scenario = None
    if disrupted:
        from .cli import CliError, scenario_from_args

        try:
            scenario = scenario_from_args(a, inst)
        except (ValueError, CliError) as exc:  # a bad scenario file (ScenarioError), a bad --noise (a CliError:
            raise UpError(str(exc).splitlines()[0]) from None  # under python -m fms_dispatch.cli, not main's own)
        if not (needs_full_net(solver) or full_model or solver.lower() in ("first", "random")):
            raise UpError(f"--scenario and --noise need a solver that decides on the full net (plan:..., first, "
                          f"random, a full-net model such as ppo:full), not {solver}")
    from .solvers import takes_seed

    noisy = disrupted and bool(scenario is not None and scenario.noise)
    if a.seed is not None and not noisy and a.solver.lower() != "best" and not takes_seed(solver):  # as fms solve
        raise UpError(f"--seed does not apply to {solver}: it draws nothing at random (the seed is the random and "
                      "plan: solvers', and the noise's; a guided ppo model's plan search takes --guide-seed)")
    if not 0 < a.timeout < float("inf"):  # NaN would never time out
        raise UpError("--timeout must be a positive number of seconds")
    if not 0 <= a.time_scale < float("inf"):
        raise UpError(f"--time-scale must be a finite number >= 0 of seconds per time unit (0: as fast as the agent "
                      f"answers), got {a.time_scale:g}")  # (nan and inf were told "must be >= 0")
    replan = 2.0 if a.replan is None else a.replan
    if not 0 <= replan < float("inf"):
        raise UpError("--replan must be >= 0 seconds (0: never re-plan)")
    if a.replan_wait and replan == 0:
        raise UpError("--replan-wait needs re-planning (--replan > 0)")
    # by default a simulated shop without a clock waits for each re-plan: it would otherwise run on under the plan
    # in force for as many states as the agent answers during the search's second (docs/benchmarks.md §8), an
    # effect of this machine's speed that a real shop, minutes per time unit, does not see
    replans = guide_replans or (needs_full_net(solver) and replan > 0)
    wait = a.replan_wait if a.replan_wait is not None else (replans and not a.time_scale)
    domain = a.domain_id if a.domain_id is not None else os.environ.get("ROS_DOMAIN_ID") or random.randint(1, 101)
    try:
        domain = int(domain)
    except ValueError:
        raise UpError(f"ROS_DOMAIN_ID must be an integer, got {domain!r}") from None
    if not 0 <= domain <= 232:
        raise UpError(f"ROS domain id {domain} is out of range (0..232; 0..101 is safe everywhere)")

    for flag, value in (("--out", a.out), ("--db", a.db), ("--run-id", a.run_id), ("--gantt-dir", a.gantt_dir),
                        ("--log-dir", a.log_dir)):
        if value is not None and not value.strip():  # fell back to the default (--log-dir: the current folder)
            raise UpError(f"{flag} names nothing (an empty name); leave it out for the default")
    if a.run_id is not None and len(safe_run_name(a.run_id)) > MAX_RUN_NAME:  # "File name too long: ...gantt.png"
        raise UpError(f"--run-id is too long to name the run's files (at most {MAX_RUN_NAME} characters)")
    run_id = a.run_id or new_run_id(inst.name)
    out = Path(a.out) if a.out else Path(f"{safe_run_name(inst.name)}.schedule.json")  # a name is no path
    db = Path(a.db)
    if out.resolve() == db.resolve():  # the schedule was written over the recorder's database: every run lost
        raise UpError(f"--out and --db name the same file {a.out}; the schedule would overwrite the database")
    gantt_dir = Path(a.gantt_dir) if a.gantt_dir else (db.parent if str(db.parent) else Path("."))
    png = gantt_path(gantt_dir, run_id)
    # every output is checked before the nodes start: a run that cannot be written is not run
    for path, what in ((out, "--out"), (db, "--db")):
        if path.is_dir():
            raise UpError(f"{what} {path} is a directory; give a file path")
        _check_writable(path, what, folder=False)
    for path, what in ((gantt_dir, "--gantt-dir"), (Path(a.log_dir) if a.log_dir else None, "--log-dir")):
        if path is not None:
            if path.exists() and not path.is_dir():
                raise UpError(f"{what} {path} is a file, not a folder")
            _check_writable(path, what, folder=True)
    if png.exists():
        raise UpError(f"run id {run_id!r} was already recorded (its chart {png} exists); choose another --run-id")
    if run_id in _recorded_run_ids(db, strict=True):
        raise UpError(f"run id {run_id!r} is already in {db}; choose another --run-id")
    keep_logs = a.log_dir is not None
    log_dir = Path(a.log_dir) if keep_logs else Path(tempfile.mkdtemp(prefix="fms-up-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    work = log_dir / f"{safe_run_name(run_id)}.work"  # a run id such as ../x stays inside the log folder
    work.mkdir(parents=True, exist_ok=True)
    inst_in, inst_final, sched_tmp = work / "instance.json", work / "final_instance.json", work / "schedule.json"
    inst.save(inst_in)
    scenario_file = work / "scenario.json"
    if disrupted:
        scenario.save(scenario_file)
    for stale in (sched_tmp, inst_final):
        stale.unlink(missing_ok=True)

    full = needs_full_net(solver) or disrupted or full_model
    twin = needs_twin(solver) or needs_full_net(solver)
    # the agent answers this run's states only: another fms up on the same domain (an exported ROS_DOMAIN_ID) had its
    # shop steered by both agents, and its schedule reported as the solver's
    agent_params: dict[str, Any] = {"solver": solver, "seed": a.seed or 0, "run_id": run_id}
    if needs_full_net(solver):
        agent_params["replan"] = float(replan)
    if wait:
        agent_params["replan_wait"] = True
    if twin:
        agent_params["instance"] = str(inst_in)
    if effort is not None:
        agent_params.update(guide_restarts=effort.restarts, guide_budget=float(effort.budget or 0.0),
                            guide_rules=effort.rules, guide_exact=float(effort.exact),
                            guide_tabu=float(effort.tabu), guide_seed=effort.seed)
    if a.guide_replan is not None:
        agent_params["guide_replan"] = a.guide_replan
    if a.time_scale:
        agent_params["resend_s"] = paced_resend_s(inst, a.time_scale, scenario)
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("ROS_LOG_DIR", str(log_dir / "ros"))
    env.setdefault("PYTHONUNBUFFERED", "1")
    nodes = [
        NodeProcess("recorder", node_command("fms_sim.recorder_node", {"db": str(db), "gantt_dir": str(gantt_dir)}),
                    log_dir / "recorder.log", env),
        NodeProcess("shop", node_command("fms_sim.shop_node", {
            "instance": str(inst_in), "run_id": run_id, "schedule_out": str(sched_tmp),
            "instance_out": str(inst_final), "history": twin, "history_delta": twin, "features": not twin,
            "idle_stops": needs_idle_stops(solver) or needs_full_net(solver), "decisions": "full" if full else "paper",
            **({"time_scale": float(a.time_scale)} if a.time_scale else {}),
            **({"scenario": str(scenario_file), "noise": float(a.noise or 0.0)} if disrupted else {}),
            **({"noise_seed": a.seed or 0} if a.noise else {})}),  # (the scenario file holds the seed otherwise)
            log_dir / "shop.log", env),
        NodeProcess("agent", node_command("fms_dispatch.agent_node", agent_params), log_dir / "agent.log", env),
    ]
    say(f"fms up: {inst.describe()}; solver {solver}; run {run_id}; ROS_DOMAIN_ID={domain}"
        + (f"; {a.time_scale:g} s per time unit" if a.time_scale else "")
        + ("; the shop waits for each re-plan" if wait else ""))
    failure: str | None = None
    chart_missing = False  # the run delivered, but the recorder rendered no chart in time
    stop_on_term = _TermAsInterrupt()  # `kill` / a supervisor's SIGTERM stops the nodes as Ctrl-C does
    try:
        for node in nodes:
            node.start()
        # the run has --timeout seconds to make progress (an operation ended or the shop's clock moved, as the recorder
        # stored them); it is read once per check (every PROGRESS_S at most, at a report and at the deadline), and a
        # run that moved on gets the whole --timeout again: a long run is not a stuck one
        deadline = time.monotonic() + a.timeout
        next_check = time.monotonic() + min(PROGRESS_S, a.timeout / 4)
        next_report = time.monotonic() + PROGRESS_S
        seen = _progress(db, run_id) or (0, None, 0)
        while True:
            if sched_tmp.exists() and inst_final.exists() and png.exists():
                break
            dead = [n for n in nodes if n.poll() is not None]
            if dead:
                failure = f"the {dead[0].name} node exited early with code {dead[0].poll()}"
                break
            now = time.monotonic()
            if now >= min(next_check, next_report, deadline):
                progress = _progress(db, run_id)
                if progress is not None and progress != seen:  # (a read that failed is no progress: flipping
                    # between it and the real figures reset the deadline, and a stuck run outlived --timeout)
                    seen, deadline = progress, now + a.timeout
                next_check = now + min(PROGRESS_S, a.timeout / 4)
            if now > deadline:
                if sched_tmp.exists() and inst_final.exists():  # delivered: only the chart is missing; the
                    chart_missing = True                         # schedule is not lost for it
                    break
                missing = [str(p) for p in (sched_tmp, png) if not p.exists()]
                failure = (f"timed out: no progress for {a.timeout:g} s while waiting for {', '.join(missing)}; "
                           f"{_progress_text(seen, inst.n_operations)} (longer pauses need --timeout)")
                # a node that hit an error and stayed up (an exception in a callback) is the likely cause: name it
                failure += next((f"; the {n.name} node logged an error: {e}" for n in nodes
                                 if (e := n.first_error()) is not None), "")
                break
            if now >= next_report:  # a long run says how far it is, from the recorder's database
                say(f"fms up: {_progress_text(seen, inst.n_operations)}, {time.perf_counter() - t0:.0f} s")
                next_report += PROGRESS_S
            time.sleep(0.02)
    except KeyboardInterrupt:
        failure = "interrupted"
    finally:
        codes = _stop_shielded(list(reversed(nodes)))
        stop_on_term.restore()
    wall = time.perf_counter() - t0
    # a node interrupted before it could install its own handler (still importing) ends by the signal: clean then
    cleanly = (0, None) + ((-signal.SIGINT, 128 + signal.SIGINT) if failure == "interrupted" else ())
    unclean = {k: c for k, c in codes.items() if c not in cleanly}
    stop_note = ("a node did not stop cleanly: " + ", ".join(f"{k} exit code {c}" for k, c in unclean.items())
                 if unclean else None)
    if failure == "interrupted":  # the user's stop, said as the CLI says it; only a node that failed to stop shows
        print("fms: interrupted" + (f"; {stop_note}" if stop_note else "") + f" (logs: {log_dir})", file=sys.stderr)
        _print_logs([n for n in nodes if n.name in unclean])
        return EXIT_INTERRUPTED
    try:  # the nodes stopped: a signal now (the CLI makes it an interrupt) must not hide the run's kept output
        sched: Schedule | None = None
        if failure is None:
            try:
                sched = Schedule.load(sched_tmp)
                final = Instance.from_json(inst_final.read_text())
            except (OSError, ScheduleError, InstanceError) as exc:
                failure = f"cannot read the shop's output: {exc}"
            else:
                problems = validate(final, sched)
                if problems:
                    failure = f"the schedule is infeasible: {problems[0]}"
        if failure is not None or sched is None:
            print(f"fms up: error: {failure}" + (f"; {stop_note}" if stop_note else ""), file=sys.stderr)
            _print_logs(nodes)
            return EXIT_FAILED
        if stop_note:
            # the run was delivered (schedule, final instance and chart written, schedule valid): a node that then
            # fails to stop — e.g. a stalled DDS teardown — loses nothing, so it is reported, not a failed run
            keep_logs = True
            print(f"fms up: warning: the run is complete and valid, but {stop_note}", file=sys.stderr)
            _print_logs([n for n in nodes if n.name in unclean])
        # a run that took live orders has jobs the instance has not: its final instance goes beside the schedule, so
        # that `fms validate` can check it afterwards (the work folder holding it is removed)
        ordered = instance_beside(out)
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            sched.save(out)
            if final.n_jobs != inst.n_jobs:
                final.save(ordered)
        except OSError as exc:
            print(f"fms up: error: cannot write the schedule to {out}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_FAILED
        if final.n_jobs == inst.n_jobs:
            try:
                earlier = drop_instance_beside(out, sched.instance, a.instance)
            except OSError as exc:  # (the schedule is written: a warning, not a failed run)
                print(f"fms up: warning: cannot remove {ordered}, an earlier run's instance beside the schedule "
                      f"({exc.strerror or exc}); fms validate {out} would read it: give the instance", file=sys.stderr)
            else:
                if earlier is not None:
                    print(f"fms up: removed {earlier}, an earlier run's instance beside the schedule this run "
                          "replaced", file=sys.stderr)
    except KeyboardInterrupt:
        print(f"fms: interrupted while the run's output was checked and written; the shop's output is kept in "
              f"{log_dir}", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not keep_logs and not chart_missing:
        shutil.rmtree(log_dir, ignore_errors=True)
    meta = sched.meta
    from .cli import replans_summary

    recorded = _recorded_replans(db, run_id)
    # the count as fms solve gives it: in a disrupted run of an agent that re-plans even when it made none (it was
    # left out, as if the agent did not re-plan); otherwise only where the agent made some (a live order's)
    extra = replans_summary(recorded if recorded or (replans and disrupted) else None)
    print(f"{inst.name}: makespan {sched.makespan} ({meta.get('solver', solver)} over ROS 2 topics, "
          f"{meta.get('decisions', '?')} decisions{extra}, valid) in {wall:.2f} s")
    print(f"schedule: {out}")
    if final.n_jobs != inst.n_jobs:
        added = final.n_jobs - inst.n_jobs
        print(f"instance: {ordered} (with the {added} job{'s' if added != 1 else ''} ordered during the run; "
              f"fms validate {ordered} {out})")
    print(f"sqlite:   {db} (run {run_id})")
    if chart_missing:
        print(f"fms up: error: the run is complete and its schedule written, but the recorder rendered no chart "
              f"({png}) within --timeout {a.timeout:g} s", file=sys.stderr)
        _print_logs([n for n in nodes if n.name == "recorder"])
        return EXIT_FAILED
    print(f"gantt:    {png}")
    return EXIT_OK


def _check_parent(path: Path, what: str) -> None:
    """Refuse an output under a file (its folder could never be made)."""
    from fms_sim.files import file_above

    above = file_above(path)
    if above is not None:
        raise UpError(f"{what} {path}: {above} is a file, not a folder")


def _check_writable(path: Path, what: str, folder: bool) -> None:
    """Refuse an output that cannot be written, before any node starts (found after the run, it lost the run; an
    unwritable --gantt-dir left fms up waiting for the chart until --timeout): under a file, an existing file
    this user may not write, or a folder where no file can be made (tried: the folder, ``path`` itself where
    ``folder``, is made, a file written there and removed)."""
    _check_parent(path, what)
    if not folder and path.exists() and not os.access(path, os.W_OK):
        raise UpError(f"{what} {path}: the file may not be written (permission denied)")
    where = path if folder else (path.parent if str(path.parent) else Path("."))
    try:
        where.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".fms-up-check.", dir=str(where))
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UpError(f"{what} {path}: nothing can be written in {where} ({exc.strerror or exc})") from None


def _from_store(db: Path, read: Callable[[Any], Any], empty: Any) -> Any:
    """``read(store)`` of the recorder's database at ``db``; ``empty`` when there is none yet or it cannot be read
    (the recorder node reports that itself; fms up only counts or checks)."""
    import sqlite3

    from fms_sim.recorder_store import RecorderStore

    if not db.is_file():
        return empty
    try:
        store = RecorderStore(db)
    except (OSError, ValueError, sqlite3.Error):
        return empty
    try:
        return read(store)
    except sqlite3.Error:
        return empty
    finally:
        store.close()


def _recorded_run_ids(db: Path, strict: bool = False) -> set[str]:
    """The run ids already in the recorder's database; with ``strict``, a file there that is not one the recorder
    can open is refused (:class:`UpError`: before the start; the recorder node found it only after every node had
    started, and the run failed with exit code 1)."""
    if strict and db.is_file():
        import sqlite3

        from fms_sim.recorder_store import RecorderStore

        try:
            RecorderStore(db).close()
        except (OSError, ValueError, sqlite3.Error) as exc:
            raise UpError(f"--db {db} cannot be used as the recorder's database: {exc}") from None
    return _from_store(db, lambda store: set(store.run_ids()), set())


def _stop_with(parent: int) -> Callable[[], None]:
    """For a node's process, run between fork and exec (Linux): the kernel sends it SIGTERM, a clean stop, when
    ``fms up`` dies, even of a signal it cannot handle (SIGKILL: an OOM kill, ``timeout -s KILL``); in its own
    session it gets no signal from the terminal, and it would run on for good. A parent already gone by then
    (the kernel only watches from the call on) stops it at once. SIGINT, the stop ``fms up`` sends, gets its
    default action back: a shell ignores it for a job started in the background, and the node inherited that."""

    def arm() -> None:
        import ctypes

        signal.signal(signal.SIGINT, signal.SIG_DFL)
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # 1: PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            return
        if os.getppid() != parent:
            os.kill(os.getpid(), signal.SIGTERM)

    return arm


#: the signals that stop ``fms up`` (and so its nodes) as Ctrl-C does: ``kill``, a supervisor, a closed terminal
#: or a dropped SSH session (SIGHUP), SIGQUIT
STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, n))


class _TermAsInterrupt:
    """While it is installed, each of :data:`STOP_SIGNALS` raises KeyboardInterrupt in the main thread, so that
    ``fms up`` stops its nodes (each runs in its own session and would outlive it) exactly as on Ctrl-C."""

    def __init__(self) -> None:
        self._old: dict[int, Any] = {}
        try:
            for sig in STOP_SIGNALS:
                self._old[sig] = signal.signal(sig, self._raise)
        except ValueError:  # not the main thread: nothing to install
            self.restore()

    @staticmethod
    def _raise(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}


def paced_resend_s(instance: Instance, time_scale: float, scenario: Any = None) -> float:
    """The agent's ``resend_s`` under a shop keeping to a clock: longer than the shop's longest wait between two
    states (its longest operation, trip or breakdown or outage window at ``time_scale`` seconds per time unit, times 3
    for noise), so that a paced wait is not taken for a lost state. With the default 1 s every wait past a second
    re-sent the command, and the shop logged a ``stale_state`` error for each (8 in an EX12 run at 0.2 s per unit)."""
    steps = [op.duration for job in instance.jobs for op in job]
    for matrix in (instance.agv_travel, instance.tool_travel):
        steps += [t for row in matrix or () for t in row]
    if scenario is not None:
        steps += [w.duration for w in (*scenario.breakdowns, *scenario.outages)]
    return max(1.0, round(1.0 + 3 * time_scale * max(steps, default=0), 3))


def _progress(db: Path, run_id: str) -> tuple[int, int | None, int] | None:
    """How far the run is as the recorder stored it: operations ended, the latest event's time (None as the time:
    none stored yet) and the jobs orders added; None when the database is not there or cannot be read now. What
    ``--timeout`` watches and the progress lines say."""
    return _from_store(db, lambda store: store.progress(run_id), None)


def _progress_text(progress: tuple[int, int | None, int], n_operations: int) -> str:
    """:func:`_progress` in words: operations ended, of the instance's at the start (with orders: "14 operations done
    (the shop's 13 and those of 1 ordered job)", where "14 of 13" was said), and the shop's clock."""
    done, latest, ordered = progress
    if latest is None:
        return "no event recorded yet"
    if ordered:
        return (f"{done} operations done (the shop's {n_operations} and those of {ordered} ordered "
                f"job{'s' if ordered != 1 else ''}), shop time {latest}")
    return f"{done} of {n_operations} operations done, shop time {latest}"


def _recorded_replans(db: Path, run_id: str) -> list[dict[str, Any]]:
    """The agent's re-plans of the run as the recorder stored them (``fms/replans``); none if they cannot be read
    (the summary line only counts them)."""
    return _from_store(db, lambda store: store.replans(run_id), [])


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m fms_dispatch.up INSTANCE ...``: the same as ``fms up`` without the ``fms`` CLI."""
    p = argparse.ArgumentParser(prog="fms up", description=__doc__.splitlines()[0])
    _add_arguments(p)
    a = p.parse_args(argv)
    try:
        return cmd_up(a)
    except (UpError, InstanceError, ScheduleError, ValueError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"fms up: error: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
