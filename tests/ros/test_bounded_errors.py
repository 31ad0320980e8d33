"""A 5 MB ``order_id`` over the topics: the error the shop answers with, the node logs and the recorder's SQLite
``errors`` table stay within ``ERROR_MAX_CHARS`` per field (``ERROR_MAX_BYTES`` encoded). A 5 MB error from
another node is refused by the recorder in bounds too (tests/test_bounded_errors.py, without ROS)."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from fms_msgs_json import ERROR_MAX_BYTES, ERROR_MAX_CHARS, encode  # noqa: E402

from .conftest import STARTUP_S, NodeProcs, Observer  # noqa: E402

HUGE = "o" * 5_000_000


def _rows(db: Path, sql: str) -> list[tuple]:
    """The rows of a read-only query on the recorder's database (none while it does not exist yet)."""
    if not db.exists():
        return []
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        return con.execute(sql).fetchall()
    except sqlite3.OperationalError:
        return []
    finally:
        con.close()


def stored_runs(db: Path) -> list[tuple]:
    return _rows(db, "SELECT run_id FROM runs")


def stored_errors(db: Path) -> list[tuple]:
    return _rows(db, "SELECT source, code, message, run_id, received_text FROM errors")


def test_a_5_mb_order_id_gives_bounded_errors_logs_and_rows(nodes: NodeProcs, observer: Observer,
                                                           tmp_path: Path) -> None:
    db = tmp_path / "rec.sqlite"
    nodes.start("recorder", "fms_sim.recorder_node", db=db)
    nodes.start("shop", "fms_sim.shop_node", instance="EX12", run_id="huge")
    observer.wait_for(lambda g: g["state"], STARTUP_S, "the shop's first state")
    # the recorder's subscriptions are matched once it has stored the run's first events (errors are not
    # latched: one published before that would never reach it)
    deadline = time.monotonic() + STARTUP_S
    while time.monotonic() < deadline and not stored_runs(db):
        time.sleep(0.1)
    observer.publish("order", {"schema": "fms/order/v1", "order_id": HUGE, "run_id": "huge",
                               "jobs": [[{"machine": 99, "tool": None, "duration": 3}]]})
    err = observer.wait_for(lambda g: next((e for e in g["error"] if e["code"] == "bad_order"), None), 30,
                            "the shop's bad_order")
    assert err["message"].startswith("order 'ooo") and len(encode(err).encode()) <= ERROR_MAX_BYTES
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not stored_errors(db):
        time.sleep(0.1)
    rows = stored_errors(db)
    assert [r[1] for r in rows] == ["bad_order"], rows
    for row in rows:
        for field, value in zip(("source", "code", "message", "run_id", "received"), row):
            assert value is None or field == "code" or len(value) <= ERROR_MAX_CHARS[field], field
    for name in ("shop", "recorder"):
        assert len(nodes.log(name)) < 20_000, (name, len(nodes.log(name)))
    deadline = time.monotonic() + 10  # the node's log line may reach the file a moment after the message
    while time.monotonic() < deadline and "[bad_order] order 'ooo" not in nodes.log("shop"):
        time.sleep(0.1)
    assert "[bad_order] order 'ooo" in nodes.log("shop")
