"""RecorderStore and Recorder (the recorder node's logic, no ROS): dedup, gaps, replays, restart, Gantt."""

from __future__ import annotations

import random
import sqlite3
from pathlib import Path
from typing import Any

import pytest

import fms_msgs_json as m
from fms_msgs_json import decode, encode
from fms_sim import validate
from fms_sim.benchmarks import builtin
from fms_sim.recorder_store import Recorder, RecorderStore, RunConflict, gantt_path
from fms_sim.schedule import Schedule
from fms_sim.shop_service import ShopService


def finished_run(name: str = "ra01", run_id: str = "run-1") -> ShopService:
    """A complete run of the shop service (lowest enabled action each time)."""
    svc = ShopService(builtin(name), run_id=run_id)
    svc.start()
    while not svc.done:
        label = next(a for a, ok in zip(svc.state["actions"], svc.state["mask"]) if ok)
        svc.handle_command(encode(m.make_command(run_id, svc.state_seq, label)))
    return svc


def texts(svc: ShopService) -> tuple[list[str], str]:
    assert svc.final_schedule is not None
    return [encode(e) for e in svc.events], encode(m.make_schedule(svc.run_id, svc.final_schedule))


def fake_renderer(calls: list) -> Any:
    def render(schedule: Schedule, path: Path) -> None:
        calls.append((schedule.makespan, path))
        Path(path).write_bytes(b"png")
    return render


def same_schedule(a: Schedule, b: Schedule) -> bool:
    da, db = a.to_dict(), b.to_dict()
    return all(da[k] == db[k] for k in ("instance", "makespan", "n_agvs", "n_tool_transporters", "operations",
                                        "agv_trips", "tool_trips"))


# ------------------------------------------------------------------------------------------------ the store
def test_store_dedups_events_and_schedules(tmp_path: Path) -> None:
    svc = finished_run()
    store = RecorderStore(tmp_path / "log.sqlite")
    assert store.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    for e in svc.events + svc.events[::-1]:
        store.add_event(e)
    assert store.event_seqs("run-1") == list(range(len(svc.events)))
    assert store.add_event(svc.events[3]) is False
    assert store.add_schedule("run-1", svc.final_schedule.to_dict()) is True
    assert store.add_schedule("run-1", svc.final_schedule.to_dict()) is False
    assert store.end_seq("run-1") == len(svc.events) - 1 and store.is_complete("run-1")
    stored = store.events("run-1")
    assert [(e["seq"], e["time"], e["kind"], e["data"]) for e in stored] == \
        [(e["seq"], e["time"], e["kind"], e["data"]) for e in svc.events]
    assert store.run_ids() == ["run-1"]
    assert same_schedule(store.schedule("run-1"), svc.final_schedule)
    rebuilt = store.schedule_from_events("run-1")
    assert same_schedule(rebuilt, svc.final_schedule) and validate(svc.instance, rebuilt) == []
    store.close()
    # durable: a new connection (a restarted recorder) sees everything, once
    again = RecorderStore(tmp_path / "log.sqlite")
    assert again.event_seqs("run-1") == list(range(len(svc.events))) and again.is_complete("run-1")
    (n,) = sqlite3.connect(tmp_path / "log.sqlite").execute("SELECT COUNT(*) FROM events").fetchone()
    assert n == len(svc.events)


def test_a_duplicate_or_conflicting_event_leaves_the_database_unlocked(tmp_path: Path) -> None:
    """The ignored insert of a duplicate or a conflicting event opened a write transaction with nothing in it: the
    recorder (batching its commits) held the write lock until a later write, so fms up's progress reader and any
    other writer waited 10 s and failed ("database is locked"), and two runs under one id blocked each other."""
    from fms_sim.recorder_store import RunConflict

    svc = finished_run()
    store = RecorderStore(tmp_path / "log.sqlite")
    store.add_event(svc.events[0])
    other = sqlite3.connect(tmp_path / "log.sqlite", timeout=0.2)
    for event in (svc.events[0], dict(svc.events[0], time=svc.events[0]["time"] + 5)):
        try:
            store.add_event(event, commit=False)  # as the recorder stores events
        except RunConflict:
            pass
        assert not store.db.in_transaction
        other.execute("INSERT INTO errors (source, code, message, at) VALUES ('t', 't', 't', 0)")
        other.commit()  # it was "database is locked"
    store.add_event(svc.events[1], commit=False)  # a pending write is kept for the batch's commit ...
    with pytest.raises(RunConflict):
        store.add_event(dict(svc.events[0], time=99), commit=False)
    store.commit()
    assert store.event_seqs("run-1") == [0, 1]  # ... not rolled back with the conflict


