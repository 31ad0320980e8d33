"""Disruptions: breakdowns, vehicles out of service and noise, in the full net and the validator."""

import dataclasses
import json
import random

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.disruptions import Breakdown, Outage, Scenario, ScenarioError
from fms_sim.full_shop import FullShop, make_shop
from fms_sim.petri import InvalidAction
from fms_sim.replay import replay
from fms_sim.validate import validate


def _run(inst, scenario, seed=0):
    rng = random.Random(seed)
    shop = FullShop(inst, scenario=scenario)
    while not shop.done:
        shop.act(rng.choice(shop.legal_actions()))
    return shop.schedule()


# ---------------------------------------------------------------------------------------------- data
def test_bad_scenarios_are_refused_with_a_reason():
    inst = builtin("ra01")
    cases = [
        (Scenario(breakdowns=(Breakdown(99, 0, 5),)), "machine 99"),
        (Scenario(outages=(Outage("agv", 7, 0, 5),)), "AGV 7"),
        (Scenario(outages=(Outage("tt", 3, 0, 5),)), "tool transporter 3"),
    ]
    for sc, msg in cases:
        with pytest.raises(ScenarioError, match=msg):
            sc.check(inst)
    with pytest.raises(ScenarioError, match="no tool transporters"):
        Scenario(outages=(Outage("tt", 0, 0, 5),)).check(builtin("EX12"))
    with pytest.raises(ScenarioError, match="overlap"):
        Scenario(breakdowns=(Breakdown(1, 0, 10), Breakdown(1, 5, 3)))
    with pytest.raises(ScenarioError, match="overlap"):
        Scenario(outages=(Outage("agv", 0, 0, 10), Outage("agv", 0, 9, 3)))
    with pytest.raises(ScenarioError, match="duration from 1 to 1,000,000,000 .*got start 0, duration 0"):
        Scenario(breakdowns=(Breakdown(1, 0, 0),))
    with pytest.raises(ScenarioError, match="start must be from 0 .*got start -1, duration 3"):
        Scenario(outages=(Outage("agv", 0, -1, 3),))
    # times past an instance's bound ran (makespan 1e20) and then failed every insert of the recorder
    with pytest.raises(ScenarioError, match="breakdown of machine 1: .*got start 5, duration 100000000000000000000"):
        Scenario.from_dict({"breakdowns": [{"machine": 1, "start": 5, "duration": 10**20}]})
    with pytest.raises(ScenarioError, match="outage of agv 0: .*got start 1000000001, duration 3"):
        Scenario(outages=(Outage("agv", 0, 10**9 + 1, 3),))
    Scenario(breakdowns=(Breakdown(1, 10**9, 10**9),))  # the bound itself is a time
    with pytest.raises(ScenarioError, match="agv or tt"):
        Scenario(outages=(Outage("truck", 0, 0, 3),))
    with pytest.raises(ScenarioError, match="noise"):
        Scenario(noise=-0.1)
    for bad, msg in [({"breakdowns": [{"machine": "1", "start": 0, "duration": 3}]}, "integer"),
                     ({"breakdowns": {}}, "lists"), ({"schema": "fms/scenario/v9"}, "schema"),
                     ({"storms": []}, "unknown scenario field"), ([], "object")]:
        with pytest.raises(ScenarioError, match=msg):
            Scenario.from_dict(bad)
    with pytest.raises(ValueError, match="full-decision"):
        make_shop(inst, "paper", Scenario(noise=0.1))


@pytest.mark.parametrize("make, msg", [
    (lambda: Scenario(noise=50), "noise must be a spread from 0 to 1, got 50"),
    (lambda: Scenario(noise=float("inf")), "noise must be a spread"),
    (lambda: Breakdown("1", 1, 2), "breakdown: machine must be an integer, got '1'"),
    (lambda: Breakdown(1, 30.5, 2), "breakdown: start must be an integer, got 30.5"),
    (lambda: Outage("agv", 0, 1, True), "outage of agv: duration must be an integer, got True"),
    (lambda: Outage("bus", 0, 1, 2), "agv or tt"),
    (lambda: Scenario(breakdowns=((1, 0, 5),)), "breakdowns must be a sequence of Breakdown"),
    (lambda: Scenario.from_dict({"outages": [{"kind": "agv", "vehicle": 0, "start": 0, "duration": 5, "x": 1}]}),
     "outage 0: unknown field"),
])
def test_scenario_parts_are_checked_when_made(make, msg):
    # a float start used to run and be called malformed by the validator afterwards; a string machine was a raw
    # TypeError; a spread of 50 gave a makespan of 3e47
    with pytest.raises(ScenarioError, match=msg):
        make()


