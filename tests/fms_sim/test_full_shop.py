"""The full-decision net: masks, holds, dispatch ahead, tool pre-fetch, deadlock freedom, validity."""

import random

import pytest

from fms_sim import Instance, Operation
from fms_sim.benchmarks import builtin
from fms_sim.full_shop import HOLD, FullShop, make_shop
from fms_sim.petri import InvalidAction
from fms_sim.shop import Shop
from fms_sim.validate import validate


def _variants(name):
    base = builtin(name)
    out = [base, base.without_agvs()]
    if base.has_tools:
        out += [base.without_tools(), base.without_tools().without_agvs()]
    return out


def _random_run(inst, seed):
    rng = random.Random(seed)
    shop = FullShop(inst)
    n = 0
    while not shop.done:
        legal = shop.legal_actions()
        mask = shop.action_mask()
        assert [i for i, ok in enumerate(mask) if ok] == legal
        shop.act(rng.choice(legal))
        n += 1
    return shop, n


@pytest.mark.parametrize("name", ["EX12", "EX41", "ra01", "ra07L3", "ra20L4"])
def test_random_decisions_always_finish_with_a_valid_schedule(name):
    # every reachable state can finish (no deadlock is reachable), in all four modes
    for inst in _variants(name):
        for seed in range(15):
            shop, _ = _random_run(inst, seed)
            assert validate(inst, shop.schedule()) == [], (inst.mode, seed)


def test_random_decisions_on_a_larger_tool_shop():
    inst = builtin("sl10")
    for seed in range(2):
        shop, n = _random_run(inst, seed)
        assert validate(inst, shop.schedule()) == []
        assert n > 3 * inst.n_operations  # dispatch, vehicle, start and tool decisions per operation


def test_layout_and_labels():
    inst = builtin("ra01")
    shop = FullShop(inst)
    labels = shop.action_labels()
    n, a, r, t = inst.n_jobs, inst.n_agvs, inst.n_tool_transporters, inst.n_tools
    assert labels[:n] == [f"job:{j}" for j in range(n)]
    assert labels[n:n + a] == [f"agv:{v}" for v in range(a)]
    assert labels[n + a:n + a + r] == [f"tt:{i}" for i in range(r)]
    assert labels[n + a + r:2 * n + a + r] == [f"start:{j}" for j in range(n)]
    assert labels[2 * n + a + r:2 * n + a + r + t] == [f"tool:{i}" for i in range(1, t + 1)]
    assert labels[-1] == HOLD and shop.hold_action == len(labels) - 1 == shop.n_actions - 1
    for i, lab in enumerate(labels):
        assert shop.action_index(lab) == i
    with pytest.raises(InvalidAction):
        shop.action_index("bogus:1")


@pytest.mark.parametrize("cls", [FullShop, Shop])
def test_one_actions_label_is_its_label_in_the_list(cls):
    shop = cls(builtin("ra01"))
    labels = shop.action_labels()
    assert [shop.action_label(i) for i in range(len(labels))] == labels
    for bad in (len(labels), -1):
        with pytest.raises(InvalidAction, match="out of range"):
            shop.action_label(bad)
    with pytest.raises(InvalidAction):
        shop.action_label(True)


def test_make_shop_selects_the_net():
    inst = builtin("EX12")
    assert type(make_shop(inst, "paper")) is Shop and make_shop(inst, "paper").decisions == "paper"
    assert isinstance(make_shop(inst), FullShop) and make_shop(inst).decisions == "full"
    with pytest.raises(ValueError, match="unknown decisions"):
        make_shop(inst, "fifo")


def _two_job_tool_shop():
    # job 0: machine 1 (tool 1), then machine 2 (tool 1); job 1: machine 2 with tool 1
    travel = [[0, 5, 5], [5, 0, 5], [5, 5, 0]]
    return Instance(name="tiny", jobs=((Operation(1, 1, 10), Operation(2, 1, 10)), (Operation(2, 1, 3),)),
                    agv_travel=travel, n_agvs=1, tool_travel=travel, n_tool_transporters=1, n_machines=2,
                    n_tools=1)


def test_hold_only_while_something_is_in_flight_and_never_at_a_vehicle_choice():
    inst = builtin("EX12")
    shop = FullShop(inst)
    assert shop.net.next_event_time() is None and not shop.hold_allowed()  # t=0: nothing moves yet
    with pytest.raises(InvalidAction, match="hold"):
        shop.act(shop.hold_action)
    shop.act(shop.action_index("job:0"))
    assert shop.decision_kind() == "agv" and shop.hold_action not in shop.legal_actions()
    shop.act(shop.action_index("agv:0"))
    assert shop.hold_allowed()
    t0 = shop.now
    nxt = shop.net.next_event_time()
    shop.act(shop.hold_action)
    assert shop.now >= nxt > t0