def test_store_progress_counts_ended_operations_and_the_latest_time(tmp_path: Path) -> None:
    svc = finished_run()
    store = RecorderStore(tmp_path / "log.sqlite")
    assert store.progress("run-1") == (0, None, 0)                 # nothing stored yet
    half = len(svc.events) // 2
    for e in svc.events[:half]:
        store.add_event(e)
    ended = sum(e["kind"] == "op_end" for e in svc.events[:half])
    assert 0 < ended and store.progress("run-1") == (ended, max(e["time"] for e in svc.events[:half]), 0)
    for e in svc.events[half:]:
        store.add_event(e)
    assert store.progress("run-1") == (svc.instance.n_operations, svc.final_schedule.makespan, 0)
    assert store.progress("other") == (0, None, 0)
    # an event after the run's end, stored before the end came, is not the run's ("17 of 16 operations done", at
    # its time)
    late = RecorderStore(tmp_path / "late.sqlite")
    *body, end = svc.events
    for e in body:
        late.add_event(e)
    late.add_event(dict(end, seq=end["seq"] + 5, time=99_999, kind="op_end", data={"job": 0, "op": 0, "machine": 1}))
    late.add_event(end)
    assert late.progress("run-1") == (svc.instance.n_operations, svc.final_schedule.makespan, 0)
    # the jobs live orders added (fms up said "14 of 13 operations done" after an order)
    for seq, jobs in enumerate(([5, 6], [7])):
        store.add_event(dict(svc.events[0], run_id="run-2", seq=seq, time=3, kind="order_accepted",
                             data={"order_id": f"o{seq}", "jobs": jobs}))
    assert store.progress("run-2") == (0, 3, 3)


def test_store_incomplete_runs_and_errors(tmp_path: Path) -> None:
    svc = finished_run("EX12")
    store = RecorderStore(tmp_path / "sub" / "log.sqlite")      # the folder is created
    for e in svc.events[:4] + svc.events[6:]:
        store.add_event(e)
    assert store.first_missing("run-1") == 4 and not store.is_complete("run-1")
    store.add_schedule("run-1", svc.final_schedule.to_dict())
    assert not store.is_complete("run-1")
    with pytest.raises(ValueError, match="no run_end event"):
        RecorderStore(tmp_path / "other.sqlite").schedule_from_events("run-1")
    err = decode(encode(m.make_error("fms_shop", "bad_order", "order 'x' rejected", run_id="run-1",
                                     received="{}")))
    store.add_error(err)
    store.add_error(err)
    assert store.errors("run-1") == [{"source": "fms_shop", "code": "bad_order", "message": "order 'x' rejected",
                                      "run_id": "run-1", "received": "{}"}] * 2
    with pytest.raises(ValueError, match="cannot open the recorder database"):
        RecorderStore(tmp_path)                                  # a folder, not a file


@pytest.mark.parametrize("content", [b"x", b"runs of monday\n" * 100])
def test_a_file_that_is_not_a_database_is_left_as_it_is(tmp_path: Path, content: bytes) -> None:
    """SQLite turns a file shorter than its header into a database: a one-byte text file given as the database
    became a 45 kB one. A non-empty file without SQLite's header is refused, unchanged."""
    path = tmp_path / "notes.txt"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="the file is not an SQLite database .left as it is."):
        RecorderStore(path)
    assert path.read_bytes() == content
    (tmp_path / "empty.sqlite").write_bytes(b"")  # an empty file is a new database
    RecorderStore(tmp_path / "empty.sqlite").close()
    RecorderStore(tmp_path / "empty.sqlite").close()  # and opens again


def test_gantt_path_is_safe() -> None:
    assert gantt_path("out", "EX12-2024-abc") == Path("out/EX12-2024-abc.gantt.png")
    assert gantt_path("out", "../x y/z") == Path("out/_x_y_z.gantt.png")


# ------------------------------------------------------------------------------------------------ the recorder
def test_recorder_complete_run_renders_once(tmp_path: Path) -> None:
    svc = finished_run()
    events, schedule = texts(svc)
    calls: list = []
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), renderer=fake_renderer(calls))
    for t in events:
        assert rec.handle_event(t, now=0.0) == []
        assert rec.finish_ready() == []                          # no schedule yet
    assert rec.handle_schedule(schedule, now=0.0) == []
    png = tmp_path / "run-1.gantt.png"
    other = tmp_path / "run-1.gantt.png.tmp.png"  # the fixed temporary name, which two recorders charting one run
    other.write_bytes(b"another recorder's")      # into one folder shared: each has its own now
    assert rec.finish_ready() == [("run-1", png)]
    ((made, tmp),) = calls
    assert made == svc.final_schedule.makespan and tmp.parent == tmp_path and tmp.name.startswith(".run-1.gantt.png.")
    assert tmp.suffix == ".png" and not tmp.exists() and png.read_bytes() == b"png"
    assert other.read_bytes() == b"another recorder's"
    assert rec.store.gantt("run-1") == str(png)
    assert rec.handle_schedule(schedule, now=1.0) == [] and rec.finish_ready() == [] and len(calls) == 1


