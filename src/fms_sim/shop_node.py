"""ROS 2 node ``fms_shop`` (``ros2 run fms_sim shop``, ``fms-shop``): the shop simulator on topics.

A thin adapter around :class:`fms_sim.shop_service.ShopService`: it loads the instance from its parameters,
publishes the service's messages (``std_msgs/String`` carrying ``fms_msgs_json`` text) and feeds it what
arrives on ``fms/command``, ``fms/orders`` and ``fms/replay_request``. States and the final schedule are
latched (TRANSIENT_LOCAL), so an agent or recorder that starts late — or restarts — still gets them. Every
rejected message is answered on ``fms/errors`` and logged; the node keeps running. After the run it stays up
(to answer replay requests) until it is stopped (SIGINT/SIGTERM: exit 0).

Parameters: ``instance`` (built-in name or file; required), ``layout``, ``agvs``, ``tool_transporters``
(0 = the instance's own), ``no_tools``, ``no_agvs``, ``run_id`` ('' = generated), ``features`` (true: states
carry the rule features), ``history`` (true: states carry the replay history a PPO agent needs; default
false), ``history_delta`` (true, with ``history``: each state carries only what was applied since the state the
last command answered, and an agent that cannot follow asks for the whole history with a replay request; default
false), ``decisions`` (``paper``, the default, or ``full``: the net the shop runs, docs/semantics.md), ``scenario`` (a
``fms/scenario/v1`` file of breakdowns and outages, full net only), ``noise`` and ``noise_seed`` (lognormal
noise on every duration), ``idle_stops``
(true: the shop also stops, and publishes a state, when a vehicle is idle between
decisions, so a ``ppo+lookahead`` agent can pre-position it; default false), ``time_scale`` (wall seconds per unit
of shop time: each step's messages are published once the shop time since the previous state has passed at that
speed, from the command that led to it, :mod:`fms_sim.pacing`; default 0: as fast as the agent answers),
``schedule_out`` / ``instance_out`` (files written when the run completes: the
schedule JSON and the final instance including accepted orders; '' = none).

This module also holds the small rclpy helpers the other fms nodes share (:func:`qos_profile`,
:func:`spin_until_shutdown`, :func:`ros_unavailable`). rclpy is imported only by node modules such as this
one; without it, :func:`main` exits with code 2 and says how to install it.
"""

from __future__ import annotations

import faulthandler
import math
import signal
import sys
import threading
import time
from typing import Any, Callable, Iterable, Sequence

try:  # ROS 2 is optional for the rest of the package; the nodes need it
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    _ROS_ERROR: BaseException | None = None
except (ImportError, OSError) as _exc:  # pragma: no cover - exercised by a subprocess test
    rclpy = None  # type: ignore[assignment]
    _ROS_ERROR = _exc

from fms_msgs_json import KINDS, TOPIC_QOS, TOPICS, encode

from .files import output_problem, write_atomically
from .instance import InstanceError
from .shop_service import Outgoing, ShopService

__all__ = ["main", "ShopNode", "FmsNode", "qos_profile", "spin_until_shutdown", "ros_unavailable", "StartupError",
           "TopicIO", "write_atomically"]

NODE_NAME = "fms_shop"


class StartupError(ValueError):
    """A node cannot start (bad parameter, unknown instance or solver): one line, exit code 2."""


def ros_unavailable(prog: str) -> str | None:
    """The one-line error to print if rclpy cannot be imported, else None."""
    if _ROS_ERROR is None:
        return None
    return (f"{prog}: error: ROS 2 (rclpy) is not available ({_ROS_ERROR}); install the extra "
            f"`pip install 'fms[ros]'` (ROS 2 Jazzy: ros-jazzy-rclpy[fastrtps], ros-jazzy-common-interfaces) "
            "or source a ROS 2 Jazzy installation")


def qos_profile(kind: str) -> "QoSProfile":
    """The rclpy QoS profile for the topic of message ``kind`` (from ``fms_msgs_json.TOPIC_QOS``)."""
    q = TOPIC_QOS[kind]
    return QoSProfile(depth=q.depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if q.latched else DurabilityPolicy.VOLATILE)


