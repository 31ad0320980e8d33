"""Symbiotic organisms search: feasibility, seeding, determinism, improvement and argument checks."""

from __future__ import annotations

import time

import numpy as np
import pytest

from fms_dispatch.rules import parse_rule_name, solve_rule
from fms_dispatch.solvers import solve
from fms_dispatch.sos import (DEFAULT_SEED_RULES, KeyDecoder, SOSConfig, TimeUp, _vehicle, keys_from_policy,
                              solve_sos)
from fms_sim.benchmarks import builtin
from fms_sim.instance import Instance, Operation
from fms_sim.validate import validate

FEW_SEEDS = ["rule:SPTN+nearest", "rule:MTWR+first"]


def _rule_makespans(inst, names):
    out = {}
    for name in names:
        p = parse_rule_name(name)
        s = solve_rule(inst, p.job_rule, p.vehicle_rule)
        assert validate(inst, s) == []
        out[name] = s.makespan
    return out


def _valid(inst, sched):
    assert validate(inst, sched) == []
    assert sched.makespan == max(o.end for o in sched.operations)
    assert len(sched.operations) == inst.n_operations
    return sched


# ---------------------------------------------------------------- decoder
def test_decoder_layout():
    assert KeyDecoder(builtin("EX12")).dim == 2 * 13            # priority + AGV keys
    assert KeyDecoder(builtin("ra01")).dim == 3 * 13            # + transporter keys
    assert KeyDecoder(builtin("ta01")).dim == 225               # plain job shop: priorities only
    dec = KeyDecoder(builtin("ra01"))
    assert (dec.agv_base, dec.tt_base) == (13, 26)
    with pytest.raises(ValueError, match="shape"):
        dec.decode(np.zeros(5))
    with pytest.raises(TimeUp):
        dec.decode(np.zeros(dec.dim), deadline=time.perf_counter() - 1.0)
    with pytest.raises(TimeUp):
        keys_from_policy(dec, parse_rule_name("FIFO+first"), deadline=time.perf_counter() - 1.0)


@pytest.mark.parametrize("name", ["EX12", "ra01", "ta01"])
def test_rule_keys_decode_to_the_rule_schedule(name):
    inst = builtin(name)
    dec = KeyDecoder(inst)
    for rule in ["rule:FIFO+first", "rule:MTWR+nearest", "rule:LPT+least-work", "rule:SPTN+first"]:
        p = parse_rule_name(rule)
        keys, shop = keys_from_policy(dec, p)
        ref = solve_rule(inst, p.job_rule, p.vehicle_rule)
        again = dec.decode(keys).schedule()
        assert shop.makespan == again.makespan == ref.makespan
        assert sorted(again.operations, key=lambda o: (o.job, o.op)) == sorted(ref.operations,
                                                                               key=lambda o: (o.job, o.op))
        assert sorted(again.agv_trips, key=lambda t: (t.agv, t.start)) == sorted(ref.agv_trips,
                                                                                key=lambda t: (t.agv, t.start))
        _valid(inst, again)


def test_random_keys_always_decode_to_feasible_schedules():
    rng = np.random.default_rng(7)
    for name in ["EX12", "ra01"]:
        inst = builtin(name)
        dec = KeyDecoder(inst)
        for _ in range(10):
            _valid(inst, dec.decode(rng.random(dec.dim)).schedule())
        # extreme keys (all 0, all 1) decode too: ties go to the lowest job, keys of 1 clip to the last vehicle
        _valid(inst, dec.decode(np.zeros(dec.dim)).schedule())
        _valid(inst, dec.decode(np.ones(dec.dim)).schedule())


def test_vehicle_choice_keyed_then_least_travel():
    travel = ((0, 5, 9), (5, 0, 3), (9, 3, 0))
    loc = [0, 2, 1, 2]
    assert _vehicle(0.30, 4, [0, 1, 3], loc, travel, 1) == 1      # key -> index 1, legal
    assert _vehicle(0.99, 4, [0, 1, 2], loc, travel, 1) == 2      # key -> 3 not legal; vehicle 2 is at the pickup
    assert _vehicle(0.00, 4, [1, 3], loc, travel, 1) == 1         # 1 and 3 tie on travel (3); 1 is nearer to 0
    assert _vehicle(1.00, 4, [3], loc, travel, 0) == 3            # key 1.0 clips to the last vehicle


# ---------------------------------------------------------------- feasibility
@pytest.mark.parametrize("name,kw", [
    ("EX12", dict(iterations=3, population=6)),
    ("ra01", dict(iterations=3, population=6)),
    ("ta01", dict(iterations=1, population=4, initial=FEW_SEEDS)),
])
def test_valid_schedules_small(name, kw):
    inst = builtin(name)
    s = _valid(inst, solve_sos(inst, time_limit=None, seed=3, **kw))
    assert s.meta["solver"] == "sos"
    assert s.meta["iterations"] == kw["iterations"]
    assert s.meta["stopped"] == "iterations"
    assert s.meta["seed"] == 3


