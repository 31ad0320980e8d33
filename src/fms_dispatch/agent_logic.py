"""The dispatcher agent node's logic, without ROS: a state message in, a command (or an error) out.

For dispatching rules the agent never sees the :class:`~fms_sim.shop.Shop`; it decides from the ``fms/state/v1``
message alone. For dispatching rules the shop includes the optional ``features`` object in every state (per job: entry, number
of operations, next operation, its duration, remaining and total work, ready time; per vehicle: location,
free time, work; the pending AGV / tool-transport request with every vehicle's empty travel to its pickup).
:data:`FEATURE_JOB_KEYS` restates the twelve job rules of :mod:`fms_dispatch.rules` on those columns; the
tests check on whole runs that both choose the same action at every decision.

Solvers (the ``solver`` parameter):

* ``first`` — the lowest enabled action (like the offline ``first`` solver);
* ``random`` — uniform among the enabled actions, from ``seed``;
* ``rule:<JOB>[+<first|least-work|nearest>]`` — a dispatching rule pair (vehicle rule default first);
* ``ppo`` / ``ppo:<model>`` — the trained PPO policy (:mod:`fms_dispatch.rl`; ``ppo`` picks the shipped model
  that fits the instance). The policy reads the whole shop, not just rule features, so :class:`TwinDecider`
  keeps a local twin :class:`~fms_sim.shop.Shop` of the same instance (the agent's own ``instance``) and
  replays the state's ``history`` (applied action labels and accepted orders; the shop sends it when started
  with ``history``) into it. The twin is cached between states, so a new state costs one replayed step; the
  twin is checked against the state (time, action labels, mask) and rebuilt from scratch on a mismatch. If it
  still disagrees, the agent publishes an ``internal`` error *and* the first enabled action, so the run goes
  on. Nothing is kept across restarts: a restarted agent replays the latched state's history. From a shop that
  sends history deltas (``history_delta``: the labels since the state the last command answered) the twin applies
  each delta; where it cannot (a restart, a missed state, a disagreement) the agent asks for the state again with
  the whole history (:class:`NeedHistory`, a replay request ``what: "state"``) and answers that. Orders that take
  the shop past the model's padding (100 jobs for the default) hand the rest of the run over, with one
  ``internal`` error: a guided model to the guide follower, the expert it was cloned from; another model to a rule
  (:meth:`TwinDecider._outgrown`).
* ``lookahead`` / ``ppo+lookahead`` / ``ppo:<model>+lookahead`` — the PPO policy with pre-positioning of idle
  vehicles (:mod:`fms_dispatch.rl.lookahead`). It needs a shop started with ``idle_stops`` (and ``history``):
  such a shop also publishes a state when a vehicle stands idle between decisions (``idle`` lists the
  vehicles offered), and the twin, stepped by the same :class:`~fms_sim.stepping.Stepper`, answers it with
  :class:`~fms_dispatch.rl.lookahead.LookaheadPlanner`'s moves (``reposition:...``) or ``wait``. The run is
  the one the offline ``ppo+lookahead`` solver makes. ``+lookahead-fast`` is the same without retries of
  rejected moves (the offline ``ppo+lookahead-fast``); ``+lookahead-guide`` (a guided model) answers them with
  the guide plan's empty trips (the offline ``ppo+lookahead-guide``). Every other solver answers idle states
  with ``wait``.

* ``plan:<SOLVER>[:SECONDS]`` — a whole plan by an offline solver (``cpsat``, ``sos``, ``rules``, ``list``,
  ``rule:...``) computed at the first state within SECONDS, then executed through a twin of the full-decision
  net (:class:`PlanDecider`); ``plan:file:PATH`` executes the valid schedule in a file (made offline, with any
  budget). It needs a shop started with ``decisions:=full``, ``history`` and ``idle_stops``.

Offline solvers named alone (``sos``, ``cpsat``) raise :class:`UnavailableSolver` (use ``plan:sos``,
``plan:cpsat``), which the node turns into exit code 2.
"""

from __future__ import annotations

import random
from typing import TYPE_CHECKING, Any, Callable, Sequence

from fms_msgs_json import (
    TOPIC_COMMAND, TOPIC_ERRORS, TOPIC_REPLAY, MessageError, decode, error_reply, make_command, make_error,
    make_replay_request,
)
from fms_sim.instance import Instance, InstanceError, Operation
from fms_sim.petri import InvalidAction
from fms_sim.shop_service import Outgoing
from fms_sim.stepping import WAIT, Stepper, moves_label

from .forked import FORK_AVAILABLE, Forked
from .rules import JOB_RULES, VEHICLE_RULES, parse_rule_name
from .solvers import LOOKAHEAD_SUFFIXES

if TYPE_CHECKING:
    from fms_sim.shop import Shop

__all__ = ["AgentLogic", "UnavailableSolver", "DecisionError", "FallbackDecision", "NeedHistory", "FEATURE_JOB_KEYS",
           "make_decider", "AGENT_SOLVERS", "Decider", "TwinDecider", "load_ppo_agent", "needs_twin",
           "needs_idle_stops", "PlanDecider", "needs_full_net"]

SOURCE = "fms_agent"
AGENT_SOLVERS = ("first", "random", "rule:<JOB>[+<first|least-work|nearest>]", "ppo", "ppo:<model>",
                 "ppo[:<model>]+lookahead", "ppo[:<model>]+lookahead-fast", "ppo[:<model>]+lookahead-guide",
                 "plan:<SOLVER>[:SECONDS]", "plan:file:PATH")
_OFFLINE = {"sos", "cpsat"}

Decider = Callable[[dict[str, Any]], str]
"""A decision function: a decoded state message -> the label of the action to fire."""


class UnavailableSolver(ValueError):
    """The solver name is unknown, or names a solver this agent cannot run; the message lists the choices."""


class DecisionError(ValueError):
    """A state the solver cannot decide on (no enabled action, missing or inconsistent features)."""


class NeedHistory(Exception):
    """A state of a ``history_delta`` shop that the twin cannot follow (a restarted agent, a missed state, a twin
    that disagrees after the delta): the agent asks the shop for the state again with the whole history (a replay
    request with ``what: "state"``) and answers that one."""


class FallbackDecision(DecisionError):
    """The solver could not decide properly but names a safe action anyway: ``label`` is sent as the command
    and ``str(exc)`` is published as an ``internal`` error (e.g. the twin disagrees with the shop)."""

    def __init__(self, message: str, label: str) -> None:
        super().__init__(message)
        self.label = label


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


_PAPER_KINDS = ("job", "agv", "tt")
_FULL_KINDS = ("start", "use", "tool")  # and "hold", without a number


#: what replaying a state's history into the twin can raise on a history the shop could not have sent (its schema
#: leaves fields of a disruption optional, and a twin cannot check every entry before it applies it): the twin is then
#: rebuilt or the state answered by the fallback, as for a twin that disagrees (KeyError, TypeError: they crashed the
#: agent; ScenarioError is a ValueError)
_REPLAY_FAILURES = (InvalidAction, InstanceError, ValueError, KeyError, TypeError)


def _failure(exc: BaseException) -> str:
    """A replay failure in words (a KeyError alone says only the key)."""
    return f"{exc}" if isinstance(exc, (InvalidAction, InstanceError, ValueError)) else f"{type(exc).__name__}: {exc}"


