"""Saving and restoring a shop's state: trial runs on the shop itself (the lookahead's twins)."""

from __future__ import annotations

import pytest

from fms_dispatch.rules import RulePolicy
from fms_sim.benchmarks import builtin
from fms_sim.instance import Operation
from fms_sim.petri import Deadlock
from fms_sim.shop import _LIST_STATE, _SCALAR_STATE, Shop
from fms_sim.stepping import Stepper

# attributes fixed once the shop is built (or changed only by add_jobs, which restore refuses to cross)
_STRUCTURE = {"instance", "net", "rec", "n_jobs", "n_agvs", "n_tts", "_jobs", "_job_gate", "_job_outputs", "arrivals"}


def _fingerprint(shop: Shop) -> dict:
    """Everything that makes up a run's state, as plain values (tokens by colour, sojourn and order)."""
    net = shop.net
    return {
        "now": net.now, "fired": net.fired, "acted": net.acted, "enabled": net.enabled_actions(),
        "marking": {p.name: [(k, [(t.colour, t.ready) for t in b]) for k, b in p.buckets.items()]
                    for p in net.places},
        "in_flight": [p.in_flight for p in net.places],
        "pending": sorted((r, seq, p.name, t.colour) for r, seq, p, t in net._pending),
        "lists": {name: list(getattr(shop, name)) for name in _LIST_STATE},
        "scalars": {name: getattr(shop, name) for name in _SCALAR_STATE},
        "records": (list(shop.rec.ops), list(shop.rec.agv), list(shop.rec.tt)),
    }


def test_every_attribute_of_a_shop_is_state_or_structure():
    # a new mutable attribute must be added to _LIST_STATE / _SCALAR_STATE (saved) or here (structure)
    for name in ("EX12", "ra01"):
        shop = Shop(builtin(name))
        unknown = {a for a in vars(shop) if not a.startswith("p_")} - _STRUCTURE - set(_LIST_STATE) - set(_SCALAR_STATE)
        assert unknown == set(), name


@pytest.mark.parametrize("name, after", [("EX12", 0), ("EX42", 7), ("ra01", 12), ("ra05", 25)])
def test_restore_puts_back_exactly_the_saved_state(name, after):
    inst = builtin(name)
    pol = RulePolicy("MTWR", "nearest")
    shop = Shop(inst)
    for _ in range(after):
        shop.act(pol(shop))
    before = _fingerprint(shop)
    state = shop.save_state()
    while not shop.done:  # run on to the end: every part of the state changes
        shop.act(pol(shop))
    end = _fingerprint(shop)
    shop.restore_state(state)
    assert _fingerprint(shop) == before
    shop.restore_state(state)  # a state can be restored more than once
    assert _fingerprint(shop) == before
    while not shop.done:  # and the run from there is the same as the first time
        shop.act(pol(shop))
    assert _fingerprint(shop) == end
    assert shop.schedule().to_dict() == _plain(inst, pol)


def _plain(inst, pol) -> dict:
    shop = Shop(inst)
    while not shop.done:
        shop.act(pol(shop))
    return shop.schedule().to_dict()


def test_a_trial_run_leaves_the_shop_as_a_copy_would():
    inst = builtin("ra01")
    pol, other = RulePolicy("SPT", "first"), RulePolicy("LPT", "least-work")
    shop = Shop(inst)
    for _ in range(10):
        shop.act(pol(shop))
    twin = shop.copy()
    with shop.trial() as same:
        assert same is shop
        while not shop.done:
            shop.act(other(shop))
        tried = shop.makespan
    assert _fingerprint(shop) == _fingerprint(twin)
    while not twin.done:
        twin.act(other(twin))
    assert twin.makespan == tried  # the trial ran what a copy runs


def test_a_trial_restores_even_when_it_fails():
    shop = Shop(builtin("EX22"))
    pol = RulePolicy("FIFO", "first")
    shop.act(pol(shop))
    before = _fingerprint(shop)
    with pytest.raises(Deadlock):
        with shop.trial():
            shop.act(pol(shop))
            raise Deadlock("raised inside the trial")
    assert _fingerprint(shop) == before


def test_restoring_across_new_jobs_is_refused():
    shop = Shop(builtin("EX12"))
    state = shop.save_state()
    shop.add_jobs([[Operation(machine=1, tool=None, duration=3)]])
    with pytest.raises(ValueError, match="jobs were added"):
        shop.restore_state(state)
    net_state = Shop(builtin("EX12")).net.save_state()
    with pytest.raises(ValueError, match="structure changed"):
        shop.net.restore_state(net_state)


def test_a_stepper_trial_puts_back_its_stop():
    inst = builtin("EX52")
    pol = RulePolicy("SPTN", "nearest")
    st = Stepper(Shop(inst))
    stop = st.advance()
    while stop != "idle":
        stop = st.decide(pol(st.shop))
    where = (st.kind, list(st.idle), set(st.looked), st.idle_stops, _fingerprint(st.shop))
    with st.trial():
        st.idle_stops = False
        stop = st.move([(m.kind, m.vehicle, 0) for m in st.idle])
        while stop != "done":
            stop = st.decide(pol(st.shop))
    assert (st.kind, list(st.idle), set(st.looked), st.idle_stops, _fingerprint(st.shop)) == where
    stop = st.kind
    while stop != "done":  # the real run goes on as if nothing had happened
        stop = st.decide(pol(st.shop)) if stop == "decision" else st.move([])
    assert st.shop.schedule().to_dict() == _plain(inst, pol)


def test_state_keys_follow_the_state_not_the_object():
    inst = builtin("ra01")
    pol = RulePolicy("MTWR", "nearest")
    shop = Shop(inst)
    for _ in range(6):
        shop.act(pol(shop))
    key, quick = shop.state_key(), shop.state_key(quick=True)
    twin = shop.copy()
    assert twin.state_key() == key and twin.state_key(quick=True) == quick
    with shop.trial():
        shop.act(pol(shop))
        assert shop.state_key() != key
    assert shop.state_key() == key  # restored
    # the same state reached with other records of the past has the same key
    twin.rec.ops.clear()
    assert twin.state_key() == key
    # a vehicle sent elsewhere is a different state even at the same time
    idle = twin.idle_agvs()
    assert idle
    v, loc = idle[0]
    twin.reposition("agv", v, (loc + 1) % (inst.n_machines + 1), advance=False)
    assert twin.state_key() != key


def test_a_trial_across_a_breakdown_leaves_the_running_operation_as_it_was():
    """A breakdown lengthens the operation running on its machine in place (records are otherwise only appended):
    a trial run across the breakdown's start left it lengthened, and the real run lengthened it again (five trials:
    op (1,0) of ra01 ended at 270 instead of 70, a schedule the validator refuses)."""
    from fms_sim import validate
    from fms_sim.disruptions import Breakdown, Scenario
    from fms_sim.full_shop import make_shop

    inst = builtin("ra01")
    shop = make_shop(inst, "full", Scenario(breakdowns=(Breakdown(1, 11, 40),)))
    trials = 0
    while not shop.done:
        if shop.now < 11 and any(o.machine == 1 and o.start < 11 < o.end for o in shop.rec.ops):
            before = list(shop.rec.ops)
            with shop.trial():  # as the lookahead's twins run on the shop itself
                while not shop.done and shop.now < 20:
                    shop.act(shop.legal_actions()[0])
            assert shop.rec.ops == before
            trials += 1
        shop.act(shop.legal_actions()[0])
    assert trials and validate(inst, shop.schedule()) == []
