"""fms_dispatch: dispatching rules, list schedules, the SOS metaheuristic, tabu search, the exact CP-SAT model,
plans and re-planning, the RL agent and its lookahead.

Every method shares one signature, ``solver(instance, **options) -> Schedule``, selected by name through
:func:`solve` / :func:`get_solver` (``"first"``, ``"random"``, ``"rule:<JOB>+<vehicle>[+<tool>]"``, ``"list"``,
``"rules"``, ``"sos"``, ``"tabu"``, ``"cpsat"``, ``"plan:cpsat:10"``, ``"ppo"``, ...; all of them:
:mod:`fms_dispatch.solvers`). Heavy dependencies (OR-Tools, torch) load only when their solver is used.
"""

from typing import TYPE_CHECKING

from .full_rules import TOOL_RULES, FullRulePolicy, full_rule_names, run_full, solve_best_rules, solve_list
from .rules import JOB_RULES, VEHICLE_RULES, RulePolicy, all_rule_pairs, parse_rule_name, solve_rule
from .solvers import UnknownSolver, get_solver, solve, solver_names
from .tabu import solve_tabu, tabu_plan

# these load OR-Tools (the function replan stays in fms_dispatch.replan: the module has its name)
_LAZY = {"Replanner": "replan", "solve_with_replanning": "replan"}
if TYPE_CHECKING:  # their types for a type checker (at run time module __getattr__ below imports them)
    from .replan import Replanner, solve_with_replanning

__all__ = [
    "solve", "get_solver", "solver_names", "UnknownSolver", "Replanner", "solve_with_replanning",
    "RulePolicy", "JOB_RULES", "VEHICLE_RULES", "all_rule_pairs", "parse_rule_name", "solve_rule",
    "FullRulePolicy", "TOOL_RULES", "full_rule_names", "run_full", "solve_list", "solve_best_rules",
    "tabu_plan", "solve_tabu",
]


def __getattr__(name: str) -> object:
    """The re-planning API, imported on first use (it loads OR-Tools)."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
