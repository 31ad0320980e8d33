"""The shop's clock (fms_sim.pacing): each step's messages are released when the wall clock reaches their state's
shop time × the time scale, in order."""

from __future__ import annotations

import pytest

from fms_msgs_json import TOPIC_ERRORS, TOPIC_EVENTS, TOPIC_STATE
from fms_sim.pacing import Pacer
from fms_sim.shop_service import Outgoing


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def step(t: int, tag: str) -> list[Outgoing]:
    return [Outgoing(TOPIC_STATE, {"time": t, "tag": tag}), Outgoing(TOPIC_EVENTS, {"time": t, "tag": tag})]


def tags(out: list[Outgoing]) -> list[str]:
    return [o.msg["tag"] for o in out]


def test_steps_wait_for_the_shop_time_since_the_previous_state_and_keep_their_order() -> None:
    clock = Clock()
    pacer = Pacer(0.5, clock)  # half a second per time unit
    assert tags(pacer.push(step(0, "a"))) == ["a", "a"]          # the first state: at once
    clock.now += 3.0                                              # the agent thinks 3 s: the shop's clock stands
    assert pacer.push(step(4, "b")) == [] and pacer.holding      # 4 units later: 2 s after the command came
    replay = [Outgoing(TOPIC_EVENTS, {"tag": "r"})]
    assert pacer.push(replay) == []                              # no state: at once, but behind the held step
    # errors alone change nothing a held step shows: out at once (an operator's refused order waited behind a paced
    # step and reached fms send after its timeout)
    assert tags(pacer.push([Outgoing(TOPIC_ERRORS, {"tag": "e"})])) == ["e"] and pacer.holding
    clock.now += 1.9
    assert pacer.release() == [] and pacer.holding
    clock.now += 0.1
    assert tags(pacer.release()) == ["b", "b", "r"] and not pacer.holding
    assert tags(pacer.push(step(4, "same time"))) == ["same time"] * 2  # no shop time passes: at once
    assert pacer.push(step(6, "c")) == []                        # due 1 s from now
    clock.now += 0.5
    assert pacer.push(step(10, "d")) == []                       # (an order while c is held) 2 s after c's release
    clock.now += 0.5
    assert tags(pacer.release()) == ["c", "c"]
    clock.now += 1.9
    assert pacer.release() == []
    clock.now += 0.1
    assert tags(pacer.release()) == ["d", "d"]
    assert tags(pacer.push(step(20, "x") + step(21, "y"))) == []  # one step's messages: its last state's time
    clock.now += 0.5 * 11
    assert tags(pacer.release()) == ["x", "x", "y", "y"]


def test_no_time_scale_releases_everything_at_once_and_bad_scales_are_refused() -> None:
    pacer = Pacer(0.0, Clock())
    assert tags(pacer.push(step(0, "a"))) == ["a", "a"]
    assert tags(pacer.push(step(10**6, "b"))) == ["b", "b"] and not pacer.holding
    for bad in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="time scale must be a finite number"):
            Pacer(bad)


def test_the_wait_of_the_end_counts_in_the_run_times() -> None:
    from fms_msgs_json import TOPIC_SCHEDULE, encode, make_command
    from fms_sim.benchmarks import builtin
    from fms_sim.shop_service import ShopService

    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    while not svc.done:
        label = next(a for a, ok in zip(svc.state["actions"], svc.state["mask"]) if ok)
        out = svc.handle_command(encode(make_command("r", svc.state_seq, label)))
    (msg,) = [o.msg for o in out if o.topic == TOPIC_SCHEDULE]
    wall, decision = svc.wall_time, svc.decision_time
    svc.delay_end(2.5)
    for meta in (svc.final_schedule.meta, msg["schedule"]["meta"]):
        assert meta["wall_time"] == round(wall + 2.5, 4) and meta["decision_time"] == round(decision + 2.5, 4)
    svc.delay_end(0.0)
    assert svc.final_schedule.meta["wall_time"] == round(wall + 2.5, 4)
