"""Plan solvers: solve offline within a budget, then execute the plan through the full-decision net."""

import pytest

from fms_dispatch.cli import main
from fms_dispatch.solvers import UnknownSolver, parse_plan_name, solve
from fms_sim import Schedule
from fms_sim.benchmarks import builtin
from fms_sim.validate import validate


def test_plan_names():
    assert parse_plan_name("plan:cpsat:10") == ("cpsat", 10.0)
    assert parse_plan_name("plan:sos:2.5") == ("sos", 2.5)
    assert parse_plan_name("plan:rules") == ("rules", None)
    assert parse_plan_name("plan:rule:MTWR+nearest") == ("rule:MTWR+nearest", None)
    for bad in ("plan:", "plan:ppo", "plan:ppo:bu", "plan:first", "plan:cpsat:0", "plan:cpsat:-3", "plan:bogus",
                "plan:plan:cpsat"):
        with pytest.raises(UnknownSolver):
            parse_plan_name(bad)


@pytest.mark.parametrize("name", ["plan:cpsat:5", "plan:sos:1", "plan:rules", "plan:list"])
def test_executed_plans_are_valid_and_never_later_than_the_plan(name):
    inst = builtin("ra02")
    s = solve(inst, name)
    assert validate(inst, s) == []
    assert s.meta["solver"] == name and s.makespan <= s.meta["plan_makespan"]


def test_cpsat_plan_of_a_small_shop_executes_at_the_optimum():
    inst = builtin("EX12")
    s = solve(inst, "plan:cpsat:10")
    assert validate(inst, s) == []
    assert s.makespan == inst.meta["optimal_makespan"] == 82


def test_cli_plan_solver(tmp_path, capsys):
    out = tmp_path / "p.json"
    assert main(["solve", "EX21", "--solver", "plan:cpsat", "--time-limit", "5", "--out", str(out), "-q"]) == 0
    s = Schedule.load(out)
    assert validate(builtin("EX21"), s) == [] and s.meta["plan_solver"] == "cpsat"
    capsys.readouterr()
    assert main(["solve", "EX21", "--solver", "plan:ppo", "-q"]) == 2
    assert "bad plan solver" in capsys.readouterr().err


def test_a_plan_names_budget_and_a_time_limit_are_not_both_taken():
    inst = builtin("EX12")
    with pytest.raises(ValueError, match=r"plan:rules:0.5 gives its plan's budget \(0.5 s\); a time limit of 1 s "
                                         "would be ignored: give one of the two"):
        solve(inst, "plan:rules:0.5", time_limit=1.0)
    assert validate(inst, solve(inst, "plan:rules:0.5", time_limit=0.5)) == []  # the same: taken
