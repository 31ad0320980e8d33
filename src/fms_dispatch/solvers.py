"""One solver signature for every method: ``solver(instance, **options) -> Schedule``, selected by name.

Names: ``first`` (baseline: always the lowest enabled action), ``random`` (uniform among legal actions,
seeded), ``rule:<JOB>[+<first|least-work|nearest>[+<TOOL>]]`` (see :mod:`fms_dispatch.rules`; a tool rule only
on the full net, :mod:`fms_dispatch.full_rules`) — these three take ``decisions="paper"`` (the default here,
which the shipped models and the benchmarks' rule pairs use) or ``"full"`` (the default of ``fms solve``) —,
``list[:ect|:<JOB>]`` (a list schedule executed through the full net), ``rules`` / ``rules:full`` (the best
full-net rule combination or list schedule), ``rules:paper`` (the best of the paper net's 36 rule pairs),
``plan:<SOLVER>[:SECONDS]`` (solve offline within SECONDS, then execute the plan through the full net),
``sos`` (symbiotic
organisms search), ``tabu`` (tabu search over the list schedule's resource orders), ``cpsat`` (exact model) and ``ppo[:MODEL]`` (a shipped or trained MaskablePPO policy;
option ``lookahead=True`` pre-positions idle vehicles, ``lookahead="fast"`` does it without retries), each
honouring ``time_limit`` where it searches. Every schedule leaves here with ``meta["solver"]`` and
``meta["wall_time"]`` filled in.
"""

from __future__ import annotations

import math
import numbers
import random
import time
from typing import Any, Callable

from fms_sim.instance import Instance, require_instance
from fms_sim.schedule import Schedule
from fms_sim.shop import run_policy

from .progress import say
from .rules import parse_rule_name

__all__ = ["solve", "get_solver", "solver_names", "UnknownSolver"]

Solver = Callable[..., Schedule]


class UnknownSolver(ValueError):
    pass


def _run(instance: Instance, choose: Callable[[Any], int], decisions: str, scenario: Any = None) -> Schedule:
    """Run ``choose`` through the paper's net or the full-decision one (:data:`fms_sim.full_shop.DECISIONS`),
    in a shop disrupted by ``scenario`` (full net only)."""
    if decisions == "paper":
        if scenario is not None:
            raise UnknownSolver("disruptions (--scenario, --noise) run on the full-decision net only "
                                "(decisions='full')")
        return run_policy(instance, choose)
    if decisions == "full":
        from .full_rules import run_full

        return run_full(instance, choose, scenario)
    raise UnknownSolver(f"unknown decisions {decisions!r}; choose from full, paper")


def _first(instance: Instance, decisions: str = "paper", scenario: Any = None, **_: Any) -> Schedule:
    # legal_actions()[0], without listing every legal action at each decision (quadratic on thousands of jobs)
    return _run(instance, lambda shop: shop.first_legal_action(), decisions, scenario)


def _random(instance: Instance, seed: int = 0, decisions: str = "paper", scenario: Any = None,
            **_: Any) -> Schedule:
    rng = random.Random(seed)
    return _run(instance, lambda shop: rng.choice(shop.legal_actions()), decisions, scenario)


def _rule(name: str) -> Solver:
    """``rule:JOB+VEHICLE[+TOOL]``: through the paper's net (two parts only) or the full one."""
    from .full_rules import parse_full_rule

    try:
        full = parse_full_rule(name)
        paper = parse_rule_name(name) if name.count("+") < 2 else None
    except ValueError as exc:
        raise UnknownSolver(str(exc)) from None

    def solver(instance: Instance, decisions: str = "paper", scenario: Any = None, **_: Any) -> Schedule:
        if decisions == "paper" and paper is None:
            raise UnknownSolver(f"{name!r} names a tool rule, which only the full-decision net has "
                                "(decisions='full')")
        s = _run(instance, paper if decisions == "paper" else full, decisions, scenario)
        s.meta["solver"] = name
        return s

    return solver


#: solvers that decide through a net chosen by the ``decisions`` option
DECISION_SOLVERS = ("first", "random", "rule:")


def _sos(instance: Instance, **kw: Any) -> Schedule:
    from .sos import solve_sos

    return solve_sos(instance, **kw)


def _cpsat(instance: Instance, time_limit: float | None = None, workers: int = 2, progress: bool = False,
           seed: int | None = 0, **_: Any) -> Schedule:
    from .exact import cpsat

    kw: dict[str, Any] = {"workers": workers, "seed": seed or 0}  # (it was dropped: every run used 0; None: 0)
    if time_limit is not None:
        kw["time_limit"] = time_limit
    if progress:
        kw["progress"] = lambda obj, bound, secs: say(f"  cpsat: makespan {obj}, bound {bound}, {secs:.1f} s")
    return cpsat(instance, **kw)