def _legal(state: dict[str, Any]) -> list[tuple[str, int, str]]:
    """The enabled actions of a state as ``(kind, number, label)``, in action order (``hold``: number 0)."""
    out = []
    for label, enabled in zip(state["actions"], state["mask"]):
        if enabled:
            if label == "hold":
                out.append(("hold", 0, label))
                continue
            kind, _, num = label.partition(":")
            if kind not in _PAPER_KINDS + _FULL_KINDS or not (num.isascii() and num.isdigit()):  # "²" is a digit
                raise DecisionError(f"state {state['seq']} has an action label {label!r} this agent does not know "
                                    "(expected job:J, agv:V, tt:R, or on the full net start:J, use:J, tool:T, hold)")
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
        if any(k not in _PAPER_KINDS for k, _, _ in legal):
            raise DecisionError(f"state {state['seq']} is of the full net; {self.name} decides on the paper's net "
                                "(start the shop with decisions:=paper)")
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


def load_ppo_agent(model: str | None, instance: Instance) -> Any:
    """The trained :class:`fms_dispatch.rl.agent.Agent` for ``model`` (None: the shipped default for
    ``instance``); raises :class:`UnavailableSolver` if it cannot be loaded or the instance does not fit it.

    A thin adapter over :mod:`fms_dispatch.rl.models` (imported here: torch loads only for PPO agents)."""
    try:
        from .rl.models import default_model_name, load_agent
    except ImportError as exc:
        raise UnavailableSolver(f"the PPO agent needs torch and sb3-contrib ({exc}); install fms[rl]") from None
    name = model or default_model_name(instance)
    try:
        agent = load_agent(name)
    except (ValueError, OSError) as exc:
        raise UnavailableSolver(f"solver 'ppo:{name}': {str(exc).splitlines()[0]}") from None
    if not agent.fits(instance):
        raise UnavailableSolver(agent.misfit(instance))
    return agent


def _extends(text: str, done: str) -> bool:
    """Whether the history ``text`` (labels joined by single spaces) continues ``done`` (the labels replayed so far,
    joined the same way) label by label: ``"a b c"`` continues ``"a b"``, ``"a bc"`` does not."""
    return text.startswith(done) and (not done or len(text) == len(done) or text[len(done)] == " ")


