"""``solve()``: every solver by name, with the options it passes on checked."""

import pytest

from fms_dispatch.solvers import SOLVE_OPTIONS, solve, solver_names
from fms_sim.benchmarks import builtin
from fms_sim.validate import validate


def test_a_misspelt_option_is_refused_not_ignored():
    inst = builtin("EX12")
    with pytest.raises(TypeError, match="unknown solve\\(\\) option 'time_limt'"):
        solve(inst, "first", time_limt=3)
    with pytest.raises(TypeError, match="unknown solve\\(\\) option 'lookahed'"):
        solve(inst, "ppo", lookahed=True)
    s = solve(inst, "random", seed=3, time_limit=1, progress=False)  # known options a solver does not use: fine
    assert validate(inst, s) == [] and {"seed", "time_limit", "guide_effort"} <= set(SOLVE_OPTIONS)


def test_rules_stop_trying_combinations_at_the_time_limit():
    inst = builtin("sl00")
    cut = solve(inst, "rules", time_limit=0.01)
    assert cut.meta["tried"] == 1 < cut.meta["combinations"] and validate(inst, cut) == []
    whole = solve(builtin("EX12"), "rules")
    assert whole.meta["tried"] == whole.meta["combinations"]
    with pytest.raises(ValueError, match="time limit must be positive"):
        solve(inst, "rules", time_limit=0)


def test_solver_names_list_the_lookahead_suffixes():
    assert any("+lookahead-guide" in n for n in solver_names()) and "plan:file:PATH" in solver_names()
