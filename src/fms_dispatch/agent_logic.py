"""The dispatcher agent node's logic, without ROS: a state message in, a command (or an error) out.

The agent never sees the :class:`~fms_sim.shop.Shop`; it decides from the ``fms/state/v1`` message alone. For
dispatching rules the shop includes the optional ``features`` object in every state (per job: entry, number
of operations, next operation, its duration, remaining and total work, ready time; per vehicle: location,
free time, work; the pending AGV / tool-transport request with every vehicle's empty travel to its pickup).
:data:`FEATURE_JOB_KEYS` restates the twelve job rules of :mod:`fms_dispatch.rules` on those columns; the
tests check on whole runs that both choose the same action at every decision.

Solvers (the ``solver`` parameter):

* ``first`` — the lowest enabled action (like the offline ``first`` solver);
* ``random`` — uniform among the enabled actions, from ``seed``;
* ``rule:<JOB>+<first|least-work|nearest>`` — a dispatching rule pair;
* ``ppo[:model]`` and ``lookahead`` are planned but not available yet; asking for them (or for an offline
  solver such as ``cpsat``) raises :class:`UnavailableSolver`, which the node turns into exit code 2.
"""

from __future__ import annotations

import random
from typing import Any, Callable, Sequence

from fms_msgs_json import TOPIC_COMMAND, TOPIC_ERRORS, MessageError, decode, error_reply, make_command, make_error
from fms_sim.shop_service import Outgoing

from .rules import JOB_RULES, VEHICLE_RULES, parse_rule_name

__all__ = ["AgentLogic", "UnavailableSolver", "DecisionError", "FEATURE_JOB_KEYS", "make_decider",
           "AGENT_SOLVERS", "Decider"]

SOURCE = "fms_agent"
AGENT_SOLVERS = ("first", "random", "rule:<JOB>+<first|least-work|nearest>")
_PLANNED = {"ppo": "the PPO agent", "lookahead": "the lookahead agent"}
_OFFLINE = {"sos", "cpsat"}

Decider = Callable[[dict[str, Any]], str]
"""A decision function: a decoded state message -> the label of the action to fire."""


class UnavailableSolver(ValueError):
    """The solver name is unknown, or names a solver this agent cannot run; the message lists the choices."""


class DecisionError(ValueError):
    """A state the solver cannot decide on (no enabled action, missing or inconsistent features)."""


# Job keys on the feature columns (minimised; ties go to the lowest job number), one per rule of
# fms_dispatch.rules.JOB_RULES with the same meaning.
FeatureKey = Callable[[dict[str, list[int]], int], float]
FEATURE_JOB_KEYS: dict[str, FeatureKey] = {
    "FIFO": lambda f, j: f["entry"][j],
    "SPS": lambda f, j: f["n_ops"][j],
    "LPS": lambda f, j: -f["n_ops"][j],
    "SPTN": lambda f, j: f["next_duration"][j],
    "LPTN": lambda f, j: -f["next_duration"][j],
    "MTWR": lambda f, j: -f["remaining_work"][j],
    "LTWR": lambda f, j: f["remaining_work"][j],
    "LWT": lambda f, j: f["ready_since"][j],
    "SPT": lambda f, j: f["total_work"][j],
    "LPT": lambda f, j: -f["total_work"][j],
    "SPSR": lambda f, j: f["n_ops"][j] - f["next_op"][j],
    "LPSR": lambda f, j: -(f["n_ops"][j] - f["next_op"][j]),
}
assert set(FEATURE_JOB_KEYS) == set(JOB_RULES)


def _legal(state: dict[str, Any]) -> list[tuple[str, int, str]]:
    """The enabled actions of a state as ``(kind, number, label)``, in action order."""
    out = []
    for label, enabled in zip(state["actions"], state["mask"]):
        if enabled:
            kind, _, num = label.partition(":")
            if kind not in ("job", "agv", "tt") or not num.isdigit():
                raise DecisionError(f"state {state['seq']} has an action label {label!r} this agent does not know "
                                    "(expected job:J, agv:V or tt:R)")
            out.append((kind, int(num), label))
    if not out:
        raise DecisionError(f"state {state['seq']} enables no action, so there is nothing to decide")
    return out


