"""Rules for the full-decision net (:class:`fms_sim.full_shop.FullShop`), and the solvers built on them.

A full-net rule is ``JOB+VEHICLE+TOOL``: the paper's 12 job rules (:data:`fms_dispatch.rules.JOB_RULES`) order
the machine starts and the dispatches, the vehicle rules (``first``, ``least-work``, ``nearest``) choose AGVs
and transporters, and a tool rule chooses which waiting request a tool serves next:

==================  ==========================================================================
fifo                the request whose part was dispatched first (the paper's order), then job
same-machine-first  a request on the machine where the tool already is (no trip), then fifo
nearest             the request whose machine is the fewest tool-travel units away, then fifo
earliest-start      the request whose operation could start first (part, tool and machine)
==================  ==========================================================================

The policy is non-delay with look-ahead of one operation: at each decision it starts what can start, takes
up each free tool for the *current* operation of a job (pre-fetching it while the part is still on its way or
the previous operation runs), dispatches ready parts and sends an AGV ahead for a part whose operation ends
before the AGV could get there; when nothing of that is left it holds.

Solvers: ``rule:JOB+VEHICLE[+TOOL]`` with ``decisions="full"``; ``list`` — the earliest-start list schedule
(:func:`fms_dispatch.exact.greedy_schedule`) executed through the full net by replay, a strong baseline that
decides through the net, and ``list:ect`` / ``list:<JOB RULE>`` (earliest completion; operations in a job
rule's order); ``rules`` (or ``rules:full``) — the best of every full-net rule combination and every list
order on the instance; ``rules:paper`` — the best of the paper net's 36 rule pairs.
"""

from __future__ import annotations

import numbers
import time
from typing import Any, Callable

from fms_sim.disruptions import Scenario
from fms_sim.full_shop import FullShop
from fms_sim.instance import Instance, require_instance
from fms_sim.replay import replay
from fms_sim.schedule import Schedule

from .progress import say
from .rules import JOB_RULES, VEHICLE_RULES, RulePolicy, check_rule_names, choose_vehicle

__all__ = ["TOOL_RULES", "FullRulePolicy", "run_full", "full_rule_names", "solve_list", "solve_best_rules"]

TOOL_RULES = ("fifo", "same-machine-first", "nearest", "earliest-start")
_INF = float("inf")


class _OpView:
    """The shop as a job rule reads it, with the operation the decision is about as each job's next one."""

    def __init__(self, shop: FullShop, ops: dict[int, int]):
        self.instance = shop.instance
        self.job_entry = shop.job_entry
        self.job_ready_since = shop.job_ready_since
        self._ops = ops

    def next_op(self, job: int) -> int:
        return self._ops[job]


def run_full(instance: Instance, choose: Callable[[FullShop], int], scenario: Scenario | None = None) -> Schedule:
    """Run the full-decision net to completion, asking ``choose(shop)`` at every decision (in a shop disrupted
    by ``scenario``, if given)."""
    if isinstance(choose, RulePolicy):  # (it failed inside, reading the paper net's requests off a FullShop)
        raise TypeError("a RulePolicy decides through the paper's net (fms_sim.shop.run_policy); the full net's rules "
                        "are FullRulePolicy (or parse_full_rule('rule:MTWR+nearest'))")
    if not callable(choose):
        raise TypeError(f"choose must be a callable shop -> action, got {type(choose).__name__}")
    shop = FullShop(instance, scenario=scenario)
    while not shop.done:
        shop.act(choose(shop))
    return shop.schedule()