def test_recorder_asks_for_missing_events_and_retries(tmp_path: Path) -> None:
    svc = finished_run()
    events, schedule = texts(svc)
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False, retry_s=1.0)
    for t in events[:5]:
        assert rec.handle_event(t, now=0.0) == []
    out = rec.handle_event(events[8], now=0.1)                   # a gap: 5..7 missing
    assert [(o.topic, o.msg) for o in out] == [(m.TOPIC_REPLAY, m.make_replay_request("run-1", 5, "fms_recorder"))]
    assert rec.handle_event(events[9], now=0.2) == []            # asked recently: wait
    assert rec.poll(now=0.5) == []
    (again,) = rec.poll(now=1.2)                                 # still missing: ask again
    assert again.msg["from_seq"] == 5
    for t in events[5:8]:                                        # the replay arrives: duplicates are harmless
        rec.handle_event(t, now=1.3)
    for t in events[8:]:
        rec.handle_event(t, now=1.4)
    assert rec.missing_from("run-1") is None and rec.poll(now=9.0) == []
    rec.handle_schedule(schedule, now=9.0)
    assert rec.finish_ready() == [("run-1", None)]
    assert rec.store.event_seqs("run-1") == list(range(len(events)))


def test_recorder_schedule_before_the_last_events(tmp_path: Path) -> None:
    svc = finished_run("EX12")
    events, schedule = texts(svc)
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    for t in events[:-3]:
        rec.handle_event(t, now=0.0)
    (ask,) = rec.handle_schedule(schedule, now=0.0)              # run over, run_end never seen
    assert ask.msg == m.make_replay_request("run-1", len(events) - 3, "fms_recorder")
    assert rec.finish_ready() == []
    for t in events[-3:]:
        rec.handle_event(t, now=0.1)
    assert rec.finish_ready() == [("run-1", None)]


def test_recorder_restart_resumes_from_the_database(tmp_path: Path) -> None:
    svc = finished_run()
    events, schedule = texts(svc)
    db = tmp_path / "db.sqlite"
    first = Recorder(RecorderStore(db), render=False)
    for t in events[:10]:
        first.handle_event(t, now=0.0)
    first.store.close()                                          # killed: what it committed is kept
    second = Recorder(RecorderStore(db), render=False)
    assert second.startup_request().msg == m.make_replay_request("*", 0, "fms_recorder")
    (ask,) = second.handle_event(events[15], now=0.0)            # joined mid-run: ask from the first missing
    assert ask.msg["run_id"] == "run-1" and ask.msg["from_seq"] == 10
    order = events[:] + [schedule]
    random.Random(1).shuffle(order)
    for t in order:                                              # the shop's replay, in any order, with repeats
        (second.handle_schedule if '"fms/schedule/v1"' in t else second.handle_event)(t, now=5.0)
    assert second.finish_ready() == [("run-1", None)]
    store = second.store
    assert store.event_seqs("run-1") == list(range(len(events)))
    (n,) = store.db.execute("SELECT COUNT(*) FROM events WHERE run_id = 'run-1'").fetchone()
    assert n == len(events)
    assert same_schedule(store.schedule_from_events("run-1"), svc.final_schedule)


def test_recorder_answers_bad_messages(tmp_path: Path) -> None:
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    (err,) = rec.handle_event("{oops", now=0.0)
    assert err.topic == m.TOPIC_ERRORS and err.msg["code"] == "malformed_json" and err.msg["source"] == "fms_recorder"
    (err,) = rec.handle_schedule('{"schema": "fms/schedule/v1", "run_id": "r", "schedule": {}}', now=0.0)
    assert err.msg["code"] == "bad_schema"
    (err,) = rec.handle_error('{"schema": "fms/event/v1"}')
    assert err.msg["code"] == "bad_schema"
    assert rec.store.run_ids() == []


def test_recorder_renders_a_real_gantt_chart(tmp_path: Path) -> None:
    svc = finished_run("EX12", run_id="EX12 run/1")
    events, schedule = texts(svc)
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), gantt_dir=tmp_path / "charts")
    for t in events + [schedule]:
        (rec.handle_schedule if '"fms/schedule/v1"' in t else rec.handle_event)(t, now=0.0)
    ((run_id, png),) = rec.finish_ready()
    assert run_id == "EX12 run/1" and png == tmp_path / "charts" / "EX12_run_1.gantt.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list((tmp_path / "charts").glob("*.tmp.png"))


