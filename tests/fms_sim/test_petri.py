"""The generic CTPN engine, on small nets unrelated to the shop."""

import pytest

from fms_sim.petri import Arc, InvalidAction, Net, Output, Transition


def test_timed_transition_tokens_sojourn_and_time_jumps_to_events():
    net = Net()
    a, b = net.add_place("a"), net.add_place("b")
    net.put(a, "x")
    fired = []
    net.add_transition(Transition("slow", [Arc(a, "v")], [Output(b, lambda bd: bd["v"], delay=10**9)],
                                  on_fire=lambda bd, now: fired.append(now)))
    assert net.advance() is False           # nothing controllable: runs to the end
    assert fired == [0]
    assert net.now == 10**9                 # one jump, not 10**9 ticks
    assert b.colours() == ["x"] and len(a) == 0


def test_guard_and_colour_join_with_keyed_places():
    net = Net()
    parts = net.add_place("parts", key=lambda c: c[0])
    tools = net.add_place("tools", key=lambda c: c[0])
    out = net.add_place("out")
    for c in [(1, "p1"), (2, "p2")]:
        net.put(parts, c)
    net.put(tools, (2, "tool-for-2"))
    t = net.add_transition(Transition(
        "join", [Arc(parts, "p"), Arc(tools, "t", key=lambda bd: bd["p"][0])],
        [Output(out, lambda bd: (bd["p"][1], bd["t"][1]))], guard=lambda bd: bd["p"][1] != "p9"))
    net.run_autonomous()
    assert out.colours() == [("p2", "tool-for-2")]
    assert parts.colours() == [(1, "p1")]
    assert not net.is_enabled(t)


def test_read_and_inhibitor_arcs():
    net = Net()
    go, stop, q, out = (net.add_place(n) for n in ("go", "stop", "q", "out"))
    net.put(q, 1)
    net.put(q, 2)
    rm = net.add_transition(Transition("rm", [Arc(stop, "s")], controllable=True, label="rm"))
    net.add_transition(Transition("t", [Arc(go, kind="test", count_only=True), Arc(stop, kind="inhibit"),
                                        Arc(q, "x", first=True)], [Output(out, lambda bd: bd["x"])]))
    net.run_autonomous()
    assert len(out) == 0                    # no token on the read arc
    net.put(go, "g")
    net.put(stop, "s")
    assert net.advance() is True
    assert len(out) == 0                    # inhibited
    assert net.enabled_actions() == [rm.action]
    net.act(rm.action)
    net.run_autonomous()
    assert out.colours() == [1, 2]          # FIFO order, and the read token stays
    assert len(go) == 1


def test_controllable_priorities_and_invalid_actions():
    net = Net()
    a, b, c = net.add_place("a"), net.add_place("b"), net.add_place("c")
    net.put(a, 1)
    net.put(b, 1)
    low = net.add_transition(Transition("low", [Arc(a, "x")], controllable=True, priority=10, label="low"))
    high = net.add_transition(Transition("high", [Arc(b, "x")], [Output(c, lambda bd: 1)], controllable=True,
                                         priority=5, label="high"))
    never = net.add_transition(Transition("never", [Arc(c, "x")], controllable=True, priority=1,
                                          guard=lambda bd: False, label="never"))
    assert net.advance()
    assert net.enabled_actions() == [high.action]
    assert net.mask() == [False, True, False]
    with pytest.raises(InvalidAction, match="more urgent"):
        net.act(low.action)
    with pytest.raises(InvalidAction, match="not enabled"):
        net.act(never.action)
    with pytest.raises(InvalidAction, match="out of range"):
        net.act(7)
    net.act(high.action)
    assert net.enabled_actions() == [low.action]
    net.act(low.action)
    assert net.enabled_actions() == []


def test_marking_counts_sojourning_tokens():
    net = Net()
    a, b = net.add_place("a"), net.add_place("b")
    net.put(a, 1)
    net.put(b, 2, delay=5)
    assert net.marking() == {"a": 1, "b": 0, "b~": 1}
    assert net.next_event_time() == 5


def _lazy_net(lazy: bool):
    """A net with many controllable choices behind one count-only read arc (like the full net's dispatches behind
    the idle AGVs), a guard that reads state kept outside the marking, and a more urgent level of pure guards."""
    net = Net()
    gate, work = net.add_place("gate"), net.add_place("work", key=lambda c: c)
    state = {"on": set(range(0, 12, 3)), "pick": None}
    picks = [net.add_transition(Transition(
        f"pick[{i}]", [], controllable=True, priority=1, label=f"pick:{i}",
        guard=lambda b, i=i: state["pick"] is not None and (i + state["pick"]) % 4 != 0)) for i in range(8)]
    jobs = [net.add_transition(Transition(
        f"job[{i}]", [Arc(gate, kind="test", count_only=True)], controllable=True, priority=5, label=f"job:{i}",
        lazy=lazy, guard=lambda b, i=i: i in state["on"])) for i in range(12)]
    starts = [net.add_transition(Transition(
        f"start[{i}]", [Arc(work, "w", key=i)], controllable=True, priority=5, label=f"start:{i}",
        guard=lambda b, i=i: i % 2 == 0 or state["pick"] is None)) for i in range(6)]
    return net, gate, work, state, picks, jobs, starts