@pytest.mark.parametrize("tools", [True, False])
def test_valid_schedules_sl00(tools):
    inst = builtin("sl00")
    if not tools:
        inst = inst.without_tools()
    s = _valid(inst, solve_sos(inst, time_limit=None, iterations=2, population=4, initial=FEW_SEEDS))
    assert s.n_agvs == 10
    assert s.n_tool_transporters == (5 if tools else 0)
    assert (len(s.tool_trips) > 0) == tools
    # 2 seeds + 2 random organisms, then 2 iterations x 4 organisms x 4 evaluations
    assert s.meta["evaluations"] == 2 + 2 + 2 * 4 * 4
    assert s.makespan <= min(_rule_makespans(inst, FEW_SEEDS).values())


# ---------------------------------------------------------------- seeding
@pytest.mark.parametrize("name", ["EX12", "ra01"])
def test_never_worse_than_the_seed_rules(name):
    inst = builtin(name)
    rules = _rule_makespans(inst, DEFAULT_SEED_RULES)
    s = _valid(inst, solve_sos(inst, time_limit=None, iterations=0, population=4))
    assert s.makespan == min(rules.values())          # no iteration: exactly the best seed
    assert s.meta["best_seed"] == [min(rules, key=lambda r: (rules[r], DEFAULT_SEED_RULES.index(r))),
                                   min(rules.values())]
    assert s.meta["evaluations"] == len(DEFAULT_SEED_RULES) + 2
    s = _valid(inst, solve_sos(inst, time_limit=None, iterations=2, population=6, seed=5))
    assert s.makespan <= min(rules.values())


def test_explicit_initial_seeds():
    inst = builtin("EX12")
    s = _valid(inst, solve_sos(inst, time_limit=None, iterations=0, population=2,
                               initial=["rule:FIFO+first", "first"]))
    assert s.makespan == min(solve_rule(inst, "FIFO", "first").makespan, solve(inst, "first").makespan)
    assert s.meta["evaluations"] == 2 + 1                # both seeds run; the best fills half the population


# ---------------------------------------------------------------- determinism, improvement
def test_deterministic_for_seed_and_iterations():
    inst = builtin("ra01")
    a = solve_sos(inst, time_limit=None, iterations=3, population=6, seed=11)
    b = solve_sos(inst, time_limit=None, iterations=3, population=6, seed=11)
    assert a.makespan == b.makespan
    assert a.operations == b.operations
    assert a.meta["best_makespan_history"] == b.meta["best_makespan_history"]
    runs = {seed: solve_sos(inst, time_limit=None, iterations=3, population=6, seed=seed, initial=FEW_SEEDS)
            for seed in range(4)}
    for s in runs.values():
        _valid(inst, s)
    # different seeds explore differently (their improvement histories differ), though makespans may tie
    assert len({str(s.meta["best_makespan_history"]) for s in runs.values()}) > 1


def test_improves_on_ex12():
    inst = builtin("EX12")
    rules = _rule_makespans(inst, DEFAULT_SEED_RULES)
    fifo = solve_rule(inst, "FIFO", "first").makespan
    # 36 seeds + 5 random organisms + 4 iterations x 10 organisms x 4 evaluations = 201 evaluations
    s = _valid(inst, solve_sos(inst, time_limit=None, iterations=4, population=10, seed=0))
    assert s.meta["evaluations"] == 36 + 5 + 4 * 10 * 4
    assert s.makespan <= min(rules.values())
    assert s.makespan < fifo
    assert s.makespan < min(rules.values())          # strictly better than every rule pair
    hist = s.meta["best_makespan_history"]
    assert hist[-1][1] == s.makespan
    assert [m for _, m in hist] == sorted((m for _, m in hist), reverse=True)


# ---------------------------------------------------------------- budget, progress, registry
def test_time_limit_is_honoured():
    inst = builtin("ta01")
    t0 = time.perf_counter()
    s = solve_sos(inst, time_limit=0.5, population=20)
    assert time.perf_counter() - t0 < 2.0
    assert s.meta["stopped"] == "time_limit"
    _valid(inst, s)
    # a larger instance: the decode running at the deadline is abandoned, the first one always completes
    inst = builtin("sl00")
    t0 = time.perf_counter()
    s = solve_sos(inst, time_limit=0.05)
    assert time.perf_counter() - t0 < 1.0
    assert s.meta["stopped"] == "time_limit"
    assert s.meta["evaluations"] >= 1 and s.meta["iterations"] == 0
    _valid(inst, s)