def test_numpy_numbers_make_the_same_scenario_as_pythons():
    # Instance, PlanEffort and the env take numpy's integers; a Breakdown, an Outage and a Scenario refused them
    import numpy as np

    b = Breakdown(np.int64(2), np.int64(20), np.int32(40))
    o = Outage("agv", np.int64(1), np.int64(0), np.int64(5))
    sc = Scenario((b,), (o,), np.float64(0.5), np.int64(3))
    assert sc == Scenario((Breakdown(2, 20, 40),), (Outage("agv", 1, 0, 5),), 0.5, 3)
    assert [type(v) for v in (b.machine, b.start, b.duration, o.vehicle, o.start, sc.seed, sc.noise)] == \
        [int] * 6 + [float]
    json.dumps(sc.to_dict())  # (numpy's integers are no JSON)
    assert sc.op_duration(0, 0, 20) == Scenario(noise=0.5, seed=3).op_duration(0, 0, 20)
    for bad in (np.bool_(True), 2.0, "2"):
        with pytest.raises(ScenarioError, match="must be an integer"):
            Breakdown(1, bad, 5)  # type: ignore[arg-type]


def test_a_replaced_scenario_draws_its_own_noise():
    # dataclasses.replace handed the noise factors drawn so far to the new scenario: with another noise or seed it
    # realised the old one's durations (equal scenarios, different runs; a plan's replay failed its own check)
    a = Scenario(noise=0.1, seed=1)
    a.op_duration(0, 0, 20)
    b = dataclasses.replace(a, noise=1.0, seed=7)
    assert b == Scenario(noise=1.0, seed=7)
    assert [b.op_duration(j, 0, 20) for j in range(5)] == [Scenario(noise=1.0, seed=7).op_duration(j, 0, 20)
                                                           for j in range(5)]
    inst = builtin("ra01")
    for noise, seed in ((0.1, 1), (0.9, 5)):
        sched = make_shop(inst, "full", scenario=dataclasses.replace(a, noise=noise, seed=seed))
        while not sched.done:
            sched.act(sched.legal_actions()[0])
        assert validate(inst, sched.schedule()) == []
    # a disruption added during a run keeps the factors drawn so far (the same noise and seed draw the same)
    c = a.adding(Breakdown(1, 5, 5))
    assert c == Scenario((Breakdown(1, 5, 5),), (), 0.1, 1) and c.op_duration(0, 0, 20) == a.op_duration(0, 0, 20)
    assert a.adding(Outage("tt", 0, 3, 4)).outages == (Outage("tt", 0, 3, 4),) and a.breakdowns == ()


def test_a_list_of_windows_is_kept_as_a_tuple():
    sc = Scenario(breakdowns=[Breakdown(1, 0, 5)])
    assert sc.breakdowns == (Breakdown(1, 0, 5),) and sc == Scenario(breakdowns=(Breakdown(1, 0, 5),))


def test_scenario_json_round_trip_and_draw(tmp_path):
    inst = builtin("sl00")
    sc = Scenario.draw(inst, noise=0.1, breakdowns=3, horizon=500, seed=4)
    assert len(sc.breakdowns) == 3 and sc == Scenario.draw(inst, noise=0.1, breakdowns=3, horizon=500, seed=4)
    assert sc != Scenario.draw(inst, noise=0.1, breakdowns=3, horizon=500, seed=5)
    sc = dataclasses.replace(sc, outages=(Outage("tt", 1, 10, 20),))
    path = tmp_path / "s.json"
    sc.save(path)
    assert json.loads(path.read_text())["schema"] == "fms/scenario/v1"
    assert Scenario.load(path) == sc
    with pytest.raises(ScenarioError, match="cannot read"):
        Scenario.load(tmp_path / "missing.json")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(ScenarioError, match=r"bin\.json is not a text \(UTF-8 JSON\) file"):
        Scenario.load(tmp_path / "bin.json")