class TwinDecider:
    """A policy over a local twin :class:`~fms_sim.shop.Shop`, kept in step with the states' ``history``.

    ``choose(shop) -> net action`` is the policy (e.g. ``Agent.act``); ``planner`` (optional, a
    :class:`~fms_dispatch.rl.lookahead.LookaheadPlanner`) answers idle stops, else they are answered ``wait``.
    The twin is a :class:`~fms_sim.stepping.Stepper` with idle stops exactly when the states carry ``idle``.
    It is rebuilt from ``instance`` when a state belongs to another run or its history does not extend the
    one replayed so far; otherwise only the new entries are replayed. See the module docstring for the checks
    and the fallback.

    A ``choose`` that re-plans (:class:`fms_dispatch.rl.agent.GuideReplanner`: a guided model that re-plans its
    guide when a machine breaks down or its plan runs late) is asked for a trigger before every answer; a re-plan
    then runs beside the decisions, in a forked process (:data:`REPLAN_IN_PROCESS`; a thread on a copy of the twin
    elsewhere), while the plan in force goes on answering, so the shop never waits for it. Once done it is put in
    force if it ends the replanner's margin earlier than the plan in force continued from the trigger's state (as
    the offline run decides); one not done after its budget plus :data:`REPLAN_GRACE_S` is reported ``timeout``
    (its process ended). A live order is answered at once by a bridge plan (the plan in force with the new jobs
    after it); a re-plan running then runs on, and once in it is put in force re-timed from the state with the new
    jobs after its own where it beats the plan it was started against; the order's own re-plan starts then (ending
    the running one for each order starved re-planning where orders came faster than a search ends). Each is
    published as an ``fms/replan/v1`` (:meth:`drain`). With ``replan_wait`` the state that triggers a re-plan is
    answered once the re-plan is done, so a simulated shop waits for it and the run is the offline one.
    """

    handles_idle = True
    decisions = "paper"
    """The net of the twin (and of the shop it follows)."""

    def __init__(self, instance: Instance, choose: Callable[["Shop"], int], name: str, planner: Any = None,
                 source: str = SOURCE, replan_wait: bool = False) -> None:
        self.instance = instance
        self.choose = choose
        self.replan_wait = bool(replan_wait)
        self._job: _ReplanJob | None = None  # the re-plan running beside the decisions
        # a re-planning choose re-plans here, beside the decisions; its model decides
        self._act: Callable[["Shop"], int] = choose.agent.act if hasattr(choose, "trigger") else choose  # type: ignore
        self.name = name
        self.planner = planner
        self.source = source
        self._outbox: list[Outgoing] = []  # messages to publish after the next answer (drain)
        self.stepper: Stepper | None = None
        self._run_id: str | None = None
        self._idle_stops = False
        self._labels: list[str] = []           # labels replayed into the twin
        # the same joined by spaces (the history's text that far); None after deltas (joined when next needed)
        self._text: str | None = ""
        self._orders: list[dict[str, Any]] = []  # orders replayed into the twin
        self._disruptions: list[dict[str, Any]] = []  # disruptions replayed into the twin
        self._scenario: dict[str, Any] | None = None  # the run's scenario from the history (twin mirrors it)
        self.rebuilds = 0                       # twins built from scratch (for tests and logs)
        self.model_path: Any = None              # the weights file the policy was loaded from (logged)
        self.model: Any = None                   # the policy's model (its padding limits the shops it can decide)
        self._guide_jobs: int | None = None      # the jobs of the run when its guide was last planned for them
        self._order_due = False  # an order came while a guide re-plan ran: its own re-plan starts once that one is in
        self._handover: Callable[["Shop"], int] | None = None  # decides once the shop outgrew the model

    @property
    def twin(self) -> "Shop | None":
        return None if self.stepper is None else self.stepper.shop

    def _reset(self, run_id: str, idle_stops: bool) -> None:
        from fms_sim.full_shop import make_shop

        from fms_sim.disruptions import Scenario

        scenario = Scenario.from_dict(self._scenario) if self._scenario is not None else None
        if self._job is not None and self._job.run_id != run_id:  # a re-plan of another run is dropped
            self._job.cancel()
            self._job = None
        self.stepper = Stepper(make_shop(self.instance, self.decisions, scenario), idle_stops=idle_stops)
        self.stepper.advance()
        self._run_id, self._idle_stops, self._labels, self._orders = run_id, idle_stops, [], []
        self._text = ""
        self._handover = None
        self._guide_jobs = None
        self._order_due = False
        self._disruptions = []
        self.rebuilds += 1

    def _replay(self, new: list[str], orders: list[dict[str, Any]],
                disruptions: list[dict[str, Any]] | None = None, orders_from: int = 0,
                disruptions_from: int = 0) -> int:
        """Apply the entries of the history beyond those already replayed (``new``: the labels after them;
        ``orders`` and ``disruptions`` the history's from its ``orders_from`` and ``disruptions_from`` on; raises on
        an impossible step); returns how many were applied (labels, orders and disruptions)."""
        from fms_sim.disruptions import Breakdown, Outage

        st = self.stepper
        assert st is not None
        disruptions = disruptions or []
        p, q, r = len(self._labels), len(self._orders), len(self._disruptions)
        base = p
        applied = 0
        while True:
            while True:  # the orders and disruptions that came before action p, in the order they came
                d_entry = (disruptions[r - disruptions_from]
                           if 0 <= r - disruptions_from < len(disruptions) else None)
                order = orders[q - orders_from] if 0 <= q - orders_from < len(orders) else None
                if d_entry is not None and d_entry["at"] == p and d_entry["orders_before"] == q:
                    d = d_entry["disruption"]
                    st.disrupt(Breakdown(d["machine"], d["start"], d["duration"]) if d["kind"] == "breakdown"
                               else Outage(d["vehicle_kind"], d["vehicle"], d["start"], d["duration"]))
                    self._disruptions.append(d_entry)
                    r += 1
                    applied += 2
                elif order is not None and order["at"] == p:
                    jobs = [[Operation(op["machine"], op.get("tool"), op["duration"]) for op in ops]
                            for ops in order["jobs"]]
                    st.add_jobs(jobs)
                    self._orders.append(order)
                    q += 1
                    applied += 2  # an order changes the run: never "one step on" (see sync)
                else:
                    break
            if p - base >= len(new):
                return applied
            label = new[p - base]
            self._applying(label)
            st.apply(label)
            self._labels.append(label)
            p += 1
            applied += 1

    def _applying(self, label: str) -> None:
        """Called before the twin applies each label of the history (a plan follows the run with it)."""

    def _agrees(self, state: dict[str, Any]) -> str | None:
        """None if the twin matches the state (time, labels, mask, idle vehicles); else what differs."""
        st = self.stepper
        assert st is not None
        twin = st.shop
        if twin.now != state["time"]:
            return f"twin time {twin.now} != state time {state['time']}"
        if twin.action_labels() != state["actions"]:
            return "the twin's action labels differ from the state's"
        if list(st.mask()) != state["mask"]:
            return "the twin's mask differs from the state's"
        idle = state.get("idle")
        if idle is not None and [(d["kind"], d["vehicle"], d["location"]) for d in idle] != list(map(tuple, st.idle)):
            return "the twin's idle vehicles differ from the state's"
        return None

    def sync(self, state: dict[str, Any]) -> None:
        """Bring the twin to ``state``; raises :class:`DecisionError` (no history, other instance) or
        :class:`FallbackDecision` (the replayed twin disagrees with the state even when rebuilt)."""
        history = state.get("history")
        if history is None:
            raise DecisionError(f"state {state['seq']} has no 'history'; {self.name} replays it into a twin of "
                                "the shop (start the shop with history:=true)")
        net = state.get("decisions", "paper")
        if net != self.decisions:
            raise DecisionError(f"state {state['seq']} is of the {net!r} net but {self.name} decides on the "
                                f"{self.decisions!r} net; start the shop with decisions:={self.decisions}")
        name = state.get("instance")
        if name is not None and name != self.instance.name:
            raise DecisionError(f"state {state['seq']} is of instance {name!r} but this agent holds "
                                f"{self.instance.name!r}; give the agent the shop's instance")
        idle_stops = state.get("idle") is not None
        if self.planner is not None and not idle_stops:
            raise DecisionError(f"state {state['seq']} has no 'idle' field; {self.name} pre-positions idle "
                                "vehicles at the shop's idle stops (start the shop with idle_stops:=true)")
        scenario = history.get("scenario")
        if scenario != self._scenario:
            self._scenario, self.stepper = scenario, None  # another run's disruptions: rebuild the twin
        starts = (history.get("actions_from", 0), history.get("orders_from", 0), history.get("disruptions_from", 0))
        if any(starts):  # a delta (a history_delta shop): what was applied since an earlier state
            self._sync_delta(state, history, *starts, idle_stops)
            return
        # the history grows by a label or two per state (20,000 on sl70): only what follows the text already replayed
        # is split and applied; the rest is compared as text (a split and a list comparison per state made each
        # state cost in proportion to the run so far)
        text = history["actions"]
        if self._text is None:  # (deltas were followed: join once)
            self._text = " ".join(self._labels)
        done = self._text
        extends = _extends(text, done)
        orders = history["orders"]
        disruptions = history.get("disruptions") or []
        m, k = len(self._orders), len(self._disruptions)
        fresh = (self.stepper is None or self._run_id != state["run_id"] or self._idle_stops != idle_stops
                 or not extends or len(orders) < m or orders[:m] != self._orders
                 or len(disruptions) < k or disruptions[:k] != self._disruptions)
        problem = None
        for attempt in range(2):
            try:
                if fresh or attempt:
                    self._reset(state["run_id"], idle_stops)  # (a scenario in the history that cannot be read)
                tail = text[len(self._text) + 1:] if self._text else text
                applied = self._replay(tail.split(" ") if tail else [], orders, disruptions)
                self._text = text
                problem = self._agrees(state)
            except _REPLAY_FAILURES as exc:
                problem = f"replaying the history failed: {_failure(exc)}"
            if problem is None:
                # the planner's cached completion holds while the run moves one answer at a time
                if self.planner is not None and (fresh or attempt or applied != 1):
                    self.planner.reset()
                return
            if fresh:  # already rebuilt from scratch: no second try
                break
        self.stepper = None  # start afresh next time
        raise FallbackDecision(f"state {state['seq']}: the twin of the shop disagrees with the state ({problem}); "
                               f"sending {_fallback(state)!r}", _fallback(state))

    def _sync_delta(self, state: dict[str, Any], history: dict[str, Any], actions_from: int, orders_from: int,
                    disruptions_from: int, idle_stops: bool) -> None:
        """Bring the twin to ``state`` from a delta history (what was applied since the state the last command
        answered, from ``actions_from``, ``orders_from`` and ``disruptions_from`` on); raises :class:`NeedHistory`
        where the twin cannot follow it (none yet, another run, a gap, or it disagrees with the state after it)."""
        text = history["actions"]
        labels = text.split(" ") if text else []
        orders, disruptions = history["orders"], history.get("disruptions") or []
        n, m, k = len(self._labels), len(self._orders), len(self._disruptions)
        twin = self.stepper is not None and self._run_id == state["run_id"] and self._idle_stops == idle_stops
        follows = (twin and actions_from <= n <= actions_from + len(labels)
                   and self._labels[actions_from:] == labels[:n - actions_from]
                   and orders_from <= m <= orders_from + len(orders)
                   and self._orders[orders_from:] == orders[:m - orders_from]
                   and disruptions_from <= k <= disruptions_from + len(disruptions)
                   and self._disruptions[disruptions_from:] == disruptions[:k - disruptions_from])
        if not follows:
            self.stepper = None
            raise NeedHistory(f"state {state['seq']}: its history follows action {actions_from}, order "
                              f"{orders_from} and disruption {disruptions_from} of the run, but "
                              + (f"the twin has replayed {n}, {m} and {k}" if twin else "there is no twin of it"))
        try:
            applied = self._replay(labels[n - actions_from:], orders, disruptions, orders_from, disruptions_from)
            problem = self._agrees(state)
        except _REPLAY_FAILURES as exc:
            problem = f"replaying the history failed: {_failure(exc)}"
        self._text = None
        if problem is not None:
            self.stepper = None
            raise NeedHistory(f"state {state['seq']}: the twin disagrees with the state after its history "
                              f"({problem})")
        if self.planner is not None and applied != 1:
            self.planner.reset()

    def drain(self) -> list[Outgoing]:
        """The messages (``fms/replan/v1``) to publish after the last answer."""
        out, self._outbox = self._outbox, []
        return out

    def _check_replan(self, state: dict[str, Any], shop: "Shop") -> None:
        """Let a re-planning ``choose`` look at the synced twin: collect a re-plan that is done, else start one when
        a trigger fires (a breakdown begun, a late plan); see the class docstring."""
        trigger = getattr(self.choose, "trigger", None)
        if trigger is None:
            return
        self._collect_guide(state, shop)
        rp = self.choose
        reason = None
        if self._guide_jobs is not None and shop.n_jobs > self._guide_jobs:  # an order: go on with a bridge plan
            if rp.agent.bridge_guide(shop) is not None:
                # a re-plan running meanwhile runs on (ending it for each order starved re-planning where orders came
                # faster than a search ends): once in, it is put in force with the new jobs after it where it beats
                # the plan it was started against (_collect_guide), and the order's own re-plan starts then
                self._order_due = True
        self._guide_jobs = shop.n_jobs
        if self._job is not None:
            return
        if self._order_due:
            self._order_due, reason = False, "order"
        reason = reason or trigger(shop)
        if reason is None:
            return
        old, effort = rp.inputs(shop)
        job = _ReplanJob(_guide_replan, (shop, old, effort), reason, state["run_id"], state["seq"], shop.now,
                         budget=effort.budget, method="guide", thread_copy=True)
        job.n_jobs = shop.n_jobs
        job.taken_at = (shop.now, shop.net.acted)  # type: ignore[attr-defined]  # a guided model runs a FullShop
        self._job = job
        if self.replan_wait:
            self._await(job)
            self._collect_guide(state, shop)

    @staticmethod
    def _await(job: "_ReplanJob") -> None:
        """Wait for ``job`` until it is done or past its budget plus the grace (then the collector reports it
        ``timeout``; a job without a budget is waited for until it is done)."""
        job.done.wait(None if job.budget is None else job.budget + REPLAN_GRACE_S + 0.1)

    def _expired(self, job: "_ReplanJob") -> float | None:
        """If ``job``, not done, is past its budget plus the grace: drop it (a process is ended) and return its
        elapsed seconds, for the collector to report it ``timeout``; else None."""
        elapsed = job.elapsed()
        if job.done.is_set() or job.budget is None or elapsed <= job.budget + REPLAN_GRACE_S:
            return None
        self._job = None  # its plan is dropped
        job.cancel()
        return elapsed

    def _end_guide_job(self, shop: "Shop", why: str) -> None:
        """End the guide re-plan that runs, if one does (a process is ended), and report it ``failed`` for ``why``."""
        job, self._job = self._job, None
        if job is not None:
            job.cancel()
            self._drop_guide(job, shop, "failed", job.elapsed(), why)

    def _drop_guide(self, job: "_ReplanJob", shop: "Shop", status: str, wall: float, why: str) -> None:
        """A guide re-plan that brings no plan (``failed`` or ``timeout``): recorded by the replanner, reported."""
        self.choose.failed(shop, job.reason, job.time, status, wall, job.budget, why)
        self._report(job.run_id, job.seq, job.time, job.reason, status, wall, None, None, "guide", why,
                     budget=job.budget)

    def _collect_guide(self, state: dict[str, Any], shop: "Shop") -> None:
        """Put a finished guide re-plan in force if it is better (or report why not) and queue its message."""
        job = self._job
        if job is None:
            return
        if not job.done.is_set():
            elapsed = self._expired(job)
            if elapsed is not None:
                self._drop_guide(job, shop, "timeout", elapsed, f"no plan {elapsed:.1f} s after the trigger (budget "
                                 f"{job.budget:g} s); the plan in force stays")
            return
        self._job = None
        if job.error is not None:
            self._drop_guide(job, shop, "failed", job.wall, job.error)
            return
        from fms_sim.snapshot import can_snapshot

        if not can_snapshot(shop):  # a plan made meanwhile is re-timed from a state with no choice pending
            self._job = job
            return
        plan, before = job.result
        # the run moved on meanwhile: the plan is re-timed from the state now (jobs that joined meanwhile after its
        # own, as the bridge plan has them), where it beats the plan in force as both stood at the trigger
        moved = (shop.now, shop.net.acted) != job.taken_at or shop.n_jobs != job.n_jobs  # type: ignore[attr-defined]
        ev = self.choose.adopt(shop, job.reason, job.time, plan, before, job.wall, job.budget, moved)
        self._report(job.run_id, job.seq, job.time, job.reason, ev["status"], job.wall, ev["before"], ev["after"],
                     "guide", None, budget=job.budget)

    def finish(self, state: dict[str, Any]) -> list[Outgoing]:
        """At the run's final state: a re-plan not yet in force is reported ``timeout`` (its plan is dropped; one still
        running is ended), so every trigger gets its ``fms/replan/v1``. One that was done but not collected says so,
        with its own wall time (it was reported as not done); one that failed is reported ``failed`` with its error."""
        job = self._job
        if job is None or job.run_id != state["run_id"]:
            return []
        self._job = None
        done = job.done.is_set()
        job.cancel()
        elapsed = job.elapsed()
        budget = "no" if job.budget is None else f"{job.budget:g} s"
        if done and job.error is not None:  # it failed: no plan to drop, and its error is the news
            self._report(job.run_id, job.seq, job.time, job.reason, "failed", job.wall, None, None, job.method,
                         job.error, budget=job.budget)
            return self.drain()
        if done:
            wall, why = job.wall, (f"the run ended before its plan could be put in force (the re-plan was done after "
                                   f"{job.wall:.1f} s, budget {budget}); its plan was dropped")
        else:
            wall, why = elapsed, (f"the run ended {elapsed:.1f} s after the trigger, before the re-plan was done "
                                  f"(budget {budget}); its plan was dropped")
        self._report(job.run_id, job.seq, job.time, job.reason, "timeout", wall, None, None, job.method, why,
                     budget=job.budget)
        return self.drain()

    def _report(self, run_id: str, seq: int, time: int, reason: str, status: str, wall: float, before: Any,
                after: Any, method: Any, message: Any, *, budget: float | None) -> None:
        """Queue an ``fms/replan/v1`` (a re-plan without a budget reports its wall time as its budget)."""
        from fms_msgs_json import TOPIC_REPLANS, make_replan

        self._outbox.append(Outgoing(TOPIC_REPLANS, make_replan(
            run_id, self.source, seq, time, reason, status, budget_s=wall if budget is None else budget, wall_s=wall,
            before=before, after=after, method=method, message=message)))

    def _outgrown(self, state: dict[str, Any], shop: "Shop") -> Callable[["Shop"], int] | None:
        """The policy that decides for a model the shop has outgrown (orders took it past the model's padding: it
        cannot observe the shop any more), or None while the model fits. The first such state raises
        :class:`FallbackDecision` once, naming the hand-over; the run is then decided by the guide follower (a guided
        model: the expert it was cloned from, acting out a plan searched from the state with the model's search, no
        size limit) or by the full-net rule ``rule:MTWR+nearest+fifo`` (a full-net model without a guide), or by the
        rule pair ``MTWR+nearest`` (a paper-net model)."""
        model = self.model
        if model is None or (self._handover is None and model.fits(shop.instance)):
            return None
        if self._handover is None:
            if model.guide is not None:
                from .rl.guide import GuideFollower

                self._handover = GuideFollower(effort=model.guide_effort)
                what = "the guide follower (the expert it was cloned from)"
            elif self.decisions == "full":
                from .full_rules import parse_full_rule

                self._handover, what = parse_full_rule("rule:MTWR+nearest+fifo"), "rule:MTWR+nearest+fifo"
            else:
                self._handover, what = parse_rule_name("MTWR+nearest"), "the rule pair MTWR+nearest"
            label = WAIT if self.stepper.kind == "idle" else shop.action_label(self._handover(shop))
            why = (f"the shop ({shop.instance.n_jobs} jobs) has outgrown model {model.name} ({model.layout()}); {what} "
                   "decides from here on")
            self._end_guide_job(shop, why)  # the model's re-plan is of no use now (it ran on, reported at the end)
            raise FallbackDecision(f"state {state['seq']}: {why}", label)
        return self._handover

    def __call__(self, state: dict[str, Any]) -> str:
        self.sync(state)
        st = self.stepper
        assert st is not None
        try:
            handover = self._outgrown(state, st.shop)
            if handover is not None:  # (no re-plans, no pre-positioning: those are the model's)
                return WAIT if st.kind == "idle" else st.shop.action_label(handover(st.shop))
            self._check_replan(state, st.shop)
            if st.kind == "idle":
                return WAIT if self.planner is None else moves_label(self.planner.plan(st))
            legal = _legal(state)
            if len(legal) == 1:
                return legal[0][2]
            return st.shop.action_label(self._act(st.shop))
        except FallbackDecision:
            raise
        except (ValueError, RuntimeError, IndexError) as exc:
            raise FallbackDecision(f"state {state['seq']}: {self.name} failed ({exc}); sending "
                                   f"{_fallback(state)!r}", _fallback(state)) from None


