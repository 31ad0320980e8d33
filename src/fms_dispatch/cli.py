"""The ``fms`` command-line tool: one entry point, subcommands for humans.

Every bad input (unknown instance, malformed file, wrong matrix size, negative times, unknown solver) ends
with a one-line ``fms: error: ...`` on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from fms_sim.files import drop_instance_beside, folder_problem, instance_beside, output_problem
from fms_sim.instance import MAX_COUNT, Instance, InstanceError
from fms_sim.schedule import Schedule, ScheduleError

from .progress import send_nowhere, surviving_streams

if TYPE_CHECKING:
    from fms_sim.disruptions import Scenario

    from .rl.guide import PlanEffort

EXIT_BAD_INPUT = 2
EXIT_INFEASIBLE = 1

#: ``fms solve``'s solver when none is named: the earliest-start list schedule, executed through the full net (a
#: sensible schedule on every shop in seconds; ``first``, the lowest enabled action, ends several times later on
#: shops with tools: sl70 105,272 against 7,777)
DEFAULT_SOLVER = "list"
#: the same in a disrupted run (``--scenario``, ``--noise``), and ``fms up``'s: the list schedule planned on the
#: nominal shop (disruptions are not known ahead), then executed under the disruptions
DEFAULT_DISRUPTED_SOLVER = "plan:list"


class CliError(Exception):
    """A user error: printed as one line, exit code 2."""


def add_instance_args(p: argparse.ArgumentParser) -> None:
    """The instance argument and its overrides, shared by every subcommand that loads an instance."""
    p.add_argument("instance", help="built-in name (see `fms instances`) or an instance file (JSON, OR-Library, Taillard)")
    p.add_argument("--layout", type=int, help="layout 1-4 for the ra instances (default 2)")
    p.add_argument("--agvs", type=int, metavar="N", help="override the number of AGVs")
    p.add_argument("--tool-transporters", type=int, metavar="N", help="override the number of tool transporters")
    p.add_argument("--no-tools", action="store_true", help="drop tools (AGVs only)")
    p.add_argument("--no-agvs", action="store_true",
                   help="drop AGVs (parts move instantly; with --no-tools too, a plain job shop)")


#: the options of a guided model's plan search (:func:`add_guide_args`), for messages that refuse them
GUIDE_OPTIONS = "--guide-restarts, --guide-budget, --[no-]guide-rules, --guide-tabu, --guide-exact, --guide-seed"


def add_guide_args(p: argparse.ArgumentParser, replan: bool = True) -> None:
    """:data:`GUIDE_OPTIONS`: a guided model's plan search (``fms solve``, ``fms up`` and the benches);
    :func:`guide_effort_from_args` reads them. With ``replan``, ``--[no-]guide-replan``: whether it re-plans at breakdowns and delays
    (``a.guide_replan``; None: the default); a bench of nominal runs leaves it out."""
    p.add_argument("--guide-restarts", type=int, metavar="N",
                   help="ppo with a guided model: randomised restarts that improve the guide's list-schedule plan "
                        "(default 64; 0: none)")
    p.add_argument("--guide-budget", type=float, metavar="SECONDS",
                   help="ppo with a guided model: time limit of its plan search (default 1; 0: no limit)")
    p.add_argument("--guide-rules", action=argparse.BooleanOptionalAction, default=None,
                   help="ppo with a guided model: also try the 36 rule pairs' schedules as its plan on shops "
                        "without tools (default: no)")
    p.add_argument("--guide-tabu", type=float, metavar="SECONDS",
                   help="ppo with a guided model: tabu search improves its plan for this many seconds per operation "
                        "of the shop, within the budget (default 0.0025; 0: none)")
    p.add_argument("--guide-exact", type=float, metavar="SECONDS",
                   help="ppo with a guided model: CP-SAT polishes its plan for this long on shops small enough for "
                        "the full model, within the budget (default 0: no polish)")
    p.add_argument("--guide-seed", type=int, metavar="N",
                   help="ppo with a guided model: seed of its plan search's randomised restarts (default 0; "
                        "--seed seeds the noise)")
    if not replan:
        return
    p.add_argument("--guide-replan", action=argparse.BooleanOptionalAction, default=None,
                   help="ppo with a guided model in a disrupted run: re-plan the guide when a machine breaks down, "
                        "a vehicle goes out of service, or an operation starts later than planned by 5 %% of the "
                        "plan's makespan, adopting the new "
                        "plan where it ends 2 %% earlier than the plan in force (default: yes)")


def guide_effort_from_args(a: argparse.Namespace) -> PlanEffort | None:
    """The plan search of :func:`add_guide_args`' options (None: none given, the solver's default); raises
    ValueError for a negative count, budget, tabu search or polish."""
    if (a.guide_restarts is None and a.guide_budget is None and a.guide_rules is None and a.guide_exact is None
            and a.guide_tabu is None and a.guide_seed is None):
        return None
    from .rl.guide import effort_from

    for flag, key in (("--guide-restarts", "restarts"), ("--guide-budget", "budget"), ("--guide-exact", "exact"),
                      ("--guide-tabu", "tabu"), ("--guide-seed", "seed")):  # each bad value named by its option
        value = getattr(a, flag[2:].replace("-", "_"))
        if value is not None:
            try:
                effort_from(**{key: value})
            except ValueError as exc:
                raise ValueError(f"{flag}: {exc}") from None
    return effort_from(a.guide_restarts, a.guide_budget, a.guide_rules, a.guide_exact, a.guide_tabu, a.guide_seed)


def moot_choice(solver: str, inst: Instance, effort: PlanEffort | None) -> str | None:
    """Why a part of ``solver``'s name or of the plan search ``effort`` (the ``--guide-*`` options) decides nothing on
    ``inst`` (None: every part given can): a tool rule (``rule:JOB+VEHICLE+TOOL``, also in ``plan:rule:``) on a shop
    without tools, a vehicle rule on one without AGVs and without tool transporters, ``--guide-rules`` on a shop with
    tools (the search takes the rule pairs' schedules on shops without tools only) and ``--guide-exact`` on one too
    large for CP-SAT's full model (the polish runs only within it). Each was taken without a word, the run the same
    as without it."""
    low = solver.lower()
    base = solver[:len("plan:")] if low.startswith("plan:rule:") else ""
    if low[len(base):].startswith("rule:"):
        job, vehicle, tool = (solver[len(base) + len("rule:"):].split("+") + ["", "", ""])[:3]
        if tool and not inst.has_tools:
            return (f"{inst.name} has no tools, so the tool rule {tool!r} of {solver} decides nothing: give "
                    f"{base}rule:{job}+{vehicle}")
        if vehicle and not inst.has_agvs and not inst.has_tools:
            return (f"{inst.name} has no AGVs and no tool transporters, so the vehicle rule {vehicle!r} of {solver} "
                    f"decides nothing: give {base}rule:{job}")
    if effort is not None and effort.rules and inst.has_tools:
        return (f"--guide-rules: {inst.name} has tools, and the plan search takes the rule pairs' schedules on shops "
                "without tools only (with tools they are far behind the list schedules)")
    if effort is not None and effort.exact:
        from .exact import FULL_MODEL_MAX_TASKS, fits_full_model

        if not fits_full_model(inst):
            return (f"--guide-exact: {inst.name} is too large for CP-SAT's full model (more than "
                    f"{FULL_MODEL_MAX_TASKS} transport tasks), where the plan search's polish runs only")
    return None


def load_from_args(a: argparse.Namespace) -> Instance:
    from fms_sim.formats import load_instance

    return load_instance(a.instance, layout=a.layout, agvs=a.agvs, tool_transporters=a.tool_transporters,
                         no_tools=a.no_tools, no_agvs=a.no_agvs)


def cmd_instances(a: argparse.Namespace) -> int:
    from fms_sim.benchmarks import builtin, builtin_names
    from fms_sim.formats import load_instance
    from fms_sim.shopsets import heldout_names

    for name in builtin_names():
        print(builtin(name).describe() if a.details else name)
    # the held-out shops load by name too (never trained on: the generalisation figures are measured on them)
    for name in heldout_names():
        print(load_instance(name).describe() + " (held out)" if a.details else name)
    return 0


def replans_summary(events: list[dict[str, Any]] | None) -> str:
    """``", R re-plans (A adopted)"`` (``", 1 re-plan ..."``) for a run's re-plan events (``fms solve`` and ``fms up``
    summary lines); "" for None (a run that does not re-plan)."""
    if events is None:
        return ""
    n = len(events)
    return f", {n} re-plan{'' if n == 1 else 's'} ({sum(e.get('status') == 'adopted' for e in events)} adopted)"


def search_summary(sched: Schedule) -> str:
    """What the summary line adds about the search: a guided model's plan search at the start (``", 1.02 s of it the
    plan search"``, or ``", plan search 1.02 s beside the run, its first plan kept"`` where it ran on the other
    core, :mod:`fms_dispatch.rl.beside`), CP-SAT's proof (``", optimal"`` or ``", bound B"``) and its start
    schedule's makespan, the winning rule combination (``", best list"``) and those a time limit (or an interrupt)
    left untried, and ``", interrupted"`` for a search stopped by Ctrl-C."""
    m = sched.meta
    out = ""
    if m.get("guide_search_time") is not None:
        beside = m.get("guide_search_beside")  # the search ran on the other core while the run went on
        if beside is None:
            out += f", {m['guide_search_time']:.3f} s of it the plan search"
        else:
            out += f", plan search {m['guide_search_time']:.3f} s beside the run"
            out += ", which started over with its plan" if beside == "restarted" else ", its first plan kept"
    if m.get("status") == "OPTIMAL":
        out += ", optimal"
    elif m.get("lower_bound") is not None and m.get("solver") == "cpsat":
        out += f", bound {m['lower_bound']}"
    if m.get("solver") == "cpsat" and m.get("start_makespan") is not None:  # what the search itself added
        start = m["start_makespan"]
        out += (f", from a start schedule of {start}" if start > sched.makespan
                else ", no better than its start schedule (a list schedule)")
    if m.get("rule") is not None and m.get("combinations") is not None:  # rules: which combination won
        out += f", best {m['rule']}"
    if m.get("tried") is not None and m.get("combinations") is not None and m["tried"] < m["combinations"]:
        out += f", {m['tried']} of {m['combinations']} rule combinations"
        out += "" if m.get("status") == "INTERRUPTED" else " within the time limit"
    if m.get("status") == "INTERRUPTED":
        out += ", interrupted"
    return out


def cmd_solve(a: argparse.Namespace) -> int:
    from fms_sim.validate import validate

    from .solvers import get_solver, parse_plan_name, solve, takes_seed, takes_time_limit

    defaulted = a.solver is None
    if defaulted:  # the earliest-start list schedule; in a disrupted run its plan, executed under the disruptions
        a.solver = DEFAULT_DISRUPTED_SOLVER if (a.scenario or a.noise is not None) else DEFAULT_SOLVER
    named = f"{a.solver} (the default solver)" if defaulted else a.solver  # for messages
    get_solver(a.solver)  # unknown names fail before any work or output
    if a.solver.lower().startswith("ppo:"):  # and unknown models (a ppo solver finds its model when it runs)
        from .rl.models import resolve_model

        ref = resolve_model(a.solver[4:].split("+", 1)[0].strip())
        try:
            effort = guide_effort_from_args(a)
        except ValueError:
            effort = None  # a bad value: reported below with the options it concerns
        flags = [f for f, v in (("--[no-]guide-replan", a.guide_replan), ("--[no-]guide-beside", a.guide_beside),
                                ("plan search options (--guide-*)", effort)) if v is not None]
        if flags and not ref.config.get("guide"):  # taken and ignored (replan) or refused after the header (effort)
            raise CliError(f"model {ref.name} reads no plan guide, so it takes no {' and no '.join(flags)}")
    plan_file = a.solver[len("plan:file:"):] if a.solver.lower().startswith("plan:file:") else None
    check_outputs(a, a.instance, getattr(a, "scenario", None), plan_file)
    if a.seed is not None and a.seed < 0:  # (Python's and numpy's generators took -3 as 3: two seeds, one run)
        raise CliError(f"--seed must be an integer >= 0, got {a.seed}")
    inst = load_from_args(a)
    opts: dict = {"seed": a.seed if a.seed is not None else 0}
    if a.time_limit is not None:
        if not 0 < a.time_limit < math.inf:
            raise CliError(f"--time-limit must be a positive, finite number of seconds, got {a.time_limit:g}")
        low = a.solver.lower()
        if low.startswith("ppo"):
            raise CliError("--time-limit does not apply to ppo (a policy's run); its plan search's limit is "
                           "--guide-budget")
        if not takes_time_limit(a.solver):
            raise CliError(f"--time-limit does not apply to {named}: it runs once, without a search")
        if low.startswith("plan:") and parse_plan_name(a.solver)[1] is not None:
            raise CliError(f"{a.solver} gives its plan's budget in its name; give it without the seconds and "
                           "--time-limit, or no --time-limit")
        opts["time_limit"] = a.time_limit
    from .solvers import DECISION_SOLVERS

    scenario = scenario_from_args(a, inst)
    if scenario is not None:
        opts["scenario"] = scenario
    seeded = takes_seed(a.solver)
    if a.solver.lower().startswith("plan:"):  # a plan of a search, or re-planned (plan:list --seed 5 was ignored)
        base, _ = parse_plan_name(a.solver)
        seeded = a.replan is not None or (not base.lower().startswith("file:") and takes_seed(base))
    if a.seed is not None and not (scenario is not None and scenario.noise) and not seeded:  # ignored
        raise CliError(f"--seed does not apply to {named}: it draws nothing at random (the seed is the random, "
                       "cpsat, sos and tabu solvers' and their plans', a re-planning plan's (--replan), and the "
                       "noise's; a guided ppo model's plan search takes --guide-seed)")
    if a.solver.lower().startswith(DECISION_SOLVERS):
        if a.decisions == "paper" and scenario is not None and not scenario.empty:  # (solve() said decisions='full')
            raise CliError("--scenario and --noise run on the full-decision net only: drop --decisions paper")
        opts["decisions"] = a.decisions or "full"
    elif a.decisions:
        raise CliError(f"--decisions applies to the first, random and rule: solvers, not {named} "
                       "(rules:paper runs the paper net's rule pairs; a ppo model decides through the net it was "
                       "trained on)" + ("; name one of them with --solver" if defaulted else ""))
    if a.replan is not None:
        if not a.solver.lower().startswith("plan:"):
            raise CliError("--replan applies to the plan: solvers only" + (
                f", not {named}: --solver plan:list re-plans the list schedule's plan" if defaulted else ""))
        if not 0 < a.replan < math.inf:
            raise CliError(f"--replan must be positive and finite (seconds per re-plan), got {a.replan:g}")
        opts["replan"] = a.replan
    if a.lookahead or a.lookahead_fast or a.lookahead_guide:
        if a.lookahead + a.lookahead_fast + a.lookahead_guide > 1:
            raise CliError("give one of --lookahead, --lookahead-fast and --lookahead-guide")
        if not a.solver.lower().startswith("ppo"):
            raise CliError("--lookahead, --lookahead-fast and --lookahead-guide apply to the ppo solver only")
        if "+" in a.solver:
            raise CliError(f"{a.solver} chooses its lookahead in its name; give no --lookahead flag with it")
        opts["lookahead"] = "guide" if a.lookahead_guide else "fast" if a.lookahead_fast else True
    try:
        effort = guide_effort_from_args(a)
    except ValueError as e:
        raise CliError(str(e)) from None
    if effort is not None:
        if not a.solver.lower().startswith("ppo"):
            raise CliError(f"the plan search options ({GUIDE_OPTIONS}) apply to the ppo solver only")
        opts["guide_effort"] = effort
    moot = moot_choice(a.solver, inst, effort)
    if moot:
        raise CliError(moot)
    if a.guide_replan is not None:
        if not a.solver.lower().startswith("ppo"):
            raise CliError("--[no-]guide-replan applies to the ppo solver only")
        opts["guide_replan"] = a.guide_replan
    if a.guide_beside is not None:
        if not a.solver.lower().startswith("ppo"):
            raise CliError("--[no-]guide-beside applies to the ppo solver only")
        opts["guide_beside"] = a.guide_beside
    if not a.quiet:
        print(f"{inst.describe()}; solver {a.solver}", file=sys.stderr)
        opts["progress"] = True
    from .exact import SearchInterrupted

    try:
        sched = solve(inst, a.solver, **opts)
        interrupted = False
    except SearchInterrupted as exc:  # Ctrl-C in a cpsat, tabu, sos or rules search: its best schedule so far is kept
        if a.solver.lower() not in ("cpsat", "tabu", "sos") and not a.solver.lower().startswith("rules"):
            raise
        sched, interrupted = exc.best, True
    problems = validate(inst, sched)
    if problems:  # a solver bug: never hand out an infeasible schedule silently
        print(f"fms: internal error: the {a.solver} schedule is infeasible: {problems[0]}", file=sys.stderr)
        return EXIT_INFEASIBLE
    extra = replans_summary(sched.meta.get("replans")) + search_summary(sched)
    # a PPO run names the model and lookahead it ran ("ppo --lookahead" ran ppo:guided-dagger+lookahead)
    ran = str(sched.meta.get("solver", ""))
    shown = ran if a.solver.lower().startswith("ppo") and ran.lower().startswith("ppo") else a.solver
    print(f"{inst.name}: makespan {sched.makespan} ({shown}, {sched.meta.get('wall_time', 0):.3f} s{extra}, valid)")
    hint = plan_hint(sched, scenario)
    if hint and not a.quiet:
        print(f"{inst.name}: {hint}", file=sys.stderr)
    _write_outputs(sched, inst, a.out, a.gantt, a.instance)
    if interrupted:
        kept = [str(p) for p in (a.out, a.gantt) if p]
        print(f"fms: interrupted: the search stopped early; its best schedule so far is above"
              f"{' and in ' + ' and '.join(kept) if kept else ''}", file=sys.stderr)
        return 130
    return 0


def plan_hint(sched: Schedule, scenario: Scenario | None) -> str | None:
    """What to tell the user when a guided model's nominal run without the plan's empty trips ended later than the
    plan it acted out (``meta["guide_plan_makespan"]``): that plan, and the option that makes those trips. None
    otherwise (a disrupted run's plan in force is a forecast, not a makespan the run could have reached)."""
    m = sched.meta
    planned = m.get("guide_plan_makespan")
    if planned is None or sched.makespan <= planned or (scenario is not None and not scenario.empty):
        return None
    if str(m.get("solver", "")).endswith("+lookahead-guide"):
        return None
    return (f"the model's plan ends at {planned}; --lookahead-guide sends idle vehicles on the plan's empty trips, "
            "which a plain run leaves out")


def scenario_from_args(a: argparse.Namespace, inst: Instance) -> Scenario | None:
    """The disruptions of ``--scenario FILE`` and ``--noise SPREAD`` (seeded by ``--seed``), checked against the
    instance; None for an undisrupted run."""
    from fms_sim.disruptions import MAX_NOISE, Scenario

    path = getattr(a, "scenario", None)
    if path is not None and not path.strip():
        raise CliError("--scenario names no file (an empty name); leave it out for an undisrupted run")
    scenario = Scenario.load(path) if path else None
    noise = getattr(a, "noise", None)
    seed = getattr(a, "seed", None)
    if noise is not None:
        if not 0 <= noise <= MAX_NOISE:
            raise CliError(f"--noise must be a spread from 0 to {MAX_NOISE:g}, got {noise!r}")  # (:g said 1.0000001 was 1)
        base = scenario or Scenario()
        if seed is None and base.noise and base.seed:  # replaced as the help says, but no longer silently
            print(f"note: --noise replaces the noise of {path} and its seed {base.seed} (now 0; --seed N chooses "
                  "one)", file=sys.stderr)
        scenario = Scenario(base.breakdowns, base.outages, noise, seed if seed is not None else 0)
    elif seed is not None and scenario is not None and scenario.noise:  # the file's seed was silently kept
        scenario = Scenario(scenario.breakdowns, scenario.outages, scenario.noise, seed)
    if scenario is not None:
        scenario.check(inst)
    return scenario


def check_output(path: str | None, what: str) -> None:
    """Refuse an output file that cannot be written, before any work (:func:`fms_sim.files.output_problem`)."""
    if path:
        problem = output_problem(path)
        if problem is not None:
            raise CliError(f"{what} {path}{'' if problem.startswith('is a folder') else ':'} {problem}")


def check_folder(folder: Path, what: str, path: str) -> None:
    """Refuse ``folder`` if this user may not write it (:func:`fms_sim.files.folder_problem`); ``what path`` names
    the option in the message."""
    problem = folder_problem(folder)
    if problem is not None:
        raise CliError(f"{what} {path}: {problem}")


def check_outputs(a: argparse.Namespace, *inputs: str | None) -> None:
    """:func:`check_output` for ``--out`` and ``--gantt``, and refuse an empty name (it was silently ignored), the
    two naming one file (the chart overwrote the schedule), an output that is one of the ``inputs`` (``fms
    solve shop.json --out shop.json`` overwrote the instance) or a chart name whose suffix names no format a chart
    is written in (it was written as a PNG, over a ``.json`` file too)."""
    named = {}
    for flag, path in (("--out", a.out), ("--gantt", a.gantt)):
        if path is not None and not path.strip():
            raise CliError(f"{flag} names no file (an empty name); leave it out to write nothing")
        check_output(path, flag)
        if path:
            named[flag] = Path(path).resolve()
    if len(named) == 2 and named["--out"] == named["--gantt"]:
        raise CliError(f"--out and --gantt name the same file {a.out}; the chart would overwrite the schedule")
    for flag, where in named.items():
        for src in inputs:
            if src and Path(src).is_file() and Path(src).resolve() == where:
                raise CliError(f"{flag} {src} is an input of this command; name another file")
    if a.gantt:  # any other name was written as a PNG: over a .json schedule, or as g.txt
        from fms_sim.gantt import chart_formats

        fmt = Path(a.gantt).suffix[1:].lower()
        if fmt not in chart_formats():
            raise CliError(f"--gantt {a.gantt}: name the chart's format by its suffix, one of "
                           f"{', '.join('.' + f for f in chart_formats())}")


def _write_outputs(sched: Schedule, inst: Instance, out: str | None, gantt: str | None,
                   source: str | None = None) -> None:
    """Save the schedule JSON and the Gantt chart where asked, one line each. The schedule goes first: a chart
    that cannot be written (a failure :func:`check_output` could not foresee) does not cost the solve's result,
    and the error says it was kept. A final instance an earlier ``fms up`` run with orders left beside ``out`` is
    removed (:func:`fms_sim.files.drop_instance_beside`; not ``source``, the instance file solved)."""
    if out:
        try:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
            sched.save(out)
        except OSError as exc:
            raise CliError(f"cannot write --out {out}: {exc.strerror or exc}") from None
        print(f"schedule: {out}")
        with contextlib.suppress(OSError):
            stale = drop_instance_beside(out, sched.instance, source)  # an fms up run's with orders: fms validate
            if stale is not None:
                print(f"note: removed {stale}, an earlier run's instance beside the schedule this run replaced",
                      file=sys.stderr)
    if gantt:
        from fms_sim.gantt import save_gantt

        try:
            written = save_gantt(sched, gantt, instance=inst)
        except OSError as exc:
            kept = f" (the schedule was saved to {out})" if out else ""
            raise CliError(f"cannot write --gantt {gantt}: {exc.strerror or exc}{kept}") from None
        print(f"gantt:    {written}")


def _load_schedule(path: str) -> Schedule:
    try:
        return Schedule.load(path)
    except OSError as exc:
        raise CliError(f"cannot read schedule {path}: {exc.strerror}") from None


def _instance_of(a: argparse.Namespace, sched: Schedule) -> tuple[str, int | None]:
    """The instance (and ra layout) a schedule given alone (``fms validate SCHEDULE``) was made for: the final
    instance a run with live orders writes beside it (:func:`fms_sim.files.instance_beside`; one of another name is
    not this run's and is passed over), else the built-in or held-out shop it names (``ra01L3``: ra01 in layout
    3)."""
    import re

    from fms_sim.benchmarks import is_builtin_name
    from fms_sim.formats import load_instance

    beside = instance_beside(a.schedule)
    if beside.is_file():
        try:
            if load_instance(str(beside)).name == sched.instance:
                return str(beside), None
        except (InstanceError, ValueError, OSError):
            pass  # not this run's final instance: the name decides
    m = re.fullmatch(r"(ra\d\d)L([1-4])", sched.instance)
    name, layout = (m.group(1), int(m.group(2))) if m else (sched.instance, None)
    if is_builtin_name(name):
        if Path(name).is_file():  # fms_sim.formats.load_instance would read that file instead
            raise CliError(f"a file named {name} in the working folder hides the built-in shop {sched.instance} that "
                           f"{a.schedule} was made for: run from another folder, or give the instance")
        return name, layout
    raise CliError(f"{a.schedule} was made for instance {sched.instance!r}, which is no built-in shop and has no "
                   f"{beside.name} of it beside it: give the instance, fms validate INSTANCE {a.schedule}")


def cmd_validate(a: argparse.Namespace) -> int:
    from fms_sim.benchmarks import is_builtin_name
    from fms_sim.disruptions import ScenarioError
    from fms_sim.validate import recorded_scenario, validate

    alone = a.schedule is None  # fms validate SCHEDULE: against the shop the schedule was made for
    sched = None
    if alone:
        if not Path(a.instance).exists() and is_builtin_name(a.instance):  # the schedule forgotten
            raise CliError(f"give the schedule file too: fms validate {a.instance} SCHEDULE")
        a.schedule = a.instance
        sched = _load_schedule(a.schedule)
        a.instance, layout = _instance_of(a, sched)
        if a.layout is None:
            a.layout = layout
    inst = load_from_args(a)
    if sched is None:  # (read after the instance: a bad instance is named first)
        sched = _load_schedule(a.schedule)
    fleet: dict[str, Any] = {}
    if alone and not (a.agvs is not None or a.tool_transporters is not None or a.no_tools or a.no_agvs):
        # the shop it was made for has the fleet it records (fms solve EX12 --agvs 3 was called infeasible); only
        # what it records: a schedule without its fleet sizes reads as having none, and one that never moved a part
        # passed against the shop without AGVs
        fleet = fleet_of(inst, sched, recorded=_top_keys(a.schedule))
        if fleet:
            for k, v in fleet.items():
                setattr(a, k, v)
            inst = load_from_args(a)
    scenario = scenario_from_args(a, inst)
    if scenario is None:  # a malformed recorded one is a file that is not what it claims: bad input, not infeasible
        try:
            scenario = recorded_scenario(sched)
        except ScenarioError as exc:
            raise CliError(f"{a.schedule}: {exc}") from None
    if sched.instance != inst.name:
        print(f"note: the schedule names instance {sched.instance!r}, checking against {inst.name!r}", file=sys.stderr)
    elif alone:
        print(f"note: checking against {a.instance}" + (f" (layout {a.layout})" if a.layout is not None else "")
              + (f" with {_options_text(fleet)}" if fleet else "") + ", the instance the schedule was made for",
              file=sys.stderr)
    problems = validate(inst, sched, scenario)
    code = EXIT_INFEASIBLE if problems else 0
    try:
        if problems:
            print(f"INVALID: {len(problems)} violation(s)")
            for p in problems:
                print(f"  - {p}")
            hint = fleet_hint(inst, sched)
            if hint:
                print(hint, file=sys.stderr)
        else:
            print(f"valid: {inst.name}, makespan {sched.makespan}")
        sys.stdout.flush()
    except BrokenPipeError:  # `fms validate ... | head`: the reader left, the verdict stands (it exited 0)
        send_nowhere(sys.stdout)
    return code


def _top_keys(path: str) -> set[str]:
    """The top-level keys of the JSON object in file ``path`` (empty where it cannot be read as one)."""
    from fms_sim.files import loads, read_text

    try:
        data = loads(read_text(path))
    except (OSError, ValueError):
        return set()
    return set(data) if isinstance(data, dict) else set()


def fleet_of(inst: Instance, sched: Schedule, recorded: set[str] | None = None) -> dict[str, Any]:
    """The instance options (``argparse`` destinations and values: ``agvs``, ``no_agvs``, ``tool_transporters``,
    ``no_tools``) that give ``inst`` the fleet ``sched`` was made for, as ``fms solve --agvs 3`` (or ``--no-agvs``,
    ``--tool-transporters``, ``--no-tools``) makes one; empty if the fleets agree or the schedule is another shop's
    (no option of this one makes it fit). With ``recorded`` (the keys its file has), only the fleet sizes it
    records."""
    if sched.instance != inst.name:
        return {}
    opts: dict[str, Any] = {}
    if recorded is not None:
        if "n_agvs" not in recorded:
            sched = replace(sched, n_agvs=inst.n_agvs)
        if "n_tool_transporters" not in recorded:
            sched = replace(sched, n_tool_transporters=inst.n_tool_transporters)
    # (only fleets an option can give: a schedule declaring -1 or 10**12 AGVs got "solved with --agvs -1?")
    if sched.n_agvs != inst.n_agvs:
        if not sched.n_agvs:
            opts["no_agvs"] = True
        elif inst.has_agvs and 1 <= sched.n_agvs <= MAX_COUNT:
            opts["agvs"] = sched.n_agvs
    if sched.n_tool_transporters != inst.n_tool_transporters:
        if not sched.n_tool_transporters:
            opts["no_tools"] = True
        elif inst.has_tools and 1 <= sched.n_tool_transporters <= MAX_COUNT:
            opts["tool_transporters"] = sched.n_tool_transporters
    return opts


def _options_text(opts: dict[str, Any]) -> str:
    """:func:`fleet_of`'s options as they are written on the command line."""
    return " ".join(f"--{k.replace('_', '-')}" + ("" if v is True else f" {v}") for k, v in opts.items())


def fleet_hint(inst: Instance, sched: Schedule) -> str | None:
    """A hint for a schedule made for another fleet than ``inst``'s (:func:`fleet_of`): the options that give the
    instance the schedule's fleet (None if the fleets agree). Checked without them, it breaks the fleet rules and a
    run of others after them."""
    opts = fleet_of(inst, sched)
    if not opts:
        return None
    return (f"hint: the schedule was made for another fleet than {inst.name}'s; if it was solved with "
            f"{_options_text(opts)}, give the same here")


def cmd_replay(a: argparse.Namespace) -> int:
    from fms_sim.replay import ReplayError, replay

    check_outputs(a, a.instance, a.schedule)
    inst = load_from_args(a)
    given = _load_schedule(a.schedule)
    if given.instance != inst.name:  # (as fms validate says it: ten "lasts 2, travel time is 4" lines hid it)
        print(f"note: the schedule names instance {given.instance!r}, replaying it in {inst.name!r}", file=sys.stderr)
    if given.meta.get("scenario"):  # the orders are replayed; the disruptions they answered are not
        print("note: the schedule was made in a disrupted shop (meta.scenario); the replay runs the nominal shop, "
              "so its times differ and it may end later", file=sys.stderr)
    if given.meta.get("arrivals"):
        print("note: the schedule's run took live orders (meta.arrivals); the replay has every job from time 0, so "
              "the ordered jobs may start before their orders came", file=sys.stderr)
    try:
        out = replay(inst, given)
    except ReplayError as exc:
        if exc.violations:  # the validator's first findings, one per line; nothing is written
            print(f"fms: error: {a.schedule} is not a valid schedule for {inst.name} "
                  f"({len(exc.violations)} violation(s)):", file=sys.stderr)
            for v in exc.violations[:10]:
                print(f"  - {v}", file=sys.stderr)
            hint = fleet_hint(inst, given)
            if hint:
                print(hint, file=sys.stderr)
            return EXIT_BAD_INPUT
        raise
    print(f"{inst.name}: replayed makespan {out.makespan} (given {given.makespan}), valid")
    _write_outputs(out, inst, a.out, a.gantt, a.instance)
    return 0


def cmd_generate(a: argparse.Namespace) -> int:
    from fms_sim import generate as g

    if Path(a.prefix).name != a.prefix or a.prefix in ("", ".", ".."):
        raise CliError(f"--prefix {a.prefix!r} must be a plain name (the files go into --out-dir)")
    if not a.out_dir.strip():  # it wrote into the current folder
        raise CliError("--out-dir names no folder (an empty name); give one, e.g. --out-dir .")
    out = Path(a.out_dir)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out-dir {a.out_dir} is a file, not a folder")
    check_folder(out, "--out-dir", a.out_dir)  # it failed at the first file, naming a temporary
    if a.no_tools and (a.tools is not None or a.tool_transporters is not None):
        raise CliError("--tools/--tool-transporters and --no-tools contradict each other")
    if a.no_agvs and a.agvs is not None:
        raise CliError("--agvs and --no-agvs contradict each other")
    from fms_sim.instance import MAX_COUNT

    for flag, v, top in (("--jobs", a.jobs, MAX_COUNT), ("--machines", a.machines, MAX_COUNT),
                         ("--count", a.count, 10**6), ("--tools", a.tools, MAX_COUNT), ("--agvs", a.agvs, MAX_COUNT),
                         ("--tool-transporters", a.tool_transporters, MAX_COUNT)):
        if v is not None and not 1 <= v <= top:  # named by its flag, not the library's name (the same bounds)
            raise CliError(f"{flag} must be >= 1 and at most {top}, got {v}")
    last_seed = g.TaillardRNG.M - 1
    for flag, v in (("--time-seed", a.time_seed), ("--route-seed", a.route_seed), ("--tool-seed", a.tool_seed),
                    ("--agv-seed", a.agv_seed), ("--tool-travel-seed", a.tool_travel_seed)):
        if not 0 < v <= last_seed:  # checked whether used or not: --no-agvs took a bad --agv-seed, --no-tools not
            raise CliError(f"{flag} must be a Taillard seed in 1..{last_seed}, got {v}")
    insts = g.generate_instances(
        a.jobs, a.machines, a.machines if a.tools is None else a.tools, a.count, time_seed=a.time_seed,
        route_seed=a.route_seed, tool_seed=a.tool_seed, agv_seed=a.agv_seed, tool_travel_seed=a.tool_travel_seed,
        n_agvs=10 if a.agvs is None else a.agvs, n_tool_transporters=5 if a.tool_transporters is None
        else a.tool_transporters, tools=not a.no_tools, agvs=not a.no_agvs, name_prefix=a.prefix)
    from fms_sim.benchmarks import is_builtin_name

    shadow = next((inst.name for inst in insts if is_builtin_name(inst.name)), None)
    if shadow is not None:  # `fms validate sl00 file.json` then checked against the built-in sl00
        raise CliError(f"--prefix {a.prefix!r} names the files like built-in instances ({shadow}); choose another "
                       "prefix")
    for inst in insts:  # every target before the first file: a folder in the way left a partial set
        if (out / f"{inst.name}.json").is_dir():
            raise CliError(f"{out / (inst.name + '.json')} is a folder; nothing was written")
    out.mkdir(parents=True, exist_ok=True)
    for inst in insts:
        path = out / f"{inst.name}.json"
        inst.save(path)
        print(f"{path}: {inst.describe()}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fms", description="FMS intralogistics dispatcher (AGVs, shared tools, CTPN).")
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("instances", help="list the built-in instance names (benchmarks, then the held-out shops)")
    s.add_argument("--details", action="store_true", help="print sizes and fleets too")
    s.set_defaults(fn=cmd_instances)

    s = sub.add_parser("solve", help="solve an instance, write the schedule and a Gantt chart")
    add_instance_args(s)
    s.add_argument("--solver", default=None,
                   help="first | random | rule:<JOB>[+<first|least-work|nearest>[+<fifo|same-machine-first|"
                        "nearest|earliest-start>]] (defaults first, fifo) | list[:ect|:<JOB>] | rules[:full|:paper] | sos | tabu | cpsat | "
                        f"plan:<SOLVER>[:SECONDS] | plan:file:PATH | ppo[:MODEL] (default: {DEFAULT_SOLVER}, the "
                        f"earliest-start list schedule; with --scenario or --noise {DEFAULT_DISRUPTED_SOLVER}, its "
                        "plan executed under the disruptions)")
    s.add_argument("--decisions", choices=("full", "paper"),
                   help="the net that first, random and rule: decide through: full (default; every valid "
                        "schedule reachable) or paper (the paper's FIFO-tool, ready-only net)")
    s.add_argument("--lookahead", action="store_true", help="ppo: pre-position idle vehicles (digital-twin lookahead)")
    s.add_argument("--lookahead-fast", action="store_true",
                   help="ppo: the lookahead without retrying rejected moves (several times faster on 50-100 "
                        "jobs, still minutes on 100; other schedules; never worse than plain ppo either)")
    s.add_argument("--lookahead-guide", action="store_true",
                   help="ppo with a guided model: idle vehicles make the guide plan's empty trips (no trial runs; "
                        "fast on any size, not verified)")
    add_guide_args(s)
    s.add_argument("--guide-beside", action=argparse.BooleanOptionalAction, default=None,
                   help="ppo with a guided model: on large shops with a second CPU, search the plan on it while the "
                        "run goes on with the search's first plan (default: yes); --no-guide-beside searches first "
                        "(the schedule is the same where the search gets the same CPU time; choose it while another "
                        "job keeps the second CPU busy)")
    s.add_argument("--time-limit", type=float, metavar="SECONDS",
                   help="time limit of cpsat, sos, tabu, plan:SOLVER and rules (which then stops trying "
                        "combinations; defaults: cpsat 60, sos 10, tabu 10, rules none: every combination, a plan: "
                        "solver its solver's); refused for the solvers that run once. It bounds the search: on shops of "
                        "thousands of operations the start schedules built before it, and a plan: solver's run "
                        "through the net after it, take seconds more")
    s.add_argument("--seed", type=int, default=None, help="seed (>= 0) of the random, cpsat, sos and tabu solvers, "
                   "of their plans (plan:cpsat, ...) and of a plan's re-plans (--replan) (default 0), and of the "
                   "noise (--noise, or the --scenario file's: this seed replaces the file's)")
    s.add_argument("--scenario", metavar="FILE", help="disruptions (fms/scenario/v1 JSON: machine breakdowns, "
                   "vehicles out of service, noise); first, random, rule: (full net), plan: and full-net ppo models")
    s.add_argument("--noise", type=float, metavar="SPREAD", help="lognormal noise on every processing and travel "
                   "time (sigma from 0 to 1, e.g. 0.1), seeded by --seed; with --scenario it replaces the file's "
                   "noise and its seed (--seed, default 0)")
    s.add_argument("--replan", type=float, metavar="SECONDS", help="plan: solvers: re-plan within SECONDS when the "
                   "disrupted shop departs from the plan (breakdown, outage, lateness); default: keep the plan")
    s.add_argument("--out", help="write the schedule JSON here")
    s.add_argument("--gantt", help="write a Gantt chart here, in the format its suffix names (.png, .pdf, .svg, "
                   "or another matplotlib writes)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    s.set_defaults(fn=cmd_solve)

    s = sub.add_parser("validate", help="check a schedule file against an instance (exit 1 if infeasible)",
                       description="Check a schedule against an instance: fms validate INSTANCE SCHEDULE, or fms "
                                   "validate SCHEDULE for the instance it was made for (OUT.instance.json beside "
                                   "OUT.json, which a run with live orders writes, else the built-in instance the "
                                   "schedule names, with the fleet it records).")
    add_instance_args(s)
    s.add_argument("schedule", nargs="?", help="schedule JSON file")
    s.add_argument("--scenario", metavar="FILE", help="the disruptions of the run (default: the scenario the "
                   "schedule records, if any)")
    s.set_defaults(fn=cmd_validate)

    s = sub.add_parser("replay", help="run a valid schedule's orders through the full-decision net (exit 2 if the "
                                      "schedule is not valid for the instance)")
    add_instance_args(s)
    s.add_argument("schedule", help="schedule JSON file (any valid schedule: cpsat, another tool, a person)")
    s.add_argument("--out", help="write the replayed schedule JSON here")
    s.add_argument("--gantt", help="write a Gantt chart of the replayed schedule here, in the format its suffix "
                                   "names (.png, .pdf, .svg, or another matplotlib writes)")
    s.set_defaults(fn=cmd_replay)

    s = sub.add_parser("generate", help="write random instances with Taillard's LCG family",
                       description="Write random instances with Taillard's LCG family: each stream (times, routes, "
                                   "tools, travel) starts at its seed and continues from one instance to the next; "
                                   "with the default seeds, --jobs 15 --machines 15 --count 10 writes the large "
                                   "benchmark's group 0 (sl00-sl09).")
    s.add_argument("--jobs", type=int, required=True, help="jobs per instance")
    s.add_argument("--machines", type=int, required=True, help="machines (each job visits every machine once)")
    s.add_argument("--tools", type=int, default=None, help="number of tools (default: = machines)")
    s.add_argument("--count", type=int, default=1, help="instances to write (default 1)")
    s.add_argument("--agvs", type=int, default=None, help="AGVs (default 10, the large benchmark's fleet)")
    s.add_argument("--tool-transporters", type=int, default=None,
                   help="tool transporters (default 5, the large benchmark's fleet)")
    s.add_argument("--no-tools", action="store_true", help="no tools (AGVs only)")
    s.add_argument("--no-agvs", action="store_true", help="no AGVs (parts move instantly)")
    from fms_sim import generate as g

    for flag, default, what in (("--time-seed", g.TIME_SEED, "processing times"),
                                ("--route-seed", g.ROUTE_SEED, "the machine order of each job"),
                                ("--tool-seed", g.TOOL_SEED, "each operation's tool"),
                                ("--agv-seed", g.AGV_SEED, "the AGV travel times"),
                                ("--tool-travel-seed", g.TOOL_TRAVEL_SEED, "the tool transporters' travel times")):
        s.add_argument(flag, type=int, default=default, metavar="SEED",
                       help=f"seed of {what} (default {default})")
    s.add_argument("--prefix", default="gen", help="instance name prefix (names: PREFIX00, PREFIX01, ...)")
    s.add_argument("--out-dir", default="instances", help="folder for the JSON files (default: instances; files "
                   "of the same names are replaced)")
    s.set_defaults(fn=cmd_generate)

    from .benchmark import add_bench_parser
    from .experiments import add_experiment_parser
    from .rl import add_train_parser
    from .send import add_send_parser
    from .up import add_up_parser

    add_bench_parser(sub)
    add_up_parser(sub)
    add_send_parser(sub)
    add_train_parser(sub)
    add_experiment_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    stops = None
    try:
        from .up import _TermAsInterrupt  # (in the try: Ctrl-C while it loads was a traceback)

        # SIGTERM (kill, a supervisor) and SIGHUP stop every command as Ctrl-C does: temporary files removed, workers
        # stopped, "interrupted" (they ended it without a word, leaving hidden temporaries and a bench's workers
        # behind)
        stops = _TermAsInterrupt()
        parser = build_parser()
        a, extra = parser.parse_known_args(argv)  # (an interrupt while the parser's modules load was a traceback)
        if extra and getattr(a, "fn", None) is cmd_validate and a.schedule is None and len(extra) == 1 \
                and not extra[0].startswith("-"):
            a.schedule = extra[0]  # `fms validate EX12 --agvs 3 s.json`: argparse gives an optional positional no
            # place after an option (the same order is taken by fms replay, whose schedule is required)
        elif extra:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        with surviving_streams():  # a reader that left (| head) does not end the command half-way (its files not
            return a.fn(a)  # written, exit 0), nor Python's flush at exit after a complete run (exit 120)
    except (CliError, InstanceError, ScheduleError, ValueError) as exc:  # ScenarioError is a ValueError
        # one line, but all of it: a message of several lines (a list of offending specs) is joined, not cut
        msg = " ".join(line.strip() for line in str(exc).splitlines()) or type(exc).__name__
        print(f"fms: error: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("fms: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `fms bench bu | head`: the reader left; not an error of ours
        send_nowhere(sys.stdout)
        return 0
    except OSError as exc:  # a file that cannot be written or read (a folder where a file was named, no rights)
        where = f": {exc.filename}" if exc.filename else ""
        print(f"fms: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        if stops is not None:
            stops.restore()


if __name__ == "__main__":
    sys.exit(main())
