"""A 5 MB input never makes a 5 MB error: the shop's answer to an order with a 5 MB ``order_id``, the recorder's
answer to a 5 MB error message and the SQLite ``errors`` table all stay within ``ERROR_MAX_CHARS`` per field
(builders: tests/fms_msgs_json/test_schemas.py; the real nodes, their logs and database:
tests/ros/test_bounded_errors.py)."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

from fms_msgs_json import ERROR_MAX_BYTES, ERROR_MAX_CHARS, TOPIC_ERRORS, decode, encode
from fms_sim.benchmarks import builtin
from fms_sim.recorder_store import Recorder, RecorderStore
from fms_sim.shop_service import ShopService

HUGE = "o" * 5_000_000


def huge_order(order_id: str = HUGE, machine: int = 99) -> str:
    return json.dumps({"schema": "fms/order/v1", "order_id": order_id,
                       "jobs": [[{"machine": machine, "tool": None, "duration": 3}]]})


def check_capped(text: str) -> dict:
    assert len(text.encode()) <= ERROR_MAX_BYTES
    err = decode(text, expect="error")
    for field, most in ERROR_MAX_CHARS.items():
        assert err.get(field) is None or len(err[field]) <= most, field
    return err


def test_the_shops_answer_to_a_5_mb_order_id_is_capped() -> None:
    svc = ShopService(builtin("EX12"), run_id="r")
    svc.start()
    (out,) = svc.handle_order(huge_order())                         # machine 99: bad_order naming the id
    assert out.topic == TOPIC_ERRORS
    err = check_capped(encode(out.msg))
    assert err["code"] == "bad_order" and err["message"].startswith("order 'ooo") and err["message"].endswith("…")
    assert "machine" not in err["message"]                          # the cut, not the order id, is what is lost
    accepted = svc.handle_order(huge_order("o-1", machine=1))
    assert [o.msg["kind"] for o in accepted if o.msg["schema"] == "fms/event/v1"] == ["order_accepted"]
    (dup,) = svc.handle_order(huge_order("o-1", machine=1))         # repeated id: bad_order, short anyway
    assert "already accepted" in check_capped(encode(dup.msg))["message"]


def test_the_recorder_stores_and_answers_capped_errors(tmp_path: Path) -> None:
    db = tmp_path / "rec.sqlite"
    rec = Recorder(RecorderStore(db), render=False)
    big = json.dumps({"schema": "fms/error/v1", "source": "mes", "code": "internal", "message": HUGE,
                      "run_id": HUGE, "received": "x"})
    (answer,) = rec.handle_error(big)                                # too long to accept: bad_schema
    reply = check_capped(encode(answer.msg))
    assert reply["code"] == "bad_schema" and "at most 500 characters" in reply["message"]
    assert rec.handle_error(encode(answer.msg)) == []               # the answer itself comes back and is stored
    rec.store.add_error({"source": HUGE, "code": "internal", "message": HUGE, "run_id": HUGE, "received": HUGE})
    rec.store.db.commit()
    rows = sqlite3.connect(db).execute("SELECT source, message, run_id, received_text FROM errors").fetchall()
    assert len(rows) == 2
    for row in rows:
        for field, value in zip(("source", "message", "run_id", "received"), row):
            assert value is None or len(value) <= ERROR_MAX_CHARS[field], field
    assert db.stat().st_size < 1_000_000