class FullRulePolicy:
    """A job rule, a vehicle rule and a tool rule acting through the full net's masks (module docstring)."""

    def __init__(self, job_rule: str = "FIFO", vehicle_rule: str = "first", tool_rule: str = "fifo"):
        check_rule_names(job=job_rule, vehicle=vehicle_rule, tool=tool_rule)
        job_rule, vehicle_rule, tool_rule = job_rule.upper(), vehicle_rule.lower(), tool_rule.lower()
        if job_rule not in JOB_RULES:
            raise ValueError(f"unknown job rule {job_rule!r}; choose from {', '.join(JOB_RULES)}")
        if vehicle_rule not in VEHICLE_RULES:
            raise ValueError(f"unknown vehicle rule {vehicle_rule!r}; choose from {', '.join(VEHICLE_RULES)}")
        if tool_rule not in TOOL_RULES:
            raise ValueError(f"unknown tool rule {tool_rule!r}; choose from {', '.join(TOOL_RULES)}")
        self.job_rule, self.vehicle_rule, self.tool_rule = job_rule, vehicle_rule, tool_rule
        self._key = JOB_RULES[job_rule]

    @property
    def name(self) -> str:
        return f"rule:{self.job_rule}+{self.vehicle_rule}+{self.tool_rule}"

    # ------------------------------------------------------------------ the decision
    def __call__(self, shop: FullShop) -> int:
        legal = shop.legal_actions()
        kind = shop.action_kind(legal[0])[0]
        if kind == "agv":
            req = shop.awaiting_agv()
            return self._vehicle(shop, "agv", legal, req[2])
        if kind == "tt":
            req = shop.awaiting_transporter()
            return self._vehicle(shop, "tt", legal, req[1])
        if kind == "use":
            return self._use(shop, legal)
        by_kind: dict[str, list[int]] = {}
        for a in legal:
            k, num = shop.action_kind(a)
            by_kind.setdefault(k, []).append(num)
        for choose in (self._start, self._tool, self._dispatch):
            a = choose(shop, by_kind)
            if a is not None:
                return a
        return shop.hold_action if shop.hold_action in legal else legal[0]

    def _best_job(self, shop: FullShop, ops: dict[int, int]) -> int:
        view, key = _OpView(shop, ops), self._key
        return min(ops, key=lambda j: (key(view, j), j))

    def _start(self, shop: FullShop, by_kind: dict[str, list[int]]) -> int | None:
        jobs = by_kind.get("start")
        if not jobs:
            return None
        ops = {j: shop.buffered_op(j)[0] for j in jobs}
        return shop.action_index(f"start:{self._best_job(shop, ops)}")

    def _due_requests(self, shop: FullShop) -> dict[int, list[int]]:
        """Per tool, the jobs whose next operation to start needs it, is due soon and may be served now."""
        out: dict[int, list[int]] = {}
        for j in range(shop.instance.n_jobs):
            t = shop.due_tool_request(j)
            if t is not None:
                out.setdefault(t, []).append(j)
        return out

    def _tool(self, shop: FullShop, by_kind: dict[str, list[int]]) -> int | None:
        offered = by_kind.get("tool")
        if not offered or not shop.instance.has_tools:
            return None
        due = self._due_requests(shop)
        for t in offered:
            if t in due:
                return shop.action_index(f"tool:{t}")
        return None

    def _dispatch(self, shop: FullShop, by_kind: dict[str, list[int]]) -> int | None:
        jobs = by_kind.get("job")
        if not jobs:
            return None
        inst = shop.instance
        T = inst.agv_travel
        idle = shop.idle_agvs()
        ops: dict[int, int] = {}
        for j in jobs:
            k = shop.next_op(j)
            if shop.job_done_ops[j] >= k:  # the part is ready
                ops[j] = k
                continue
            pickup = inst.jobs[j][k - 1].machine
            reach = min(T[loc][pickup] for _, loc in idle)
            if shop.machine_busy_until[pickup] - shop.now <= reach:  # ahead: the AGV would not wait
                ops[j] = k
        if not ops:
            return None
        return shop.action_index(f"job:{self._best_job(shop, ops)}")

    def _use(self, shop: FullShop, legal: list[int]) -> int:
        t = shop.tool_choice
        assert t is not None
        cands = [shop.action_kind(a)[1] for a in legal]
        current = [j for j in cands if shop.part_on_its_way(j, shop.request_of(t, j))]
        cands = current or cands
        inst = shop.instance
        TT = inst.tool_travel
        here = shop.tool_loc[t]

        def stamp(j: int) -> float:
            k = shop.request_of(t, j)
            return shop.job_started_ops[j] if shop.job_started_ops[j] > k else _INF

        rule = self.tool_rule
        if rule == "fifo":
            key: Callable[[int], Any] = lambda j: (stamp(j), j)
        elif rule == "same-machine-first":
            key = lambda j: (inst.jobs[j][shop.request_of(t, j)].machine != here, stamp(j), j)
        elif rule == "nearest":
            key = lambda j: (TT[here][inst.jobs[j][shop.request_of(t, j)].machine], stamp(j), j)
        else:
            key = lambda j: (self._start_estimate(shop, t, j), j)
        return shop.action_index(f"use:{min(cands, key=key)}")

    @staticmethod
    def _start_estimate(shop: FullShop, tool: int, j: int) -> int:
        """When the operation that ``use:j`` serves could start: its machine, its part and the tool."""
        inst = shop.instance
        k = shop.request_of(tool, j)
        m = inst.jobs[j][k].machine
        part = shop.now if shop.job_done_ops[j] >= k else shop.machine_busy_until[inst.jobs[j][k - 1].machine]
        if inst.has_agvs and k and inst.jobs[j][k - 1].machine != m and shop.buffered_op(j) is None:
            part += inst.agv_travel[inst.jobs[j][k - 1].machine][m]
        elif inst.has_agvs and not k and shop.buffered_op(j) is None:
            part += inst.agv_travel[0][m]
        here = shop.tool_loc[tool]
        free = shop.machine_busy_until[here] if shop.tool_running[tool] else shop.now
        arrive = free + (inst.tool_travel[here][m] if here != m else 0)
        return max(part, arrive, shop.machine_busy_until[m])

    def _vehicle(self, shop: FullShop, kind: str, legal: list[int], target: int) -> int:
        agv = kind == "agv"
        cands = [shop.action_kind(a)[1] for a in legal]
        free_at, work, loc = ((shop.agv_free_at, shop.agv_work, shop.agv_loc) if agv
                              else (shop.tt_free_at, shop.tt_work, shop.tt_loc))
        travel = shop.instance.agv_travel if agv else shop.instance.tool_travel
        v = choose_vehicle(self.vehicle_rule, cands, free_at, work, loc, travel, target)
        return shop.action_index(f"{kind}:{v}")


