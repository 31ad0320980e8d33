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
