"""The recorder node's logic, without ROS: a durable SQLite log of runs, events, schedules and errors.

:class:`RecorderStore` is the database: SQLite in WAL mode (readers never block the writer; a killed recorder
loses nothing it committed), one commit per stored message. Events are keyed by ``(run_id, seq)`` and inserted
with ``INSERT OR IGNORE``, so replays and duplicates are stored exactly once; a schedule is stored once per
run. :meth:`RecorderStore.schedule_from_events` rebuilds a run's schedule from its ``*_end`` events alone, so
the log can be checked against the published schedule.

:class:`Recorder` is what the node runs: it decodes messages, stores them, and notices what is missing: a gap
in a run's event numbers, or a final schedule whose run has not all its events. It then asks the shop to
replay the run from the first missing event (``fms/replay_request/v1``), again every ``retry_s`` seconds while
something is missing. When a run is complete (:meth:`RecorderStore.is_complete`: schedule stored, events
``0..run_end`` all present, and the schedule the one its events give) it renders the Gantt chart once
(:func:`fms_sim.gantt.save_gantt`) to ``<gantt_dir>/<run_id>.gantt.png``. A message that contradicts what the log
holds for its run (:class:`RunConflict`: another run under the same run id, a stray event after the end) is not
stored and is answered with a ``run_conflict`` error; a run whose stored schedule is not the one its events give
(:meth:`RecorderStore.disagreement`) is not called complete, by :meth:`RecorderStore.is_complete` nor by the
recorder (a ``run_conflict`` error, no chart). A run begun again under its run id (a shop restarted with the same
``run_id``: an event of another ``incarnation``, :meth:`RecorderStore.begins_again`) is recorded anew, and
the earlier incarnation's rows are kept as ``<run_id>~1`` (``~2``, ...: :meth:`RecorderStore.archive_run`).

Tables: ``runs(run_id, instance, first_seen, end_seq, makespan, gantt)``, ``events(run_id, seq, time, kind,
data, received)``, ``schedules(run_id, makespan, schedule, received)``, ``errors(id, source, code, message,
run_id, received_text, at)``, ``replans(run_id, source, state_seq, time, reason, status, data, received)`` (the
agent's ``fms/replan/v1`` messages, each stored once); ``data``/``schedule`` hold JSON text.
"""

from __future__ import annotations

import json
import re
import sqlite3
import time
from collections import Counter
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable

from fms_msgs_json import (
    ERROR_MAX_CHARS, TOPIC_ERRORS, TOPIC_REPLAY, MessageError, bounded, decode, error_reply, make_error,
    make_replay_request,
)

from .files import replacing
from .instance import MAX_COUNT
from .schedule import AgvTrip, OperationRecord, Schedule, ToolTrip
from .shop_service import Outgoing

__all__ = ["RecorderStore", "Recorder", "gantt_path", "safe_run_name", "DEFAULT_DB"]

SOURCE = "fms_recorder"
INT64_MAX = 2**63 - 1  # (SQLite's largest integer: "every seq" where a run's end is not known yet)
DEFAULT_DB = "fms_recorder.sqlite"
"""The recorder's database file when no path is given (relative to the working directory)."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY,
    instance TEXT,
    first_seen REAL NOT NULL,
    end_seq INTEGER,
    makespan INTEGER,
    gantt TEXT
);
CREATE TABLE IF NOT EXISTS events (
    run_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    time INTEGER NOT NULL,
    kind TEXT NOT NULL,
    data TEXT NOT NULL,
    received REAL NOT NULL,
    PRIMARY KEY (run_id, seq)
);
CREATE TABLE IF NOT EXISTS schedules (
    run_id TEXT PRIMARY KEY,
    makespan INTEGER NOT NULL,
    schedule TEXT NOT NULL,
    received REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS replans (
    run_id TEXT NOT NULL,
    source TEXT NOT NULL,
    state_seq INTEGER NOT NULL,
    time INTEGER NOT NULL,
    reason TEXT NOT NULL,
    status TEXT NOT NULL,
    data TEXT NOT NULL,
    received REAL NOT NULL,
    PRIMARY KEY (run_id, source, state_seq, reason)
);
CREATE TABLE IF NOT EXISTS errors (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    source TEXT NOT NULL,
    code TEXT NOT NULL,
    message TEXT NOT NULL,
    run_id TEXT,
    received_text TEXT,
    at REAL NOT NULL
);
"""


#: the longest run id (as a file name) a run may have: its chart (and fms up's work folder) are named by it, and a
#: file name has 255 bytes at most (``<run_id>_1.gantt.png`` for a run begun again); the shop node and fms up refuse
#: a longer one at start
MAX_RUN_NAME = 200