# ---------------------------------------------------------------------------------------------- runs
@pytest.mark.parametrize("name", ["EX12", "ra01", "ra11L3"])
def test_random_deciders_finish_valid_runs_under_random_disruptions(name):
    base = builtin(name)
    for inst in (base, base.without_agvs()):
        for seed in range(8):
            outs = []
            if inst.has_agvs:
                outs.append(Outage("agv", seed % inst.n_agvs, 5 + seed, 20))
            if inst.has_tools:
                outs.append(Outage("tt", 0, 3 + seed, 30))
            sc = dataclasses.replace(Scenario.draw(inst, noise=0.2, breakdowns=2, horizon=120, seed=seed),
                                     outages=tuple(outs))
            s = _run(inst, sc, seed)
            assert validate(inst, s) == [], (inst.mode, seed)
            assert Scenario.from_dict(s.meta["scenario"]) == sc


def test_noise_is_reproducible_and_checked_by_the_validator():
    inst = builtin("ra01")
    a, b = _run(inst, Scenario(noise=0.2, seed=1)), _run(inst, Scenario(noise=0.2, seed=1))
    c = _run(inst, Scenario(noise=0.2, seed=2))
    assert a.to_dict() == b.to_dict() and a.to_dict() != c.to_dict()
    nominal = _run(inst, None)
    assert validate(inst, nominal) == [] and "scenario" not in nominal.meta
    # the realised durations differ from the nominal ones, and the validator knows both
    durations = {(r.job, r.op): r.end - r.start for r in a.operations}
    assert any(durations[j, k] != op.duration for j, job in enumerate(inst.jobs) for k, op in enumerate(job))
    assert validate(inst, a) == []
    assert validate(inst, dataclasses.replace(a, meta={k: v for k, v in a.meta.items() if k != "scenario"}))
    ops = list(a.operations)
    ops[0] = dataclasses.replace(ops[0], end=ops[0].end + 1)
    assert any("realised duration" in v for v in validate(inst, dataclasses.replace(a, operations=ops)))


def test_noise_keeps_zero_durations_zero():
    """A zero-length operation stays zero under noise, as a zero-length trip does (semantics.md), in the shop
    and in the validator alike."""
    base = builtin("ra01")
    jobs = [list(job) for job in base.jobs]
    jobs[0][0] = dataclasses.replace(jobs[0][0], duration=0)
    inst = dataclasses.replace(base, jobs=tuple(tuple(j) for j in jobs))
    sc = Scenario(noise=0.3, seed=1)
    assert sc.op_duration(0, 0, 0) == 0 and sc.op_duration(0, 0, 5) >= 1
    s = _run(inst, sc)
    first = next(r for r in s.operations if (r.job, r.op) == (0, 0))
    assert first.end == first.start and validate(inst, s) == []


def test_a_breakdown_suspends_the_running_operation_and_blocks_starts():
    inst = builtin("EX12")
    nominal = _run(inst, None)
    first = min(nominal.operations, key=lambda r: r.start)
    mid = first.start + 1  # the machine breaks down while its first operation runs
    sc = Scenario(breakdowns=(Breakdown(first.machine, mid, 17),))
    s = _run(inst, sc)
    assert validate(inst, s) == []
    rec = next(r for r in s.operations if (r.job, r.op) == (first.job, first.op))
    assert rec.start == first.start and rec.end == first.end + 17
    for r in s.operations:
        if r.machine == first.machine:
            assert not mid <= r.start < mid + 17
    bad = dataclasses.replace(s, operations=[dataclasses.replace(r, end=r.end - 17) if r is rec else r
                                             for r in s.operations])
    assert validate(inst, bad)