#: solver-name suffixes of the PPO lookahead, each with the ``lookahead`` option it stands for (offline solvers
#: here, the agent node in :mod:`fms_dispatch.agent_logic`, and the names that schedules carry)
LOOKAHEAD_SUFFIXES: dict[str, bool | str] = {"+lookahead": True, "+lookahead-fast": "fast",
                                             "+lookahead-guide": "guide"}


def lookahead_suffix(mode: bool | str) -> str:
    """The solver-name suffix of a ``lookahead`` option: ``""`` for False, ``"+lookahead"`` for True,
    ``"+lookahead-fast"`` for ``"fast"``, ``"+lookahead-guide"`` for ``"guide"``; raises ValueError for anything
    else."""
    for suffix, m in {"": False, **LOOKAHEAD_SUFFIXES}.items():
        if mode == m and type(mode) is type(m):
            return suffix
    raise ValueError(f"lookahead must be False, True, 'fast' or 'guide', got {mode!r}")


def solver_names() -> list[str]:
    return ["first", "random", "rule:<JOB>[+<first|least-work|nearest>[+<TOOL>]]", "list[:ect|:<JOB>]",
            "rules[:full|:paper]", "sos", "tabu", "cpsat", "plan:<SOLVER>[:SECONDS]", "plan:file:PATH",
            "ppo[:MODEL][+lookahead|+lookahead-fast|+lookahead-guide]"]


def get_solver(name: str) -> Solver:
    """The solver function for a name; raises :class:`UnknownSolver` with the list of names."""
    if not isinstance(name, str):
        raise UnknownSolver(f"a solver is named by a string, got {type(name).__name__} {name!r:.60}")
    low = name.lower()
    if low == "first":
        return _first
    if low == "random":
        return _random
    if low.startswith("rule:"):
        return _rule(name)
    if low == "list" or low.startswith("list:"):
        from .full_rules import LIST_ORDERS, solve_list

        head, colon, order = name.partition(":")
        if colon and not order.strip():  # 'list:' ran as list, while 'rule:' and 'plan:' were refused
            raise UnknownSolver(f"{name!r} names no list order; use list, list:ect or list:<JOB RULE>")
        order = order or "est"
        if order.lower() not in ("est", "ect") and order.upper() not in LIST_ORDERS:
            raise UnknownSolver(f"unknown list order in {name!r}; use list, list:ect or list:<JOB RULE>")
        return lambda inst, **kw: solve_list(inst, order)
    if low.startswith("plan:"):
        return plan_solver(name)
    if low in ("rules", "rules:full", "rules:paper"):
        from .full_rules import solve_best_rules

        net = "paper" if low == "rules:paper" else "full"
        return lambda inst, **kw: solve_best_rules(inst, **{**kw, "decisions": net})
    if low == "sos":
        return _sos
    if low == "tabu":
        from .tabu import solve_tabu

        return solve_tabu
    if low == "cpsat":
        return _cpsat
    if low == "ppo" or low.startswith(("ppo:", "ppo+")):
        from .rl import ppo_solver

        base, plus, flag = name.partition("+")
        mode = LOOKAHEAD_SUFFIXES.get(plus + flag.lower())
        if plus and mode is None:
            raise UnknownSolver(f"unknown ppo option {flag!r} in {name!r} (only +lookahead, +lookahead-fast or "
                                "+lookahead-guide)")
        try:
            fn = ppo_solver(base)
        except ValueError as exc:
            raise UnknownSolver(str(exc)) from None
        if plus:  # "ppo[:MODEL]+lookahead[-fast|-guide]": names for benches, as the lookahead option
            def with_lookahead(inst: Instance, **kw: Any) -> Schedule:
                if kw.get("lookahead") not in (None, mode):  # another lookahead (or none: False): refused, not dropped
                    raise ValueError(f"{name} chooses its lookahead ({plus}{flag}); another one "
                                     f"({kw['lookahead']!r}) cannot be given with it")
                return fn(inst, **{**kw, "lookahead": mode})

            return with_lookahead
        return fn
    head, colon, tail = low.partition(":")
    if colon and head in ("cpsat", "sos", "tabu", "rules") and _is_seconds(tail):
        # a limit in the name works for plan: solvers only
        raise UnknownSolver(f"unknown solver {name!r}: give {head}'s time limit as --time-limit {tail} "
                            f"(time_limit=...); only plan:{head}:SECONDS takes it in its name")
    if colon and head == "rules":  # (a misspelt variant was told to be a time limit: --time-limit ful)
        raise UnknownSolver(f"unknown solver {name!r}: the rules solver's variants are rules:full (the default) and "
                            "rules:paper")
    if low == "best":  # (shown in the README with fms up, which picks it: fms solve listed every name instead)
        raise UnknownSolver("best is fms up's choice of the best agent for a shop; fms solve takes the solver itself "
                            f"(e.g. rules, plan:rules, ppo); choose from {', '.join(solver_names())}")
    raise UnknownSolver(f"unknown solver {name!r}; choose from {', '.join(solver_names())}")


