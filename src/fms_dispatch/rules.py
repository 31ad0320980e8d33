"""Dispatching rules: 12 job-selection rules x vehicle-selection rules, acting through the net's masks.

Job rules (the paper's meanings; ties go to the lowest job index):

======  ==============================================================
FIFO    earliest entry into the shop (release order)
SPS     shortest processing sequence (fewest operations in the job)
LPS     longest processing sequence
SPTN    shortest processing time of the next operation
LPTN    longest processing time of the next operation
MTWR    most total work remaining (sum of the remaining durations)
LTWR    least total work remaining
LWT     longest waiting time (since the part became ready)
SPT     shortest total processing time of the job
LPT     longest total processing time of the job
SPSR    shortest remaining sequence (fewest remaining operations)
LPSR    longest remaining sequence
======  ==============================================================

Vehicle rules (AGVs and tool transporters alike): ``first`` (first available: idle the longest, then lowest
index), ``least-work`` (least cumulative busy time), ``nearest`` (least empty travel to the pickup; our
addition). Names are case-insensitive; a solver is named ``rule:<JOB>+<vehicle>``.
"""

from __future__ import annotations

from typing import Callable

from fms_sim.instance import Instance
from fms_sim.schedule import Schedule
from fms_sim.shop import Shop, run_policy

__all__ = ["JOB_RULES", "VEHICLE_RULES", "RulePolicy", "solve_rule", "parse_rule_name", "all_rule_pairs"]

JobKey = Callable[[Shop, int], float]


def _remaining_work(shop: Shop, j: int) -> int:
    return sum(op.duration for op in shop.instance.jobs[j][shop.next_op(j):])


def _next_duration(shop: Shop, j: int) -> int:
    return shop.instance.jobs[j][shop.next_op(j)].duration


def _total(shop: Shop, j: int) -> int:
    return sum(op.duration for op in shop.instance.jobs[j])


# each key is minimised; the job index breaks ties
JOB_RULES: dict[str, JobKey] = {
    "FIFO": lambda s, j: s.job_entry[j],
    "SPS": lambda s, j: len(s.instance.jobs[j]),
    "LPS": lambda s, j: -len(s.instance.jobs[j]),
    "SPTN": _next_duration,
    "LPTN": lambda s, j: -_next_duration(s, j),
    "MTWR": lambda s, j: -_remaining_work(s, j),
    "LTWR": _remaining_work,
    "LWT": lambda s, j: s.job_ready_since[j],
    "SPT": _total,
    "LPT": lambda s, j: -_total(s, j),
    "SPSR": lambda s, j: len(s.instance.jobs[j]) - s.next_op(j),
    "LPSR": lambda s, j: -(len(s.instance.jobs[j]) - s.next_op(j)),
}

VEHICLE_RULES = ("first", "least-work", "nearest")


def check_rule_names(**rules: object) -> None:
    """Raise ValueError unless each of ``rules`` (``job=``, ``vehicle=``, ``tool=``) names its rule by a string (None
    was an AttributeError from ``.upper()``)."""
    for what, name in rules.items():
        if not isinstance(name, str):
            raise ValueError(f"the {what} rule is named by a string (e.g. 'MTWR', 'nearest', 'fifo'), got {name!r}")


class RulePolicy:
    """Choose the legal action by a job rule and a vehicle rule; callable as ``policy(shop) -> action``."""

    def __init__(self, job_rule: str = "FIFO", vehicle_rule: str = "first"):
        check_rule_names(job=job_rule, vehicle=vehicle_rule)
        job_rule, vehicle_rule = job_rule.upper(), vehicle_rule.lower()
        if job_rule not in JOB_RULES:
            raise ValueError(f"unknown job rule {job_rule!r}; choose from {', '.join(JOB_RULES)}")
        if vehicle_rule not in VEHICLE_RULES:
            raise ValueError(f"unknown vehicle rule {vehicle_rule!r}; choose from {', '.join(VEHICLE_RULES)}")
        self.job_rule, self.vehicle_rule = job_rule, vehicle_rule
        self._key = JOB_RULES[job_rule]

    @property
    def name(self) -> str:
        return f"rule:{self.job_rule}+{self.vehicle_rule}"

    def __call__(self, shop: Shop) -> int:
        legal = shop.legal_actions()
        n_jobs, n_agvs = shop.n_jobs, shop.n_agvs
        agvs = [a - n_jobs for a in legal if n_jobs <= a < n_jobs + n_agvs]
        if agvs:
            req = shop.awaiting_agv()
            return n_jobs + self._vehicle(agvs, shop.agv_free_at, shop.agv_work, shop.agv_loc,
                                          shop.instance.agv_travel, req[2])
        tts = [a - n_jobs - n_agvs for a in legal if a >= n_jobs + n_agvs]
        if tts:
            req = shop.awaiting_transporter()
            return n_jobs + n_agvs + self._vehicle(tts, shop.tt_free_at, shop.tt_work, shop.tt_loc,
                                                   shop.instance.tool_travel, req[1])
        key = self._key
        return min(legal, key=lambda j: (key(shop, j), j))

    def _vehicle(self, cands: list[int], free_at: list[int], work: list[int], loc: list[int],
                 travel, pickup: int) -> int:
        return choose_vehicle(self.vehicle_rule, cands, free_at, work, loc, travel, pickup)


def choose_vehicle(rule: str, cands: list[int], free_at: list[int], work: list[int], loc: list[int], travel,
                   target: int) -> int:
    """The vehicle a vehicle rule picks among ``cands`` for a trip that starts (loaded) at ``target``."""
    if rule == "first":
        return min(cands, key=lambda v: (free_at[v], v))
    if rule == "least-work":
        return min(cands, key=lambda v: (work[v], v))
    return min(cands, key=lambda v: (travel[loc[v]][target], work[v], v))


def parse_rule_name(name: str) -> RulePolicy:
    """``"MTWR+nearest"`` or ``"rule:MTWR+nearest"`` -> policy (vehicle rule defaults to ``first``)."""
    if not isinstance(name, str):  # None was an AttributeError
        raise ValueError(f"a rule name is a string such as rule:MTWR+nearest, got {name!r}")
    body = name.split(":", 1)[1] if name.lower().startswith("rule:") else name
    job, plus, vehicle = body.partition("+")
    if not job or (plus and not vehicle):  # "rule:" or "rule:MTWR+" ran as FIFO or MTWR+first: a typo
        raise ValueError(f"rule name {name!r} has an empty part; use rule:JOB[+VEHICLE], e.g. rule:MTWR+nearest")
    if "+" in vehicle:  # (it said "unknown vehicle rule 'nearest+fifo'")
        raise ValueError(f"rule {name!r}: a tool rule (its third part, {vehicle.split('+', 1)[1]!r}) is read only by "
                         "the full-decision net's rules of fms solve; here give rule:JOB+VEHICLE")
    return RulePolicy(job, vehicle or "first")


def solve_rule(instance: Instance, job_rule: str = "FIFO", vehicle_rule: str = "first") -> Schedule:
    """Run the shop net with one rule pair to completion."""
    policy = RulePolicy(job_rule, vehicle_rule)
    s = run_policy(instance, policy)
    s.meta["solver"] = policy.name
    return s


def all_rule_pairs(include_nearest: bool = False) -> list[str]:
    """``rule:JOB+vehicle`` names: the paper's 12 x 2 (first, least-work), plus ``nearest`` on request."""
    vs = VEHICLE_RULES if include_nearest else VEHICLE_RULES[:2]
    return [f"rule:{j}+{v}" for j in JOB_RULES for v in vs]