class PlanDecider(TwinDecider):
    """``plan:SOLVER[:SECONDS]``: at the first state, solve the shop's instance offline with SOLVER within
    SECONDS, then answer every state of the run from that plan through a twin of the full-decision net
    (:class:`fms_sim.replay.PlanPolicy`): the run is the one the offline ``plan:`` solver makes.

    The plan follows the run: each label of the history moves it on as the twin applies it, so answers never
    drift from what the shop did. With ``replan`` > 0 (seconds, the budget of one re-plan) the agent re-plans
    (:mod:`fms_dispatch.replan`) when an order arrives, a breakdown or outage begins, an operation starts late by
    more than ``drift`` of the plan's makespan, or the plan cannot go on. A re-plan runs in a forked process
    (:data:`REPLAN_IN_PROCESS`; a thread elsewhere) from a snapshot of the twin; until it is ready the current plan
    answers (jobs it does not cover wait; a state it cannot answer gets the ``fallback`` rule), so the shop never
    waits for it. A finished re-plan is put in force if it predicts an earlier end (always for an order) and is
    published as an ``fms/replan/v1`` (:meth:`drain`); one not done after its budget plus :data:`REPLAN_GRACE_S` is
    reported ``timeout`` (a process is then ended) and the current plan stays. With ``replan_wait`` the state that triggers a re-plan is answered only once the re-plan is
    done (and by the new plan, if it is put in force): the shop waits, as the offline re-planning does. That suits a
    simulated shop, which otherwise runs on under the old plan for as many states as the agent answers meanwhile; a
    real shop goes on anyway. With ``replan`` 0, jobs the plan does not know and a plan that cannot go on are
    answered by the fallback rule from then on, and the first such state publishes an ``internal`` error."""

    decisions = "full"

    def __init__(self, instance: Instance, name: str, fallback: str = "rule:MTWR+nearest+fifo",
                 replan: float = 0.0, drift: float | None = None, source: str = SOURCE,
                 replan_wait: bool = False) -> None:
        from fms_dispatch.full_rules import parse_full_rule

        from .replan import DEFAULT_DRIFT

        super().__init__(instance, lambda shop: 0, name, source=source, replan_wait=replan_wait)
        from .solvers import parse_plan_name

        if replan < 0:
            raise UnavailableSolver(f"the re-planning budget must be >= 0 seconds (0: off), got {replan}")
        self.base, self.seconds = parse_plan_name(name)
        self.fallback_name = fallback
        self.fallback = parse_full_rule(fallback)
        self.replan_budget = float(replan)
        self.drift = DEFAULT_DRIFT if drift is None else float(drift)
        if not self.drift > 0:
            raise UnavailableSolver(f"the re-planning drift must be positive, got {self.drift}")
        self.plan: Any = None
        self.policy: Any = None
        self.replanner: Any = None
        self.plan_wall_time: float | None = None
        self.plan_error: str | None = None      # why no plan could be made (the fallback rule decides then)
        self.on_fallback = False
        self._answered: str | None = None  # the plan's last answer, not yet seen in the history
        if self.base.lower().startswith("file:"):
            self._make_plan()  # a given plan is checked at once: a bad file stops the agent before the run

    def _make_plan(self) -> None:
        import time

        from .solvers import make_plan

        t0 = time.perf_counter()
        self.plan = make_plan(self.instance, self.base, self.seconds)
        self.plan_wall_time = time.perf_counter() - t0

    def _reset(self, run_id: str, idle_stops: bool) -> None:
        super()._reset(run_id, idle_stops)
        if self.plan is None and self.plan_error is None:
            try:
                self._make_plan()
            except (ValueError, RuntimeError) as exc:  # e.g. no schedule within the budget
                self.plan_error = str(exc).splitlines()[0]
        from fms_sim.replay import PlanPolicy

        from .replan import Replanner

        # a fresh twin: the plan starts over with it (a re-plan of an earlier twin is dropped)
        if self._job is not None:
            self._job.cancel()
        self._job = None
        self._answered = None
        self.replanner = None  # with re-planning, the plan's policy is the replanner's (it changes with each plan)
        self.policy = None
        if self.plan is not None:
            if self.replan_budget > 0:
                self.replanner = Replanner(self.instance, self.plan, budget=self.replan_budget, drift=self.drift)
            else:
                self.policy = PlanPolicy(self.instance, self.plan)
        self.on_fallback = self.plan is None

    def _applying(self, label: str) -> None:
        st = self.stepper
        rp = self.replanner
        if st is None or self.on_fallback or (self.policy is None and rp is None):
            return
        if rp is None:
            if st.shop.n_jobs != self.instance.n_jobs:
                self.on_fallback = True  # an order joined: the plan no longer covers the run
                return
            self.policy.apply(st, label)
            return
        from fms_sim.replay import ReplayError

        self._resync()
        planned, self._answered = self._answered, None
        if planned is None:  # not our last answer (another state, a restart): ask the plan
            try:
                planned = rp.answer(st)
            except ReplayError:
                planned = None
        if label == planned:
            rp.apply(st, label)
        else:  # the run did something else here (the fallback answered, or a plan adopted meanwhile)
            rp._off_plan = True

    def _resync(self) -> None:
        """After a label the plan did not give, the plan goes on from the twin's state."""
        rp = self.replanner
        if rp is not None and rp._off_plan and self.stepper is not None:
            from fms_sim.replay import PlanPolicy

            rp.policy = PlanPolicy.resume(self.stepper.shop, rp.plan)
            rp._off_plan = False

    def __call__(self, state: dict[str, Any]) -> str:
        if state.get("idle") is None:
            raise DecisionError(f"state {state['seq']} has no 'idle' field; {self.name} moves vehicles at the "
                                "shop's idle stops (start the shop with idle_stops:=true)")
        self.sync(state)
        st = self.stepper
        assert st is not None
        if self.plan_error is not None:
            why, self.plan_error = self.plan_error, ""  # said once; "" keeps the plan from being tried again
            if why:
                raise FallbackDecision(f"state {state['seq']}: {self.name} could not plan ({why}); "
                                       f"{self.fallback_name} decides from here on", self._fallback_answer(st))
        if self.replanner is not None and not self.on_fallback:
            return self._answer_replanning(state, st)
        if not self.on_fallback and st.shop.n_jobs != self.instance.n_jobs:
            self.on_fallback = True
            raise FallbackDecision(f"state {state['seq']}: jobs joined that the plan of {self.name} does not cover "
                                   f"(re-planning is off); {self.fallback_name} decides from here on",
                                   self._fallback_answer(st))
        if self.on_fallback:
            return self._fallback_answer(st)
        try:
            return self.policy.answer(st)
        except ValueError as exc:
            self.on_fallback = True
            raise FallbackDecision(f"state {state['seq']}: {self.name} cannot go on ({exc}); "
                                   f"{self.fallback_name} decides from here on", self._fallback_answer(st)) from None

    def _fallback_answer(self, st: Stepper) -> str:
        if st.kind == "idle":
            return WAIT
        return st.shop.action_label(self.fallback(st.shop))

    # ------------------------------------------------------------------ re-planning beside the decisions
    def _answer_replanning(self, state: dict[str, Any], st: Stepper) -> str:
        from fms_sim.replay import ReplayError

        rp = self.replanner
        shop = st.shop
        self._resync()
        self._collect(state)
        if self._job is None:
            reason = rp.trigger(shop)
            if reason is not None:
                self._start(reason, state)
                self._wait(state)
        try:
            self._answered = rp.answer(st)  # the next history label is this one if the shop applied it
            return self._answered
        except ReplayError:
            self._answered = None
            if self._job is None and rp.can_snapshot(shop):
                self._start("stuck", state)
                if self._wait(state):  # answered by the new plan, if it can
                    try:
                        self._answered = rp.answer(st)
                        return self._answered
                    except ReplayError:
                        self._answered = None
            rp._off_plan = True
            return self._fallback_answer(st)

    def _wait(self, state: dict[str, Any]) -> bool:
        """With ``replan_wait``: wait for the re-plan just started (at most its budget plus the grace) and put it in
        force; returns whether a re-plan was collected."""
        job = self._job
        if not self.replan_wait or job is None:
            return False
        self._await(job)
        self._collect(state)
        self._resync()
        return self._job is None

    def _start(self, reason: str, state: dict[str, Any]) -> None:
        rp = self.replanner
        shop = self.stepper.shop
        try:
            args = rp.take(shop)
        except ValueError as exc:  # pragma: no cover - take is only called where a snapshot can be taken
            self._report(state["run_id"], state["seq"], shop.now, reason, "failed", 0.0, None, None, None, str(exc),
                         budget=self.replan_budget)
            return
        self._job = _ReplanJob(rp.compute, args, reason, state["run_id"], state["seq"], shop.now, budget=rp.budget)

    def _collect(self, state: dict[str, Any]) -> None:
        """Put a finished re-plan in force (or report a timed-out one) and queue its message."""
        job = self._job
        if job is None:
            return
        rp = self.replanner
        if not job.done.is_set():
            elapsed = self._expired(job)
            if elapsed is not None:
                rp.dropped(self.stepper.shop)
                self._report(job.run_id, job.seq, job.time, job.reason, "timeout", elapsed, None, None, None,
                             f"no plan {elapsed:.1f} s after the trigger (budget {rp.budget:g} s); the current "
                             "plan stays in force", budget=rp.budget)
            return
        shop = self.stepper.shop
        if job.error is None and not rp.can_snapshot(shop):
            return  # a plan made meanwhile is re-timed from a state where no choice is pending: collect it then
        self._job = None
        if job.error is not None:
            ev = rp.adopt(shop, None, job.reason, wall_time=job.wall, error=job.error)
        else:
            ev = rp.adopt(shop, job.result, job.reason, wall_time=job.wall)
        self._report(job.run_id, job.seq, job.time, job.reason, ev["status"], job.wall, ev.get("before"),
                     ev.get("after"), ev.get("method"), ev.get("error"), budget=rp.budget)