def test_a_recorded_runs_chart_has_a_row_for_every_machine_of_the_shop(tmp_path: Path, monkeypatch) -> None:
    """The schedule names only the machines its operations used, and the recorder has no instance: a machine no
    operation used had no row in the recorder's chart (fms solve's chart, drawn with the instance, has one). The
    run_start names the shop's machine count, and the chart gets that many machine rows."""
    import fms_sim.gantt as gantt
    from fms_sim import Instance, Operation

    inst = Instance(name="idle-m3", jobs=[[Operation(1, None, 3), Operation(2, None, 2)], [Operation(2, None, 4)]],
                    agv_travel=[[0, 2, 2, 2], [2, 0, 2, 2], [2, 2, 0, 2], [2, 2, 2, 0]], n_agvs=1)
    svc = ShopService(inst, run_id="r")
    svc.start()
    while not svc.done:
        label = next(a for a, ok in zip(svc.state["actions"], svc.state["mask"]) if ok)
        svc.handle_command(encode(m.make_command("r", svc.state_seq, label)))
    events, schedule = texts(svc)
    assert m.decode(events[0], expect="event")["data"]["machines"] == 3
    drawn = []
    real = gantt.save_gantt

    def spy(sched: Schedule, path: Path, *args: Any, **kw: Any) -> Path:
        drawn.append([r.label for r in gantt._layout(sched, None, kw.get("machines"))[0] if r.kind == "machine"])
        return real(sched, path, *args, **kw)

    monkeypatch.setattr(gantt, "save_gantt", spy)
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), gantt_dir=tmp_path)
    for t in events + [schedule]:
        (rec.handle_schedule if '"fms/schedule/v1"' in t else rec.handle_event)(t, now=0.0)
    ((_, png),) = rec.finish_ready()
    assert {r.machine for r in svc.final_schedule.operations} == {1, 2}
    assert drawn == [["M1", "M2", "M3"]] and png.exists()


# ------------------------------------------------------------------------------------------------ bad databases
def test_a_database_that_cannot_be_made_written_or_is_someone_elses_is_refused(tmp_path: Path, monkeypatch) -> None:
    # a folder that cannot be made was a traceback (FileNotFoundError, NotADirectoryError); another program's
    # table named "events" and a read-only database were taken, and every message then failed to be stored
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match="its folder cannot be made"):
        RecorderStore(tmp_path / "afile" / "sub" / "db.sqlite")
    theirs = tmp_path / "theirs.sqlite"
    with sqlite3.connect(theirs) as con:
        con.execute("CREATE TABLE events (a, b)")
    con.close()
    with pytest.raises(ValueError, match=r"its table 'events' is laid out otherwise \(columns a, b; the recorder's: "
                                         r"data, kind, received, run_id, seq, time\): not a recorder database"):
        RecorderStore(theirs)
    ours = tmp_path / "ours.sqlite"
    RecorderStore(ours).close()
    real = sqlite3.connect

    def read_only(path: str, *args: Any, **kw: Any) -> sqlite3.Connection:  # as for a user who may not write it
        return real(f"file:{path}?mode=ro", *args, uri=True, **kw)

    monkeypatch.setattr(sqlite3, "connect", read_only)
    with pytest.raises(ValueError, match="cannot open the recorder database .*readonly"):
        RecorderStore(ours)


@pytest.mark.parametrize("events_sql, differs", [
    # the recorder's names without its key: INSERT OR IGNORE stored every replayed event again
    ("run_id TEXT NOT NULL, seq INTEGER NOT NULL, time INTEGER NOT NULL, kind TEXT NOT NULL, data TEXT NOT NULL, "
     "received REAL NOT NULL", "primary key none, the recorder's: (run_id, seq)"),
    ("run_id TEXT NOT NULL, seq INTEGER NOT NULL, time INTEGER NOT NULL, kind TEXT NOT NULL, data TEXT NOT NULL, "
     "received REAL NOT NULL, PRIMARY KEY (seq, run_id)", "primary key (seq, run_id), the recorder's: (run_id, seq)"),
    ("run_id TEXT NOT NULL, seq INTEGER NOT NULL, time INTEGER NOT NULL, kind TEXT, data TEXT NOT NULL, "
     "received REAL NOT NULL, PRIMARY KEY (run_id, seq)", "column kind: TEXT, the recorder's: TEXT NOT NULL"),
    ("run_id TEXT NOT NULL, seq TEXT NOT NULL, time INTEGER NOT NULL, kind TEXT NOT NULL, data TEXT NOT NULL, "
     "received REAL NOT NULL, PRIMARY KEY (run_id, seq)",
     "column seq: TEXT NOT NULL, the recorder's: INTEGER NOT NULL"),
])
def test_a_table_with_the_recorders_names_but_other_constraints_is_refused_untouched(
        tmp_path: Path, events_sql: str, differs: str) -> None:
    """The layout check read the column names only: a file whose events table had no primary key was taken, and a
    replayed event was stored twice. The constraints are compared too, before anything is written to the file."""
    theirs = tmp_path / "theirs.sqlite"
    con = sqlite3.connect(theirs)
    con.execute(f"CREATE TABLE events ({events_sql})")
    con.commit()
    con.close()
    before = theirs.read_bytes()
    with pytest.raises(ValueError) as caught:
        RecorderStore(theirs)
    assert str(caught.value) == (f"cannot open the recorder database {str(theirs)!r}: its table 'events' is laid out "
                                 f"otherwise ({differs}): not a recorder database (left as it is; give another file)")
    assert theirs.read_bytes() == before  # no WAL mode set, none of the recorder's tables added