def _is_seconds(text: str) -> bool:
    """Whether ``text`` reads as a number of seconds (``cpsat:10``, a limit given in the wrong place)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def parse_plan_name(name: str) -> tuple[str, float | None]:
    """``plan:BASE[:SECONDS]`` -> (base solver name, seconds or None); ``plan:file:PATH`` -> ("file:PATH",
    None). Raises :class:`UnknownSolver`."""
    body = name.split(":", 1)[1] if name.lower().startswith("plan:") else ""
    if body.lower().startswith("file:"):
        path = body[5:]
        if not path:
            raise UnknownSolver(f"bad plan solver {name!r}: plan:file:PATH names a schedule file")
        return body, None
    base, seconds = body, None
    head, sep, tail = body.rpartition(":")
    if sep and head:
        try:
            seconds = float(tail)
        except ValueError:
            pass
        else:
            base = head
            if not 0 < seconds < math.inf:
                raise UnknownSolver(f"the time budget of {name!r} must be a positive, finite number of seconds")
    if not base or base.lower().startswith(("plan:", "ppo")) or base.lower() in ("first", "random"):
        raise UnknownSolver(f"bad plan solver {name!r}: use plan:SOLVER[:SECONDS] with an offline solver "
                            "(cpsat, sos, rules, list, rule:...) or plan:file:PATH")
    try:
        get_solver(base)
    except UnknownSolver:
        if seconds is None and sep and head:  # plan:cpsat:abc: a known solver and a budget that is no number
            try:
                get_solver(head)
            except UnknownSolver:
                pass
            else:
                raise UnknownSolver(f"bad plan solver {name!r}: {tail!r} is not a time budget in seconds") from None
        raise
    if seconds is not None and not takes_time_limit(base):  # it was accepted and ignored
        raise UnknownSolver(f"bad plan solver {name!r}: {base} runs once, without a search; drop ':{tail}'")
    return base, seconds


def make_plan(instance: Instance, base: str, seconds: float | None = None, **options: Any) -> Schedule:
    """The plan of a ``plan:`` solver: ``base`` solved on the nominal instance within ``seconds`` (its time
    limit), or the schedule in ``file:PATH`` (refused with the validator's first errors if it is not valid for
    the instance)."""
    if base.lower().startswith("file:"):
        from fms_sim.schedule import Schedule as _Schedule
        from fms_sim.validate import validate

        path = base[5:]
        try:
            plan = _Schedule.load(path)
        except OSError as exc:
            raise UnknownSolver(f"cannot read plan {path}: {exc.strerror}") from None
        problems = validate(instance, plan)
        if problems:
            raise UnknownSolver(f"plan {path} is not valid for {instance.name}: {problems[0]}"
                                + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else ""))
        return plan
    opts = {k: v for k, v in options.items() if k not in ("decisions", "scenario")}
    if base.lower().startswith("rule:"):  # planned through the full net, as fms solve --solver rule:... runs it: one
        opts["decisions"] = "full"        # rule, one plan (the library's default, the paper's net, planned another
        # run where the rule named no tool rule, and a tool rule only the full net has)
    if seconds is not None and takes_time_limit(base):  # rules too: plan:rules:2 searched for 18 s
        opts["time_limit"] = seconds
    return solve(instance, base, **opts)


def plan_solver(name: str) -> Solver:
    """``plan:BASE[:SECONDS]``: solve the whole instance with BASE within SECONDS (its ``time_limit``), then
    execute that plan through the full-decision net (:func:`fms_sim.replay.replay`): the schedule a shop gets
    when it follows the plan, never later than the plan. ``plan:file:PATH`` executes the schedule in a file.

    Option ``replan`` (seconds, default None: off): re-plan within that budget when the (disrupted) shop departs
    from the plan (:mod:`fms_dispatch.replan`; ``drift`` sets the lateness that triggers it); the events are in
    ``meta["replans"]``."""
    base, seconds = parse_plan_name(name)

    def solver(instance: Instance, time_limit: float | None = None, scenario: Any = None,
               replan: float | None = None, drift: float | None = None, **kw: Any) -> Schedule:
        from fms_sim.replay import replay

        if seconds is not None and time_limit is not None and time_limit != seconds:
            raise ValueError(f"{name} gives its plan's budget ({seconds:g} s); a time limit of {time_limit:g} s "
                             "would be ignored: give one of the two")
        budget = seconds if seconds is not None else time_limit
        plan = make_plan(instance, base, budget, **kw)  # on the nominal shop: disruptions are not known ahead
        if replan is not None:
            from .replan import DEFAULT_DRIFT, solve_with_replanning

            if not replan > 0:
                raise ValueError(f"the re-planning budget must be positive, got {replan}")
            out = solve_with_replanning(instance, plan, budget=replan, scenario=scenario,
                                        drift=drift if drift is not None else DEFAULT_DRIFT,
                                        seed=int(kw.get("seed", 0) or 0))
        else:
            out = replay(instance, plan, scenario=scenario)
        out.meta.update(solver=name, plan_solver=base, plan_makespan=plan.makespan,
                        plan_wall_time=plan.meta.get("wall_time"), lower_bound=plan.meta.get("lower_bound"))
        return out

    return solver


def searches_time(method: str) -> bool:
    """Whether a solver takes a time limit (everything but rules, list, first and random)."""
    low = method.lower()
    return not (low.startswith(("rule:", "rules", "list")) or low in ("first", "random"))


def takes_time_limit(method: str) -> bool:
    """Whether a time limit means something to a solver: a search (:func:`searches_time`), ``rules`` (it stops
    trying combinations), or a ``plan:`` of one of those (not ``plan:file:``, nor ``plan:list``)."""
    low = method.lower()
    if low.startswith("plan:"):
        base = parse_plan_name(method)[0].lower()
        return not base.startswith("file:") and takes_time_limit(base)
    return low.startswith("rules") or (searches_time(low) and not low.startswith("ppo"))


def takes_seed(method: str) -> bool:
    """Whether a seed means something to a solver: ``random``, the searches ``cpsat``, ``sos`` and ``tabu``, and the
    ``plan:`` solvers (their searches and re-plans). The others draw nothing at random (a seed still seeds a noisy
    shop's noise)."""
    low = method.lower()
    return low in ("random", "cpsat", "sos", "tabu") or low.startswith("plan:")


#: solvers that can run in a disrupted shop (option ``scenario``): online deciders on the full net (rules,
#: full-net PPO models), and plans executed without re-planning
DISRUPTABLE = ("first", "random", "rule:", "plan:", "ppo")


#: the options :func:`solve` passes on (every solver takes them all and uses its own, see each solver; those that
#: change what only some solvers do are refused for the others: :data:`OPTION_SOLVERS`)
SOLVE_OPTIONS = ("seed", "time_limit", "progress", "scenario", "decisions", "workers", "population", "iterations",
                 "initial", "config", "lookahead", "guide_effort", "guide_replan", "guide_beside", "replan", "drift")


def check_options(options: dict[str, Any]) -> dict[str, Any]:
    """``options`` with the ones every solver shares checked (TypeError, ValueError: one message, before any solver
    runs; each solver reads only its own, so a ``time_limit="3"`` or a scenario given as a file name would otherwise
    fail deep inside one solver and be ignored by another) and numpy numbers made Python ones."""
    from fms_sim.disruptions import Scenario

    def number(v: Any) -> bool:
        return isinstance(v, numbers.Real) and not isinstance(v, bool)

    unknown = sorted(set(options) - set(SOLVE_OPTIONS))
    if unknown:
        raise TypeError(f"unknown solve() option {unknown[0]!r}; the options are {', '.join(SOLVE_OPTIONS)}")
    limit = options.get("time_limit")
    if limit is not None and not number(limit):
        raise TypeError(f"time_limit must be a number of seconds or None, got {limit!r}")
    if limit is not None and not 0 < limit < math.inf:
        raise ValueError(f"time_limit must be a positive, finite number of seconds, got {limit!r}")
    seed = options.get("seed")
    if seed is not None and (not isinstance(seed, numbers.Integral) or isinstance(seed, bool)):
        raise TypeError(f"seed must be an integer, got {seed!r}")
    scenario = options.get("scenario")
    if scenario is not None and not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be a fms_sim.disruptions.Scenario (Scenario.load(path) reads a file), "
                        f"got {type(scenario).__name__}")
    decisions = options.get("decisions")
    if decisions is not None and decisions not in ("full", "paper"):
        raise UnknownSolver(f"unknown decisions {decisions!r}; choose from full, paper")
    for name, what in (("replan", "the re-planning budget, seconds"), ("drift", "a fraction of the plan's makespan")):
        v = options.get(name)  # replan=inf ran a search with no deadline: it never ended
        if v is not None and not number(v):
            raise TypeError(f"{name} must be a number ({what}) or None, got {v!r}")
        if v is not None and not 0 < v < math.inf:
            raise ValueError(f"{name} must be a positive, finite number ({what}), got {v!r}")
    for name in ("progress", "guide_replan", "guide_beside"):
        if name in options and not isinstance(options[name], bool):
            raise TypeError(f"{name} must be True or False, got {options[name]!r}")
    out = dict(options)
    if seed is not None:
        out["seed"] = int(seed)
    if limit is not None:
        out["time_limit"] = float(limit) if not isinstance(limit, int) else limit
    return out