def test_tool_prefetch_before_the_part_is_dispatched_and_request_order_is_chosen():
    inst = _two_job_tool_shop()
    shop = FullShop(inst)
    # serve job 1's request first although job 0 comes first in every FIFO sense: the tool goes to machine 2
    shop.act(shop.action_index("tool:1"))
    assert shop.decision_kind() == "use"
    legal = {shop.action_labels()[a] for a in shop.legal_actions()}
    assert legal == {"use:0", "use:1"}
    shop.act(shop.action_index("use:1"))
    assert shop.decision_kind() == "tt"
    shop.act(shop.action_index("tt:0"))
    trips = shop.rec.tt
    assert trips[-1].loaded and trips[-1].job == 1 and trips[-1].to == 2 and trips[-1].start == 0
    # no part has been dispatched yet: the tool was fetched ahead of its part
    assert shop.rec.agv == [] and shop.p_parts.count == 2


def test_a_reservation_that_would_close_a_circular_wait_is_masked():
    inst = _two_job_tool_shop()
    shop = FullShop(inst)
    shop.act(shop.action_index("tool:1"))
    # job 0's second operation needs tool 1, but so does its first (unstarted): reserving the tool for
    # (0, 1) would make (0, 0) wait for it forever
    assert shop.request_of(1, 0) == 0
    assert not shop._safe(1, (0, 1)) and shop._safe(1, (0, 0))


def test_dispatch_ahead_sends_the_agv_before_the_part_is_ready():
    inst = builtin("EX12")
    shop = FullShop(inst)
    j = 0
    shop.act(shop.action_index(f"job:{j}"))
    shop.act(shop.action_index("agv:0"))
    # run until op (0,0) starts, then dispatch op (0,1) at once, while (0,0) is still running
    while not any(r.job == j and r.op == 0 for r in shop.rec.ops):
        legal = shop.legal_actions()
        a = shop.action_index(f"start:{j}") if shop.action_index(f"start:{j}") in legal else shop.hold_action
        shop.act(a)
    end00 = next(r.end for r in shop.rec.ops if r.job == j and r.op == 0)
    assert shop.now < end00
    assert shop.action_index(f"job:{j}") in shop.legal_actions()
    shop.act(shop.action_index(f"job:{j}"))
    assert shop.next_op(j) >= 2
    idle = shop.idle_agvs()
    shop.act(shop.action_index(f"agv:{idle[0][0]}"))
    while not shop.done:
        shop.act(shop.legal_actions()[0])
    s = shop.schedule()
    assert validate(inst, s) == []
    carry = next(t for t in s.agv_trips if t.loaded and t.job == j and t.op == 1)
    assert carry.start >= end00


def test_machines_wait_for_the_chosen_operation():
    # nothing starts by itself: a buffered operation waits until start:J is chosen
    inst = builtin("EX12")
    shop = FullShop(inst)
    shop.act(shop.action_index("job:0"))
    shop.act(shop.action_index("agv:0"))
    while shop.action_index("start:0") not in shop.legal_actions():
        shop.act(shop.hold_action)
    ready = shop.now
    # something in flight (job 2's part on AGV 1), so time can pass while job 0's part waits in its buffer
    shop.act(shop.action_index("job:2"))
    shop.act(shop.action_index("agv:1"))
    for _ in range(3):
        assert shop.hold_allowed()
        shop.act(shop.hold_action)
        if shop.now > ready:
            break
    assert shop.now > ready  # time passed ...
    assert shop.action_index("start:0") in shop.legal_actions()  # ... the start is still offered ...
    assert not any(r.job == 0 for r in shop.rec.ops)  # ... and was not taken by itself


def test_trial_restores_the_full_state():
    inst = builtin("ra01")
    shop = FullShop(inst)
    rng = random.Random(3)
    for _ in range(20):
        shop.act(rng.choice(shop.legal_actions()))
    key = shop.state_key()
    with shop.trial():
        while not shop.done:
            shop.act(rng.choice(shop.legal_actions()))
    assert shop.state_key() == key
    while not shop.done:
        shop.act(rng.choice(shop.legal_actions()))
    assert validate(inst, shop.schedule()) == []


def test_live_orders_join_the_full_net():
    inst = builtin("ra01")
    for seed in range(4):
        rng = random.Random(seed)
        shop = FullShop(inst)
        for _ in range(25):
            shop.act(rng.choice(shop.legal_actions()))
        t0 = shop.now
        ids = shop.add_jobs([[Operation(1, 1, 3), Operation(2, 2, 4)], [Operation(3, None, 5)]])
        assert ids == [inst.n_jobs, inst.n_jobs + 1] and shop.n_jobs == inst.n_jobs + 2
        labels = shop.action_labels()
        for j in ids:
            assert f"job:{j}" in labels and f"start:{j}" in labels and f"use:{j}" in labels
        assert shop.request_of(1, ids[0]) == 0
        while not shop.done:
            shop.act(rng.choice(shop.legal_actions()))
        s = shop.schedule()
        assert validate(shop.instance, s) == []
        assert min(r.start for r in s.operations if r.job in ids) >= t0


