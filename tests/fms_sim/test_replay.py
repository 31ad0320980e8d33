"""Replay through the full-decision net: never later than the given schedule, always valid, bad input refused."""

import dataclasses
import gzip
import json
import random
from pathlib import Path

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop
from fms_sim.replay import ReplayError, replay
from fms_sim.schedule import Schedule
from fms_sim.shop import run_policy
from fms_sim.validate import validate

DATA = Path(__file__).resolve().parents[1] / "data" / "replay"
INDEX = json.loads((DATA / "index.json").read_text())


def _instance(name, mode):
    inst = builtin(name)
    return inst.without_tools() if mode == "agvs" and inst.has_tools else inst


def _check(inst, given):
    out = replay(inst, given)
    assert validate(inst, out) == []
    assert out.makespan <= given.makespan
    return out


def test_the_kept_data_cover_every_set_of_the_issue():
    have = {(e["instance"], e["mode"], e["method"]) for e in INDEX}
    bu = {(f"EX{s}{lay}", "agvs", "cpsat") for s in range(1, 11) for lay in range(1, 5)}
    ra = {(f"ra{i:02d}", "tools", "cpsat") for i in range(1, 21)}
    sl = {(n, m, meth) for n in ("sl00", "sl30", "sl70") for m in ("tools", "agvs") for meth in ("cpsat", "list")}
    assert bu | ra | sl <= have


@pytest.mark.parametrize("entry", INDEX, ids=[e["file"] for e in INDEX])
def test_kept_schedules_replay_no_later(entry):
    inst = _instance(entry["instance"], entry["mode"])
    given = Schedule.from_json(gzip.decompress((DATA / entry["file"]).read_bytes()).decode())
    assert given.makespan == entry["makespan"]
    out = _check(inst, given)
    if entry.get("optimal"):
        assert out.makespan == given.makespan  # nothing beats a proven optimum


def _modes(name):
    base = builtin(name)
    out = [base, base.without_agvs()]
    if base.has_tools:
        out += [base.without_tools(), base.without_tools().without_agvs()]
    return out


@pytest.mark.parametrize("name", ["EX23", "EX74", "ra03", "ra11L2", "ra16L4", "sl00"])
def test_random_list_schedules_replay_no_later(name):
    from fms_dispatch.exact import greedy_schedule

    for inst in _modes(name):
        for seed in range(4 if inst.n_jobs < 20 else 1):
            rng = random.Random(seed)
            noise = {(j, k): rng.uniform(0, 40) for j, job in enumerate(inst.jobs) for k in range(len(job))}
            _check(inst, greedy_schedule(inst, rule="est", rng=rng, noise=noise))
            _check(inst, greedy_schedule(inst, rule="ect", rng=rng))


@pytest.mark.parametrize("name", ["EX12", "ra01", "ra09L3"])
def test_random_full_net_and_paper_net_schedules_replay_no_later(name):
    # schedules with arbitrary waits, pre-fetches and odd orders (random deciders) and the paper net's
    for inst in _modes(name):
        for seed in range(6):
            rng = random.Random(seed)
            shop = FullShop(inst)
            while not shop.done:
                shop.act(rng.choice(shop.legal_actions()))
            _check(inst, shop.schedule())
            _check(inst, run_policy(inst, lambda s: rng.choice(s.legal_actions())))


def test_an_invalid_schedule_is_refused_with_the_validators_errors():
    inst = builtin("EX12")
    entry = next(e for e in INDEX if e["instance"] == "EX12")
    good = Schedule.from_json(gzip.decompress((DATA / entry["file"]).read_bytes()).decode())
    ops = list(good.operations)
    ops[0] = dataclasses.replace(ops[0], start=ops[0].start - 1, end=ops[0].end - 1)
    bad = dataclasses.replace(good, operations=ops)
    with pytest.raises(ReplayError, match="not valid for EX12") as err:
        replay(inst, bad)
    assert err.value.violations == validate(inst, bad) and err.value.violations
    with pytest.raises(ReplayError):
        replay(builtin("EX13"), good)  # another layout: travel times differ


def test_a_plan_policy_refuses_another_shops_plan_and_the_paper_net():
    """Executing a plan (``PlanPolicy`` + ``execute``, which take residual plans and so do not validate) still
    refuses a plan naming operations the shop does not have, and a shop of the paper's net, each with a message."""
    from fms_sim.full_shop import make_shop
    from fms_sim.replay import PlanPolicy, execute

    big, small = builtin("sl00"), builtin("EX12")
    plan = run_policy(big, lambda shop: shop.legal_actions()[0])
    with pytest.raises(ReplayError, match=r"has operation \(\d+, \d+\), which EX12 does not have"):
        PlanPolicy(small, plan)
    own = run_policy(small, lambda shop: shop.legal_actions()[0])
    with pytest.raises(ReplayError, match="executed through the full-decision net"):
        execute(make_shop(small, "paper"), PlanPolicy(small, own))
    shop = make_shop(small, "full")
    execute(shop, PlanPolicy(small, own))
    assert validate(small, shop.schedule()) == [] and shop.schedule().makespan <= own.makespan


def test_a_schedule_with_zero_travel_times_replays():
    # an AGV's 0-length carry starts and ends at one instant: it never looked busy, so it was not offered again
    # and the plan's empty move back never came ("replay is stuck")
    from fms_dispatch.exact import greedy_schedule
    from fms_sim.instance import Instance

    inst = Instance.from_dict({"name": "ztr", "n_agvs": 1, "agv_travel": [[0, 0], [4, 0]],
                               "jobs": [[{"machine": 1, "tool": None, "duration": 5}],
                                        [{"machine": 1, "tool": None, "duration": 5}]]})
    ra01 = builtin("ra01")
    zero = dataclasses.replace(ra01, agv_travel=tuple(tuple(0 for _ in r) for r in ra01.agv_travel),
                               tool_travel=tuple(tuple(0 for _ in r) for r in ra01.tool_travel))
    for case in (inst, zero):
        plan = greedy_schedule(case, rule="est")
        assert validate(case, plan) == []
        again = replay(case, plan)
        assert validate(case, again) == [] and again.makespan <= plan.makespan
