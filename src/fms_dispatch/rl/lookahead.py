"""Running a policy on the shop, optionally with the digital-twin lookahead (pre-positioning idle vehicles).

Without lookahead, :func:`run_agent` is the plain loop ``while not shop.done: shop.act(policy(shop))``.

With lookahead, the net is advanced event by event (the same steps as :meth:`fms_sim.petri.Net.advance`) so
that the moments when a vehicle stands idle with nothing assigned become visible: no decision is due, yet an
AGV (or tool transporter) is idle. At each such moment, for each idle vehicle not looked at in this state, a
twin of the shop (:meth:`~fms_sim.shop.Shop.copy`) is rolled forward with the same policy until a task lands
on that vehicle (the policy picks it for a request); the request's pickup (the part's location, or the tool's
location for a transporter) is read at that moment. If it differs from where the vehicle is, the real vehicle
is sent there empty now (:meth:`~fms_sim.shop.Shop.reposition_agv` /
:meth:`~fms_sim.shop.Shop.reposition_transporter`) instead of waiting for the request. Repositioning is a
net transition like any other, so every schedule stays feasible by construction (tests validate it); it can
cost time when another request arrives while the vehicle is on its way, which the benchmarks measure.
"""

from __future__ import annotations

from typing import Callable

from fms_sim.schedule import Schedule
from fms_sim.shop import Shop

__all__ = ["run_agent", "run_with_lookahead", "predict_task"]

Choose = Callable[[Shop], int]

#: at most this many decisions are simulated in the twin per idle vehicle
DEFAULT_HORIZON = 200


def run_agent(shop: Shop, choose: Choose, lookahead: bool = False, horizon: int = DEFAULT_HORIZON,
              verify: bool = True) -> Schedule:
    """Run ``shop`` to completion with ``choose(shop) -> net action``; pre-position idle vehicles if asked."""
    if lookahead:
        return run_with_lookahead(shop, choose, horizon, verify)
    while not shop.done:
        shop.act(choose(shop))
    return shop.schedule()


def predict_task(shop: Shop, choose: Choose, kind: str, vehicle: int, horizon: int = DEFAULT_HORIZON) -> int | None:
    """Where the next task of ``vehicle`` (``kind`` "agv" or "tt") starts, by rolling ``choose`` on a twin.

    Returns the pickup location (AGV: the part's location; transporter: the tool's location), or None if no
    task lands on the vehicle within ``horizon`` decisions or before the run ends.
    """
    twin = shop.copy()
    twin.net.advance()
    base = twin.n_jobs if kind == "agv" else twin.n_jobs + twin.n_agvs
    target = base + vehicle
    for _ in range(horizon):
        if twin.done:
            return None
        a = choose(twin)
        if a == target:
            if kind == "agv":
                req = twin.awaiting_agv()
                return None if req is None else req[2]
            treq = twin.awaiting_transporter()
            return None if treq is None else treq[1]
        twin.act(a)
    return None


def finish(shop: Shop, choose: Choose) -> int:
    """Makespan of running a twin of ``shop`` (possibly between decisions) to the end with ``choose``."""
    twin = shop.copy()
    twin.net.advance()
    while not twin.done:
        twin.act(choose(twin))
    return twin.makespan


def _finish_after_moves(shop: Shop, choose: Choose, orders: list[tuple[str, int, int]]) -> int:
    twin = shop.copy()
    _place_orders(twin, orders)
    while not twin.done:
        twin.act(choose(twin))
    return twin.makespan


def _place_orders(shop: Shop, orders: list[tuple[str, int, int]]) -> None:
    """Order every move at the current time; the last call runs the net on to the next decision."""
    for kind, v, dest in orders[:-1]:
        shop.net.put(shop.p_agv_orders if kind == "agv" else shop.p_tt_orders, (v, dest))
    kind, v, dest = orders[-1]
    if kind == "agv":
        shop.reposition_agv(v, dest)
    else:
        shop.reposition_transporter(v, dest)


def _idle_vehicles(shop: Shop) -> list[tuple[str, int, int]]:
    out = [("agv", v, loc) for v, loc in shop.idle_agvs()]
    out += [("tt", r, loc) for r, loc in shop.idle_transporters()]
    return sorted(out)


def run_with_lookahead(shop: Shop, choose: Choose, horizon: int = DEFAULT_HORIZON, verify: bool = True) -> Schedule:
    """The lookahead loop of :func:`run_agent` (see the module docstring).

    With ``verify`` (default), each proposed set of moves is also checked in a twin: the run is completed
    with the moves and compared with the completion without them (the plain policy from here); the moves are
    made only if the completed makespan is strictly smaller. As the completion without moves is exactly what
    the real run does if nothing more is moved, the final makespan is never worse than the plain policy's.
    """
    net = shop.net
    # (kind, vehicle, decisions so far): a vehicle is looked at (and moved) at most once between two
    # decisions, so repositioning cannot cycle even where travel times are 0
    looked: set[tuple] = set()
    decisions = 0
    expected: int | None = None  # makespan of the plain completion from the current state (when verified)
    while not shop.done:
        # the body of Net.advance, one event time at a time
        net.run_autonomous()
        if net.enabled_actions():
            # fire only: the loop itself advances, so that idle moments between decisions are seen
            net.act(choose(shop))
            decisions += 1
            continue
        if shop.done:
            break
        orders = []
        for kind, v, loc in _idle_vehicles(shop):
            key = (kind, v, decisions)
            if key in looked:
                continue
            looked.add(key)
            dest = predict_task(shop, choose, kind, v, horizon)
            if dest is not None and dest != loc:
                orders.append((kind, v, dest))
        if orders and verify:
            if expected is None:
                expected = finish(shop, choose)
            with_moves = _finish_after_moves(shop, choose, orders)
            if with_moves < expected:
                expected = with_moves
            else:
                orders = []
        if orders:
            _place_orders(shop, orders)
            continue
        t = net.next_event_time()
        if t is None:
            break
        net.release_until(t)
    return shop.schedule()