def test_progress_lines_on_stderr(capsys):
    inst = builtin("EX12")
    solve_sos(inst, time_limit=None, iterations=1, population=4, progress=True, initial=["rule:FIFO+first"])
    err = capsys.readouterr().err
    fifo = solve_rule(inst, "FIFO", "first").makespan  # the one seed organism's makespan
    assert f"sos: iteration 0, evaluations 1, best makespan {fifo}" in err
    solve_sos(inst, time_limit=None, iterations=1, population=4, initial=["rule:FIFO+first"])
    assert capsys.readouterr().err == ""


def test_through_the_solver_registry_ignores_unknown_options():
    inst = builtin("EX12")
    s = solve(inst, "sos", iterations=1, population=4, seed=2, workers=3, progress=False, time_limit=5)
    _valid(inst, s)
    assert s.meta["solver"] == "sos" and "wall_time" in s.meta


# ---------------------------------------------------------------- bad parameters
@pytest.mark.parametrize("kw,msg", [
    (dict(population=1), "population must be an integer >= 2"),
    (dict(population=0), "population must be an integer >= 2"),
    (dict(population=2.5), "population must be an integer >= 2"),
    (dict(time_limit=-1.0), "time_limit must be positive"),
    (dict(time_limit=0), "time_limit must be positive"),
    (dict(time_limit="10"), "time_limit must be a number"),
    (dict(iterations=-2), "iterations must be a non-negative integer"),
    (dict(seed="x"), "seed must be an integer"),
    (dict(initial=["rule:NOPE+first"]), "unknown job rule"),
    (dict(initial="rule:FIFO+first"), "initial must be a list"),
])
def test_bad_parameters(kw, msg):
    with pytest.raises(ValueError, match=msg):
        solve_sos(builtin("EX12"), **kw)


def test_bad_config():
    with pytest.raises(ValueError, match="parasite_rate"):
        SOSConfig(parasite_rate=0.0)
    with pytest.raises(ValueError, match="benefit factors"):
        SOSConfig(benefit_factors=())
    with pytest.raises(ValueError, match="population"):
        SOSConfig(population=1)


def test_a_configs_population_is_used_unless_one_is_given():
    # solve_sos's default population of 20 replaced every config's (SOSConfig(population=50) ran with 20)
    inst = builtin("EX12")
    assert solve_sos(inst, time_limit=None, iterations=0, config=SOSConfig(population=6)).meta["population"] == 6
    assert solve_sos(inst, time_limit=None, iterations=0, config=SOSConfig(population=6),
                     population=4).meta["population"] == 4
    assert solve_sos(inst, time_limit=None, iterations=0).meta["population"] == SOSConfig().population == 20
    with pytest.raises(ValueError, match="population must be an integer >= 2, got 1"):
        solve_sos(inst, time_limit=None, iterations=0, config=SOSConfig(population=6), population=1)


def test_the_search_stops_at_the_lower_bound():
    """Once a schedule meets the lower bound nothing better exists: a one-operation shop ran the whole 10 s."""
    from fms_dispatch.exact import simple_lower_bound

    inst = Instance(name="one", jobs=((Operation(1, None, 5),),), n_machines=1)
    t0 = time.perf_counter()
    s = _valid(inst, solve_sos(inst, time_limit=10.0))
    assert time.perf_counter() - t0 < 2.0
    assert s.makespan == simple_lower_bound(inst) == 5 and s.meta["stopped"] == "lower_bound"
    assert solve_sos(builtin("EX12"), iterations=1, population=4).meta["stopped"] == "iterations"  # 82 > its bound


def test_a_negative_seed_is_taken_by_its_absolute_value():
    # as Python's random takes it (random, tabu); numpy's generator refused it: "expected non-negative integer"
    inst = builtin("EX12")
    neg = _valid(inst, solve_sos(inst, time_limit=None, seed=-3, iterations=2, population=6))
    pos = _valid(inst, solve_sos(inst, time_limit=None, seed=3, iterations=2, population=6))
    assert neg.makespan == pos.makespan and neg.meta["evaluations"] == pos.meta["evaluations"]


def test_sos_refuses_an_endless_budget_and_factors_that_make_no_keys():
    # time_limit=inf without iterations searched for ever; a NaN benefit factor made NaN keys and crashed a decode
    # ("cannot convert float NaN to integer"); a shop's name was an AttributeError deep inside
    inst = builtin("EX11")
    with pytest.raises(ValueError, match="time_limit must be positive and finite"):
        solve_sos(inst, time_limit=float("inf"), iterations=1)  # (refused with or without iterations; without, the
        # old code never returned)
    for bf in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="benefit factors must be positive, finite"):
            SOSConfig(benefit_factors=(1, bf))
    with pytest.raises(TypeError, match="solve_sos takes an Instance"):
        solve_sos("EX11", iterations=1)
