"""ROS 2 node ``fms_agent`` (``ros2 run fms_dispatch agent``, ``fms-agent``): the dispatcher on topics.

A thin adapter around :class:`fms_dispatch.agent_logic.AgentLogic`: it subscribes to the latched
``fms/state`` (so a late or restarted agent receives the current state at once), decides with the ``solver``
parameter and publishes one ``fms/command`` per state. A command is sent as soon as the shop listens on
``fms/command``; if no newer state has arrived ``resend_s`` seconds later it is sent again (the shop answers
a duplicate with a ``stale_state`` error and ignores it). A state of a ``history_delta`` shop that the agent's
twin cannot follow (a restarted agent receives the latched state, which carries only the last delta) is asked for
again with the whole history (``fms/replay_request``, ``what: "state"``), again every ``resend_s`` until it comes.
An unknown or unavailable solver stops the node at start with a one-line error and exit code 2.

Parameters: ``solver`` (``first``, ``random``, ``rule:<JOB>[+<first|least-work|nearest>]``, ``ppo``,
``ppo:<model>``, ``ppo[:<model>]+lookahead`` or ``+lookahead-fast``; default ``first``), ``seed`` (for
``random``), ``instance`` with
``layout``, ``agvs``, ``tool_transporters``, ``no_tools``, ``no_agvs`` (the shop's instance, the same values
as the shop node's; needed by ``ppo`` solvers, which replay the states' ``history`` into a twin of the shop —
start the shop with ``history:=true``, and with ``idle_stops:=true`` for lookahead), ``delay_s`` (think time before each command, for demos and tests),
``resend_s`` (default 1.0), and for ``plan:`` solvers ``replan`` (seconds per re-plan, default 2.0; 0 turns
re-planning off), ``drift`` (the lateness that triggers a re-plan, as a fraction of the plan's makespan,
default 0.05) and ``replan_wait`` (default false: the run goes on under the current plan while a re-plan runs;
true: the state that triggered it is answered once the re-plan is done, so a simulated shop waits for it; it applies
to a guided model's re-plans too). Re-plans are published on ``fms/replans`` (``fms/replan/v1``). A guided PPO model (the default
``guided-dagger``) searches its plan as ``guide_restarts`` (randomised restarts), ``guide_budget`` (seconds; 0: no
limit), ``guide_rules`` (the rule pairs' schedules, shops without tools; default false), ``guide_tabu`` (seconds of
tabu search per operation; 0: none), ``guide_exact`` (seconds of CP-SAT polish on small shops; 0: none) and
``guide_seed`` (its restarts' seed) say; -1:
the solver's default (:data:`fms_dispatch.rl.guide.DEFAULT_EFFORT`); with ``guide_replan`` (default true) it re-plans
its guide in a disrupted shop when a machine breakdown begins or an operation starts late against its plan, adopting
the new plan where it ends 2 % earlier than the plan in force (:class:`fms_dispatch.rl.agent.GuideReplanner`), and
publishes each re-plan on ``fms/replans``. Those re-plans run beside the decisions, in a forked process, as a plan
solver's do: the model goes on deciding with the plan in force meanwhile (:class:`~fms_dispatch.agent_logic.TwinDecider`).
"""

from __future__ import annotations

import sys
import time
from typing import Sequence

from fms_msgs_json import TOPIC_COMMAND, TOPIC_REPLAY
from fms_sim.instance import Instance
from fms_sim.shop_node import INSTANCE_PARAMETERS, FmsNode, StartupError, TopicIO, instance_param, param, run_node
from fms_sim.shop_service import Outgoing

from .agent_logic import AgentLogic, UnavailableSolver

__all__ = ["main", "AgentNode"]

NODE_NAME = "fms_agent"