#: options that change what only some solvers do: the solvers (name prefixes) that read each, and who they are in
#: words. Given to another solver (not None; ``lookahead`` also not False) :func:`solve` refuses them, where they were
#: taken and ignored (a ``replan`` given to a rule ran without re-planning and said nothing)
OPTION_SOLVERS: dict[str, tuple[tuple[str, ...], str]] = {
    "replan": (("plan:",), "the plan: solvers"),
    "drift": (("plan:",), "the plan: solvers, with replan"),
    "lookahead": (("ppo",), "the ppo solvers"),
    "guide_effort": (("ppo",), "the ppo solvers (a guided model)"),
    "guide_replan": (("ppo",), "the ppo solvers (a guided model)"),
    "guide_beside": (("ppo",), "the ppo solvers (a guided model)"),
    "decisions": (DECISION_SOLVERS, "first, random and the rule: solvers"),
    **{name: (("sos", "plan:sos"), "sos and plan:sos") for name in ("population", "iterations", "config", "initial")},
}


def check_applicable(solver: str, options: dict[str, Any]) -> None:
    """Raise ValueError for an option of :data:`OPTION_SOLVERS` given to a solver that does not read it (and for a
    ``drift`` without ``replan``: it sets when a re-plan starts)."""
    low = solver.lower()
    for name, (readers, who) in OPTION_SOLVERS.items():
        v = options.get(name)
        if v is None or (name == "lookahead" and v is False):
            continue
        if not low.startswith(readers) or (name == "drift" and options.get("replan") is None):
            raise ValueError(f"{solver} does not take option {name}={v!r}: it would be ignored (it is read by {who})")