def full_rule_names(instance: Instance | None = None) -> list[str]:
    """Every ``rule:JOB+VEHICLE+TOOL`` name (one tool rule when ``instance`` has no tools: they do not act)."""
    tools = TOOL_RULES if instance is None or instance.has_tools else TOOL_RULES[:1]
    return [f"rule:{j}+{v}+{t}" for j in JOB_RULES for v in VEHICLE_RULES for t in tools]


def parse_full_rule(name: str) -> FullRulePolicy:
    """``"rule:MTWR+nearest+same-machine-first"`` (vehicle rule defaults to first, tool rule to fifo)."""
    body = name.split(":", 1)[1] if name.lower().startswith("rule:") else name
    parts = body.split("+")
    if len(parts) > 3:
        raise ValueError(f"rule name {name!r} has more than three parts (JOB+VEHICLE+TOOL)")
    if not all(parts):  # "rule:" or "rule:MTWR+" ran as FIFO or MTWR+first: a typo, not a choice
        raise ValueError(f"rule name {name!r} has an empty part; use rule:JOB[+VEHICLE[+TOOL]], e.g. "
                         "rule:MTWR+nearest")
    job, vehicle, tool = (parts + ["", "", ""])[:3]
    return FullRulePolicy(job, vehicle or "first", tool or "fifo")


#: list-scheduling variants: ``list`` (earliest start), ``list:ect`` (earliest completion), ``list:<JOB RULE>``
LIST_ORDERS = ("est", "ect") + tuple(JOB_RULES)


def list_names() -> list[str]:
    """Every list-scheduling solver name: ``list``, ``list:ect`` and ``list:<JOB RULE>`` for the 12 job rules."""
    return ["list", "list:ect"] + [f"list:{r}" for r in JOB_RULES]


def _static_priority(instance: Instance, rule: str) -> dict[tuple[int, int], float]:
    """A job rule's key for each operation, as if it were its job's next one at time 0 (smaller first)."""
    key = JOB_RULES[rule]

    class _At:
        def __init__(self, k: int) -> None:
            self.instance, self.k = instance, k
            self.job_entry = list(range(instance.n_jobs))
            self.job_ready_since = [0] * instance.n_jobs

        def next_op(self, job: int) -> int:
            return self.k

    return {(j, k): key(_At(k), j) for j, job in enumerate(instance.jobs) for k in range(len(job))}