class AgentNode(FmsNode):
    """The dispatcher agent node (see the module docstring)."""

    default_name = NODE_NAME
    parameters = ("solver", "seed", "delay_s", "resend_s", "replan", "drift", "replan_wait", "guide_restarts",
                  "guide_budget", "guide_rules", "guide_exact", "guide_tabu", "guide_seed", "guide_replan", "run_id",
                  *INSTANCE_PARAMETERS)

    def _setup(self) -> None:
        n = self.node
        solver = param(n, "solver", "first")
        seed = param(n, "seed", 0)
        if seed < 0:  # Python's generator seeds with abs(seed): -3 ran as 3 (two seeds, one run); as fms up --seed
            raise StartupError(f"parameter 'seed' must be an integer >= 0, got {seed}")
        self.delay_s = float(param(n, "delay_s", 0.0))
        self.resend_s = float(param(n, "resend_s", 1.0))
        replan = float(param(n, "replan", 2.0))
        drift = float(param(n, "drift", 0.05))
        replan_wait = bool(param(n, "replan_wait", False))
        inst = self._instance()
        restarts = int(param(n, "guide_restarts", -1))
        budget = float(param(n, "guide_budget", -1.0))
        rules = bool(param(n, "guide_rules", False))  # false: DEFAULT_EFFORT's
        exact = float(param(n, "guide_exact", -1.0))
        tabu = float(param(n, "guide_tabu", -1.0))
        guide_seed = int(param(n, "guide_seed", -1))
        guide_replan = bool(param(n, "guide_replan", True))
        only_run = str(param(n, "run_id", ""))
        effort = None
        if restarts != -1 or budget != -1.0 or rules or exact != -1.0 or tabu != -1.0 or guide_seed != -1:
            from .rl.guide import effort_from

            try:
                effort = effort_from(None if restarts == -1 else restarts, None if budget == -1.0 else budget, rules,
                                     None if exact == -1.0 else exact, None if tabu == -1.0 else tabu,
                                     None if guide_seed == -1 else guide_seed)
            except ValueError as exc:
                raise StartupError(f"parameters guide_restarts / guide_budget / guide_tabu / guide_exact / guide_seed: "
                                   f"{exc}") from None
        # checked for every solver (a plan: agent refused them, any other started with them: a typo went unnoticed)
        if replan < 0:
            raise StartupError(f"parameter 'replan' must be >= 0 (seconds per re-plan; 0: never), got {replan:g}")
        if drift <= 0:
            raise StartupError(f"parameter 'drift' must be > 0 (a fraction of the plan's makespan), got {drift:g}")
        try:
            self.logic = AgentLogic(solver, seed=seed, instance=inst, replan=replan, drift=drift, guide_effort=effort,
                                    guide_replan=guide_replan, replan_wait=replan_wait, only_run=only_run)
        except UnavailableSolver as exc:
            raise StartupError(str(exc)) from None
        if self.delay_s < 0:
            raise StartupError(f"parameter 'delay_s' must be >= 0 (seconds of think time), got {self.delay_s:g}")
        if self.resend_s <= 0:
            raise StartupError(f"parameter 'resend_s' must be > 0 (seconds before a command is sent again), "
                               f"got {self.resend_s:g}")
        self.io = TopicIO(n, ["command", "error", "replan", "replay_request"])
        self._pending: Outgoing | None = None     # a command waiting for the shop to listen
        self._ask: Outgoing | None = None         # a request for a state with its whole history (history_delta)
        self._asked_at: float | None = None       # when it was sent (None: not yet, the shop not listening)
        self._sent: Outgoing | None = None        # the last command sent, and when
        self._sent_at = 0.0
        self.io.subscribe("state", self._on_state)
        self._timer = n.create_timer(0.02, self._tick)
        model = getattr(self.logic.decide, "model_path", None)
        n.get_logger().info(f"deciding with {self.logic.name}" + (f" (model {model})" if model else ""))

    def _instance(self) -> Instance | None:
        """The instance named by the parameters (as the shop node reads them), or None without ``instance``."""
        inst: Instance | None = instance_param(self.node, required=False)
        return inst

    def _on_state(self, text: str) -> None:
        out = self.logic.on_state(text)
        for o in out:
            if o.topic == TOPIC_COMMAND:
                if self.delay_s and not self._think():
                    return  # stopped while thinking: the command is not sent
                self._pending = o
            elif o.topic == TOPIC_REPLAY:
                asked = self.logic.history_asked()
                self.node.get_logger().info(f"cannot follow state {asked[1] if asked else '?'} from its history "
                                            "delta (restarted, or a state missed); asking for it with the whole "
                                            "history")
                self._ask, self._asked_at = o, None
            else:
                self.io.publish([o])
        self._flush()

    def _think(self) -> bool:
        """Wait ``delay_s`` (the think time) unless the node is stopped meanwhile; returns whether it was not.

        The wait is in the state callback, so a stop signal is seen only when it returns: one plain sleep made a
        stop during a long think time (``delay_s:=30``) look like a stalled callback, ended by the stop watchdog
        with its stacks in the log and exit code 1 instead of a clean stop (exit code 0)."""
        deadline = time.monotonic() + self.delay_s
        while self.node.context.ok():
            left = deadline - time.monotonic()
            if left <= 0:
                return True
            time.sleep(min(left, 0.05))
        return False

    def _flush(self) -> None:
        if self._ask is not None and self._asked_at is None and self.io.matched(TOPIC_REPLAY) > 0:
            self.io.publish([self._ask])
            self._asked_at = time.monotonic()
        if self._pending is not None and self.io.matched(TOPIC_COMMAND) > 0:
            self.io.publish([self._pending])
            self._sent, self._pending = self._pending, None
            self._sent_at = time.monotonic()

    def _tick(self) -> None:
        self._flush()
        if self._ask is not None and self.logic.history_asked() is None:
            self._ask = None  # the state came with its whole history and was answered
        elif (self._ask is not None and self._asked_at is not None
              and time.monotonic() - self._asked_at >= self.resend_s):
            self.node.get_logger().warning(f"no state with the whole history {self.resend_s:.1f} s after asking for "
                                           "it; asking again")
            self._asked_at = None
            self._flush()
        sent = self._sent
        if sent is None or time.monotonic() - self._sent_at < self.resend_s:
            return
        if self.logic.waiting_for() == (sent.msg["run_id"], sent.msg["state_seq"]):
            self.node.get_logger().warning(f"no new state {self.resend_s:.1f} s after answering state "
                                           f"{sent.msg['state_seq']}; sending the command again")
            self._sent_at = time.monotonic()  # the next try (and warning) is resend_s away, sent or not
            self._pending = sent
            self._flush()
        else:
            self._sent = None

def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``fms-agent`` / ``ros2 run fms_dispatch agent`` / ``python -m fms_dispatch.agent_node``."""
    return run_node("fms-agent", AgentNode, argv)


if __name__ == "__main__":
    sys.exit(main())
