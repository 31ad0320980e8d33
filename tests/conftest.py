"""Helpers the test packages share: running a plan through the full net up to a state a snapshot can be taken
of, and running a shop to its end by a residual plan from there; and how the tests share several workers."""

import pytest

from fms_sim.full_shop import FullShop
from fms_sim.replay import PlanPolicy, execute
from fms_sim.snapshot import can_snapshot
from fms_sim.stepping import Stepper


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist: unknown without it
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """With several workers (``pytest -n N``, as ``make test`` runs), every test of ``tests/ros`` goes to one worker
    and runs there in turn, the other tests one by one to whichever worker is free. The ROS tests start nodes on
    random domains (and some on whatever domain ``fms up`` draws), so two of them at once could share a domain's
    localhost traffic. (xdist's own ``--dist loadgroup`` marks stopped grouping on pytest 9.2, pytest-xdist issue
    1386.) Another ``--dist`` mode than ``load`` (the default) is left to xdist."""
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class RosTogether(LoadScopeScheduling):  # a scope is one work unit; the largest go first (the ROS tests)
        def _split_scope(self, nodeid: str) -> str:
            return "tests/ros" if nodeid.startswith("tests/ros/") else nodeid

    return RosTogether(config, log)


def run_plan_until(inst, plan, cut, scenario=None):
    """Replay ``plan`` for ``cut`` answers, then on to the next stop where a snapshot can be taken; returns the
    shop and its stepper (``stepper.kind == "done"`` if the run ended first)."""
    shop = FullShop(inst, scenario=scenario)
    st = Stepper(shop, idle_stops=True)
    st.advance()
    pol = PlanPolicy(inst, plan)
    n = 0
    while st.kind != "done":
        if n >= cut and can_snapshot(shop):
            break
        label = pol.answer(st)
        pol.apply(st, label)
        st.apply(label)
        n += 1
    return shop, st


def finish_by(shop, residual):
    """Run ``shop`` to its end by ``residual`` (a residual plan resumed from its state; a stuck plan raises
    :class:`fms_sim.replay.ReplayError`); its schedule."""
    execute(shop, PlanPolicy.resume(shop, residual))
    return shop.schedule()