class TopicIO:
    """Publishers for some message kinds and a ``publish(outgoing)`` that encodes, sends and logs errors."""

    def __init__(self, node: Any, kinds: Iterable[str]) -> None:
        self.node = node
        self.pubs = {TOPICS[k]: node.create_publisher(String, TOPICS[k], qos_profile(k)) for k in kinds}

    def subscribe(self, kind: str, callback: Callable[[str], None]) -> Any:
        """Subscribe to the topic of ``kind`` with its QoS; ``callback`` gets the message text."""
        assert kind in KINDS
        return self.node.create_subscription(String, TOPICS[kind], lambda m: callback(m.data), qos_profile(kind))

    def publish(self, out: Sequence[Outgoing]) -> None:
        log = self.node.get_logger()
        for topic, msg in out:
            try:
                self.pubs[topic].publish(String(data=encode(msg, check=False)))  # built (and checked) by make_*
            except Exception as exc:  # one message that cannot be sent must not take the node down with it
                log.error(f"cannot publish a {msg.get('schema')} message on {topic}: {exc}")
                continue
            if msg["schema"] == "fms/error/v1":
                # an answer to an older state is a race every disruption or order can cause, not a fault: a warning
                # (fms up names the first [ERROR] line of a node's log as the likely cause of a stalled run)
                # (two call sites: rclpy refuses one site logging at two severities)
                if msg["code"] == "stale_state":
                    log.warning(f"[{msg['code']}] {msg['message']}")
                else:
                    log.error(f"[{msg['code']}] {msg['message']}")

    def matched(self, topic: str) -> int:
        """How many subscribers the publisher on ``topic`` is matched with."""
        return self.pubs[topic].get_subscription_count()


def _asked(node: Any) -> set[str]:
    """The parameters :func:`param` was asked for on ``node`` (declared, or refused for their value)."""
    asked = getattr(node, "_fms_asked", None)
    if asked is None:
        asked = set()
        node._fms_asked = asked
    return asked


def param(node: Any, name: str, default: Any) -> Any:
    """Declare a parameter and return its value; a value of the wrong type is a :class:`StartupError`. A number
    parameter also takes an integer (``resend_s:=2``, which ROS parses as an integer), and must be finite (no
    parameter of these nodes means anything by ``.nan`` or ``.inf``: ``resend_s:=.nan`` re-sent every 20 ms,
    ``delay_s:=.inf`` crashed the agent at its first state)."""
    _asked(node).add(name)  # a known parameter even when its value is refused (not "unknown")
    try:
        if isinstance(default, float):
            from rcl_interfaces.msg import ParameterDescriptor

            value = node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True)).value
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"got {value!r}")
            return float(value)
        return node.declare_parameter(name, default).value
    except Exception as exc:  # rclpy raises several exception types for bad overrides
        kind = {bool: "a boolean (true/false)", int: "an integer", float: "a finite number", str: "a string"}.get(
            type(default), type(default).__name__)
        raise StartupError(f"parameter {name!r} must be {kind}: {exc}") from None


#: the parameters :func:`instance_param` declares
INSTANCE_PARAMETERS = ("instance", "layout", "agvs", "tool_transporters", "no_tools", "no_agvs")


def instance_param(node: Any, required: bool = True) -> Any:
    """The instance named by a node's ``instance`` parameter, with ``layout``, ``agvs``, ``tool_transporters``,
    ``no_tools`` and ``no_agvs`` applied (the shop's and the agent's, which must agree); None without ``instance``
    where it is not ``required``. A bad value is a :class:`StartupError` in the parameters' words (the loader names
    the command line's flags: "use --no-agvs")."""
    from .formats import load_instance

    spec = param(node, "instance", "")
    layout, agvs, tts = param(node, "layout", 0), param(node, "agvs", 0), param(node, "tool_transporters", 0)
    no_tools, no_agvs = param(node, "no_tools", False), param(node, "no_agvs", False)
    if not spec:
        if not required:
            return None
        raise StartupError("parameter 'instance' is required (a built-in name such as EX12, or a file): "
                           "--ros-args -p instance:=EX12")
    try:
        return load_instance(spec, layout=layout or None, agvs=agvs or None, tool_transporters=tts or None,
                             no_tools=no_tools, no_agvs=no_agvs)
    except (InstanceError, OSError) as exc:
        text = str(exc).splitlines()[0]
        for flag, name in (("--no-agvs", "no_agvs:=true"), ("--no-tools", "no_tools:=true"),
                           ("--tool-transporters", "tool_transporters:=N"), ("--agvs", "agvs:=N"),
                           ("--layout", "layout:=L")):
            text = text.replace(flag, name)
        raise StartupError(text) from None


#: parameters every rclpy node declares by itself
_RCLPY_PARAMETERS = {"use_sim_time", "start_type_description_service"}


