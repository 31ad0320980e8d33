"""Helpers for the multi-process ROS 2 tests: an isolated ROS environment per test, node processes in their
own process groups (always stopped), and an in-process observer node that sees every topic.

Isolation: each test gets a random ``ROS_DOMAIN_ID`` (1..101), ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``,
``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` (no shared-memory segments left behind by killed nodes) and a temporary
``ROS_LOG_DIR``. Each test module starts with ``pytest.importorskip("rclpy")``, so the folder is skipped when
rclpy is not installed; an rclpy of another ROS 2 distribution than Jazzy fails every test that uses
``ros_env``.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest

from fms_dispatch.up import _signal_group as signal_group
from fms_msgs_json import TOPICS, decode

try:  # the test modules skip themselves without rclpy; this file must still import
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    from fms_sim.shop_node import qos_profile
except ModuleNotFoundError:  # pragma: no cover - CI has rclpy
    rclpy = None

STARTUP_S = 30.0   # generous: node start-up on a loaded 2-core machine
RUN_S = 45.0


class NodeProcs:
    """Starts ``python -m <module> --ros-args -p k:=v ...`` in new sessions; stops them all at teardown."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env, self.log_dir = env, log_dir
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, module_or_cmd: str | list[str], **params: Any) -> subprocess.Popen:
        cmd = [sys.executable, "-m", module_or_cmd] if isinstance(module_or_cmd, str) else list(module_or_cmd)
        if params:
            cmd.append("--ros-args")
            for k, v in params.items():
                cmd += ["-p", f"{k}:={str(v).lower() if isinstance(v, bool) else v}"]
        log = open(self.log_dir / f"{name}.log", "ab")
        proc = subprocess.Popen(cmd, env=self.env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
        log.close()
        self.procs.append((name, proc))
        return proc

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text(errors="replace")

    def report(self, codes: dict[str, int], tail: int = 4000) -> str:
        """Each node's exit code and the end of its log, as one string: an assertion message that pytest
        prints whole (a list or dict would be cut to a short repr, hiding the log of the node that failed)."""
        return "\n".join(f"--- {name}: exit {code}\n{self.log(name)[-tail:]}" for name, code in codes.items())

    @staticmethod
    def kill(proc: subprocess.Popen) -> None:
        """SIGKILL the node's process group (a crash)."""
        signal_group(proc.pid, signal.SIGKILL)
        proc.wait(10)

    @staticmethod
    def stop(proc: subprocess.Popen, grace: float = 8.0, interrupt: bool = True) -> int:
        """SIGINT the group (unless ``interrupt`` is false: already sent) and wait; SIGKILL if it does not stop;
        returns the exit code."""
        if proc.poll() is None:
            if interrupt:
                signal_group(proc.pid, signal.SIGINT)
            try:
                proc.wait(grace)
            except subprocess.TimeoutExpired:
                NodeProcs.kill(proc)
        return proc.returncode

    def stop_all(self) -> dict[str, int]:
        """SIGINT every running node once, all at the same time, then wait for each."""
        running = [p for _, p in self.procs if p.poll() is None]
        for p in running:
            signal_group(p.pid, signal.SIGINT)
        return {name: self.stop(p, interrupt=False) for name, p in self.procs}


class Observer:
    """An rclpy node in the test process (own context, spun in a thread): records every message of the fms
    topics, decoded, and publishes commands, orders and replay requests."""

    KINDS_IN = ("state", "event", "schedule", "error", "replan")
    KINDS_OUT = ("command", "order", "replay_request", "disruption")

    def __init__(self, domain_id: int) -> None:
        self.ctx = rclpy.context.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("fms_test_observer", context=self.ctx)
        self.cond = threading.Condition()
        self.got: dict[str, list[dict[str, Any]]] = {k: [] for k in self.KINDS_IN}
        for kind in self.KINDS_IN:
            self.node.create_subscription(String, TOPICS[kind], self._callback(kind), qos_profile(kind))
        self.pubs = {k: self.node.create_publisher(String, TOPICS[k], qos_profile(k)) for k in self.KINDS_OUT}
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _callback(self, kind: str) -> Callable[[String], None]:
        def cb(msg: String) -> None:
            with self.cond:
                self.got[kind].append(decode(msg.data, expect=kind))
                self.cond.notify_all()
        return cb

    def _spin(self) -> None:
        while self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:
                if self.ctx.ok():
                    raise

    def wait_for(self, pred: Callable[[dict[str, list[dict[str, Any]]]], Any], timeout: float, what: str) -> Any:
        """Wait until ``pred(got)`` is truthy (called under the lock); returns its value."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                value = pred(self.got)
                if value:
                    return value
                left = deadline - time.monotonic()
                if left <= 0:
                    summary = {k: len(v) for k, v in self.got.items()}
                    raise AssertionError(f"timed out after {timeout:g} s waiting for {what} (received {summary})")
                self.cond.wait(min(left, 0.1))

    def latest_state(self) -> dict[str, Any] | None:
        with self.cond:
            return self.got["state"][-1] if self.got["state"] else None

    def snapshot(self, kind: str) -> list[dict[str, Any]]:
        with self.cond:
            return list(self.got[kind])

    def publish(self, kind: str, text: str | dict, timeout: float = STARTUP_S) -> None:
        """Publish once the topic has a subscriber (a message sent before matching would be lost)."""
        pub = self.pubs[kind]
        deadline = time.monotonic() + timeout
        while pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise AssertionError(f"nobody subscribes to {TOPICS[kind]}")
            time.sleep(0.02)
        pub.publish(String(data=text if isinstance(text, str) else json.dumps(text)))

    def publish_now(self, kind: str, text: str | dict) -> None:
        """Publish at once, matched subscriber or not (latched topics deliver it later)."""
        self.pubs[kind].publish(String(data=text if isinstance(text, str) else json.dumps(text)))

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        self._thread.join(5)


def ros_distro() -> str | None:
    """The ROS 2 distribution of the rclpy in use: ``jazzy`` for the PyPI wheels of the ros extra
    (``ros-jazzy-rclpy``), else ``$ROS_DISTRO`` (set by a sourced ROS installation)."""
    try:
        importlib.metadata.distribution("ros-jazzy-rclpy")
        return "jazzy"
    except importlib.metadata.PackageNotFoundError:
        return os.environ.get("ROS_DISTRO")


@pytest.fixture
def ros_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Environment for node processes (and the observer): isolated domain, localhost, UDP, temp logs."""
    pytest.importorskip("rclpy")
    assert ros_distro() == "jazzy", f"the ROS tests run on ROS 2 Jazzy (pip install '.[ros]'), not {ros_distro()}"
    domain = random.randint(1, 101)
    values = {"ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
              "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", "ROS_LOG_DIR": str(tmp_path / "roslog"),
              "PYTHONUNBUFFERED": "1"}
    for k, v in values.items():
        monkeypatch.setenv(k, v)
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    return dict(os.environ)


@pytest.fixture
def nodes(ros_env: dict[str, str], tmp_path: Path) -> Iterator[NodeProcs]:
    procs = NodeProcs(ros_env, tmp_path)
    try:
        yield procs
    finally:
        procs.stop_all()


@pytest.fixture
def observer(ros_env: dict[str, str]) -> Iterator[Observer]:
    obs = Observer(int(ros_env["ROS_DOMAIN_ID"]))
    try:
        yield obs
    finally:
        obs.close()


def wait_file(path: Path, timeout: float, procs: NodeProcs | None = None) -> Path:
    """Wait for ``path`` to exist (failing early, with the logs, if a node died)."""
    deadline = time.monotonic() + timeout
    while not path.exists():
        if procs is not None:
            dead = [(n, p.returncode) for n, p in procs.procs if p.poll() is not None and p.returncode != -9]
            if dead:
                raise AssertionError(f"node died: {dead}; logs: " + " | ".join(procs.log(n) for n, _ in dead))
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {path}")
        time.sleep(0.05)
    return path