def test_no_trip_starts_while_its_vehicle_is_out():
    inst = builtin("ra01")
    sc = Scenario(outages=(Outage("agv", 0, 0, 60), Outage("tt", 0, 0, 60)))
    s = _run(inst, sc, seed=3)
    assert validate(inst, s) == []
    assert all(t.start >= 60 for t in s.agv_trips if t.agv == 0)
    assert all(t.start >= 60 for t in s.tool_trips if t.transporter == 0)
    trips = list(s.agv_trips)
    i = next(i for i, t in enumerate(trips) if t.agv == 1)
    moved = dataclasses.replace(s, agv_trips=[dataclasses.replace(t, agv=0) if k == i else t
                                              for k, t in enumerate(trips)])
    assert validate(inst, moved)  # AGV 0 cannot have driven then (out of service, or two places at once)


def test_a_vehicle_out_of_service_is_not_sent_and_a_past_disruption_is_refused():
    inst = builtin("ra01")
    sc = Scenario(outages=(Outage("agv", 0, 0, 60), Outage("tt", 0, 0, 60)))
    shop = FullShop(inst, scenario=sc)
    with pytest.raises(InvalidAction, match="^AGV 0 is out of service at time 0$"):
        shop.check_reposition("agv", 0, 1)
    with pytest.raises(InvalidAction, match="^tool transporter 0 is out of service at time 0$"):
        shop.check_reposition("tt", 0, 1)
    shop.check_reposition("agv", 1, 1)  # the other AGV is in service
    while shop.now == 0:
        shop.act(shop.legal_actions()[0])
    with pytest.raises(ScenarioError, match=f"^the disruption starts at {shop.now - 1}, before the shop's time "
                                            f"{shop.now}$"):
        shop.add_disruption(Breakdown(1, shop.now - 1, 5))
    assert shop.scenario == sc  # nothing changed
    shop.add_disruption(Breakdown(1, shop.now, 5))  # from now on it is taken
    assert shop.scenario.breakdowns == (Breakdown(1, shop.now, 5),)


def test_a_plan_executed_under_disruptions_keeps_its_orders_and_stays_valid():
    from fms_dispatch.exact import greedy_schedule

    inst = builtin("ra05")
    plan = greedy_schedule(inst, rule="est")
    sc = Scenario.draw(inst, noise=0.15, breakdowns=2, horizon=plan.makespan, seed=7)
    out = replay(inst, plan, scenario=sc)
    assert validate(inst, out) == [] and out.meta["scenario"] == sc.to_dict()
    for m in range(1, inst.n_machines + 1):  # each machine keeps the plan's order
        order = lambda sched: [(r.job, r.op) for r in sorted(sched.operations, key=lambda r: r.start)  # noqa: E731
                               if r.machine == m]
        assert order(out) == order(plan)


@pytest.mark.parametrize("kind", ["breakdown", "outage"])
def test_a_disruption_reported_at_the_instant_something_started_suspends_or_finishes_it(kind):
    # a live shop hears of a breakdown (outage) at the time an operation (trip) has just started on its machine
    # (vehicle): that operation is running at the breakdown's first instant and is suspended (the trip is under way
    # and is finished); the validator used to call the start one made while the machine was down
    inst = builtin("EX12")
    rng = random.Random(1)
    shop = FullShop(inst, scenario=None)
    hit = None
    while not shop.done:
        shop.act(rng.choice(shop.legal_actions()))
        if hit is None and shop.now > 0:
            if kind == "breakdown":
                hit = next((r for r in shop.rec.ops if r.start == shop.now and r.end > r.start), None)
                if hit is not None:
                    shop.add_disruption(Breakdown(hit.machine, shop.now, 10))
            else:
                hit = next((t for t in shop.rec.agv if t.start == shop.now and t.end > t.start), None)
                if hit is not None:
                    shop.add_disruption(Outage("agv", hit.agv, shop.now, 10))
    assert hit is not None
    s = shop.schedule()
    assert validate(inst, s) == []
    if kind == "breakdown":
        rec = next(r for r in s.operations if (r.job, r.op) == (hit.job, hit.op))
        assert rec.start == hit.start and rec.end == hit.end + 10  # suspended for the repair
        late = dataclasses.replace(s, operations=[dataclasses.replace(r, end=r.end - 10) if r is rec else r
                                                  for r in s.operations])
        assert validate(inst, late)  # not suspended: wrong
        others = [r for r in s.operations if r.machine == hit.machine and r is not rec]
        assert all(not hit.start < r.start < hit.start + 10 for r in others)
    else:
        assert any(t.start == hit.start and t.end == hit.end and t.agv == hit.agv for t in s.agv_trips)
        assert all(not hit.start < t.start < hit.start + 10 for t in s.agv_trips if t.agv == hit.agv)