def test_incremental_and_naive_engines_decide_identically():
    # the incremental engine (dirty sets, touched guards, per-priority enabled sets) offers exactly what
    # re-evaluating every transition at every step offers
    for name in ("ra01", "EX41"):
        inst = builtin(name)
        for seed in range(3):
            rng_a, rng_b = random.Random(seed), random.Random(seed)
            a, b = FullShop(inst), FullShop(inst, incremental=False)
            while not a.done:
                la, lb = a.legal_actions(), b.legal_actions()
                assert la == lb
                x = rng_a.choice(la)
                assert x == rng_b.choice(lb)
                a.act(x)
                b.act(x)
            assert b.done and a.schedule().to_dict() == b.schedule().to_dict()


def test_stepper_drives_the_full_net_with_labels_including_hold():
    from fms_sim.stepping import Stepper

    inst = builtin("ra01")
    st = Stepper(FullShop(inst), idle_stops=False)
    st.advance()
    rng = random.Random(5)
    holds = 0
    while st.kind != "done":
        labels = [st.shop.action_labels()[a] for a in st.shop.legal_actions()]
        label = "hold" if "hold" in labels and rng.random() < 0.3 else rng.choice(labels)
        holds += label == "hold"
        st.apply(label)
    assert holds > 0 and validate(inst, st.shop.schedule()) == []


@pytest.mark.parametrize("asked", [True, False])
def test_a_transporter_outage_during_an_open_tool_choice_takes_back_the_uses_that_need_it(asked):
    # a tool's request choice is open (use:0 needs the only transporter: the tool must travel) and the transporter
    # goes out of service now: the choice's candidates were not re-evaluated, and use:0 stayed offered
    from fms_sim.disruptions import Outage

    T = [[0, 3], [3, 0]]
    inst = Instance(name="r", jobs=[[Operation(1, 1, 5)]], agv_travel=T, n_agvs=1, tool_travel=T,
                    n_tool_transporters=1, n_tools=1)
    shops = [FullShop(inst), FullShop(inst, incremental=False)]
    for s in shops:
        s.net.advance()
        s.act(s.action_index("tool:1"))
        if asked:  # (a decider looked at the choice: use:0 evaluated, enabled)
            assert [s.action_label(a) for a in s.legal_actions()] == ["use:0"]
        s.add_disruption(Outage(kind="tt", vehicle=0, start=s.now, duration=4))
        s.net.advance()
    lazy, eager = ([s.action_label(a) for a in s.legal_actions()] for s in shops)
    assert lazy == eager == ["job:0", "hold"]
    while not shops[0].done:  # the run goes on: the tool is carried once the transporter is back
        shops[0].act(shops[0].legal_actions()[0])
    assert validate(inst, shops[0].schedule(), shops[0].scenario) == []


def _tool_offered_by_definition(shop: FullShop, t: int) -> bool:
    """take_tool[t]'s guard as docs/semantics.md states it: no tool choice is open, the tool may take up a new
    request (free, or running with nothing queued) and some pending request on it is a candidate (reachable now
    and closing no circular wait)."""
    if shop.tool_choice is not None or not shop._servable(t):
        return False
    return any(shop._candidate(t, j) for j in shop.treq[t])


@pytest.mark.parametrize("name,seed,outage", [("ra01", 1, False), ("ra05", 2, False), ("sl00", 3, False),
                                              ("ra01", 4, True)])
def test_the_tool_take_up_guard_is_its_definition_at_every_state(name, seed, outage):
    """The take_tool guard tries the requests for their job's next operation first and walks the wait-for graph
    only without one (FullShop._tool_ok): it must still offer exactly the tools whose definition holds, at every
    state of random runs (with a transporter out of service for a while: no idle transporter in service)."""
    from fms_sim.disruptions import Outage, Scenario

    inst = builtin(name)
    scenario = Scenario(outages=(Outage(kind="tt", vehicle=0, start=30, duration=200),)) if outage else None
    shop = FullShop(inst, scenario=scenario)
    rng = random.Random(seed)
    offered_seen = states = 0
    while not shop.done:
        legal = shop.legal_actions()
        offered = {shop.action_kind(a)[1] for a in legal if shop.action_kind(a)[0] == "tool"}
        expected = {t for t in range(1, inst.n_tools + 1) if _tool_offered_by_definition(shop, t)}
        if shop.decision_kind() != "agv" and shop.decision_kind() != "tt":  # (a vehicle choice offers nothing else)
            assert offered == expected, f"time {shop.now}: offered {sorted(offered)}, by definition {sorted(expected)}"
        offered_seen += bool(offered)
        states += 1
        shop.act(rng.choice(legal))
    assert offered_seen > 10 and validate(inst, shop.schedule(), shop.scenario) == []