def safe_run_name(run_id: str) -> str:
    """``run_id`` as a file name: unsafe characters (a path separator among them) → ``_``, no leading dot."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", run_id).strip(".") or "run"


def gantt_path(gantt_dir: str | Path, run_id: str) -> Path:
    """Where the Gantt chart of ``run_id`` goes: ``<gantt_dir>/<safe run id>.gantt.png`` (:func:`safe_run_name`)."""
    return Path(gantt_dir) / f"{safe_run_name(run_id)}.gantt.png"


#: the first bytes of every SQLite 3 database file
_SQLITE_HEADER = b"SQLite format 3\x00"

def _layout(db: sqlite3.Connection, table: str) -> dict[str, tuple[str, bool, int]]:
    """How ``table`` is laid out in ``db``: column -> (declared type, NOT NULL, place in the primary key, 0 if not
    in it), from ``PRAGMA table_info`` ({} if there is no such table)."""
    return {r[1]: (str(r[2]).upper(), bool(r[3]), int(r[5])) for r in db.execute(f"PRAGMA table_info({table})")}


@lru_cache(maxsize=1)
def _our_layouts() -> dict[str, dict[str, tuple[str, bool, int]]]:
    """The layout (:func:`_layout`) of each table as :data:`_SCHEMA` makes it: what an existing file must match."""
    db = sqlite3.connect(":memory:")
    try:
        db.executescript(_SCHEMA)
        tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE "
                                           "'sqlite_%' ORDER BY name")]
        return {t: _layout(db, t) for t in tables}
    finally:
        db.close()


def _layout_problem(have: dict[str, tuple[str, bool, int]], want: dict[str, tuple[str, bool, int]]) -> str | None:
    """How a table laid out as ``have`` differs from the recorder's ``want`` in what the recorder relies on (column
    names and types, NOT NULL, the primary key: without the key on ``events(run_id, seq)``, ``INSERT OR IGNORE``
    stored every replayed event again); None if it does not."""
    if set(have) != set(want):
        return f"columns {', '.join(sorted(have))}; the recorder's: {', '.join(sorted(want))}"

    def column(layout: dict[str, tuple[str, bool, int]], col: str) -> str:
        kind, not_null, _ = layout[col]
        return (kind or "untyped") + (" NOT NULL" if not_null else "")

    problems = [f"column {col}: {column(have, col)}, the recorder's: {column(want, col)}" for col in sorted(want)
                if column(have, col) != column(want, col)]

    def key(layout: dict[str, tuple[str, bool, int]]) -> str:
        cols = sorted((pk, col) for col, (_, _, pk) in layout.items() if pk)
        return f"({', '.join(col for _, col in cols)})" if cols else "none"

    if key(have) != key(want):
        problems.append(f"primary key {key(have)}, the recorder's: {key(want)}")
    return "; ".join(problems) or None


class RunConflict(ValueError):
    """A message that contradicts what the log holds for its run (another run under the same run id, or a stray
    event): it is not stored, and the recorder answers it with a ``run_conflict`` error."""


class RecorderStore:
    """The SQLite log (see the module docstring). Not thread-safe: one recorder, one thread."""

    def __init__(self, path: str | Path = DEFAULT_DB) -> None:
        self.path = Path(path)
        self._ends: dict[str, int | None] = {}  # run -> the seq of its run_end (None: not stored), as read or stored
        self._incarnations: dict[str, str | None] = {}  # run -> its stored run_start's incarnation, as read
        where = f"cannot open the recorder database {str(self.path)!r}"
        if self.path.parent and not self.path.parent.exists():
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:  # under a file, in /proc, in a folder this user may not write: a traceback
                raise ValueError(f"{where}: its folder cannot be made ({exc.strerror or exc})") from None
        if self.path.is_file() and self.path.stat().st_size:  # SQLite made a database of a file shorter than its
            with open(self.path, "rb") as fh:               # header (a one-line text file): never overwrite one
                head = fh.read(len(_SQLITE_HEADER))
            if head != _SQLITE_HEADER:
                raise ValueError(f"cannot open the recorder database {str(self.path)!r}: the file is not an SQLite "
                                 "database (left as it is)")
        try:
            self.db = sqlite3.connect(str(self.path), timeout=10.0)
            # checked before anything is written: another program's file is refused as it was (no WAL mode set, none
            # of the recorder's tables added); a table of one of the recorder's names is compared in its columns,
            # their types, NOT NULL and the primary key (the names alone took a file whose events had no key)
            for table, want in _our_layouts().items():
                have = _layout(self.db, table)
                problem = _layout_problem(have, want) if have else None
                if problem is not None:
                    self.db.close()
                    raise ValueError(f"{where}: its table {table!r} is laid out otherwise ({problem}): not a recorder "
                                     "database (left as it is; give another file)")
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=NORMAL")
            self.db.executescript(_SCHEMA)
            self.db.commit()
            # a database this user may read but not write was taken, and every message then failed to be stored
            self.db.execute("INSERT INTO errors (source, code, message, at) VALUES ('', '', '', 0)")
            self.db.rollback()
        except sqlite3.Error as exc:
            if getattr(self, "db", None) is not None:
                self.db.close()
            raise ValueError(f"{where}: {exc}") from None

    def close(self) -> None:
        """Commit and close (a WAL checkpoint folds the log into the main file)."""
        try:
            self.db.commit()
            self.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        finally:
            self.db.close()

    # ------------------------------------------------------------------ writing
    def _touch_run(self, run_id: str, now: float, instance: str | None = None) -> None:
        self.db.execute("INSERT OR IGNORE INTO runs (run_id, first_seen) VALUES (?, ?)", (run_id, now))
        if instance is not None:
            self.db.execute("UPDATE runs SET instance = ? WHERE run_id = ?", (instance, run_id))

    def commit(self) -> None:
        """Make the writes so far durable (the ``add_*`` methods commit unless told not to)."""
        self.db.commit()

    def _stored_event(self, run_id: str, seq: int) -> tuple[int, str, Any] | None:
        """``(time, kind, data)`` of the event stored under ``(run_id, seq)``, None if there is none."""
        row = self.db.execute("SELECT time, kind, data FROM events WHERE run_id = ? AND seq = ?",
                              (run_id, seq)).fetchone()
        return None if row is None else (row[0], row[1], json.loads(row[2]))

    def machines(self, run_id: str) -> int | None:
        """The shop's machine count its stored ``run_start`` names (``data.machines``), for the chart's rows: the
        schedule names only the machines its operations used. None where the event is not stored or names none (an
        older shop's)."""
        count = self._run_start_data(run_id).get("machines")
        return count if isinstance(count, int) and not isinstance(count, bool) and 1 <= count <= MAX_COUNT else None

    def _run_start_data(self, run_id: str) -> dict[str, Any]:
        """The data of ``run_id``'s stored ``run_start`` (event 0); empty where none is stored."""
        stored = self._stored_event(run_id, 0)
        return stored[2] if stored is not None and stored[1] == "run_start" else {}

    def incarnations(self, run_id: str) -> list[str]:
        """The names the earlier incarnations of ``run_id`` are kept under (:meth:`archive_run`:
        ``<run_id>~1``, ``<run_id>~2``, ... in the order they were replaced)."""
        pattern = re.compile(re.escape(run_id) + r"~([1-9][0-9]*)")
        found = [(int(match.group(1)), r) for r in self.run_ids() if (match := pattern.fullmatch(r))]
        return [r for _, r in sorted(found)]

    def _earlier_incarnation(self, event: dict[str, Any]) -> str | None:
        """The earlier incarnation (:meth:`incarnations`) whose event of ``event``'s seq is ``event``, if any."""
        mine = (event["time"], event["kind"], event["data"])
        return next((name for name in self.incarnations(event["run_id"])
                     if self._stored_event(name, event["seq"]) == mine), None)

    def _incarnation(self, run_id: str) -> str | None:
        """The incarnation of ``run_id``'s stored ``run_start`` (event 0), None if there is none or it names none."""
        if run_id not in self._incarnations:
            self._incarnations[run_id] = self._run_start_data(run_id).get("incarnation")
        return self._incarnations[run_id]

    def begins_again(self, event: dict[str, Any]) -> bool:
        """Whether ``event`` (decoded) starts its run again: it names an incarnation (the event's own
        ``incarnation``, or a ``run_start``'s in its data) that is not the one of the run's stored event 0 (a shop
        restarted with the same run id) nor an earlier incarnation's (:meth:`archive_run` keeps those apart; one of
        theirs replayed is a conflict). Any event of the new incarnation tells it, not only its ``run_start``: a
        restarted shop's first events can be lost to discovery, and the recorder never asked for an event 0 it had.
        Another difference (a run_start of the same incarnation at another time) is a conflict, as for any event."""
        incarnation = self._incarnation_of(event)
        if incarnation is None:
            return False
        stored = self._incarnation(event["run_id"])
        if stored is None or stored == incarnation:
            return False
        return self._archived_as(event["run_id"], incarnation) is None

    @staticmethod
    def _incarnation_of(event: dict[str, Any]) -> str | None:
        """The incarnation ``event`` names: its own, or a ``run_start``'s in its data (None: it names none)."""
        incarnation = event.get("incarnation")
        if incarnation is None and event["seq"] == 0 and event["kind"] == "run_start":
            incarnation = event["data"].get("incarnation")
        return incarnation

    def _archived_as(self, run_id: str, incarnation: str) -> str | None:
        """The name an earlier incarnation ``incarnation`` of ``run_id`` is kept under (:meth:`archive_run`), if any."""
        return next((name for name in self.incarnations(run_id) if self._incarnation(name) == incarnation), None)

    @staticmethod
    def _of_earlier(event: dict[str, Any], earlier: str) -> RunConflict:
        """The conflict of an event of the earlier incarnation kept as ``earlier`` (its shop still running)."""
        return RunConflict(f"run {event['run_id']!r}: event {event['seq']} ({event['kind']} at {event['time']}) is an "
                           f"earlier incarnation's of the run, kept as {earlier!r} (not stored)")

    def archive_run(self, run_id: str, *, commit: bool = True) -> str:
        """Keep the run's rows (``runs``, ``events``, ``schedules``, ``replans``) under the next free name
        ``<run_id>~<n>`` (n = 1, 2, ...) and return it, so that the run id is recorded anew: a run begun again
        (:meth:`begins_again`) had its events mixed with the earlier incarnation's. Errors stay under the run id
        they named (each is a report about a message, kept as it came)."""
        tables = ("runs", "events", "schedules", "replans")
        n = 1
        while any(self.db.execute(f"SELECT 1 FROM {t} WHERE run_id = ? LIMIT 1", (f"{run_id}~{n}",)).fetchone()
                  for t in tables):
            n += 1
        name = f"{run_id}~{n}"
        for table in tables:
            self.db.execute(f"UPDATE {table} SET run_id = ? WHERE run_id = ?", (name, run_id))
        self._ends.pop(run_id, None)
        self._incarnations.pop(run_id, None)
        self._incarnations.pop(name, None)
        self._ends.pop(name, None)
        if commit:
            self.db.commit()
        return name

    def add_event(self, event: dict[str, Any], now: float | None = None, *, commit: bool = True) -> bool:
        """Store a decoded ``fms/event/v1``; False if ``(run_id, seq)`` was already stored as it is. Raises
        :class:`RunConflict` (and stores nothing) for an event that differs from the one stored under its
        ``(run_id, seq)`` — another run under the same id; it was dropped without a word, and the run's log mixed
        two runs — that comes after the run's ``run_end``, or for a second ``run_end`` under another seq (a run
        ends once: an earlier second one moved the run's end back, and its events after it were left out), or for an
        event of an earlier incarnation kept apart (its shop still running). An event that begins the run again
        (:meth:`begins_again`) first moves the earlier incarnation's rows to their own name (:meth:`archive_run`)."""
        now = time.time() if now is None else now
        run_id, data, seq = event["run_id"], event["data"], event["seq"]
        if self.begins_again(event):
            self.archive_run(run_id, commit=False)
        incarnation = self._incarnation_of(event)
        if incarnation is not None and incarnation != self._incarnation(run_id):
            earlier = self._archived_as(run_id, incarnation)
            if earlier is not None:  # a shop of an earlier incarnation still running: its events stay out of the run
                raise self._of_earlier(event, earlier)
        if run_id not in self._ends:
            self._ends[run_id] = self.end_seq(run_id)
        end = self._ends[run_id]
        if end is not None and seq > end:
            raise RunConflict(f"run {run_id!r}: event {seq} ({event['kind']}) comes after the run's end (event {end}, "
                              "run_end): not stored")
        if end is not None and seq != end and event["kind"] == "run_end":  # an earlier one moved the end back
            raise RunConflict(f"run {run_id!r}: a second run_end (event {seq}) before the run's end (event {end}, "
                              "run_end): a run ends once; another run with the same run id? (not stored)")
        fresh = not self.db.in_transaction
        cur = self.db.execute(
            "INSERT OR IGNORE INTO events (run_id, seq, time, kind, data, received) VALUES (?, ?, ?, ?, ?, ?)",
            (run_id, seq, event["time"], event["kind"], json.dumps(data, separators=(",", ":")), now))
        if cur.rowcount != 1:  # stored already: a replay or a duplicate, unless it differs
            if fresh:  # the ignored insert opened a write transaction with nothing in it: it held the database's
                self.db.rollback()  # write lock until a later write was committed (other writers: "locked")
            row = self._stored_event(run_id, seq)
            assert row is not None
            if row == (event["time"], event["kind"], data):
                return False
            earlier = self._earlier_incarnation(event)  # (an event that names no incarnation: by its content)
            if earlier is not None:
                raise self._of_earlier(event, earlier)
            raise RunConflict(f"run {run_id!r}: event {seq} ({event['kind']} at {event['time']}) differs from the one "
                              f"stored ({row[1]} at {row[0]}): another run with the same run id? (not stored)")
        self._touch_run(run_id, now, data.get("instance") if event["kind"] == "run_start" else None)
        if seq == 0:
            self._incarnations.pop(run_id, None)  # (read again when next asked)
        if event["kind"] == "run_end":
            self.db.execute("UPDATE runs SET end_seq = ?, makespan = ? WHERE run_id = ?",
                            (seq, data.get("makespan"), run_id))
            self._ends[run_id] = seq
        if commit:
            self.db.commit()
        return True

    def add_schedule(self, run_id: str, schedule: dict[str, Any], now: float | None = None, *,
                     commit: bool = True) -> bool:
        """Store a run's final schedule (the Schedule JSON); False if the run already has it. Raises
        :class:`RunConflict` (and stores nothing) for another schedule of a run that has one (the first was kept,
        and the other dropped without a word)."""
        row = self.db.execute("SELECT schedule FROM schedules WHERE run_id = ?", (run_id,)).fetchone()
        if row is not None:
            if json.loads(row[0]) == schedule:
                return False
            raise RunConflict(f"run {run_id!r}: a schedule (makespan {schedule.get('makespan')!r}) that differs from "
                              f"the one stored (makespan {json.loads(row[0]).get('makespan')!r}): another run with "
                              "the same run id? (not stored)")
        now = time.time() if now is None else now
        self._touch_run(run_id, now, schedule.get("instance"))
        cur = self.db.execute("INSERT OR IGNORE INTO schedules (run_id, makespan, schedule, received) "
                              "VALUES (?, ?, ?, ?)", (run_id, schedule["makespan"], json.dumps(schedule), now))
        if commit:
            self.db.commit()
        return cur.rowcount == 1

    def add_error(self, error: dict[str, Any], now: float | None = None, *, commit: bool = True) -> None:
        """Store a decoded ``fms/error/v1`` (errors are not de-duplicated: each report is a fact). Its fields
        are cut to ``ERROR_MAX_CHARS`` as :func:`~fms_msgs_json.make_error` does (a decoded error already fits)."""
        def cap(field: str) -> Any:
            value = error.get(field)
            return bounded(value, ERROR_MAX_CHARS[field]) if isinstance(value, str) else value

        self.db.execute("INSERT INTO errors (source, code, message, run_id, received_text, at) "
                        "VALUES (?, ?, ?, ?, ?, ?)",
                        (cap("source"), error["code"], cap("message"), cap("run_id"), cap("received"),
                         time.time() if now is None else now))
        if commit:
            self.db.commit()

    def add_replan(self, msg: dict[str, Any], now: float | None = None, *, commit: bool = True) -> bool:
        """Store a decoded ``fms/replan/v1`` once (a re-delivered one is ignored); True if it was new."""
        data = {k: v for k, v in msg.items() if k != "schema"}
        cur = self.db.execute(
            "INSERT OR IGNORE INTO replans (run_id, source, state_seq, time, reason, status, data, received) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (msg["run_id"], msg["source"], msg["state_seq"], msg["time"], msg["reason"], msg["status"],
             json.dumps(data, separators=(",", ":")), time.time() if now is None else now))
        if commit:
            self.db.commit()
        return cur.rowcount == 1

    def replans(self, run_id: str) -> list[dict[str, Any]]:
        """The stored re-plans of a run (the message fields without ``schema``), by state and time."""
        rows = self.db.execute("SELECT data FROM replans WHERE run_id = ? ORDER BY state_seq, time", (run_id,))
        return [json.loads(d) for (d,) in rows]

    def set_gantt(self, run_id: str, path: str | Path | None) -> None:
        """Record where the run's chart is (None: it has none)."""
        self.db.execute("UPDATE runs SET gantt = ? WHERE run_id = ?", (None if path is None else str(path), run_id))
        self.db.commit()

    # ------------------------------------------------------------------ reading
    def run_ids(self) -> list[str]:
        return [r[0] for r in self.db.execute("SELECT run_id FROM runs ORDER BY first_seen, run_id")]

    def event_seqs(self, run_id: str) -> list[int]:
        return [r[0] for r in self.db.execute("SELECT seq FROM events WHERE run_id = ? ORDER BY seq", (run_id,))]

    def events(self, run_id: str) -> list[dict[str, Any]]:
        """The stored events of a run as ``{"seq", "time", "kind", "data"}`` dicts, by seq."""
        rows = self.db.execute("SELECT seq, time, kind, data FROM events WHERE run_id = ? ORDER BY seq", (run_id,))
        return [{"seq": s, "time": t, "kind": k, "data": json.loads(d)} for s, t, k, d in rows]

    def progress(self, run_id: str) -> tuple[int, int | None, int]:
        """How far the stored events of a run go: the operations ended (``op_end`` events), the latest event's time
        (None: no event stored yet) and the jobs live orders added (``order_accepted`` events) — for a progress line
        while the run goes on. Events after the run's end, once it is known, are not the run's (:meth:`after_end`):
        one counted "17 of 16 operations done")."""
        end = self.end_seq(run_id)
        last = end if end is not None else INT64_MAX
        done, latest = self.db.execute("SELECT COUNT(CASE WHEN kind = 'op_end' THEN 1 END), MAX(time) FROM events "
                                       "WHERE run_id = ? AND seq <= ?", (run_id, last)).fetchone()
        ordered = 0
        for (data,) in self.db.execute("SELECT data FROM events WHERE run_id = ? AND kind = 'order_accepted' AND "
                                       "seq <= ?", (run_id, last)):
            jobs = json.loads(data).get("jobs") if data else None
            ordered += len(jobs) if isinstance(jobs, list) else 0
        return int(done or 0), latest, ordered

    def end_seq(self, run_id: str) -> int | None:
        """The seq of the run's ``run_end`` event, if stored."""
        row = self.db.execute("SELECT end_seq FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else row[0]

    def first_missing(self, run_id: str) -> int:
        """The smallest event seq of the run not stored (= the number stored if they are 0..n-1)."""
        expect = 0
        for seq in self.event_seqs(run_id):
            if seq != expect:
                return expect
            expect += 1
        return expect

    def schedule(self, run_id: str) -> Schedule | None:
        row = self.db.execute("SELECT schedule FROM schedules WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else Schedule.from_json(row[0], strict=False)  # as its message carried it

    def gantt(self, run_id: str) -> str | None:
        row = self.db.execute("SELECT gantt FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else row[0]

    def errors(self, run_id: str | None = None) -> list[dict[str, Any]]:
        sql = "SELECT source, code, message, run_id, received_text FROM errors"
        rows = self.db.execute(sql + " WHERE run_id = ? ORDER BY id" if run_id else sql + " ORDER BY id",
                               (run_id,) if run_id else ())
        return [{"source": s, "code": c, "message": m, "run_id": r, "received": t} for s, c, m, r, t in rows]

    def after_end(self, run_id: str) -> list[int]:
        """The seqs of the run's stored events that come after its ``run_end`` (stored before it arrived: strays,
        or another run's under the same id); they are not part of the run (its schedule is rebuilt without them)."""
        end = self.end_seq(run_id)
        if end is None:
            return []
        return [r[0] for r in self.db.execute("SELECT seq FROM events WHERE run_id = ? AND seq > ? ORDER BY seq",
                                              (run_id, end))]

    def has_all_events(self, run_id: str) -> bool:
        """The run's schedule is stored and every event ``0..run_end`` is present (whether the two agree or not:
        :meth:`disagreement`)."""
        end = self.end_seq(run_id)
        if end is None or self.schedule(run_id) is None:
            return False
        (count,) = self.db.execute("SELECT COUNT(*) FROM events WHERE run_id = ? AND seq <= ?", (run_id, end)).fetchone()
        return count == end + 1

    def is_complete(self, run_id: str) -> bool:
        """The run is complete: its schedule is stored, every event ``0..run_end`` is present, and the schedule is the
        one its events give (:meth:`disagreement`; a run whose stored schedule and events are of two runs under one
        id was called complete, while the recorder reported the conflict and rendered no chart)."""
        return self.has_all_events(run_id) and self.disagreement(run_id) is None

    def disagreement(self, run_id: str) -> str | None:
        """Why the run's stored schedule is not the one its events give (None: it is, or the run has no schedule or
        no ``run_end`` stored yet): a schedule of another run under the same id arrived first and was kept."""
        stored = self.schedule(run_id)
        if stored is None or self.end_seq(run_id) is None:
            return None
        rebuilt = self.schedule_from_events(run_id)
        for what, a, b in (("makespan", [stored.makespan], [rebuilt.makespan]),
                           ("operations", stored.operations, rebuilt.operations),
                           ("AGV trips", stored.agv_trips, rebuilt.agv_trips),
                           ("tool trips", stored.tool_trips, rebuilt.tool_trips)):
            if Counter(a) != Counter(b):  # (the records are values: the orders may differ)
                return (f"run {run_id!r}: the schedule stored (makespan {stored.makespan}) is not the one its events "
                        f"give (makespan {rebuilt.makespan}; the {what} differ): another run with the same run id? "
                        "(no chart; the run is not called complete)")
        return None

    def schedule_from_events(self, run_id: str) -> Schedule:
        """Rebuild the run's schedule from its stored ``*_end`` events (which carry ``start``).

        The header (instance name, fleet sizes) comes from the stored schedule if there is one, else from the
        ``run_start`` event and the vehicles seen; so do the disruptions and live orders of the run (``meta``'s
        ``scenario`` and ``arrivals``, which the validator needs: the events name the disruptions and ordered jobs but
        not a start scenario's noise, nor the ordered operations). Raises ``ValueError`` if the run has no ``run_end``
        event.
        """
        last = self.end_seq(run_id)
        evs = [e for e in self.events(run_id) if last is None or e["seq"] <= last]  # (strays after the end: not)
        end = [e for e in evs if e["kind"] == "run_end"]
        if not end:
            raise ValueError(f"run {run_id!r} has no run_end event in the log; it is not complete")
        ops, agv, tt = [], [], []
        for e in evs:
            d, k = e["data"], e["kind"]
            if k == "op_end":
                ops.append(OperationRecord(d["job"], d["op"], d["machine"], d.get("tool"), d["start"], e["time"]))
            elif k == "agv_trip_end":
                agv.append(AgvTrip(d["agv"], d.get("job"), d.get("op"), d["from"], d["to"], d["start"], e["time"],
                                   d["loaded"]))
            elif k == "tool_trip_end":
                tt.append(ToolTrip(d["transporter"], d.get("tool"), d.get("job"), d.get("op"), d["from"], d["to"],
                                   d["start"], e["time"], d["loaded"]))
        stored = self.schedule(run_id)
        start = [e for e in evs if e["kind"] == "run_start"]
        name = stored.instance if stored else (start[0]["data"].get("instance", "") if start else "")
        n_agvs = stored.n_agvs if stored else len({t.agv for t in agv})
        n_tts = stored.n_tool_transporters if stored else len({t.transporter for t in tt})
        makespan = end[-1]["data"].get("makespan")
        if makespan is None:
            makespan = max((o.end for o in ops), default=0)
        meta: dict[str, Any] = {k: stored.meta[k] for k in ("scenario", "arrivals") if stored and k in stored.meta}
        return Schedule(instance=name, makespan=makespan, n_agvs=n_agvs, n_tool_transporters=n_tts,
                        operations=ops, agv_trips=agv, tool_trips=tt, meta=meta)


class Recorder:
    """Decodes, stores, asks for what is missing, and renders a Gantt chart per completed run.

    ``handle_*`` take the raw text of a received message and return the :class:`Outgoing` messages to publish
    (replay requests, errors). The caller passes the current time (``now``, seconds, monotonic) so that the
    retry rule is testable; :meth:`poll` repeats overdue requests.

    ``commit_s`` groups writes: with 0 every message is committed at once; otherwise at most every
    ``commit_s`` seconds (by the handlers or :meth:`poll`) and always before a run is finished. A crash then
    loses at most the last ``commit_s`` seconds of messages, which the next start asks the shop to replay.
    """

    def __init__(self, store: RecorderStore, *, gantt_dir: str | Path | None = None, render: bool = True,
                 source: str = SOURCE, retry_s: float = 1.0, commit_s: float = 0.0,
                 renderer: Callable[[Schedule, Path], Any] | None = None) -> None:
        self.store = store
        self.gantt_dir = Path(gantt_dir) if gantt_dir is not None else (store.path.parent or Path("."))
        self.render = render
        self.source = source
        self.retry_s = retry_s
        self.commit_s = commit_s
        self._dirty = False
        self._committed_at = float("-inf")
        self._renderer = renderer
        self._next: dict[str, int] = {}        # run -> first missing seq (contiguous prefix), per run seen
        self._above: dict[str, set[int]] = {}  # run -> seqs stored above the prefix
        self._end: dict[str, int | None] = {}  # run -> seq of its run_end event, once stored
        self._has_schedule: dict[str, bool] = {}
        self._asked: dict[str, float] = {}     # run -> when a replay was last requested
        self._finished: set[str] = set()
        self._given_up: set[str] = set()       # runs the shop does not know (it answered unknown_run): not asked
        self._conflicts: set[tuple[str, int | str]] = set()  # (run, the event's seq or what else) reported once
        self._outbox: list[Outgoing] = []      # errors found outside a message's handling, sent by the next poll
        self.rendered: list[tuple[str, Path]] = []

    # ------------------------------------------------------------------ bookkeeping
    def _seen(self, run_id: str) -> None:
        if run_id not in self._next:  # first sight in this session: resume from what the database holds
            seqs = self.store.event_seqs(run_id)
            nxt = 0
            for s in seqs:
                if s != nxt:
                    break
                nxt += 1
            self._next[run_id] = nxt
            self._above[run_id] = {s for s in seqs if s > nxt}
            self._end[run_id] = self.store.end_seq(run_id)
            self._has_schedule[run_id] = self.store.schedule(run_id) is not None

    def _advance(self, run_id: str, seq: int) -> None:
        if seq == self._next[run_id]:
            nxt, above = seq + 1, self._above[run_id]
            while nxt in above:
                above.discard(nxt)
                nxt += 1
            self._next[run_id] = nxt
        elif seq > self._next[run_id]:
            self._above[run_id].add(seq)

    def missing_from(self, run_id: str) -> int | None:
        """The first seq to ask for if the run is known to miss events (a gap, or events after a stored
        schedule's run_end), else None."""
        if run_id not in self._next or run_id in self._given_up:
            return None
        nxt = self._next[run_id]
        end = self._end[run_id]
        if end is not None:  # (events stored past the end are strays: they make no gap)
            return nxt if nxt <= end else None
        if self._above[run_id]:
            return nxt
        if self._has_schedule[run_id]:  # the run is over but its run_end never arrived
            return nxt
        return None

    def _ask(self, run_id: str, now: float, force: bool = False) -> list[Outgoing]:
        start = self.missing_from(run_id)
        if start is None:
            return []
        last = self._asked.get(run_id)
        if not force and last is not None and now - last < self.retry_s:
            return []
        self._asked[run_id] = now
        return [Outgoing(TOPIC_REPLAY, make_replay_request(run_id, start, self.source))]

    def _wrote(self, now: float) -> None:
        self._dirty = True
        if now - self._committed_at >= self.commit_s:
            self.flush(now)

    def flush(self, now: float) -> None:
        """Commit pending writes now."""
        if self._dirty:
            self.store.commit()
            self._dirty = False
        self._committed_at = now

    # ------------------------------------------------------------------ entry points
    def startup_request(self) -> Outgoing:
        """Ask the shop to replay the current run from the start (sent once the shop is listening)."""
        return Outgoing(TOPIC_REPLAY, make_replay_request("*", 0, self.source))

    def handle_event(self, text: str, now: float) -> list[Outgoing]:
        try:
            ev = decode(text, expect="event")
        except MessageError as exc:
            return [self._error(exc, text)]
        run_id = ev["run_id"]
        out: list[Outgoing] = []
        if self.store.begins_again(ev):  # a shop restarted with the same run id: the run is recorded anew
            out += self._begun_again(run_id, text)
        self._seen(run_id)
        try:
            new = self.store.add_event(ev, commit=False)
        except RunConflict as exc:
            return out + self._conflict(run_id, ev["seq"], exc, text)
        self._wrote(now)
        if new and ev["kind"] == "run_end":
            self._end[run_id] = ev["seq"]
            strays = self.store.after_end(run_id)
            if strays:  # stored before the end was known (a stray, or another run's): kept, not part of the run
                out += self._conflict(run_id, "strays", RunConflict(
                    f"run {run_id!r}: {len(strays)} event(s) stored before its run_end (event {ev['seq']}) come "
                    f"after it (from event {strays[0]}): kept in the log, left out of the run"), None)
        self._advance(run_id, ev["seq"])
        return out + self._ask(run_id, now)

    def _begun_again(self, run_id: str, text: str) -> list[Outgoing]:
        """Keep the run's earlier incarnation under its own name (:meth:`RecorderStore.archive_run`; its chart, if
        rendered, is renamed with it), forget what this session knew of the run, and say so in a ``run_conflict``
        error (the two incarnations' events were mixed under one run id, or the new one's refused as conflicts)."""
        earlier = self.store.archive_run(run_id, commit=False)
        chart, note = self.store.gantt(earlier), ""
        if chart and Path(chart).exists():  # the new incarnation's chart would replace it
            moved = gantt_path(Path(chart).parent, earlier)
            try:
                Path(chart).replace(moved)
            except OSError as exc:
                note = f"; its chart {chart} could not be renamed ({exc.strerror or exc}) and is the new run's now"
                self.store.set_gantt(earlier, None)
            else:
                self.store.set_gantt(earlier, moved)
                note = f"; its chart is {moved}"
        for table in (self._next, self._above, self._end, self._has_schedule, self._asked):
            table.pop(run_id, None)
        self._finished.discard(run_id)
        self._given_up.discard(run_id)
        self._conflicts = {key for key in self._conflicts if key[0] != run_id}
        self._dirty = True  # (committed with the event that began the run again)
        return [Outgoing(TOPIC_ERRORS, make_error(
            self.source, "run_conflict", f"run {run_id!r} began again (an event of another incarnation: a shop "
            f"restarted with the same run id): the earlier incarnation's events, schedule and re-plans are kept as "
            f"{earlier!r}{note}; the run is recorded anew", run_id=run_id, received=text))]

    def _conflict(self, run_id: str, about: int | str, exc: RunConflict, text: str | None) -> list[Outgoing]:
        """The ``run_conflict`` error answering ``exc``, once per run and what it is about: an event's seq, or
        ``"strays"``, ``"schedule"``, ``"disagreement"`` (one key each: the strays and a later disagreement shared
        one, and the second went unreported)."""
        if (run_id, about) in self._conflicts:
            return []
        self._conflicts.add((run_id, about))
        return [Outgoing(TOPIC_ERRORS, make_error(self.source, "run_conflict", str(exc), run_id=run_id,
                                                  received=text))]

    def handle_schedule(self, text: str, now: float) -> list[Outgoing]:
        try:
            msg = decode(text, expect="schedule")
        except MessageError as exc:
            return [self._error(exc, text)]
        run_id = msg["run_id"]
        self._seen(run_id)
        try:
            self.store.add_schedule(run_id, msg["schedule"], commit=False)
        except RunConflict as exc:
            return self._conflict(run_id, "schedule", exc, text)
        self._has_schedule[run_id] = True
        self._wrote(now)
        return self._ask(run_id, now)

    def handle_replan(self, text: str, now: float = 0.0) -> list[Outgoing]:
        return self._store(text, "replan", self.store.add_replan, now)

    def handle_error(self, text: str, now: float = 0.0) -> list[Outgoing]:
        """Store an error; one that answers this recorder's replay request with ``unknown_run`` (a run the shop
        does not run: one stray event named it) ends the requests for that run (they went on every ``retry_s``)."""
        out = self._store(text, "error", self.store.add_error, now)
        try:
            err = decode(text, expect="error")
            asked = decode(err.get("received") or "", expect="replay_request") if err["code"] == "unknown_run" else None
        except MessageError:
            return out
        if asked is not None and asked["requester"] == self.source and asked["run_id"] in self._next:
            self._given_up.add(asked["run_id"])
        return out

    def _store(self, text: str, kind: str, add: Callable[..., Any], now: float) -> list[Outgoing]:
        """Decode a message of ``kind`` that is stored as it is (no run bookkeeping) and store it."""
        try:
            msg = decode(text, expect=kind)
        except MessageError as exc:
            return [self._error(exc, text)]
        add(msg, commit=False)
        self._wrote(now)
        return []

    def poll(self, now: float) -> list[Outgoing]:
        """Commit what is due and repeat the replay request of every run seen in this session that still
        misses events."""
        if self._dirty and now - self._committed_at >= self.commit_s:
            self.flush(now)
        out, self._outbox = self._outbox, []
        for run_id in list(self._next):
            out += self._ask(run_id, now)
        return out

    def finish_ready(self) -> list[tuple[str, Path | None]]:
        """Mark complete runs (seen in this session) finished, rendering their Gantt charts; returns
        ``(run_id, png path or None)`` for each run finished by this call."""
        done = []
        for run_id in list(self._next):
            if run_id in self._finished or self.missing_from(run_id) is not None:
                continue
            if self._end[run_id] is None or not self._has_schedule[run_id] or not self.store.has_all_events(run_id):
                continue
            if self._dirty:  # a finished run is durable before anyone is told
                self.store.commit()
                self._dirty = False
            self._finished.add(run_id)
            problem = self.store.disagreement(run_id)
            if problem is not None:  # the schedule and the events are of two runs: no chart, no "complete"
                self._outbox += self._conflict(run_id, "disagreement", RunConflict(problem), None)
                continue
            path = self._render(run_id) if self.render else None
            done.append((run_id, path))
        return done

    def _render(self, run_id: str) -> Path:
        existing = self.store.gantt(run_id)
        target = gantt_path(self.gantt_dir, run_id)
        if existing and Path(existing).exists():
            return Path(existing)
        schedule = self.store.schedule(run_id)
        assert schedule is not None
        target.parent.mkdir(parents=True, exist_ok=True)
        # a temporary of its own (a fixed name was shared by two recorders charting one run into one folder)
        with replacing(target, suffix=".tmp" + target.suffix) as tmp:  # atomic: no half-written chart is seen
            if self._renderer is not None:
                self._renderer(schedule, tmp)
            else:
                from .gantt import chart_title, save_gantt

                save_gantt(schedule, tmp, title=chart_title(schedule, run_id), machines=self.store.machines(run_id))
        self.store.set_gantt(run_id, target)
        self.rendered.append((run_id, target))
        return target

    def _error(self, exc: BaseException, text: str) -> Outgoing:
        return Outgoing(TOPIC_ERRORS, error_reply(self.source, exc, received=text))