def test_a_database_the_recorder_wrote_opens_again_with_a_table_added_if_missing(tmp_path: Path) -> None:
    path = tmp_path / "ours.sqlite"
    store = RecorderStore(path)
    store.add_event(finished_run().events[0])
    store.close()
    con = sqlite3.connect(path)  # as a database of a recorder from before the re-plans were stored
    con.execute("DROP TABLE replans")
    con.commit()
    con.close()
    again = RecorderStore(path)
    assert again.event_seqs("run-1") == [0] and again.replans("run-1") == []


# ------------------------------------------------------------------------------------------------ conflicts
def test_a_second_run_under_the_same_id_is_reported_not_mixed_in(tmp_path: Path) -> None:
    """Run 2 under run 1's id: its events that differ from run 1's were dropped without a word (the log mixed the
    two runs) and its schedule too (the first one kept); the run was then called complete."""
    one, two = finished_run("EX12"), ShopService(builtin("EX12"), run_id="run-1")
    two.incarnation = one.incarnation  # a shop that names no other incarnation: its run_start is run 1's
    two.start()
    while not two.done:  # another policy: the last enabled action
        label = [a for a, ok in zip(two.state["actions"], two.state["mask"]) if ok][-1]
        two.handle_command(encode(m.make_command("run-1", two.state_seq, label)))
    ev1, sched1 = texts(one)
    ev2, sched2 = texts(two)
    assert ev1 != ev2 and one.final_schedule.makespan != two.final_schedule.makespan
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    for t in ev1[:10]:  # run 1 stopped after 10 events
        assert rec.handle_event(t, now=0.0) == []
    differ = [i for i in range(10) if ev1[i] != ev2[i]]
    out = [o for t in ev2 for o in rec.handle_event(t, now=0.0)]
    errs = [o.msg for o in out if o.topic == m.TOPIC_ERRORS]
    assert len(errs) == len(differ) and all(e["code"] == "run_conflict" for e in errs)
    assert f"run 'run-1': event {differ[0]} " in errs[0]["message"] and "another run with the same run id" in \
        errs[0]["message"]
    assert [o.msg for o in rec.handle_event(ev2[differ[0]], now=1.0) if o.topic == m.TOPIC_ERRORS] == []  # once
    rec.handle_schedule(sched2, now=0.0)
    assert rec.finish_ready() == []  # the events and the schedule are of two runs: not complete, no chart
    assert not rec.store.is_complete("run-1") and "is not the one its events give" in rec.store.disagreement("run-1")
    (err,) = [o.msg for o in rec.poll(now=5.0) if o.topic == m.TOPIC_ERRORS]
    assert err["code"] == "run_conflict" and "the schedule stored" in err["message"] and "is not the one its " \
        "events give" in err["message"]
    # a second schedule for a run that has one is reported, not dropped in silence
    (err,) = rec.handle_schedule(sched1, now=6.0)
    assert err.msg["code"] == "run_conflict" and "a schedule (makespan" in err.msg["message"]


def test_a_run_whose_schedule_and_events_disagree_is_not_complete(tmp_path: Path) -> None:
    """The store called such a run complete (every event there, a schedule stored) while the recorder reported the
    conflict and rendered no chart; a reader of the database (a test, a monitor) took it as a finished run."""
    one, two = finished_run("EX12"), finished_run("EX12", run_id="run-2")
    two_schedule = ShopService(builtin("EX12"), run_id="run-1")
    two_schedule.start()
    while not two_schedule.done:
        label = [a for a, ok in zip(two_schedule.state["actions"], two_schedule.state["mask"]) if ok][-1]
        two_schedule.handle_command(encode(m.make_command("run-1", two_schedule.state_seq, label)))
    store = RecorderStore(tmp_path / "db.sqlite")
    for e in one.events:
        store.add_event(e)
    assert not store.is_complete("run-1")  # no schedule yet
    store.add_schedule("run-1", two_schedule.final_schedule.to_dict())
    assert not store.is_complete("run-1")
    assert store.has_all_events("run-1")
    assert store.disagreement("run-1") == (
        f"run 'run-1': the schedule stored (makespan {two_schedule.final_schedule.makespan}) is not the one its events "
        f"give (makespan {one.final_schedule.makespan}; the makespan differ): another run with the same run id? (no "
        "chart; the run is not called complete)")
    for e in two.events:  # the same events and schedule agree: complete
        store.add_event(e)
    store.add_schedule("run-2", two.final_schedule.to_dict())
    assert store.disagreement("run-2") is None and store.is_complete("run-2")