def solve(instance: Instance, solver: str = "first", **options: Any) -> Schedule:
    """Solve ``instance`` with the named solver; options (``time_limit``, ``seed``, ...) pass through. The default
    stays ``first`` through the paper's net (the benches and models rely on it); ``fms solve`` without ``--solver``
    runs ``list`` (``plan:list`` in a disrupted run) instead.
    ``scenario`` (a :class:`fms_sim.disruptions.Scenario`) disrupts the run of the solvers in
    :data:`DISRUPTABLE`; the others refuse it. An option not in :data:`SOLVE_OPTIONS` (a misspelt
    ``time_limt``) raises TypeError instead of being ignored, the shared options are checked
    (:func:`check_options`), and one that only other solvers read (``replan`` for a rule, ``lookahead`` for ``list``:
    :data:`OPTION_SOLVERS`) raises ValueError. The first ``ppo`` solve of a process freezes its heap, so that
    garbage collection does not pause decisions (``fms_dispatch.rl.models.FREEZE_HEAP``: data alive then in
    reference cycles stays in memory; set it False before, in a program that frees such data later)."""
    options = check_options(options)
    fn = get_solver(solver)
    check_applicable(solver, options)
    require_instance(instance, "solve")
    scenario = options.get("scenario")
    if scenario is not None and scenario.empty:
        options = {k: v for k, v in options.items() if k != "scenario"}
    elif scenario is not None:
        if not solver.lower().startswith(DISRUPTABLE):
            raise UnknownSolver(f"{solver} does not run in a disrupted shop; use first, random, rule: (full net), "
                                "ppo (the default model) or another full-net model (ppo:full, ppo:guided-ppo), or "
                                "plan:SOLVER (its plan executed under the disruptions)")
        scenario.check(instance)
    t0 = time.perf_counter()
    s = fn(instance, **options)
    s.meta.setdefault("solver", solver)
    s.meta["wall_time"] = round(time.perf_counter() - t0, 4)
    return s
