"""Helpers the test packages share: running a plan through the full net up to a state a snapshot can be taken
of, and running a shop to its end by a residual plan from there."""

from fms_sim.full_shop import FullShop
from fms_sim.replay import PlanPolicy, execute
from fms_sim.snapshot import can_snapshot
from fms_sim.stepping import Stepper


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