def test_deferred_and_lazy_transitions_answer_as_eager_evaluation_does():
    """first_offered and offers (which evaluate deferred and lazy transitions only as far as they must) give what
    enabled_actions gives on a twin that touches everything, through a random run of changes."""
    import random as _random

    rng = _random.Random(7)
    lazy = _lazy_net(True)
    eager = _lazy_net(False)
    for step in range(400):
        what = rng.randrange(6)
        for net, gate, work, state, picks, jobs, starts in (lazy, eager):
            r = _random.Random(step)
            if what == 0:
                net.put(gate, "g")
            elif what == 1 and len(gate):
                net.take(gate, None)
            elif what == 2:
                i = r.randrange(12)
                state["on"] ^= {i}
                net.touch(jobs[i])
            elif what == 3:
                net.put(work, r.randrange(6))
            elif what == 4:
                state["pick"] = r.randrange(4) if state["pick"] is None else None
                touched = picks + starts
                if net is lazy[0]:
                    net.defer(touched)
                else:
                    for t in touched:
                        net.touch(t)
            elif what == 5 and state["pick"] is not None and net is lazy[0]:
                state["pick"] = None
                net.disable(picks)
                net.defer(starts)
            elif what == 5 and state["pick"] is not None:
                state["pick"] = None
                for t in picks + starts:
                    net.touch(t)
        probe = rng.randrange(len(lazy[0].controllable))
        want = eager[0].enabled_actions()
        assert lazy[0].offers(probe) == (probe in want), step
        assert lazy[0].first_offered() == (want[0] if want else None), step
        if rng.random() < 0.3:  # sometimes the full list too (it evaluates everything deferred)
            assert lazy[0].enabled_actions() == want, step
        if rng.random() < 0.1:  # and a saved state comes back with what was deferred
            saved = lazy[0].save_state()
            lazy[0].enabled_actions()
            lazy[0].restore_state(saved)


def test_act_evaluates_a_deferred_action_and_refuses_a_less_urgent_one():
    net, gate, work, state, picks, jobs, starts = _lazy_net(True)
    net.put(gate, "g")
    state["pick"] = 1
    net.defer(picks)
    assert net.first_offered() == picks[0].action  # (0 + 1) % 4 != 0
    with pytest.raises(InvalidAction, match="more urgent"):
        net.act(jobs[0].action)
    with pytest.raises(InvalidAction, match="not enabled"):
        net.act(picks[3].action)  # (3 + 1) % 4 == 0
    with pytest.raises(ValueError, match="controllable"):
        net.defer([net.add_transition(Transition("auto", [Arc(work, "w")]))])


@pytest.mark.parametrize("how", ["defer", "disable"])
@pytest.mark.parametrize("lazy", [True, False])
def test_defer_or_disable_while_a_lazy_gate_is_closed_forgets_the_remembered_binding(how, lazy):
    # the gate's place empties (the lazy transition's binding is remembered), its guard turns false and the module
    # says so with defer (or disable): the remembered binding came back when the place filled, and the net offered
    # (and would have fired) a transition whose guard was false
    net = Net()
    gate = net.add_place("gate")
    state = {"ok": True}
    t = net.add_transition(Transition("job", [Arc(gate, kind="test", count_only=True)], controllable=True,
                                      priority=5, label="job:0", lazy=lazy, guard=lambda b: state["ok"]))
    net.put(gate, "g")
    assert net.enabled_actions() == [0]
    net.take(gate, None)
    state["ok"] = False
    getattr(net, how)([t])
    assert net.first_offered() is None
    net.put(gate, "g")
    assert net.first_offered() is None and not net.offers(0) and net.enabled_actions() == []
    state["ok"] = True  # and a change the module reports after the gate opened is seen as before
    net.touch(t)
    assert net.first_offered() == 0 and net.enabled_actions() == [0]


def test_lazy_transitions_of_one_gate_must_share_their_priority_when_added():
    # (a mismatch was found only when the place first emptied or filled, in the middle of a firing)
    net = Net()
    gate = net.add_place("gate")
    net.add_transition(Transition("a", [Arc(gate, kind="test", count_only=True)], controllable=True, priority=5,
                                  lazy=True))
    with pytest.raises(ValueError, match="must share one"):
        net.add_transition(Transition("b", [Arc(gate, kind="test", count_only=True)], controllable=True, priority=6,
                                      lazy=True))
