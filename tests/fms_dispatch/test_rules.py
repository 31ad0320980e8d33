"""Dispatching rules: every pair yields valid schedules; each rule picks what its definition says."""

import pytest

from fms_dispatch.rules import JOB_RULES, RulePolicy, all_rule_pairs, parse_rule_name, solve_rule
from fms_sim import Instance, validate
from fms_sim.benchmarks import builtin
from fms_sim.shop import Shop

INSTANCES = {
    "EX12": builtin("EX12"), "ra01": builtin("ra01"), "ta01": builtin("ta01"),
    "sl00": builtin("sl00"), "sl00-agvs": builtin("sl00").without_tools(),
}


@pytest.mark.parametrize("name", INSTANCES)
def test_every_rule_pair_is_valid(name):
    inst = INSTANCES[name]
    pairs = all_rule_pairs(include_nearest=True)
    assert len(pairs) == 36
    for pair in pairs:
        p = parse_rule_name(pair)
        s = solve_rule(inst, p.job_rule, p.vehicle_rule)
        assert validate(inst, s) == [], (name, pair)
        assert s.meta["solver"] == pair


# three jobs at L/U: totals 9, 9, 4; next durations 5, 1, 4; op counts 2, 3, 1
JOBS = [[(1, 5), (2, 4)], [(2, 1), (1, 4), (2, 4)], [(1, 4)]]
T = [[0, 1, 1], [1, 0, 1], [1, 1, 0]]


@pytest.mark.parametrize("rule, expected", [
    ("FIFO", 0), ("SPS", 2), ("LPS", 1), ("SPTN", 1), ("LPTN", 0), ("MTWR", 0), ("LTWR", 2),
    ("LWT", 0), ("SPT", 2), ("LPT", 0), ("SPSR", 2), ("LPSR", 1),
])
def test_job_rule_choice(rule, expected):
    shop = Shop(Instance("r", JOBS, agv_travel=T, n_agvs=1))
    assert RulePolicy(rule)(shop) == expected


def test_the_twelve_job_rules_of_the_paper():
    assert set(JOB_RULES) == {"FIFO", "SPS", "LPS", "SPTN", "LPTN", "MTWR", "LTWR", "LWT", "SPT", "LPT",
                              "SPSR", "LPSR"}


def test_vehicle_rules():
    # AGV travel: from L/U everything is 1, from M1 to L/U 9. Two AGVs: send AGV0 to M1 first.
    T2 = [[0, 1, 1], [9, 0, 1], [1, 1, 0]]
    inst = Instance("v", [[(1, 1)], [(2, 9)], [(2, 1)]], agv_travel=T2, n_agvs=2)
    shop = Shop(inst)
    shop.act(0)
    shop.act(shop.action_index("agv:0"))          # AGV0: 0->1 (work 1), idle at M1 from t=1
    shop.act(1)
    shop.act(shop.action_index("agv:1"))          # AGV1: 0->2, idle at M2 from t=1
    # t=1: both idle; job 2 waits at L/U. AGV0 at M1 (9 to L/U), AGV1 at M2 (1 to L/U)
    assert shop.now == 1
    shop.act(2)
    assert RulePolicy("FIFO", "nearest")(shop) == shop.action_index("agv:1")
    assert RulePolicy("FIFO", "first")(shop) == shop.action_index("agv:0")     # both free since 1: lowest
    assert RulePolicy("FIFO", "least-work")(shop) == shop.action_index("agv:0")  # equal work: lowest index


def test_bad_rule_names():
    with pytest.raises(ValueError, match="unknown job rule"):
        RulePolicy("XYZ")
    with pytest.raises(ValueError, match="unknown vehicle rule"):
        parse_rule_name("rule:FIFO+teleport")
    assert parse_rule_name("mtwr").name == "rule:MTWR+first"
    # fms up's agent node was told "unknown vehicle rule 'nearest+fifo'" of a full-net rule with a tool rule
    with pytest.raises(ValueError, match="a tool rule .its third part, 'fifo'. is read only by the full-decision"):
        parse_rule_name("rule:MTWR+nearest+fifo")
