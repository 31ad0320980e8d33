"""Issue 'Baselines' done-when: every rule pair, SOS and CP-SAT give validated schedules on every EXx2 and on
sl00 with and without tools (CP-SAT's EXx2 optima are asserted in test_exact.py)."""

import pytest

from fms_dispatch.exact import cpsat
from fms_dispatch.rules import all_rule_pairs, parse_rule_name, solve_rule
from fms_dispatch.sos import solve_sos
from fms_sim import validate
from fms_sim.benchmarks import builtin

EXX2 = [f"EX{s}2" for s in range(1, 11)]


@pytest.mark.parametrize("name", EXX2)
def test_rules_and_sos_on_every_exx2(name):
    inst = builtin(name)
    best = None
    for pair in all_rule_pairs(include_nearest=True):
        p = parse_rule_name(pair)
        s = solve_rule(inst, p.job_rule, p.vehicle_rule)
        assert validate(inst, s) == [], pair
        assert s.makespan >= inst.meta["optimal_makespan"]
        best = s.makespan if best is None else min(best, s.makespan)
    s = solve_sos(inst, iterations=2, population=4, seed=1)
    assert validate(inst, s) == []
    assert inst.meta["optimal_makespan"] <= s.makespan <= best


@pytest.mark.parametrize("tools", [True, False])
def test_cpsat_on_sl00_gives_schedule_and_bound(tools):
    inst = builtin("sl00") if tools else builtin("sl00").without_tools()
    s = cpsat(inst, time_limit=5, workers=2)
    assert validate(inst, s) == []
    assert s.makespan >= 1231          # sl00's machines and times are ta01's (optimum 1231 as a job shop)
    assert 0 < s.meta["lower_bound"] <= s.makespan
    assert s.meta["status"] in ("FEASIBLE", "OPTIMAL")
    sos = solve_sos(inst, iterations=1, population=2, seed=0)
    assert validate(inst, sos) == []