@pytest.mark.parametrize("sc", [
    Scenario(breakdowns=(Breakdown(1, 1, 9), Breakdown(1, 10, 9))),
    Scenario(outages=(Outage("agv", 0, 1, 5), Outage("agv", 0, 6, 20), Outage("agv", 1, 1, 5),
                      Outage("agv", 1, 6, 20))),
], ids=["breakdowns", "outages"])
def test_back_to_back_windows_keep_the_machine_or_vehicle_out(sc):
    # the repair of the first window and the start of the next fall at the same time; the repair came last and
    # put the machine (vehicle) back in service for the whole second window
    inst = builtin("EX12")
    for seed in range(4):
        s = _run(inst, sc, seed=seed)
        assert validate(inst, s) == [], seed


@pytest.mark.parametrize("kwargs, msg", [
    # each was an error of the random module (empty range, sample larger than population, non-integer arg), or a
    # ScenarioError about a drawn window of duration 0 that never named the argument; a negative horizon passed
    ({"breakdowns": 2, "horizon": 50, "duration": (5, 2)}, r"duration must be a range .* got \(5, 2\)"),
    ({"breakdowns": 2, "horizon": 50, "duration": (0, 5)}, r"1 <= low <= high"),
    ({"breakdowns": -1, "horizon": 50}, "breakdowns must be an integer >= 0, got -1"),
    ({"breakdowns": 1.5, "horizon": 50}, "breakdowns must be an integer >= 0, got 1.5"),
    ({"breakdowns": 1, "horizon": 50.5}, "horizon must be an integer >= 0"),
    ({"breakdowns": 1, "horizon": -5}, "horizon must be an integer >= 0"),
])
def test_draw_refuses_arguments_that_draw_nothing_sensible(kwargs, msg):
    with pytest.raises(ScenarioError, match=msg):
        Scenario.draw(builtin("sl00"), **kwargs)


def test_draw_takes_numpy_integers_and_a_list_range():
    import numpy as np

    inst = builtin("sl00")
    got = Scenario.draw(inst, breakdowns=np.int64(2), horizon=np.int64(100), duration=[3, 4], seed=np.int64(1))
    assert got == Scenario.draw(inst, breakdowns=2, horizon=100, duration=(3, 4), seed=1)
    assert len(got.breakdowns) == 2 and all(3 <= b.duration <= 4 for b in got.breakdowns)
    # [0, 0] is the default range, as (0, 0) (it was refused by a message that offered (0, 0))
    assert Scenario.draw(inst, breakdowns=2, horizon=100, duration=[0, 0], seed=1) == \
        Scenario.draw(inst, breakdowns=2, horizon=100, seed=1)


def test_draw_keeps_breakdowns_within_the_largest_time_on_a_long_horizon():
    # a shop of times near the largest has more work per machine than MAX_TIME: breakdowns drawn past it were
    # refused by the scenario's own check ("start must be from 0 ... got start 1072270025"), and an env with
    # disruptions on such a shop failed at its reset
    from fms_sim.instance import MAX_TIME

    inst = builtin("sl00")
    for seed in range(20):
        sc = Scenario.draw(inst, breakdowns=3, horizon=50 * MAX_TIME, seed=seed)
        assert len(sc.breakdowns) == 3
        assert all(0 <= b.start < MAX_TIME and 1 <= b.duration <= MAX_TIME for b in sc.breakdowns)
