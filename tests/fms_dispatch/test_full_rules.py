"""Rules on the full-decision net, the list policy through it, and the best-of-rules solver."""

import pytest

from fms_dispatch.cli import main
from fms_dispatch.full_rules import TOOL_RULES, FullRulePolicy, full_rule_names, parse_full_rule, run_full
from fms_dispatch.solvers import UnknownSolver, solve
from fms_sim import Schedule
from fms_sim.benchmarks import builtin
from fms_sim.validate import validate


@pytest.mark.parametrize("tool_rule", TOOL_RULES)
@pytest.mark.parametrize("name", ["ra01", "ra12L3", "sl00"])
def test_every_tool_rule_gives_valid_schedules(name, tool_rule):
    for inst in (builtin(name), builtin(name).without_agvs()):
        s = run_full(inst, parse_full_rule(f"MTWR+nearest+{tool_rule}"))
        assert validate(inst, s) == []


def test_tool_rules_decide_differently():
    inst = builtin("sl30")
    spans = {t: run_full(inst, FullRulePolicy("MTWR", "nearest", t)).makespan for t in TOOL_RULES}
    assert len(set(spans.values())) > 1, spans


def test_list_policy_through_the_net_is_the_list_schedule():
    from fms_dispatch.exact import greedy_schedule
    from fms_dispatch.full_rules import _static_priority

    for name in ("EX12", "ra05", "sl00"):
        inst = builtin(name)
        s = solve(inst, "list")
        assert validate(inst, s) == [] and s.makespan <= greedy_schedule(inst, rule="est").makespan
        s = solve(inst, "list:ect")
        assert validate(inst, s) == [] and s.makespan <= greedy_schedule(inst, rule="ect").makespan
        s = solve(inst, "list:mtwr")
        guided = greedy_schedule(inst, rule="guided", priority=_static_priority(inst, "MTWR"))
        assert validate(inst, s) == [] and s.makespan <= guided.makespan and s.meta["solver"] == "list:MTWR"
    with pytest.raises(UnknownSolver, match="list order"):
        solve(builtin("EX12"), "list:fastest")


def test_rules_is_the_best_of_every_combination():
    inst = builtin("ra03")
    best = solve(inst, "rules")
    assert validate(inst, best) == []
    from fms_dispatch.full_rules import list_names

    names = full_rule_names(inst)
    lists = list_names()
    assert len(names) == 12 * 3 * 4 and len(lists) == 14 and best.meta["combinations"] == len(names) + len(lists)
    spans = [run_full(inst, parse_full_rule(n)).makespan for n in names] + [solve(inst, n).makespan for n in lists]
    assert best.makespan == min(spans)
    assert best.meta["rule"] in names + lists
    assert len(full_rule_names(builtin("EX12"))) == 12 * 3  # no tools: the tool rule does not act


def test_rule_names_and_decisions():
    inst = builtin("ra01")
    paper = solve(inst, "rule:MTWR+nearest")
    full = solve(inst, "rule:MTWR+nearest", decisions="full")
    assert validate(inst, paper) == [] and validate(inst, full) == []
    with pytest.raises(UnknownSolver, match="tool rule"):
        solve(inst, "rule:MTWR+nearest+fifo")  # the paper's net has no tool choice
    with pytest.raises(UnknownSolver, match="unknown decisions"):
        solve(inst, "first", decisions="fifo")
    with pytest.raises(UnknownSolver):
        solve(inst, "rule:MTWR+nearest+closest", decisions="full")


def test_cli_decisions(tmp_path, capsys):
    out = tmp_path / "s.json"
    assert main(["solve", "ra01", "--solver", "rule:MTWR+nearest+same-machine-first", "--out", str(out), "-q"]) == 0
    assert validate(builtin("ra01"), Schedule.load(out)) == []
    assert main(["solve", "ra01", "--solver", "rule:MTWR+nearest", "--decisions", "paper", "-q"]) == 0
    capsys.readouterr()
    assert main(["solve", "ra01", "--solver", "cpsat", "--decisions", "full", "-q"]) == 2
    assert "--decisions applies to" in capsys.readouterr().err


def test_best_of_names_for_each_net():
    from fms_dispatch.benchmark import searches
    from fms_dispatch.rules import all_rule_pairs, parse_rule_name
    from fms_sim.shop import run_policy

    inst = builtin("EX21")
    paper = solve(inst, "rules:paper")
    assert paper.meta["combinations"] == 36 and paper.meta["decisions"] == "paper"
    assert paper.makespan == min(run_policy(inst, parse_rule_name(n)).makespan
                                 for n in all_rule_pairs(include_nearest=True))
    assert solve(inst, "rules:full").makespan == solve(inst, "rules").makespan
    assert not any(searches(m) for m in ("rules", "rules:full", "rules:paper", "list"))