REPLAN_GRACE_S = 5.0
"""How long past its budget a re-plan may run before the agent reports it ``timeout``."""


REPLAN_IN_PROCESS = FORK_AVAILABLE
"""Whether a live re-plan runs in a forked process (on Linux) rather than in a thread of the agent. In a thread it
shares the interpreter lock with the decisions: each is about half as fast while the other runs (on sl70 the agent
answered 667-869 states during a 2 s re-plan in a thread against 1,680-1,887 in a process; docs/benchmarks.md §8). A
forked process needs nothing pickled (it starts as a copy of the agent, in a few milliseconds) and sends only the
result back."""


def _guide_replan(shop: "Shop", old: Any, effort: Any) -> Any:
    """A guide re-plan beside the run (:func:`fms_dispatch.rl.guide.replan_search`): ``(new plan, before)``."""
    from .rl.guide import replan_search

    return replan_search(shop, old, effort)  # type: ignore[arg-type]


class _ReplanJob:
    """One re-plan running in a forked daemon process (:data:`REPLAN_IN_PROCESS`) or a daemon thread; a node that
    stops never waits for it. :meth:`cancel` ends a process at once (a thread ends by itself: its searches have
    time limits). With ``thread_copy`` a re-plan that runs in a thread gets deep copies of ``args`` (taken here,
    before the caller goes on: the twin it reads keeps moving); a forked process has its own copy anyway."""

    def __init__(self, fn: Callable[..., Any], args: tuple, reason: str, run_id: str, seq: int, time: int, *,
                 budget: float | None = None, method: str | None = None, thread_copy: bool = False) -> None:
        import threading
        import time as _time

        self.reason, self.run_id, self.seq, self.time = reason, run_id, seq, time
        self.budget, self.method = budget, method  # the search's budget in seconds (None: none); as reported
        self.n_jobs = 0  # the run's jobs when it started (set by the caller that needs it)
        self.result: Any = None
        self.error: str | None = None
        self.wall = 0.0
        self.done = threading.Event()
        self._t0 = _time.monotonic()
        self._clock = _time.monotonic
        self.process: Any = None  # the child process (pid, exitcode), where the re-plan runs in one
        self._forked: Forked | None = None
        if REPLAN_IN_PROCESS:
            try:
                self._forked = Forked(fn, args, name="fms-replan")
            except OSError:  # no fork now (out of memory or processes), or a daemonic process (a multiprocessing.Pool's
                pass  # worker, which may not start one): the re-plan runs in a thread instead
            else:
                self.process = self._forked.process
        if self._forked is None and thread_copy:  # a thread shares the agent's objects: it works on copies
            import copy

            args = copy.deepcopy(args)
        forked = self._forked
        if forked is not None:

            def work() -> None:
                try:
                    self.result = forked.result()  # (reaped there, before done is set)
                except RuntimeError as exc:  # its error, or its death (killed, out of memory, cancelled)
                    self.error = str(exc)
                self.wall = self._clock() - self._t0
                self.done.set()
        else:
            def work() -> None:
                try:
                    self.result = fn(*args)
                except Exception as exc:  # noqa: BLE001 - reported as a failed re-plan, the plan stays
                    self.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                self.wall = self._clock() - self._t0
                self.done.set()

        threading.Thread(target=work, name="fms-replan", daemon=True).start()

    def elapsed(self) -> float:
        return self._clock() - self._t0

    def cancel(self) -> None:
        """Stop a re-plan that is no longer wanted (a process is terminated; a thread runs out by itself)."""
        if self._forked is not None and not self.done.is_set():  # (only the job's own thread reaps the process)
            self._forked.terminate()