def test_a_disrupted_runs_schedule_rebuilt_from_its_log_keeps_its_disruptions_and_orders(tmp_path: Path) -> None:
    # the rebuilt schedule carried no meta: against the run's final instance it failed the validator (an operation
    # lengthened by a breakdown "lasts 50, its duration is 20")
    from fms_sim.disruptions import Breakdown, Scenario

    svc = ShopService(builtin("EX12"), run_id="run-1", decisions="full", history=True,
                      scenario=Scenario((Breakdown(1, 5, 30),), (), 0.1, 2))
    svc.start()
    steps = 0
    while not svc.done:
        if steps == 3:
            svc.handle_order(encode(m.make_order("o1", [[{"machine": 2, "tool": None, "duration": 4}]])))
        if steps == 6:
            svc.handle_disruption(encode(m.make_disruption("d1", "breakdown", 20, machine=3)))
        label = next(a for a, ok in zip(svc.state["actions"], svc.state["mask"]) if ok)
        svc.handle_command(encode(m.make_command("run-1", svc.state_seq, label)))
        steps += 1
    events, schedule = texts(svc)
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    for t in events:
        rec.handle_event(t, now=0.0)
    rec.handle_schedule(schedule, now=0.0)
    rebuilt = rec.store.schedule_from_events("run-1")
    assert len(rebuilt.meta["scenario"]["breakdowns"]) == 2 and rebuilt.meta["arrivals"]
    assert validate(svc.instance, rebuilt) == [] and svc.instance.n_jobs == builtin("EX12").n_jobs + 1


def test_a_stray_event_after_the_end_is_kept_out_of_the_run(tmp_path: Path) -> None:
    """One bogus event numbered past the run's end made the run incomplete for ever (or, after the end, its
    schedule rebuilt from events invalid), with a replay request every second."""
    svc = finished_run("EX12")
    events, schedule = texts(svc)
    stray = decode(events[3])
    stray["seq"] = 500
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    assert rec.handle_event(encode(stray), now=0.0)[0].msg["from_seq"] == 0  # a gap, for all it knows
    out = [o for t in events for o in rec.handle_event(t, now=0.0)]
    (err,) = [o.msg for o in out if o.topic == m.TOPIC_ERRORS]  # when the end arrives
    assert err["code"] == "run_conflict" and "1 event(s) stored before its run_end" in err["message"]
    rec.handle_schedule(schedule, now=0.0)
    assert rec.missing_from("run-1") is None and rec.poll(now=9.0) == []
    assert rec.finish_ready() == [("run-1", None)]
    assert validate(svc.instance, rec.store.schedule_from_events("run-1")) == []
    late = dict(stray, seq=501)  # after the end is known: refused
    (err,) = rec.handle_event(encode(late), now=10.0)
    assert err.msg["code"] == "run_conflict" and "comes after the run's end" in err.msg["message"]
    assert 501 not in rec.store.event_seqs("run-1")


def test_a_second_earlier_run_end_is_a_conflict_and_keeps_the_runs_end(tmp_path: Path) -> None:
    """A second run_end with a smaller seq, arriving after the first, was stored where that seq was free and moved
    the run's end back: the events after it were left out of the run as strays, and the run called complete."""
    svc = finished_run("EX12")
    events, schedule = texts(svc)
    end = decode(events[-1])
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    for t in events[:5] + events[10:]:  # 5..9 not here yet
        rec.handle_event(t, now=0.0)
    rec.handle_schedule(schedule, now=0.0)
    early = dict(end, seq=7, time=3)
    (err,) = [o.msg for o in rec.handle_event(encode(early), now=1.0) if o.topic == m.TOPIC_ERRORS]
    assert err["code"] == "run_conflict" and err["message"] == (
        f"run 'run-1': a second run_end (event 7) before the run's end (event {end['seq']}, run_end): a run ends once; "
        "another run with the same run id? (not stored)")
    store = rec.store
    assert store.end_seq("run-1") == end["seq"] and store.after_end("run-1") == []
    assert 7 not in store.event_seqs("run-1")
    with pytest.raises(RunConflict, match="a second run_end"):  # the store alone refuses it too
        store.add_event(early)
    for t in events[5:10]:  # the real events 5..9 then complete the run
        rec.handle_event(t, now=2.0)
    assert rec.finish_ready() == [("run-1", None)] and store.is_complete("run-1")
    assert store.event_seqs("run-1") == list(range(len(events)))


def test_a_run_the_shop_does_not_know_is_asked_for_no_more(tmp_path: Path) -> None:
    svc = finished_run("EX12", run_id="ghost")
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False, retry_s=1.0)
    (ask,) = rec.handle_event(encode(svc.events[5]), now=0.0)
    shop = ShopService(builtin("EX12"), run_id="real")
    shop.start()
    (answer,) = shop.handle_replay(encode(ask.msg))
    assert answer.msg["code"] == "unknown_run"
    assert rec.handle_error(encode(answer.msg), now=0.5) == []
    assert rec.poll(now=2.0) == [] and rec.poll(now=9.0) == []  # it asked every second, for ever


