"""``fms bench``: tables, outputs, validation of every schedule, resumable cache, parallel runs, bad input."""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import pytest

from fms_dispatch import benchmark as bm
from fms_dispatch import solvers
from fms_sim.benchmarks import builtin
from fms_sim.validate import validate

RULES = ["rule:FIFO+first", "rule:MTWR+nearest"]


def run_cli(argv: list[str]) -> int:
    """Parse ``argv`` with a parser holding only ``bench`` (as cli.build_parser adds it) and run it."""
    p = argparse.ArgumentParser(prog="fms")
    sub = p.add_subparsers(dest="cmd", required=True)
    bm.add_bench_parser(sub)
    a = p.parse_args(argv)
    return a.fn(a)


def solved(name: str, method: str, no_tools: bool = False) -> int:
    """The makespan of an independent solve, after checking the schedule with the validator."""
    inst = builtin(name)
    if no_tools:
        inst = inst.without_tools()
    s = solvers.solve(inst, method)
    assert validate(inst, s) == []
    return s.makespan


def count_solves(monkeypatch: pytest.MonkeyPatch, fail_at: int | None = None) -> list[tuple[str, str, dict]]:
    """Wrap ``solvers.solve`` (used by in-process runs) to record (instance, method, options) per call."""
    calls: list[tuple[str, str, dict]] = []
    real = solvers.solve

    def spy(instance, name, **options):
        calls.append((instance.name, name, options))
        if fail_at is not None and len(calls) == fail_at:
            raise KeyboardInterrupt
        return real(instance, name, **options)

    monkeypatch.setattr(solvers, "solve", spy)
    return calls


def cache_lines(d: Path) -> list[dict]:
    path = d / bm.CACHE_NAME
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