def needs_full_net(solver: str) -> bool:
    """Whether ``solver`` decides on the full-decision net (plan solvers): the shop must run it, with history
    and idle stops."""
    return solver.strip().lower().startswith("plan:")


def _fallback(state: dict[str, Any]) -> str:
    """The safe answer to a state: ``wait`` at an idle stop, else the first enabled action."""
    return WAIT if state.get("idle") else _legal(state)[0][2]


def needs_twin(solver: str) -> bool:
    """Whether ``solver`` is a PPO solver, which replays the run into a twin: the shop must send history."""
    low = solver.strip().lower()
    return low in ("ppo", "lookahead") or low.startswith(("ppo:", "ppo+"))


def needs_idle_stops(solver: str) -> bool:
    """Whether ``solver`` pre-positions idle vehicles (lookahead): the shop must stop for them."""
    low = solver.strip().lower()
    return low == "lookahead" or low.endswith(tuple(LOOKAHEAD_SUFFIXES))


#: the agent node's parameters of a guided model's plan search (:mod:`fms_dispatch.agent_node`), for messages
GUIDE_PARAMETERS = "guide_restarts, guide_budget, guide_rules, guide_tabu, guide_exact, guide_seed"


def _ppo_decider(name: str, instance: Instance | None, guide_effort: Any = None,
                 guide_replan: bool = True, replan_wait: bool = False) -> tuple[Decider, str]:
    """``ppo`` / ``ppo:<model>`` (optionally ``+lookahead`` or ``+lookahead-fast``; ``lookahead`` alone is
    ``ppo+lookahead``) over a twin of ``instance``; a guided model searches its plan with ``guide_effort``
    (:class:`fms_dispatch.rl.guide.PlanEffort`; None: the default) and, with ``guide_replan``, re-plans it when a
    machine breaks down or its plan runs late (:class:`fms_dispatch.rl.agent.GuideReplanner`), beside its decisions
    (with ``replan_wait`` the shop waits for each re-plan; see :class:`TwinDecider`)."""
    low = name.lower()
    lookahead = needs_idle_stops(name)
    suffix = next((s for s in LOOKAHEAD_SUFFIXES if low.endswith(s)), "+lookahead")
    base = "ppo" if low == "lookahead" else (name[:-len(suffix)] if lookahead else name).strip()
    low_base = base.lower()
    if low_base != "ppo" and not low_base.startswith("ppo:"):
        raise UnavailableSolver(f"unknown solver {name!r}; the agent node accepts {', '.join(AGENT_SOLVERS)}")
    model = base[4:].strip() if low_base.startswith("ppo:") else None
    if low_base.startswith("ppo:") and not model:
        raise UnavailableSolver(f"solver {name!r} names no model; use ppo or ppo:<model>")
    if instance is None:
        raise UnavailableSolver(f"solver {name!r} is not available without the shop's instance: it replays the "
                                "shop into a twin; give the agent the parameter instance (the same as the shop's)")
    agent = load_ppo_agent(model, instance)
    try:
        agent.use_guide_effort(guide_effort)  # a cached agent: set for every decider
    except ValueError as exc:
        raise UnavailableSolver(f"solver {name!r}: {exc} ({GUIDE_PARAMETERS})") from None
    canonical = f"ppo:{agent.name}"
    planner = None
    if lookahead and LOOKAHEAD_SUFFIXES[suffix] == "guide":
        from .rl.guide import GuideMoves

        try:
            planner = GuideMoves.for_agent(agent)  # the guide plan's empty trips, read from the twin's state
        except ValueError as exc:
            raise UnavailableSolver(f"solver {name!r}: {exc}") from None
        canonical += suffix
    elif lookahead:
        from .rl.lookahead import LookaheadPlanner, nominal_twin

        # a twin that mirrors a disrupted shop knows its scenario: the planner's twins are nominal copies then
        planner = LookaheadPlanner(agent.act, retry=LOOKAHEAD_SUFFIXES[suffix] != "fast", twin=nominal_twin)
        canonical += suffix
    choose: Callable[["Shop"], int] = agent.act
    if guide_replan and agent.guide is not None:
        import importlib

        from .rl.agent import GuideReplanner

        importlib.import_module("fms_dispatch.replan")  # loaded now, not at the run's first order (0.3 s: OR-Tools)

        choose = GuideReplanner(agent)
    decider = TwinDecider(instance, choose, canonical, planner, replan_wait=replan_wait)
    decider.decisions = agent.decisions  # a full-net model follows a full-net shop
    decider.model_path = agent.path
    decider.model = agent
    return decider, canonical


