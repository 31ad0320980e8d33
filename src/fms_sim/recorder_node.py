"""ROS 2 node ``fms_recorder`` (``ros2 run fms_sim recorder``, ``fms-recorder``): the durable run log.

A thin adapter around :class:`fms_sim.recorder_store.Recorder`: it stores every ``fms/events``,
``fms/schedule``, ``fms/replans`` and ``fms/errors`` message in SQLite (WAL), events de-duplicated by
``(run_id, seq)``, and renders a Gantt PNG when a run is complete. On start — as soon as a shop listens on
``fms/replay_request`` — it asks the shop to replay the current run from event 0, so a recorder restarted
mid-run ends with every event exactly once; gaps in the event numbers (and a final schedule whose events are
incomplete) trigger further requests, repeated every ``retry_s`` seconds while something is missing.

Parameters: ``db`` (SQLite file, default ``fms_recorder.sqlite`` in the working directory), ``gantt`` (true:
render charts), ``gantt_dir`` ('' = the database's folder; charts are ``<run_id>.gantt.png``), ``retry_s``
(seconds between repeated replay requests, default 1.0), ``commit_s`` (group commits: at most this many seconds
of messages uncommitted, default 0.05; 0 = commit every message).
"""

from __future__ import annotations

import importlib
import sys
import threading
import time
from typing import Callable, Sequence

from fms_msgs_json import TOPIC_ERRORS, TOPIC_REPLAY, error_reply

from .files import folder_problem
from .recorder_store import DEFAULT_DB, Recorder, RecorderStore
from .shop_node import FmsNode, StartupError, TopicIO, param, run_node
from .shop_service import Outgoing

__all__ = ["main", "RecorderNode"]

NODE_NAME = "fms_recorder"


class RecorderNode(FmsNode):
    """The recorder node (see the module docstring)."""

    default_name = NODE_NAME
    parameters = ("db", "gantt", "gantt_dir", "retry_s", "commit_s")
    store: RecorderStore | None = None  # open once the setup has opened the database

    def _setup(self) -> None:
        n = self.node
        db = param(n, "db", DEFAULT_DB)
        render = param(n, "gantt", True)
        gantt_dir = param(n, "gantt_dir", "")
        retry_s = param(n, "retry_s", 1.0)
        commit_s = param(n, "commit_s", 0.05)
        if retry_s <= 0:
            raise StartupError(f"parameter 'retry_s' must be positive, got {retry_s}")
        if commit_s < 0:
            raise StartupError(f"parameter 'commit_s' must be >= 0, got {commit_s}")
        if not db.strip():  # it was the default file, silently
            raise StartupError(f"parameter 'db' names no file (an empty name); leave it out for {DEFAULT_DB}")
        problem = folder_problem(gantt_dir) if render and gantt_dir else None
        if problem is not None:  # found when the chart was due: the run's chart lost, the error "File exists"
            raise StartupError(f"parameter 'gantt_dir' ({gantt_dir}): {problem}")
        try:
            self.store = RecorderStore(db)
        except ValueError as exc:
            raise StartupError(str(exc)) from None
        self.recorder = Recorder(self.store, gantt_dir=gantt_dir or None, render=render, retry_s=retry_s,
                                 commit_s=commit_s)
        if render:  # load matplotlib while the run is going, not when the chart is due
            threading.Thread(target=importlib.import_module, args=("fms_sim.gantt",), daemon=True).start()
        self.io = TopicIO(n, ["replay_request", "error"])
        rec = self.recorder
        self.io.subscribe("event", lambda t: self._handle(lambda: rec.handle_event(t, time.monotonic()), t))
        self.io.subscribe("schedule", lambda t: self._handle(lambda: rec.handle_schedule(t, time.monotonic()), t))
        self.io.subscribe("replan", lambda t: self._handle(lambda: rec.handle_replan(t, time.monotonic()), t))
        # failures to store an error are logged only: publishing them would feed them back to this node
        self.io.subscribe("error", lambda t: self._handle(lambda: rec.handle_error(t, time.monotonic()), t,
                                                          report=False))
        self._startup_sent = False
        self._timer = n.create_timer(0.05, self._tick)
        n.get_logger().info(f"recording to {self.store.path} (charts in {self.recorder.gantt_dir})")

    def _handle(self, step: Callable[[], list[Outgoing]], received: str | None = None,
                report: bool = True) -> None:
        """Run one step of the recorder; a failure (database, chart) is reported and logged, not fatal."""
        try:
            out = step()
            for run_id, path in self.recorder.finish_ready():
                where = f"; Gantt chart {path}" if path else ""
                self.node.get_logger().info(f"run {run_id} complete in {self.recorder.store.path}{where}")
        except Exception as exc:  # e.g. sqlite3.OperationalError (disk full), a chart that cannot be written
            err = error_reply(NODE_NAME, exc, received=received)
            if not report:
                self.node.get_logger().error(f"[{err['code']}] {err['message']}")
                return
            out = [Outgoing(TOPIC_ERRORS, err)]
        self.io.publish(out)

    def _tick(self) -> None:
        if not self._startup_sent and self.io.matched(TOPIC_REPLAY) > 0:
            self._startup_sent = True
            self.io.publish([self.recorder.startup_request()])
        self._handle(lambda: self.recorder.poll(time.monotonic()))

    def close(self) -> None:
        if self.store is not None:
            recorder = getattr(self, "recorder", None)
            if recorder is not None:
                recorder.flush(time.monotonic())
            self.store.close()
            self.store = None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``fms-recorder`` / ``ros2 run fms_sim recorder`` / ``python -m fms_sim.recorder_node``."""
    return run_node("fms-recorder", RecorderNode, argv)


if __name__ == "__main__":
    sys.exit(main())