def test_strays_a_differing_end_and_a_disagreement_of_one_run_are_each_reported(tmp_path: Path) -> None:
    # the strays were reported under the run_end's seq: a differing run_end that came later went unreported
    one, two = finished_run("EX12"), ShopService(builtin("EX12"), run_id="run-1")
    two.start()
    while not two.done:
        label = [a for a, ok in zip(two.state["actions"], two.state["mask"]) if ok][-1]
        two.handle_command(encode(m.make_command("run-1", two.state_seq, label)))
    events, _ = texts(one)
    _, other_schedule = texts(two)
    stray = dict(decode(events[3]), seq=500)
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    rec.handle_event(encode(stray), now=0.0)
    out = [o.msg for t in events for o in rec.handle_event(t, now=0.0) if o.topic == m.TOPIC_ERRORS]
    assert [e["code"] for e in out] == ["run_conflict"] and "stored before its run_end" in out[0]["message"]
    end = decode(events[-1])
    (err,) = rec.handle_event(encode(dict(end, time=end["time"] + 1)), now=1.0)
    assert err.msg["code"] == "run_conflict" and f"event {end['seq']} (run_end" in err.msg["message"]
    rec.handle_schedule(other_schedule, now=0.0)
    assert rec.finish_ready() == []
    (err,) = [o.msg for o in rec.poll(now=5.0) if o.topic == m.TOPIC_ERRORS]
    assert err["code"] == "run_conflict" and "is not the one its events give" in err["message"]


# ------------------------------------------------------------------------------------------------ a run begun again
def last_action_run(run_id: str = "run-1") -> ShopService:
    """A complete EX12 run choosing the last enabled action (another run than :func:`finished_run`'s)."""
    svc = ShopService(builtin("EX12"), run_id=run_id)
    svc.start()
    while not svc.done:
        label = [a for a, ok in zip(svc.state["actions"], svc.state["mask"]) if ok][-1]
        svc.handle_command(encode(m.make_command(run_id, svc.state_seq, label)))
    return svc


def replan_text(run_id: str, status: str) -> str:
    return encode(m.make_replan(run_id, "fms_agent", 3, 10, "breakdown", status, budget_s=1.0, wall_s=0.5,
                                before=90, after=80))


def test_a_shop_restarted_with_the_same_run_id_is_recorded_anew_and_the_earlier_run_kept(tmp_path: Path) -> None:
    """A shop respawned with fixed parameters starts the run again at event 0 under the same run id. Its events
    that differed from the first incarnation's were refused as conflicts and the rest stored beside the first
    incarnation's: the log mixed two runs (and lost the second's first events). Its run_start names another
    incarnation: the earlier one is kept under its own name and the run recorded anew."""
    one, two = finished_run("EX12"), last_action_run()
    assert one.events[0]["data"]["incarnation"] != two.events[0]["data"]["incarnation"]
    ev1, _ = texts(one)
    ev2, sched2 = texts(two)
    calls: list = []
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), renderer=fake_renderer(calls))
    for t in ev1[:10]:  # the first shop died after 10 events
        assert rec.handle_event(t, now=0.0) == []
    rec.handle_replan(replan_text("run-1", "adopted"), now=0.0)
    (err,) = rec.handle_event(ev2[0], now=1.0)
    assert err.topic == m.TOPIC_ERRORS and err.msg["code"] == "run_conflict" and err.msg["message"] == (
        "run 'run-1' began again (an event of another incarnation: a shop restarted with the same run id): the "
        "earlier incarnation's events, schedule and re-plans are kept as 'run-1~1'; the run is recorded anew")
    out = [o for t in ev2[1:] for o in rec.handle_event(t, now=1.0)]
    assert out == []  # no conflict, no replay request: the new incarnation is a run of its own
    rec.handle_replan(replan_text("run-1", "kept"), now=1.0)  # same key as the first incarnation's: stored too
    assert rec.handle_schedule(sched2, now=1.0) == []
    assert rec.finish_ready() == [("run-1", tmp_path / "run-1.gantt.png")]
    store = rec.store
    assert store.run_ids() == ["run-1~1", "run-1"] and store.incarnations("run-1") == ["run-1~1"]
    assert [(e["seq"], e["time"], e["kind"], e["data"]) for e in store.events("run-1")] == \
        [(e["seq"], e["time"], e["kind"], e["data"]) for e in two.events]
    assert [(e["seq"], e["time"], e["kind"], e["data"]) for e in store.events("run-1~1")] == \
        [(e["seq"], e["time"], e["kind"], e["data"]) for e in one.events[:10]]
    assert store.is_complete("run-1") and validate(two.instance, store.schedule_from_events("run-1")) == []
    assert [r["status"] for r in store.replans("run-1~1")] == ["adopted"]
    assert [r["status"] for r in store.replans("run-1")] == ["kept"]
    assert not store.is_complete("run-1~1") and store.schedule("run-1~1") is None
    (made, _), = calls
    assert made == two.final_schedule.makespan