def make_decider(solver: str, seed: int = 0, instance: Instance | None = None, *, replan: float = 0.0,
                 drift: float | None = None, guide_effort: Any = None, guide_replan: bool = True,
                 replan_wait: bool = False) -> tuple[Decider, str]:
    """The decision function and canonical name for a solver name; raises :class:`UnavailableSolver`.

    ``instance`` (the shop's instance) is needed by ``ppo`` and ``plan:`` solvers; ``replan`` (seconds, 0: off) and
    ``drift`` configure the re-planning of ``plan:`` solvers (:class:`PlanDecider`); ``guide_effort`` the plan search
    of a guided PPO model, ``guide_replan`` whether it re-plans at breakdowns and delays; ``replan_wait`` whether the
    state that triggers a re-plan (of either) waits for it."""
    if not isinstance(solver, str) or not solver.strip():
        raise UnavailableSolver(f"a solver must be named; choose from {', '.join(AGENT_SOLVERS)}")
    name = solver.strip()
    low = name.lower()
    if guide_effort is not None and not needs_twin(name):
        raise UnavailableSolver(f"a guide search ({GUIDE_PARAMETERS}) applies to ppo solvers only, not to {name!r}")
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
    if needs_twin(name):
        return _ppo_decider(name, instance, guide_effort, guide_replan, replan_wait)
    if needs_full_net(name):
        if instance is None:
            raise UnavailableSolver(f"solver {name!r} is not available without the shop's instance: it plans the "
                                    "whole run; give the agent the parameter instance (the same as the shop's)")
        from .solvers import UnknownSolver

        try:
            plan_decider = PlanDecider(instance, name, replan=replan, drift=drift, replan_wait=replan_wait)
        except (UnknownSolver, ValueError) as exc:
            raise UnavailableSolver(str(exc)) from None
        return plan_decider, name
    base = low.split(":", 1)[0]
    if base in _OFFLINE:
        raise UnavailableSolver(f"solver {name!r} plans a whole schedule offline and cannot decide state by state "
                                f"in the agent node: execute its plan with plan:{name}; choose from "
                                f"{', '.join(AGENT_SOLVERS)}")
    raise UnavailableSolver(f"unknown solver {name!r}; the agent node accepts {', '.join(AGENT_SOLVERS)} "
                            f"(job rules: {', '.join(JOB_RULES)}; vehicle rules: {', '.join(VEHICLE_RULES)})")