class RuleDecider:
    """A job rule and a vehicle rule applied to a state's ``features`` (same choices as ``RulePolicy``)."""

    def __init__(self, job_rule: str, vehicle_rule: str) -> None:
        self.job_rule, self.vehicle_rule = job_rule, vehicle_rule
        self._key = FEATURE_JOB_KEYS[job_rule]

    @property
    def name(self) -> str:
        return f"rule:{self.job_rule}+{self.vehicle_rule}"

    def __call__(self, state: dict[str, Any]) -> str:
        legal = _legal(state)
        f = state.get("features")
        if f is None:
            raise DecisionError(f"state {state['seq']} has no 'features'; {self.name} needs them (start the shop "
                                "with features enabled)")
        try:
            for kind, group, req_name in (("agv", "agvs", "agv_request"), ("tt", "transporters", "tt_request")):
                cands = [(num, label) for k, num, label in legal if k == kind]
                if cands:
                    request = f.get(req_name)
                    if request is None:
                        raise DecisionError(f"state {state['seq']} offers {kind} actions but features."
                                            f"{req_name} is null")
                    return self._vehicle(cands, f[group], request["empty_travel"])
            key, cols = self._key, f["jobs"]
            jobs = [(num, label) for k, num, label in legal if k == "job"]
            return min(jobs, key=lambda c: (key(cols, c[0]), c[0]))[1]
        except (IndexError, KeyError) as exc:
            raise DecisionError(f"state {state['seq']}: features do not cover action {exc}; the state's features "
                                "and actions disagree") from None

    def _vehicle(self, cands: list[tuple[int, str]], cols: dict[str, list[int]], empty: list[int]) -> str:
        rule = self.vehicle_rule
        if rule == "first":
            return min(cands, key=lambda c: (cols["free_at"][c[0]], c[0]))[1]
        if rule == "least-work":
            return min(cands, key=lambda c: (cols["work"][c[0]], c[0]))[1]
        return min(cands, key=lambda c: (empty[c[0]], cols["work"][c[0]], c[0]))[1]


def make_decider(solver: str, seed: int = 0) -> tuple[Decider, str]:
    """The decision function and canonical name for a solver name; raises :class:`UnavailableSolver`."""
    if not isinstance(solver, str) or not solver.strip():
        raise UnavailableSolver(f"a solver must be named; choose from {', '.join(AGENT_SOLVERS)}")
    name = solver.strip()
    low = name.lower()
    if low == "first":
        return (lambda state: _legal(state)[0][2]), "first"
    if low == "random":
        rng = random.Random(seed)
        return (lambda state: rng.choice(_legal(state))[2]), "random"
    if low.startswith("rule:"):
        try:
            policy = parse_rule_name(name)
        except ValueError as exc:
            raise UnavailableSolver(f"solver {name!r}: {exc}") from None
        decider = RuleDecider(policy.job_rule, policy.vehicle_rule)
        return decider, decider.name
    base = low.split(":", 1)[0]
    if base in _PLANNED:
        raise UnavailableSolver(f"solver {name!r} is not available: {_PLANNED[base]} is not part of this build "
                                f"yet; choose from {', '.join(AGENT_SOLVERS)}")
    if base in _OFFLINE:
        raise UnavailableSolver(f"solver {name!r} plans a whole schedule offline and cannot decide state by state "
                                f"in the agent node; choose from {', '.join(AGENT_SOLVERS)}")
    raise UnavailableSolver(f"unknown solver {name!r}; the agent node accepts {', '.join(AGENT_SOLVERS)} "
                            f"(job rules: {', '.join(JOB_RULES)}; vehicle rules: {', '.join(VEHICLE_RULES)})")


class AgentLogic:
    """Answers each new state of a run with one command, decided by a solver.

    A state is answered once: a repeated ``(run_id, seq)`` (a latched state delivered again) or an older
    ``seq`` of the same run is ignored, as is a final (``done``) state. A state that cannot be decided on
    gives an ``fms/error/v1`` instead of a command.
    """

    def __init__(self, solver: str = "first", *, seed: int = 0, source: str = SOURCE) -> None:
        self.decide, self.name = make_decider(solver, seed)
        self.source = source
        self.run_id: str | None = None
        self.last_seq = -1           # the newest state seq seen in run_id
        self.answered_seq = -1       # the newest state seq answered in run_id
        self.decisions = 0

    def on_state(self, text: str) -> list[Outgoing]:
        """The command answering ``text`` (an ``fms/state/v1``), nothing, or an error."""
        try:
            state = decode(text, expect="state")
        except MessageError as exc:
            return [Outgoing(TOPIC_ERRORS, error_reply(self.source, exc, received=text))]
        run_id, seq = state["run_id"], state["seq"]
        if run_id != self.run_id:
            self.run_id, self.last_seq, self.answered_seq = run_id, -1, -1
        if seq <= self.last_seq:
            return []
        self.last_seq = seq
        if state["done"]:
            return []
        try:
            label = self.decide(state)
        except DecisionError as exc:
            return [Outgoing(TOPIC_ERRORS, make_error(self.source, "bad_schema", str(exc), run_id=run_id,
                                                      received=text))]
        self.answered_seq = seq
        self.decisions += 1
        return [Outgoing(TOPIC_COMMAND, make_command(run_id, seq, label, agent=self.name))]

    def waiting_for(self) -> tuple[str, int] | None:
        """``(run_id, seq)`` of the state last answered if no newer state has arrived since, else None."""
        if self.run_id is None or self.answered_seq < 0 or self.answered_seq != self.last_seq:
            return None
        return self.run_id, self.answered_seq


def legal_labels(state: dict[str, Any]) -> Sequence[str]:
    """The enabled action labels of a decoded state (a convenience for tests and tools)."""
    return [label for _, _, label in _legal(state)]