# ------------------------------------------------------------------------------------------------ bu
def test_bu_subset_writes_every_output_with_gaps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = run_cli(["bench", "bu", "--methods", *RULES, "--instances", "1,2", "--jobs", "1", "-q",
                  "--results-dir", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    stem = tmp_path / "bench_bu_L2"
    for ext in ("csv", "json", "md", "png"):
        assert Path(f"{stem}.{ext}").stat().st_size > 0
    assert Path(f"{stem}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    expected = {(i, m): solved(i, m) for i in ("EX12", "EX22") for m in RULES}
    with open(f"{stem}.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["instance"], r["method"]) for r in rows] == list(expected)
    for r in rows:
        assert r["valid"] == "True" and r["error"] == "" and r["variant"] == "agvs" and r["time_limit"] == ""
        assert int(r["makespan"]) == expected[r["instance"], r["method"]]
    # gap by hand: EX12 (layout 2) has the known optimum 82, EX22 76
    ex12 = next(r for r in rows if r["instance"] == "EX12" and r["method"] == "rule:FIFO+first")
    assert int(ex12["optimum"]) == 82
    assert float(ex12["gap_pct"]) == pytest.approx(round(100 * (expected["EX12", "rule:FIFO+first"] - 82) / 82, 3))
    ex22 = next(r for r in rows if r["instance"] == "EX22" and r["method"] == "rule:FIFO+first")
    assert int(ex22["optimum"]) == 76

    doc = json.loads(Path(f"{stem}.json").read_text())
    assert doc["benchmark"] == "bu" and doc["layout"] == 2 and doc["methods"] == RULES
    gaps = ([100 * (expected["EX12", m] - 82) / 82 for m in RULES],
            [100 * (expected["EX22", m] - 76) / 76 for m in RULES])
    for k, m in enumerate(RULES):
        avg = (gaps[0][k] + gaps[1][k]) / 2
        assert doc["summary"][m]["mean_gap_pct"] == pytest.approx(avg, abs=1e-3)
        assert doc["summary"][m]["mean_makespan"] == pytest.approx((expected["EX12", m] + expected["EX22", m]) / 2)
        assert doc["summary"][m]["n_failed"] == 0
    best12 = min(expected["EX12", m] for m in RULES)
    assert doc["best_rule"]["EX12/agvs"]["makespan"] == best12
    assert doc["best_rule"]["EX12/agvs"]["methods"] == [m for m in RULES if expected["EX12", m] == best12]

    # the Markdown table: header, one row per instance, then average / gap / hits
    md = Path(f"{stem}.md").read_text()
    assert md.strip() in out
    lines = [ln for ln in md.splitlines() if ln.startswith("|")]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
    assert cells[0] == ["instance", "opt", "FIFO+first", "MTWR+nearest", "best rule"]
    assert [c[0] for c in cells[2:7]] == ["EX12", "EX22", "average", "gap %", "at opt"]
    assert cells[2][:4] == ["EX12", "82", str(expected["EX12", RULES[0]]), str(expected["EX12", RULES[1]])]
    avg_gap = (gaps[0][0] + gaps[1][0]) / 2
    assert cells[5][2] == f"{avg_gap:.2f}"
    assert cells[6][1] == "2/2"
    assert bm.bu_table(doc["rows"]) in md


def test_resume_skips_cached_tasks_and_force_redoes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks(RULES, sets=[1, 2])
    first = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert len(calls) == 4 and len(cache_lines(tmp_path)) == 4
    again = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert len(calls) == 4, "a second run must not solve again"
    assert again == first and bm.bu_table(again) == bm.bu_table(first)
    # the CLI resumes too (same cache), and --force re-solves everything
    assert run_cli(["bench", "bu", "--methods", *RULES, "--instances", "1..2", "-q", "--jobs", "1",
                    "--results-dir", str(tmp_path)]) == 0
    assert len(calls) == 4
    assert run_cli(["bench", "bu", "--methods", *RULES, "--instances", "1..2", "-q", "--jobs", "1", "--force",
                    "--results-dir", str(tmp_path)]) == 0
    assert len(calls) == 8 and len(cache_lines(tmp_path)) == 8
    # another seed is another run (it reused seed 0's rows and printed their makespans)
    seeded = bm.run_bench(bm.bu_tasks(RULES, sets=[1, 2], seed=7), jobs=1, results_dir=tmp_path)
    assert len(calls) == 12 and {r["seed"] for r in seeded} == {7}
    rows = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert len(calls) == 12 and {r["seed"] for r in rows} == {0}  # seed 0's rows are still cached


def test_interrupted_run_loses_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tasks = bm.bu_tasks(RULES, sets=[1, 2])
    calls = count_solves(monkeypatch, fail_at=3)
    with pytest.raises(KeyboardInterrupt):
        bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    done = cache_lines(tmp_path)
    assert [(r["instance"], r["method"]) for r in done] == [("EX12", RULES[0]), ("EX12", RULES[1])]
    # a run killed while writing leaves a partial line: it is ignored
    with (tmp_path / bm.CACHE_NAME).open("a") as fh:
        fh.write('{"benchmark": "bu", "inst')
    calls.clear()
    monkeypatch.undo()
    calls = count_solves(monkeypatch)
    rows = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert [(c[0], c[1]) for c in calls] == [("EX22", RULES[0]), ("EX22", RULES[1])]
    assert [r["instance"] for r in rows] == ["EX12", "EX12", "EX22", "EX22"] and all(r["valid"] for r in rows)


def test_an_interrupt_while_the_outputs_are_written_keeps_the_last_ones(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """They were written in place: an interrupt while the chart was saved left half a PNG over the last run's."""
    from matplotlib.figure import Figure

    rows = bm.run_bench(bm.bu_tasks(RULES, sets=[1]), jobs=1, results_dir=tmp_path)
    paths = bm.write_outputs(rows, tmp_path, "t", title="t")
    before = {p: p.read_bytes() for p in paths.values()}

    def cut(self, fname, **kwargs):
        Path(fname).write_bytes(b"\x89PNG half")
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", cut)
    with pytest.raises(KeyboardInterrupt):
        bm.write_outputs(rows, tmp_path, "t", title="t")
    assert {p: p.read_bytes() for p in paths.values()} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_a_stopped_parallel_bench_stops_its_workers(tmp_path: Path) -> None:
    """SIGTERM (kill, a supervisor) left the workers running on for their task's whole time limit without their
    parent; an interrupt waited for them, then dropped their results."""
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "bench", "sl", "--group", "0", "--instances",
                             "0..1", "--methods", "cpsat", "--cpsat-time-limit", "60", "--tools", "no", "--jobs", "2",
                             "-q", "--results-dir", str(tmp_path)], stderr=subprocess.PIPE, text=True)
    children: set[int] = set()
    deadline = time.monotonic() + 60
    while len(children) < 2 and time.monotonic() < deadline:  # the two workers (and spawn's resource tracker)
        time.sleep(0.2)
        try:
            text = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text()
        except OSError:
            break
        children |= {int(c) for c in text.split()}
    time.sleep(3)  # into their CP-SAT searches
    proc.send_signal(signal.SIGTERM)
    t0 = time.monotonic()
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "fms: interrupted" in err, err
    assert time.monotonic() - t0 < 10  # not the searches' 60 s
    time.sleep(1)

    def alive(pid: int) -> bool:
        try:
            return "\nState:\tZ" not in Path(f"/proc/{pid}/status").read_text()
        except OSError:
            return False

    assert len(children) >= 2 and not [pid for pid in children if alive(pid)]


def test_parallel_run_gives_the_same_table(tmp_path: Path) -> None:
    tasks = bm.bu_tasks(RULES, sets=[1, 2, 3])
    serial = bm.run_bench(tasks, jobs=1, results_dir=tmp_path / "serial")
    parallel = bm.run_bench(tasks, jobs=2, results_dir=tmp_path / "parallel")
    assert all(r["valid"] for r in parallel)
    assert [(r["instance"], r["method"]) for r in parallel] == [(r["instance"], r["method"]) for r in serial]
    assert bm.bu_table(parallel) == bm.bu_table(serial)
    assert len(cache_lines(tmp_path / "parallel")) == len(tasks)


def test_time_limits_and_cpsat_workers_per_method(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[str, dict]] = []
    real = solvers.solve

    def fake(instance, name, **options):  # record options; answer with a quick, valid rule schedule
        calls.append((name, options))
        s = real(instance, "rule:FIFO+first")
        s.meta["lower_bound"] = 50
        return s

    monkeypatch.setattr(solvers, "solve", fake)
    tasks = bm.bu_tasks(["rule:LPT+first", "sos", "cpsat"], sets=[1], time_limit=3, cpsat_time_limit=7)
    assert [t.time_limit for t in tasks] == [None, 3.0, 7.0]
    rows = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    opts = dict(calls)
    assert "time_limit" not in opts["rule:LPT+first"] and "workers" not in opts["rule:LPT+first"]
    assert opts["sos"]["time_limit"] == 3.0 and "workers" not in opts["sos"]
    assert opts["cpsat"]["time_limit"] == 7.0 and opts["cpsat"]["workers"] == bm.cpsat_threads(1)
    assert rows[2]["workers"] == bm.cpsat_threads(1) and rows[2]["lower_bound"] == 50
    # a different time limit is a different cache key: rules are reused, searching methods are not
    calls.clear()
    bm.run_bench(bm.bu_tasks(["rule:LPT+first", "sos", "cpsat"], sets=[1], time_limit=4, cpsat_time_limit=7),
                 jobs=1, results_dir=tmp_path)
    assert [c[0] for c in calls] == ["sos"]


# ------------------------------------------------------------------------------------------------ failures
def test_invalid_schedule_is_an_error_row_and_exit_1(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    real = solvers.solve

    def broken(instance, name, **options):
        if name == "rule:MTWR+nearest":
            s = real(instance, name, **options)
            s.makespan += 1  # a solver bug the validator must catch
            return s
        if name == "random":
            raise RuntimeError("boom\nsecond line")
        return real(instance, name, **options)

    monkeypatch.setattr(solvers, "solve", broken)
    rc = run_cli(["bench", "bu", "--methods", *RULES, "random", "--instances", "1", "-q", "--jobs", "1",
                  "--results-dir", str(tmp_path)])
    assert rc == bm.EXIT_FAILED
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "bench_bu_L2.json").read_text())
    by_method = {r["method"]: r for r in doc["rows"]}
    assert by_method[RULES[0]]["valid"] and by_method[RULES[0]]["gap_pct"] is not None
    bad = by_method[RULES[1]]
    assert not bad["valid"] and bad["error"].startswith("invalid schedule") and "makespan" in bad["error"]
    assert bad["gap_pct"] is None
    assert by_method["random"]["error"] == "RuntimeError: boom"
    assert doc["summary"][RULES[1]]["n_failed"] == 1 and doc["summary"][RULES[1]]["mean_makespan"] is None
    row = next(ln for ln in out.splitlines() if ln.startswith("| EX12"))
    assert "INVALID" in row and "ERROR" in row
    assert "### Failures" in out and "EX12 (agvs) rule:MTWR+nearest: invalid schedule" in out
    # failed tasks are retried on the next run (valid ones are not)
    calls = count_solves(monkeypatch)
    bm.run_bench(bm.bu_tasks([*RULES, "random"], sets=[1]), jobs=1, results_dir=tmp_path)
    assert sorted(c[1] for c in calls) == ["random", "rule:MTWR+nearest"]


def test_unknown_method_fails_before_any_work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = count_solves(monkeypatch)
    for bad, msg in ((["rule:FIFO+first", "ppo-does-not-exist"], "unknown solver 'ppo-does-not-exist'"),
                     (["rule:NOPE+first"], "unknown job rule 'NOPE'"),
                     (["rule:FIFO+sideways"], "unknown vehicle rule 'sideways'"),
                     (["rule:FIFO+first", "ppo:no-such-model"], "no model named 'no-such-model'"),
                     (["rule:MTWR+nearest+same-machine-first"], "'rule:MTWR\\+nearest\\+same-machine-first' names a "
                      "tool rule: fms bench runs first, random and rule:JOB\\+VEHICLE through the paper's net")):
        with pytest.raises(ValueError, match=msg):
            run_cli(["bench", "bu", "--methods", *bad, "-q", "--results-dir", str(tmp_path)])
        with pytest.raises(ValueError, match=msg):
            run_cli(["bench", "sl", "--methods", *bad, "-q", "--results-dir", str(tmp_path)])
    assert calls == [] and not (tmp_path / bm.CACHE_NAME).exists()
    for limit in ("0", "nan", "inf"):  # NaN and inf would reach the caches as non-JSON
        with pytest.raises(ValueError, match="time-limit must be a positive number"):
            run_cli(["bench", "bu", "--time-limit", limit, "-q", "--results-dir", str(tmp_path)])
    with pytest.raises(ValueError, match="cpsat-time-limit must be a positive number"):
        run_cli(["bench", "sl", "--cpsat-time-limit", "nan", "-q", "--results-dir", str(tmp_path)])


@pytest.mark.parametrize("spec", ["8", "0..8", "3..1", "a", "0,,x", "", "-1", "1.5"])
def test_bad_group_spec(spec: str, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="sl group"):
        run_cli(["bench", "sl", "--group", spec, "--methods", "rule:FIFO+first", "-q",
                 "--results-dir", str(tmp_path)])
    assert not (tmp_path / bm.CACHE_NAME).exists()


def test_index_spec_syntax() -> None:
    assert bm.parse_index_spec("0", 0, 7) == [0]
    assert bm.parse_index_spec("0..7", 0, 7) == list(range(8))
    assert bm.parse_index_spec("0,3", 0, 7) == [0, 3]
    assert bm.parse_index_spec("5-9", 0, 9) == [5, 6, 7, 8, 9]
    assert bm.parse_index_spec("3, 1..2,3", 0, 9) == [1, 2, 3]
    with pytest.raises(ValueError, match="BU job set"):
        bm.parse_index_spec("0", 1, 10, "BU job set")


# ------------------------------------------------------------------------------------------------ sl
def test_sl_one_instance_both_tool_variants(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = run_cli(["bench", "sl", "--group", "0", "--instances", "0", "--methods", "rule:FIFO+first", "-q",
                  "--jobs", "1", "--results-dir", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "bench_sl.json").read_text())
    rows = doc["rows"]
    assert [(r["instance"], r["variant"], r["method"]) for r in rows] == [
        ("sl00", "agvs", "rule:FIFO+first"), ("sl00", "agvs+tools", "rule:FIFO+first")]
    assert rows[0]["makespan"] == solved("sl00", "rule:FIFO+first", no_tools=True)
    assert rows[1]["makespan"] == solved("sl00", "rule:FIFO+first")
    assert all(r["valid"] and r["n_jobs"] == 15 and r["n_machines"] == 15 for r in rows)
    assert rows[0]["wall_time"] >= 0 and rows[0]["optimum"] is None
    assert "### AGVs only (agvs)" in out and "### AGVs + tools (agvs+tools)" in out
    for ext in ("csv", "md", "png"):
        assert (tmp_path / f"bench_sl.{ext}").stat().st_size > 0
    # one variant only
    assert run_cli(["bench", "sl", "--group", "0", "--instances", "0", "--methods", "rule:FIFO+first", "-q",
                    "--tools", "yes", "--jobs", "1", "--results-dir", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "bench_sl.json").read_text())
    assert [r["variant"] for r in doc["rows"]] == ["agvs+tools"]


def test_sl_table_reports_the_lower_bound_and_gap() -> None:
    rows = [
        {"benchmark": "sl", "instance": "sl00", "variant": "agvs", "method": "rule:FIFO+first", "makespan": 120,
         "valid": True, "lower_bound": None, "optimum": None, "wall_time": 0.1, "error": None},
        {"benchmark": "sl", "instance": "sl00", "variant": "agvs", "method": "cpsat", "makespan": 110,
         "valid": True, "lower_bound": 100, "optimum": None, "wall_time": 5.0, "error": None},
    ]
    table = bm.sl_table(rows)
    lines = [[c.strip() for c in ln.strip("|").split("|")] for ln in table.splitlines() if ln.startswith("|")]
    assert lines[0] == ["instance", "LB", "FIFO+first", "cpsat", "best rule"]
    assert lines[2] == ["sl00", "100", "120", "110", "FIFO+first (120)"]
    assert lines[4] == ["gap %", "0.00", "20.00", "10.00", ""]
    assert bm.summary(rows)["cpsat"]["mean_gap_pct"] == pytest.approx(10.0)


def test_bad_library_arguments_are_refused_before_any_work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = count_solves(monkeypatch)
    with pytest.raises(ValueError, match="layout must be 1, 2, 3 or 4, got 5"):
        bm.bu_tasks(RULES, layout=5)
    with pytest.raises(ValueError, match="--jobs must be >= 1, got 0"):
        bm.run_bench(bm.bu_tasks(RULES, sets=[1]), jobs=0, results_dir=tmp_path)
    (tmp_path / "afile").write_text("")
    with pytest.raises(ValueError, match="--results-dir .*afile: .*afile is a file; name a folder"):
        bm.run_bench(bm.bu_tasks(RULES, sets=[1]), results_dir=tmp_path / "afile")
    task = bm.bu_tasks(RULES, sets=[1])[0]
    with pytest.raises(ValueError, match="EX12 has no tools; variant agvs\\+tools does not apply"):
        bm.load_task_instance(replace(task, variant="agvs+tools"))
    with pytest.raises(ValueError, match="unknown variant 'tools'"):
        bm.load_task_instance(replace(task, variant="tools"))
    assert calls == [] and not (tmp_path / bm.CACHE_NAME).exists()


def test_a_task_runs_and_is_cached_under_the_budget_it_really_has() -> None:
    assert bm._time_limit_for("plan:cpsat:8", 10.0, 60.0) == 8.0  # the name's budget, not --time-limit's
    assert bm._time_limit_for("plan:cpsat", 10.0, 60.0) == 10.0 and bm._time_limit_for("cpsat", 10.0, 60.0) == 60.0
    assert bm._time_limit_for("rule:FIFO+first", 10.0, 60.0) is None
    # ppo and plan:list take no time limit: they were cached under --time-limit (and solved again when it changed)
    assert bm._time_limit_for("ppo:bu", 10.0, 60.0) is None and bm._time_limit_for("plan:list", 10.0, 60.0) is None


def test_a_cut_or_foreign_cache_line_costs_no_result(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run killed mid-write leaves its last line cut: the next run's first row was glued onto it and lost (solved
    again by every later run); a line that is JSON but no row (no makespan) crashed the tables with a KeyError."""
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks(RULES, sets=[1])
    bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    cache = tmp_path / bm.CACHE_NAME
    whole = cache.read_text()
    cache.write_text(whole[:-40])  # the last row cut
    bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert len(calls) == 3  # the cut row's task solved again, once
    bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert len(calls) == 3 and json.loads(cache.read_text().splitlines()[-1])["valid"]  # its new row, whole
    with cache.open("a") as fh:  # a line that is JSON, but not a row
        fh.write(json.dumps({"benchmark": "bu", "instance": "EX12", "variant": "agvs", "method": RULES[0],
                             "time_limit": None, "valid": True}) + "\n")
    rows = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert len(calls) == 3 and all(isinstance(r["makespan"], int) for r in rows)


def test_cpsat_threads_given_are_not_answered_by_a_row_of_other_threads(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    # --cpsat-workers 1 reused a row solved with 2 threads (CP-SAT under a time limit depends on them)
    calls = count_solves(monkeypatch)
    two = bm.bu_tasks(["cpsat"], sets=[1], cpsat_time_limit=1.0, cpsat_workers=2)
    bm.run_bench(two, jobs=1, results_dir=tmp_path)
    bm.run_bench(two, jobs=1, results_dir=tmp_path)
    assert len(calls) == 1
    rows = bm.run_bench(bm.bu_tasks(["cpsat"], sets=[1], cpsat_time_limit=1.0, cpsat_workers=1), jobs=1,
                        results_dir=tmp_path)
    assert len(calls) == 2 and calls[-1][2]["workers"] == 1 and rows[0]["workers"] == 1
    bm.run_bench(bm.bu_tasks(["cpsat"], sets=[1], cpsat_time_limit=1.0), jobs=1, results_dir=tmp_path)
    assert len(calls) == 2  # without --cpsat-workers the threads follow --jobs: any cached row serves


def test_a_missing_plan_file_is_refused_before_any_work(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=f"'plan:file:{tmp_path}/none.json': no plan file {tmp_path}/none.json"):
        bm.check_methods(["list", f"plan:file:{tmp_path}/none.json"])


def test_the_table_says_what_it_ran_with_and_which_optima_are_the_literatures() -> None:
    rows = [{"benchmark": "bu", "instance": name, "variant": "agvs", "method": m, "time_limit": tl, "seed": 0,
             "workers": w, "makespan": 120, "wall_time": 1.0, "valid": True, "error": None, "lower_bound": None,
             "status": None, "optimum": opt, "n_jobs": 5, "n_machines": 4}
            for name, opt in (("EX61", 111), ("EX71", 111)) for m, tl, w in (("list", None, None),
                                                                             ("tabu", 3.0, None), ("cpsat", 30.0, 2))]
    text = bm.render_markdown(rows, "t")
    assert "Time limits: tabu 3 s; cpsat 30 s. CP-SAT threads: 2." in text
    assert "| EX71     | 111†" in text and "| EX61     | 111 " in text and "† the literature's opt" in text


def test_a_results_dir_where_nothing_can_be_written_is_refused_with_the_option(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Under /proc no folder can be made: fms bench said "No such file or directory: /proc/..." (naming neither the
    option nor the cause); fms experiment named both. Now bench does too, before any task runs."""
    where = "/proc/fms-no-such-results"
    with pytest.raises(ValueError, match=f"--results-dir {where}: nothing can be written"):
        bm.run_bench(bm.bu_tasks(["first"], sets=[1]), results_dir=where)
    from fms_dispatch.cli import main

    assert main(["bench", "bu", "--methods", "first", "--instances", "1", "-q", "--results-dir", where]) == 2
    assert "fms: error: --results-dir /proc/fms-no-such-results: nothing can be written" in capsys.readouterr().err


def test_an_interrupt_says_what_was_kept_and_how_to_go_on(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """An interrupted bench said only "fms: interrupted": not that the finished tasks are cached, nor that the
    tables were not written and a rerun continues."""
    real = bm.run_task

    def second_interrupted(task: bm.Task) -> dict:
        if task.method == RULES[1]:
            raise KeyboardInterrupt
        return real(task)

    monkeypatch.setattr(bm, "run_task", second_interrupted)
    with pytest.raises(KeyboardInterrupt):
        bm.run_bench(bm.bu_tasks(RULES, sets=[1]), results_dir=tmp_path)
    err = capsys.readouterr().err
    assert f"interrupted after 1 of 2 task(s) to run; the finished ones are cached in {tmp_path / bm.CACHE_NAME}" in err
    assert "run the same command again to continue" in err
    assert [r["method"] for r in bm.read_cache(tmp_path / bm.CACHE_NAME).values()] == RULES[:1]


# ------------------------------------------------------------------------------------------------ cache digests
MODELS = Path(__file__).resolve().parents[2] / "models"


def _rebuild_bu() -> None:
    """Forget the built EX instances, as a new process would, so that they are read from the job sets again."""
    import fms_sim.benchmarks as fb

    fb._ex.cache_clear()


@pytest.fixture
def bu_jobsets(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A copy of the package's BU job sets that the EX built-ins are read from while the test runs."""
    import fms_sim.benchmarks as fb

    path = tmp_path / "bu_jobsets.json"
    path.write_text(json.dumps(fb._data("bu_jobsets.json")))
    real = fb._data

    def data(filename: str) -> dict:
        return json.loads(path.read_text()) if filename == "bu_jobsets.json" else real(filename)

    monkeypatch.setattr(fb, "_data", data)
    _rebuild_bu()
    yield path
    _rebuild_bu()  # (the package's data again for the tests after this one)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_row_is_solved_again_after_its_instance_data_change(bu_jobsets: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """The key names the instance only: after its data changed under the same name (a job set's time corrected),
    the row solved from the old data was reused without a word. A data file only reformatted is the same instance."""
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks(["list"], sets=[1])
    out = tmp_path / "out"
    first = bm.run_bench(tasks, jobs=1, results_dir=out)
    data = json.loads(bu_jobsets.read_text())
    bu_jobsets.write_text(json.dumps(data, indent=4, sort_keys=True))  # other bytes, the same instance
    _rebuild_bu()
    assert bm.run_bench(tasks, jobs=1, results_dir=out) == first and len(calls) == 1
    data["jobsets"]["set1"]["jobs"][0][0][1] += 30  # job 1's first operation takes 30 more
    bu_jobsets.write_text(json.dumps(data))
    _rebuild_bu()
    capsys.readouterr()
    rows = bm.run_bench(tasks, jobs=1, results_dir=out)
    err = capsys.readouterr().err
    assert len(calls) == 2
    assert rows[0]["makespan"] == solved("EX12", "list") != first[0]["makespan"]  # (a third call, the test's)
    assert err.count("solved again") == 1 and "1 cached row(s) solved again" in err and "instance data: 1" in err
    assert rows[0]["digests"]["instance"] == bm.instance_digest(builtin("EX12")) != first[0]["digests"]["instance"]
    assert bm.run_bench(tasks, jobs=1, results_dir=out) == rows and len(calls) == 3  # the new row serves now


def test_a_ppo_row_is_solved_again_after_its_models_weights_change(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A model retrained into the same folder kept its cached rows: the tables showed the old weights' makespans."""
    model = tmp_path / "mine"
    shutil.copytree(MODELS / "bu", model)
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks([f"ppo:{model}"], sets=[1])
    out = tmp_path / "out"
    first = bm.run_bench(tasks, jobs=1, results_dir=out)
    assert bm.run_bench(tasks, jobs=1, results_dir=out) == first and len(calls) == 1
    for old, new in (("best_model.zip", "model.zip"), ("best_model.actor.npz", "model.actor.npz")):
        shutil.copyfile(MODELS / "bu" / new, model / old)  # other weights (and their export) under the same name
    capsys.readouterr()
    rows = bm.run_bench(tasks, jobs=1, results_dir=out)
    err = capsys.readouterr().err
    assert len(calls) == 2 and rows[0]["valid"] and "1 cached row(s) solved again" in err and "model weights: 1" in err
    assert rows[0]["digests"]["weights"] == _sha256(model / "best_model.zip") != first[0]["digests"]["weights"]
    assert rows[0]["digests"]["instance"] == first[0]["digests"]["instance"]  # the instance did not change
    bm.run_bench(tasks, jobs=1, results_dir=out)
    assert len(calls) == 2


def test_the_default_ppo_row_is_solved_again_when_the_default_model_is_another(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``ppo`` resolves to the default model per instance: rows of the former default served for another."""
    from fms_dispatch.rl import models

    one, two = tmp_path / "one", tmp_path / "two"
    shutil.copytree(MODELS / "bu", one)
    shutil.copytree(MODELS / "bu", two)
    for old, new in (("best_model.zip", "model.zip"), ("best_model.actor.npz", "model.actor.npz")):
        shutil.copyfile(MODELS / "bu" / new, two / old)
    default = one
    monkeypatch.setattr(models, "default_model_name", lambda inst: str(default))
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks(["ppo"], sets=[1])
    out = tmp_path / "out"
    first = bm.run_bench(tasks, jobs=1, results_dir=out)
    bm.run_bench(tasks, jobs=1, results_dir=out)
    assert len(calls) == 1 and first[0]["digests"]["weights"] == _sha256(one / "best_model.zip")
    default = two
    capsys.readouterr()
    rows = bm.run_bench(tasks, jobs=1, results_dir=out)
    assert len(calls) == 2 and rows[0]["digests"]["weights"] == _sha256(two / "best_model.zip")
    assert "model weights: 1" in capsys.readouterr().err


def test_a_plan_file_row_is_solved_again_after_the_file_changes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A ``plan:file:PATH`` row was cached by its path: a plan written over it left the old plan's makespan."""
    plan, other = tmp_path / "plan.json", tmp_path / "other.json"
    solvers.solve(builtin("EX12"), "list").save(plan)
    solvers.solve(builtin("EX12"), "rule:FIFO+first").save(other)
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks([f"plan:file:{plan}"], sets=[1])
    out = tmp_path / "out"
    first = bm.run_bench(tasks, jobs=1, results_dir=out)
    bm.run_bench(tasks, jobs=1, results_dir=out)
    assert len(calls) == 1
    shutil.copyfile(other, plan)
    capsys.readouterr()
    rows = bm.run_bench(tasks, jobs=1, results_dir=out)
    assert len(calls) == 2 and "plan file: 1" in capsys.readouterr().err
    assert rows[0]["makespan"] == solved("EX12", f"plan:file:{other}") != first[0]["makespan"]
    assert rows[0]["digests"]["plan"] == _sha256(other)


def test_rows_cached_before_digests_are_reused_with_one_notice(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """Rows cached before the digests were recorded (hours of CP-SAT runs) are reused, and the run says how many
    carry no digest and that --force solves them again; --force records their digests."""
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks(RULES, sets=[1])
    bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    cache = tmp_path / bm.CACHE_NAME
    old = [{k: v for k, v in row.items() if k != "digests"} for row in cache_lines(tmp_path)]
    cache.write_text("".join(json.dumps(row) + "\n" for row in old))
    capsys.readouterr()
    rows = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    err = capsys.readouterr().err
    assert len(calls) == 2 and rows == old
    assert err.count("carry no digest") == 1 and "--force solves them again" in err
    assert "reused 2 cached row(s) that carry no digest" in err
    bm.run_bench(tasks, jobs=1, results_dir=tmp_path, force=True)
    assert len(calls) == 4 and all("digests" in row for row in cache_lines(tmp_path)[2:])
    bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    assert len(calls) == 4 and "carry no digest" not in capsys.readouterr().err


def test_rows_of_unchanged_inputs_are_reused_and_record_their_digests(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    plan = tmp_path / "plan.json"
    solvers.solve(builtin("EX12"), "list").save(plan)
    calls = count_solves(monkeypatch)
    tasks = bm.bu_tasks(["list", "ppo:full", f"plan:file:{plan}"], sets=[1])
    first = bm.run_bench(tasks, jobs=1, results_dir=tmp_path)
    capsys.readouterr()
    assert bm.run_bench(tasks, jobs=1, results_dir=tmp_path) == first and len(calls) == 3
    assert capsys.readouterr().err == ""
    inst = bm.instance_digest(builtin("EX12"))
    base = {"format": bm.CACHE_FORMAT, "instance": inst}
    assert [r["digests"] for r in first] == [base, {**base, "weights": _sha256(MODELS / "full" / "best_model.zip")},
                                             {**base, "plan": _sha256(plan)}]
    assert [r["digests"] for r in cache_lines(tmp_path)] == [r["digests"] for r in first]


def test_fms_bench_refuses_a_negative_seed(tmp_path, capsys):
    # sos and tabu ran -1 as seed 1 and cached the rows under -1: the same runs under two seeds
    from fms_dispatch import cli

    for bench in ("bu", "sl"):
        code = cli.main(["bench", bench, "--methods", "list", "--seed", "-1", "-q", "--results-dir", str(tmp_path)])
        assert code == 2 and "--seed must be an integer >= 0, got -1" in capsys.readouterr().err
    assert not (tmp_path / "bench_cache.jsonl").exists()