class FmsNode:
    """What every fms node shares: an rclpy node named ``node_name`` (default :attr:`default_name`) that
    :meth:`_setup` fills in; if the setup fails, the node is closed before the error propagates."""

    default_name = ""
    #: every parameter the node declares (a test keeps it equal to what :meth:`_setup` declares): a refused value
    #: stops the setup before the later ones are declared, and those were then named "unknown, ignored"
    parameters: tuple[str, ...] = ()

    def __init__(self, node_name: str | None = None) -> None:
        self.node = rclpy.create_node(node_name or self.default_name, start_parameter_services=False)
        try:
            try:
                self._setup()
            except StartupError as exc:  # a misspelt parameter is the likely cause of a missing or default one
                unknown = self.unknown_parameters()
                if unknown:
                    raise StartupError(f"{exc} (unknown parameters, ignored: {', '.join(unknown)})") from None
                raise
        except BaseException:
            try:
                self.close()
            finally:
                self.node.destroy_node()
            raise
        unknown = self.unknown_parameters()
        if unknown:  # ROS ignores them; say so, or a misspelt one silently runs with its default
            self.node.get_logger().warning(
                f"unknown parameters, ignored: {', '.join(unknown)}; this node's parameters are "
                f"{', '.join(self.declared_parameters())} (docs/ros.md)")

    def declared_parameters(self) -> list[str]:
        """The parameters the node declared (its own: rclpy's ``use_sim_time`` and
        ``start_type_description_service`` left out)."""
        return sorted(set(self.node.get_parameters_by_prefix("")) - _RCLPY_PARAMETERS)

    def unknown_parameters(self) -> list[str]:
        """Parameters given on the command line or in a parameters file that the node did not declare (a
        misspelt name): ROS ignores them."""
        given = getattr(self.node, "_parameter_overrides", None) or {}  # rclpy keeps no public view of them
        asked = _asked(self.node)
        return sorted(name for name in given
                      if not self.node.has_parameter(name) and name not in asked and name not in self.parameters)

    def _setup(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Release what the node holds besides its rclpy node (flush and close files); called once when it
        stops, before the rclpy node is destroyed. Nothing by default."""


class ShopNode(FmsNode):
    """The shop simulator node (see the module docstring)."""

    default_name = NODE_NAME
    parameters = ("run_id", "features", "history", "history_delta", "idle_stops", "decisions", "scenario", "noise",
                  "noise_seed", "time_scale", "schedule_out", "instance_out", *INSTANCE_PARAMETERS)

    def _setup(self) -> None:
        n = self.node
        run_id = param(n, "run_id", "")
        features = param(n, "features", True)
        history = param(n, "history", False)
        history_delta = param(n, "history_delta", False)
        idle_stops = param(n, "idle_stops", False)
        decisions = param(n, "decisions", "paper")
        scenario_file = param(n, "scenario", "")
        noise = param(n, "noise", 0.0)
        noise_seed = param(n, "noise_seed", 0)
        time_scale = float(param(n, "time_scale", 0.0))
        self.schedule_out = param(n, "schedule_out", "")
        self.instance_out = param(n, "instance_out", "")
        from .full_shop import DECISIONS

        if decisions not in DECISIONS:
            raise StartupError(f"parameter 'decisions' must be one of {', '.join(DECISIONS)}, got {decisions!r}")
        from .recorder_store import MAX_RUN_NAME, safe_run_name

        if len(safe_run_name(run_id)) > MAX_RUN_NAME:  # the recorder's chart failed: "File name too long"
            raise StartupError(f"parameter 'run_id' is too long to name the run's files (at most {MAX_RUN_NAME} "
                               f"characters; got {len(run_id)}): choose a shorter one, or '' for a generated one")
        inst = instance_param(n)
        for name in ("schedule_out", "instance_out"):  # found at the end: the file was lost, named confusingly
            path = getattr(self, name)
            problem = output_problem(path) if path else None
            if problem is not None:
                raise StartupError(f"parameter {name!r} ({path}): {problem}")
        if noise_seed and not noise:  # ignored: a scenario file's noise keeps its own seed
            raise StartupError("parameter 'noise_seed' seeds the noise of parameter 'noise', which is 0 (a scenario "
                               "file's noise has its own seed)")
        scenario = None
        if scenario_file or noise:
            from .disruptions import Scenario, ScenarioError

            try:
                scenario = Scenario.load(scenario_file) if scenario_file else Scenario()
                if noise:
                    scenario = Scenario(scenario.breakdowns, scenario.outages, noise, noise_seed)
                scenario.check(inst)
            except ScenarioError as exc:
                raise StartupError(str(exc)) from None
            if decisions != "full":
                raise StartupError("a scenario or noise needs decisions:=full")
        if history_delta and not history:
            raise StartupError("parameter 'history_delta' needs history:=true (the deltas are of the history)")
        from .pacing import Pacer

        try:
            self.pacer = Pacer(time_scale)
        except ValueError as exc:
            raise StartupError(f"parameter 'time_scale': {exc}") from None
        self.service = ShopService(inst, run_id=run_id or None, features=features, history=history,
                                   idle_stops=idle_stops, decisions=decisions, scenario=scenario,
                                   history_delta=history_delta)
        self.io = TopicIO(n, ["state", "event", "schedule", "error"])
        self.io.subscribe("command", lambda t: self._handle(self.service.handle_command, t))
        self.io.subscribe("order", lambda t: self._handle(self.service.handle_order, t))
        self.io.subscribe("replay_request", lambda t: self._handle(self.service.handle_replay, t))
        self.io.subscribe("disruption", lambda t: self._handle(self.service.handle_disruption, t))
        self._written = False
        n.get_logger().info(f"run {self.service.run_id}: {inst.describe()}"
                            + (f"; {time_scale:g} s per time unit" if time_scale else ""))
        if time_scale:
            n.create_timer(0.005, self._release)
        self._emit(self.service.start())

    def _handle(self, fn: Callable[[str], list[Outgoing]], text: str) -> None:
        try:
            out = fn(text)
        except Exception as exc:  # a bug must not take the shop down: report it and keep serving
            out = self.service.handle_bad_text(text, exc)
        self._emit(out)

    def _emit(self, out: list[Outgoing]) -> None:
        """Publish a step's messages once their time has come (at once without a time scale)."""
        released = self.pacer.push(out)
        if any(o.topic == TOPICS["schedule"] for o in out):  # the end: its wait counts in the run's times
            self.service.delay_end(self.pacer.last_delay)
        self.io.publish(released)
        self._after()

    def _release(self) -> None:
        if self.pacer.holding:
            self.io.publish(self.pacer.release())
            self._after()

    def _after(self) -> None:
        svc = self.service
        if not svc.done or self._written or self.pacer.holding:  # (the files once the end is published)
            return
        self._written = True
        sched = svc.final_schedule
        assert sched is not None
        for path, text in ((self.instance_out, svc.instance.to_json(indent=1)), (self.schedule_out, sched.to_json())):
            if path:
                try:
                    write_atomically(path, text + "\n")
                except OSError as exc:  # the run is still served (replays); say why the file is missing
                    self.node.get_logger().error(f"cannot write {path}: {exc}")
        self.node.get_logger().info(
            f"run {svc.run_id} complete: makespan {sched.makespan}, {svc.decisions} decisions, "
            f"{len(svc.events)} events, {len(svc.orders)} orders, {svc.wall_time or 0:.3f} s")

def _ignore_stop_signals() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


#: how long an executor error may precede the context's shutdown and still count as part of stopping
SHUTDOWN_GRACE_S = 1.0

#: seconds a stopping node may take, once its data are saved (destroying the rclpy node, shutting rclpy down,
#: the interpreter's exit), before the stall watchdog fires
STOP_STALL_S = 5.0


def _arm_stop_watchdog() -> None:
    """Bound the stop: if the process is still alive :data:`STOP_STALL_S` seconds from now, dump the stacks of
    all its threads on stderr (the node's log) and exit with code 1.

    A normal stop takes well under a second. A teardown that blocks inside the middleware (a DDS participant
    that never finishes deleting) would otherwise hang until the launcher's SIGKILL and leave no trace of
    where; this way it ends on its own, with the place in the log. faulthandler's watchdog is a C thread that
    needs no GIL, so it also fires when the main thread blocks in native code holding it, and it stays armed
    through the interpreter's exit."""
    faulthandler.dump_traceback_later(STOP_STALL_S, exit=True, file=sys.stderr)


class _Spinning:
    """What :func:`_watch_busy_stop` watches with: :meth:`release` says that spin returned (no busy callback to
    bound)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.done = False

    def release(self) -> None:
        with self.lock:
            if not self.done:
                self.done = True
                faulthandler.cancel_dump_traceback_later()  # the stop reached spin in time: close() is unbounded


def _watch_busy_stop(node: Any, spinning: _Spinning, poll_s: float = 0.1) -> None:
    """Bound a stop that arrives while a callback is busy: once the node's context is shut down (SIGINT/SIGTERM:
    rclpy shuts it down at once, even while a callback runs), spin returns only when that callback does, which
    for a plan search can be a minute (``plan:cpsat:60`` at the first state). A watcher thread arms the stop
    watchdog (:func:`_arm_stop_watchdog`: stacks in the log, exit code 1 after :data:`STOP_STALL_S` s) when it sees
    the shutdown, unless spin has returned by then (:meth:`_Spinning.release` cancels it), and from then on wakes
    the executor every ``poll_s`` until spin returns (:func:`_wake_executor`). A node without a context (a
    stand-in) is not watched."""
    context = getattr(node, "context", None)
    if context is None:
        return

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            with spinning.lock:
                if spinning.done:
                    return
                if not context.ok():
                    _arm_stop_watchdog()
                    break
        # then wake the executor until spin returns: the shutdown wakes it once, and once in a fresh-clone test run
        # a stopped shop node stayed in the executor's wait regardless, until the watchdog ended it (exit 1)
        while True:
            with spinning.lock:
                if spinning.done:
                    return
            _wake_executor()
            time.sleep(poll_s)

    threading.Thread(target=watch, name="fms-stop-watch", daemon=True).start()


def _wake_executor() -> None:
    """Wake the executor ``rclpy.spin`` waits in (its guard condition), so that its loop looks at the context again;
    nothing if that cannot be done (a stand-in rclpy, a context already torn down)."""
    try:
        rclpy.get_global_executor().wake()
    except Exception:  # the executor or its guard condition may already be gone: the watchdog still bounds the stop
        pass


def _shutting_down(grace_s: float) -> bool:
    """Whether rclpy is shut down now or within ``grace_s`` seconds."""
    deadline = time.monotonic() + grace_s
    while rclpy.ok():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)
    return True


def spin_until_shutdown(node: Any, close: Callable[[], None]) -> int:
    """Spin ``node`` until SIGINT/SIGTERM, then ``close()`` (the node's own data), destroy ``node`` and shut
    rclpy down; returns exit code 0.

    Two rclpy behaviours are absorbed here (both seen with Fast DDS when several nodes stop at once): a
    message arriving while the context shuts down can make the executor raise (``RuntimeError``, or a
    ``TypeError`` "Unable to convert call argument", in ``take_message``), possibly a moment before the context
    reports the shutdown — such an error counts as stopping if rclpy is down within :data:`SHUTDOWN_GRACE_S`; and the stop signal can be delivered a second time — during ``close()`` or while the
    interpreter finalises, where it would kill a cleanly stopped node with -SIGINT. Once the node is
    stopping, further stop signals are therefore ignored. ``close()`` runs unbounded (it saves data); the
    middleware teardown after it is bounded by :func:`_arm_stop_watchdog` (stacks in the log and exit code 1
    if it stalls).
    """
    spinning = _Spinning()
    try:
        # (in the try: a stop signal while the watcher starts, just after the node said it is up, ended in a
        # traceback and exit -2 without close())
        _watch_busy_stop(node, spinning)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # the stop signal may still be on its way to shutting the context down (the executor can fail in
        # take_message a moment before): only an error while rclpy stays up is a real failure
        if not _shutting_down(SHUTDOWN_GRACE_S):
            raise
    finally:
        spinning.release()
        _ignore_stop_signals()
        try:
            close()
        finally:
            _arm_stop_watchdog()  # what follows is middleware teardown only: the node's data are saved
            try:
                node.destroy_node()
            finally:
                rclpy.try_shutdown()
                _ignore_stop_signals()  # try_shutdown may restore the handlers rclpy replaced
    return 0


def run_node(prog: str, factory: Callable[[], Any], argv: Sequence[str] | None) -> int:
    """Shared ``main`` of the fms nodes: init rclpy with ``argv``, build the node object (a
    :class:`StartupError` → one line on stderr, exit 2), spin until shutdown."""
    args = list(sys.argv if argv is None else argv)
    own = args[1:args.index("--ros-args")] if "--ros-args" in args else args[1:]
    if "-h" in own or "--help" in own:  # before rclpy starts anything (a recorder would create its database)
        print(f"usage: {prog} [--ros-args -p NAME:=VALUE ...]\n\nA ROS 2 node of fms; its parameters, topics and "
              "defaults are in docs/ros.md.")
        return 0
    problem = ros_unavailable(prog)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    try:
        rclpy.init(args=args)
    except Exception as exc:  # rclpy's RCLError for malformed --ros-args (e.g. '-p name' without ':=value')
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"{prog}: error: bad ROS arguments: {first}", file=sys.stderr)
        return 2
    try:
        obj = factory()
    except StartupError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        rclpy.try_shutdown()
        return 0
    return spin_until_shutdown(obj.node, obj.close)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``fms-shop`` / ``ros2 run fms_sim shop`` / ``python -m fms_sim.shop_node``."""
    return run_node("fms-shop", ShopNode, argv)


if __name__ == "__main__":
    sys.exit(main())