def solve_list(instance: Instance, order: str = "est", **_: Any) -> Schedule:
    """A list schedule (:func:`fms_dispatch.exact.greedy_schedule`), executed through the full-decision net by
    replay: ``order`` ``est`` (earliest start, the default), ``ect`` (earliest completion) or a job rule (the
    operations in the order of the rule's key, each as early as its resources allow)."""
    from .exact import greedy_schedule

    require_instance(instance, "solve_list")
    if not isinstance(order, str):  # (an AttributeError from .upper())
        raise ValueError(f"the list order is named by a string ({', '.join(LIST_ORDERS)}), got {order!r}")
    up = order.upper()
    if order.lower() in ("est", "ect"):
        plan = greedy_schedule(instance, rule=order.lower())
    elif up in JOB_RULES:
        plan = greedy_schedule(instance, rule="guided", priority=_static_priority(instance, up))
    else:
        raise ValueError(f"unknown list order {order!r}; choose from {', '.join(LIST_ORDERS)}")
    s = replay(instance, plan)
    s.meta["solver"] = "list" if order.lower() == "est" else f"list:{order if order.lower() == 'ect' else up}"
    return s


def solve_best_rules(instance: Instance, *, progress: bool = False, decisions: str = "full",
                     time_limit: float | None = None, **_: Any) -> Schedule:
    """The best schedule of every rule combination on ``instance`` (ties: the first listed), with
    ``meta["rule"]`` naming the winner. ``decisions="full"``: every full-net combination and ``list`` (solvers
    ``rules``, ``rules:full``); ``"paper"``: the 36 pairs of the paper's net (``rules:paper``). With
    ``progress`` a line goes to stderr every 10 s. ``time_limit`` (seconds; None: try them all, the default, as
    the benchmarks do) stops trying new combinations once it has passed, after at least one;
    ``meta["tried"]`` says how many were run. The list schedules are tried first (usually the best on shops with
    tools, where a rule can end twice as late: what a short time limit keeps), ties still going to the first
    listed, so a run that tries them all ends with the same schedule whatever the order."""
    require_instance(instance, "solve_best_rules")  # a name was an AttributeError
    if time_limit is not None and (not isinstance(time_limit, numbers.Real) or isinstance(time_limit, bool)):
        raise TypeError(f"time_limit must be a number of seconds or None, got {time_limit!r}")  # ("1": a TypeError
    if time_limit is not None and not time_limit > 0:                                          # from a comparison)
        raise ValueError(f"the time limit must be positive, got {time_limit}")
    from fms_sim.shop import run_policy

    from .rules import all_rule_pairs, parse_rule_name

    if decisions == "full":
        names = full_rule_names(instance) + list_names()
    elif decisions == "paper":
        names = all_rule_pairs(include_nearest=True)
    else:
        raise ValueError(f"unknown decisions {decisions!r}; choose from full, paper")
    best: Schedule | None = None
    best_at = 0  # the winner's place in ``names`` (ties go to the first listed)
    t0 = last = time.perf_counter()
    tried = 0
    interrupted = False
    lists = [i for i, name in enumerate(names) if name.startswith("list")]
    order = lists + sorted(set(range(len(names))) - set(lists))
    try:
        for at in order:
            name = names[at]
            if time_limit is not None and best is not None and time.perf_counter() - t0 >= time_limit:
                break
            if name.startswith("list"):
                s = solve_list(instance, name.partition(":")[2] or "est")
            elif decisions == "full":
                s = run_full(instance, parse_full_rule(name))
            else:
                s = run_policy(instance, parse_rule_name(name))
            tried += 1  # (counted once run: an interrupt between two combinations counts neither wrongly)
            if best is None or (s.makespan, at) < (best.makespan, best_at):
                best, best_at = s, at
                best.meta["rule"] = name
            now = time.perf_counter()
            if progress and now - last >= 10:
                say(f"  rules: {tried}/{len(names)} tried, best {best.makespan} ({best.meta['rule']}), "
                    f"{now - t0:.0f} s")
                last = now
    except KeyboardInterrupt:  # the best combination so far goes with the interrupt (fms solve keeps it)
        if best is None:
            raise
        interrupted = True
    assert best is not None
    best.meta["solver"] = "rules" if decisions == "full" else "rules:paper"
    best.meta["combinations"] = len(names)
    best.meta["tried"] = tried
    best.meta["decisions"] = decisions
    if interrupted:
        from .exact import SearchInterrupted

        best.meta.update(status="INTERRUPTED", wall_time=round(time.perf_counter() - t0, 3))
        raise SearchInterrupted(best, 0, time.perf_counter() - t0)
    return best