class AgentLogic:
    """Answers each new state of a run with one command, decided by a solver.

    A state is answered once: a repeated ``(run_id, seq)`` (a latched state delivered again) or an older
    ``seq`` of the same run is ignored, as is a final (``done``) state. A state that names another ``incarnation``
    (the start of the shop, an extra field of the fms shop's states) than the run's earlier states begins the run
    again from it (a shop restarted with the same ``run_id``); an older state of the same incarnation is never
    answered, however often it comes (reordered and duplicated), nor is a late state of an incarnation the run has
    since begun again from. From a shop whose states name no incarnation the
    same older state twice in a row begins the run again (a restarted shop publishes its state anew for each
    re-sent command it cannot answer). A state that cannot be decided on
    gives an ``fms/error/v1`` instead of a command. A state of a ``history_delta`` shop that the twin cannot follow
    (:class:`NeedHistory`) gives a replay request for that state with the whole history (``what: "state"``, once
    per state; :meth:`history_asked` says which is awaited) and is answered when it comes again so.
    """

    def __init__(self, solver: str = "first", *, seed: int = 0, source: str = SOURCE,
                 instance: Instance | None = None, replan: float = 0.0, drift: float | None = None,
                 guide_effort: Any = None, guide_replan: bool = True, replan_wait: bool = False,
                 only_run: str | None = None) -> None:
        self.only_run = only_run or None  # answer the states of this run only (None: of any run)
        self.decide, self.name = make_decider(solver, seed, instance, replan=replan, drift=drift,
                                              guide_effort=guide_effort, guide_replan=guide_replan,
                                              replan_wait=replan_wait)
        self.source = source
        self.run_id: str | None = None
        self.last_seq = -1           # the newest state seq seen in run_id
        self.answered_seq = -1       # the newest state seq answered in run_id
        self.decisions = 0
        self.history_requests = 0    # states asked for again with the whole history
        self._asked: tuple[str, int] | None = None  # (run_id, seq) of the state asked for so, not yet answered
        self._older: tuple[str, int] | None = None  # (run_id, seq) of the last older state ignored, if no newer since
        self._incarnation: Any = None  # the state's incarnation (the start of the shop) of run_id, if it names one
        self._retired: set[tuple[str, Any]] = set()  # (run_id, incarnation) of starts of runs restarted since

    def on_state(self, text: str) -> list[Outgoing]:
        """The command answering ``text`` (an ``fms/state/v1``), nothing, or an error."""
        try:
            state = decode(text, expect="state")
        except MessageError as exc:
            return [Outgoing(TOPIC_ERRORS, error_reply(self.source, exc, received=text))]
        run_id, seq = state["run_id"], state["seq"]
        if self.only_run is not None and run_id != self.only_run:  # another run's shop on the same domain: its
            return []  # own agent answers it (two fms up runs on one domain steered each other's shops)
        # the start of the run that sent it (an extra field of the fms shop; None from a shop that sends none)
        incarnation = state.get("incarnation")
        known = incarnation is not None and self._incarnation is not None
        if incarnation is not None and (run_id, incarnation) in self._retired:
            return []  # a late state of a start the shop has since begun again from: never answered (it would
            # take the agent back to the dead start, and the next state of the live one forth again)
        if run_id == self.run_id and known and incarnation != self._incarnation:
            self._retired.add((run_id, self._incarnation))
            self.run_id = None  # the shop began the run again (restarted with the same run_id): a new run at once
        elif run_id == self.run_id and seq < self.last_seq:
            if known:  # an old state of this start of the run, delivered late (twice: reordered and duplicated) is
                return []  # never answered (taken for a restart, it was answered and the twin rebuilt from it)
            if self._older != (run_id, seq):  # an old state delivered late: ignored
                self._older = (run_id, seq)
                return []
            # the same older state again: the shop published it anew, answering a re-sent command for a state it
            # never published: it began the run again (restarted with the same run_id, a respawn with fixed
            # parameters). Taken for an old state each time, neither moved again.
            self.run_id = None
        self._older = None
        if run_id != self.run_id:
            self.run_id, self.last_seq, self.answered_seq, self._asked = run_id, -1, -1, None
            self._incarnation = incarnation
        if seq < self.last_seq or (seq == self.last_seq and self._asked != (run_id, seq)):
            return []
        self.last_seq = seq
        if state["done"]:
            finish = getattr(self.decide, "finish", None)  # e.g. a plan decider's re-plan cut short by the end
            return [] if finish is None else finish(state)
        out: list[Outgoing] = []
        try:
            if state.get("idle") and not getattr(self.decide, "handles_idle", False):
                label = WAIT  # an idle stop: only pre-positioning solvers move vehicles there
            else:
                label = self.decide(state)
        except FallbackDecision as exc:
            out.append(Outgoing(TOPIC_ERRORS, make_error(self.source, "internal", str(exc), run_id=run_id)))
            label = exc.label
        except DecisionError as exc:
            return [Outgoing(TOPIC_ERRORS, make_error(self.source, "bad_schema", str(exc), run_id=run_id,
                                                      received=text))]
        except NeedHistory:
            if self._asked == (run_id, seq):  # asked already; the node asks again if it does not come
                return []
            self._asked = (run_id, seq)
            self.history_requests += 1
            return [Outgoing(TOPIC_REPLAY, make_replay_request(run_id, 0, self.source, what="state"))]
        except Exception as exc:  # a state that none of the checks caught (or a bug): it took the agent down; now
            # an error, and the safe answer (the shop waits for one) where the state names one
            why = f"state {seq}: cannot decide: {type(exc).__name__}: {exc}"
            try:
                label = _fallback(state)
            except DecisionError:
                return [Outgoing(TOPIC_ERRORS, make_error(self.source, "internal", why, run_id=run_id, received=text))]
            out.append(Outgoing(TOPIC_ERRORS, make_error(self.source, "internal", f"{why}; sending {label!r}",
                                                         run_id=run_id, received=text)))
        self._asked = None
        self.answered_seq = seq
        self.decisions += 1
        drain = getattr(self.decide, "drain", None)  # e.g. re-plan reports of a plan decider
        if drain is not None:
            out.extend(drain())
        return out + [Outgoing(TOPIC_COMMAND, make_command(run_id, seq, label, agent=self.name))]

    def history_asked(self) -> tuple[str, int] | None:
        """``(run_id, seq)`` of the state asked for again with the whole history and not yet answered, else None."""
        return self._asked

    def waiting_for(self) -> tuple[str, int] | None:
        """``(run_id, seq)`` of the state last answered if no newer state has arrived since, else None."""
        if self.run_id is None or self.answered_seq < 0 or self.answered_seq != self.last_seq:
            return None
        return self.run_id, self.answered_seq


def legal_labels(state: dict[str, Any]) -> Sequence[str]:
    """The enabled action labels of a decoded state (a convenience for tests and tools)."""
    return [label for _, _, label in _legal(state)]