def test_a_run_begun_again_after_its_chart_keeps_the_chart_and_an_old_replay_is_refused(tmp_path: Path) -> None:
    one, two, three = finished_run("EX12"), last_action_run(), finished_run("EX12")
    calls: list = []
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), renderer=fake_renderer(calls))
    for svc in (one, two):
        events, schedule = texts(svc)
        for t in events + [schedule]:
            (rec.handle_schedule if '"fms/schedule/v1"' in t else rec.handle_event)(t, now=0.0)
        assert rec.finish_ready() == [("run-1", tmp_path / "run-1.gantt.png")]
    store = rec.store
    moved = gantt_path(tmp_path, "run-1~1")  # (run-1_1.gantt.png)
    assert store.gantt("run-1~1") == str(moved) and moved.exists() and store.gantt("run-1") == str(
        tmp_path / "run-1.gantt.png")
    assert [c[0] for c in calls] == [one.final_schedule.makespan, two.final_schedule.makespan]
    assert store.is_complete("run-1~1") and store.is_complete("run-1")
    # the first shop's run_start replayed (a second shop under the same run id): refused, no ping-pong of runs
    (err,) = rec.handle_event(texts(one)[0][0], now=2.0)
    assert err.msg["code"] == "run_conflict" and err.msg["message"] == (
        "run 'run-1': event 0 (run_start at 0) is an earlier incarnation's of the run, kept as 'run-1~1' (not stored)")
    assert rec.handle_event(texts(two)[0][0], now=2.0) == []  # the current one's: a replay, stored once
    assert store.run_ids() == ["run-1~1", "run-1"]
    # a third start: the next name
    (err,) = rec.handle_event(texts(three)[0][0], now=3.0)
    assert "kept as 'run-1~2'; its chart is " + str(gantt_path(tmp_path, "run-1~2")) in err.msg["message"]
    assert store.incarnations("run-1") == ["run-1~1", "run-1~2"] and store.event_seqs("run-1") == [0]


def test_a_restarted_shop_whose_run_start_was_lost_is_still_recorded_apart(tmp_path: Path) -> None:
    """Seen live: a shop killed and restarted under its run id published its run_start before DDS matched it with
    the recorder; its later events, equal to the earlier incarnation's, were stored beside them (and the recorder,
    holding an event 0, never asked for the new one). Every event names its incarnation: the first one that comes
    keeps the earlier incarnation apart, the recorder asks for the run from event 0, and the earlier shop's events
    (one still running) are refused."""
    one, two = finished_run("EX12"), finished_run("EX12")  # the same decisions: equal events but for the incarnation
    assert [e["data"] for e in one.events[1:]] == [e["data"] for e in two.events[1:]]
    ev1, _ = texts(one)
    ev2, sched2 = texts(two)
    rec = Recorder(RecorderStore(tmp_path / "db.sqlite"), render=False)
    for t in ev1[:10]:
        assert rec.handle_event(t, now=0.0) == []
    out = rec.handle_event(ev2[3], now=1.0)  # the restarted shop's events 0..2 were lost
    errors = [o.msg for o in out if o.topic == m.TOPIC_ERRORS]
    asks = [o.msg for o in out if o.topic == m.TOPIC_REPLAY]
    assert [e["code"] for e in errors] == ["run_conflict"] and "kept as 'run-1~1'" in errors[0]["message"]
    assert [(a["run_id"], a["from_seq"]) for a in asks] == [("run-1", 0)]
    (err,) = rec.handle_event(ev1[10], now=1.0)  # the earlier shop, still running
    assert err.msg["code"] == "run_conflict" and "an earlier incarnation's of the run, kept as 'run-1~1'" in \
        err.msg["message"]
    for t in ev2:
        rec.handle_event(t, now=2.0)
    rec.handle_schedule(sched2, now=2.0)
    store = rec.store
    assert store.is_complete("run-1") and store.event_seqs("run-1~1") == list(range(10))
    assert store.events("run-1")[0]["data"]["incarnation"] == two.incarnation


def test_the_store_alone_keeps_a_run_begun_again_apart(tmp_path: Path) -> None:
    one, two = finished_run("EX12"), last_action_run()
    store = RecorderStore(tmp_path / "db.sqlite")
    for e in one.events[:10]:
        store.add_event(e)
    assert not store.begins_again(one.events[0]) and store.begins_again(two.events[0])
    assert store.begins_again(two.events[1])  # any event of the new incarnation tells it (its run_start can be lost)
    assert not store.begins_again(dict(two.events[1], incarnation=None))  # (one that names none: not told)
    for e in two.events:
        store.add_event(e)
    assert store.event_seqs("run-1") == list(range(len(two.events))) and store.event_seqs("run-1~1") == list(range(10))
    store.close()
    again = RecorderStore(tmp_path / "db.sqlite")  # durable
    assert again.incarnations("run-1") == ["run-1~1"] and again.end_seq("run-1") == len(two.events) - 1
