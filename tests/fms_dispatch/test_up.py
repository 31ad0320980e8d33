"""``fms up``'s stop policy, with stand-in node processes (no DDS): the nodes deliver the run, then one of
them will not stop. The real three-node runs are in ``tests/ros/test_nodes.py``."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")  # fms up refuses to start without it, even with stand-in nodes

from fms_dispatch import up  # noqa: E402
from fms_sim.benchmarks import builtin  # noqa: E402
from fms_sim.formats import load_instance  # noqa: E402
from fms_sim.schedule import Schedule  # noqa: E402
from fms_sim.validate import validate  # noqa: E402

#: a stand-in node: argv[1] is the node module, argv[2] its parameters as JSON. The shop writes a rule
#: schedule (or, with ``bad_schedule``, one with an operation dropped) and the final instance, the recorder
#: writes the chart file; a node named in ``stuck`` ignores SIGINT (so fms up must kill it), the others exit 0.
FAKE_NODE = textwrap.dedent('''
    import json, signal, sys, time
    from pathlib import Path

    module, params = sys.argv[1], json.loads(sys.argv[2])
    role = module.rsplit(".", 1)[1].removesuffix("_node")
    stopped = []

    def stop(*_):  # like the real nodes: once stopping, a repeated SIGINT is ignored
        stopped.append(1)
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    signal.signal(signal.SIGINT, signal.SIG_IGN if role == params["stuck"] else stop)
    if role == "agent" and params["log_error"]:  # an error logged by a node that stays up
        print(params["log_error"], file=sys.stderr, flush=True)
    if role == "recorder" and params["slow"]:  # a run under way: two operations ended, as the recorder stores them
        from fms_sim.recorder_store import RecorderStore
        store = RecorderStore(params["db"])
        for seq, (t, kind) in enumerate([(0, "run_start"), (5, "op_end"), (9, "agv_trip_end"), (12, "op_end")]):
            store.add_event({"run_id": params["run"], "seq": seq, "time": t, "kind": kind, "data": {}})
        store.close()
    if role == "recorder" and params["steady"]:  # a long run that keeps moving: an operation ends every 0.1 s
        from fms_sim.recorder_store import RecorderStore
        store = RecorderStore(params["db"])
        end, seq = time.monotonic() + params["slow"], 4
        while time.monotonic() < end:
            time.sleep(0.1)
            store.add_event({"run_id": params["run"], "seq": seq, "time": 10 * seq, "kind": "op_end", "data": {}})
            seq += 1
        store.close()
    elif params["slow"]:  # a run under way; a stop still ends the node at once
        end = time.monotonic() + params["slow"]
        while time.monotonic() < end and not stopped:
            time.sleep(0.02)
    if role == "shop":
        from fms_sim.instance import Instance
        from fms_dispatch.rules import solve_rule
        inst = Instance.from_json(Path(params["instance"]).read_text())
        if params["ordered"]:  # a live order joined the run: one job more than the instance
            data = inst.to_dict()
            data["jobs"].append([{"machine": 1, "tool": None, "duration": 5}])
            inst = Instance.from_dict(data)
        sched = solve_rule(inst, "SPT", "first")
        if params["bad_schedule"]:
            data = json.loads(sched.to_json())
            data["operations"] = data["operations"][1:]
            text = json.dumps(data)
        else:
            text = sched.to_json()
        Path(params["instance_out"]).write_text(inst.to_json())
        Path(params["schedule_out"]).write_text(text)
    if role == "recorder" and not params["no_chart"]:
        Path(params["png"]).parent.mkdir(parents=True, exist_ok=True)
        Path(params["png"]).write_bytes(b"png")
    while not stopped:
        time.sleep(0.02)
''')


@pytest.fixture
def fake_nodes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    script = tmp_path / "fake_node.py"
    script.write_text(FAKE_NODE)

    def install(stuck: str = "", bad_schedule: bool = False, slow: float = 0.0, steady: bool = False,
                ordered: bool = False, no_chart: bool = False, log_error: str = "") -> None:
        def command(module: str, params: dict[str, Any], python: str | None = None) -> list[str]:
            extra = {"stuck": stuck, "bad_schedule": bad_schedule, "png": str(tmp_path / "out" / "t1.gantt.png"),
                     "slow": slow, "steady": steady, "run": "t1", "ordered": ordered,
                     "no_chart": no_chart, "log_error": log_error}
            return [sys.executable, str(script), module, json.dumps({**params, **extra})]
        monkeypatch.setattr(up, "node_command", command)
        monkeypatch.setattr(up, "STOP_GRACE_S", 1.0)
    return install


def _record_params(monkeypatch: pytest.MonkeyPatch) -> dict[str, dict[str, Any]]:
    """Record each node's parameters as ``fms up`` starts it (``{"agent_node": {...}, ...}``), the node started by the
    ``node_command`` in place (e.g. the stand-in of :func:`fake_nodes`)."""
    seen: dict[str, dict[str, Any]] = {}
    fake = up.node_command

    def command(module: str, params: dict[str, Any], python: str | None = None) -> list[str]:
        seen[module.rsplit(".", 1)[1]] = params
        return fake(module, params, python)

    monkeypatch.setattr(up, "node_command", command)
    return seen


def _up(tmp_path: Path, *extra: str) -> int:
    return up.main(["EX12", "--solver", "first", "--out", str(tmp_path / "out" / "s.json"), "--db",
                    str(tmp_path / "out" / "fms.sqlite"), "--run-id", "t1", "--timeout", "60", *extra])


def test_a_node_that_will_not_stop_after_a_delivered_run_is_a_warning(fake_nodes, tmp_path: Path, capsys) -> None:
    fake_nodes(stuck="recorder")
    assert _up(tmp_path) == up.EXIT_OK
    err = capsys.readouterr().err
    assert "warning: the run is complete and valid, but a node did not stop cleanly: recorder exit code -9" in err
    # the log folder is a temporary one here: the warning names the log and keeps it
    kept = [line for line in err.splitlines() if line.startswith("  recorder log (")]
    assert kept and Path(kept[0].split("(", 1)[1].rstrip("):")).exists()
    sched = Schedule.load(tmp_path / "out" / "s.json")
    assert validate(load_instance("EX12"), sched) == []


def test_clean_stops_give_no_warning(fake_nodes, tmp_path: Path, capsys) -> None:
    fake_nodes()
    assert _up(tmp_path) == up.EXIT_OK
    out = capsys.readouterr()
    assert "warning" not in out.err and "instance:" not in out.out  # no order: the instance is the one given
    assert not (tmp_path / "out" / "s.instance.json").exists()


def test_a_chart_that_never_comes_does_not_lose_the_delivered_schedule(fake_nodes, tmp_path: Path, capsys) -> None:
    """The recorder failing to render (a full disk) left fms up waiting until --timeout, then failing with 'no
    progress' and without writing the valid schedule it had."""
    fake_nodes(no_chart=True)
    assert _up(tmp_path, "--timeout", "1") == up.EXIT_FAILED
    out = capsys.readouterr()
    assert "the run is complete and its schedule written, but the recorder rendered no chart" in out.err
    assert "  recorder log (" in out.err and "gantt:" not in out.out
    assert validate(load_instance("EX12"), Schedule.load(tmp_path / "out" / "s.json")) == []


def test_a_run_with_live_orders_writes_the_instance_its_schedule_is_valid_for(fake_nodes, tmp_path: Path,
                                                                              capsys) -> None:
    """The schedule of a run that took orders has jobs the instance has not: `fms validate INSTANCE` refused it, and
    the final instance was removed with the work folder. It is written beside the schedule and named."""
    fake_nodes(ordered=True)
    assert _up(tmp_path) == up.EXIT_OK
    final_path = tmp_path / "out" / "s.instance.json"
    assert f"instance: {final_path} (with the 1 job ordered during the run; fms validate {final_path} " in \
        capsys.readouterr().out
    sched, final = Schedule.load(tmp_path / "out" / "s.json"), load_instance(str(final_path))
    assert validate(final, sched) == [] and final.n_jobs == load_instance("EX12").n_jobs + 1
    assert validate(load_instance("EX12"), sched)  # what the user had before: the ordered job is unknown there


@pytest.mark.skipif(not Path("/proc/self").exists(), reason="needs /proc, where no folder can be made")
@pytest.mark.parametrize("flag", ["--gantt-dir", "--log-dir", "--out", "--db"])
def test_an_output_where_nothing_can_be_written_is_refused_before_the_run(flag: str, tmp_path: Path,
                                                                           capsys) -> None:
    """An unwritable --gantt-dir was found after the run: fms up waited for the chart until --timeout and lost the
    valid schedule (an unwritable --out lost it too). Checked before any node starts, even for root."""
    where = "/proc/fms-no-such-folder" + ("" if flag.endswith("dir") else "/x.json")
    args = {"--out": str(tmp_path / "s.json"), "--db": str(tmp_path / "fms.sqlite"), flag: where}
    code = up.main(["EX12", "--solver", "first", *[x for kv in args.items() for x in kv]])
    err = capsys.readouterr().err
    assert code == 2 and f"{flag} {where}: nothing can be written in /proc/fms-no-such-folder" in err
    assert not (tmp_path / "s.json").exists()


def test_a_long_run_reports_its_progress_and_a_timeout_says_how_far_it_got(fake_nodes, tmp_path: Path,
                                                                           monkeypatch, capsys) -> None:
    """Every PROGRESS_S seconds `fms up` says how far the run is (operations ended, the shop's clock: read from the
    recorder's database); --quiet says nothing; a run that makes no progress for --timeout seconds fails, naming the
    progress made and the option to raise, while one that keeps moving runs past it."""
    monkeypatch.setattr(up, "PROGRESS_S", 0.3)
    fake_nodes(slow=2.0)
    assert _up(tmp_path) == up.EXIT_OK
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "operations done" in line]
    assert lines and re.fullmatch(r"fms up: 2 of 13 operations done, shop time 12, \d+ s", lines[-1]), err
    chart = tmp_path / "out" / "t1.gantt.png"  # (the stand-in recorder's chart: fms up refuses a recorded run id)
    chart.unlink()
    assert _up(tmp_path, "--quiet", "--db", str(tmp_path / "out" / "q.sqlite")) == up.EXIT_OK  # (the last --db)
    assert "operations done" not in capsys.readouterr().err
    chart.unlink()
    assert _up(tmp_path, "--timeout", "0.8", "--db", str(tmp_path / "out" / "t.sqlite")) == up.EXIT_FAILED
    err = capsys.readouterr().err
    assert "timed out: no progress for 0.8 s while waiting for" in err and "2 of 13 operations done, shop time 12 " \
        "(longer pauses need --timeout)" in err, err


def test_progress_text_counts_the_operations_of_ordered_jobs() -> None:
    # after a live order fms up said "14 of 13 operations done"
    assert up._progress_text((2, 12, 0), 13) == "2 of 13 operations done, shop time 12"
    assert up._progress_text((14, 143, 1), 13) == ("14 operations done (the shop's 13 and those of 1 ordered job), "
                                                   "shop time 143")
    assert up._progress_text((14, 143, 3), 13).startswith("14 operations done (the shop's 13 and those of 3 "
                                                          "ordered jobs)")
    assert up._progress_text((0, None, 0), 13) == "no event recorded yet"


@pytest.mark.parametrize("logged, named", [
    ("[INFO] [1.0] [fms_agent]: planning\n[ERROR] [1.5] [fms_agent]: [plan_failed] no plan for EX12\n[ERROR] [2.0] "
     "[fms_agent]: again", "[ERROR] [1.5] [fms_agent]: [plan_failed] no plan for EX12"),
    ("Traceback (most recent call last):\n  File \"agent.py\", line 3, in on_state\n    plan()\nValueError: no plan",
     "ValueError: no plan")])
def test_a_timeout_names_the_error_a_node_logged(fake_nodes, tmp_path: Path, capsys, logged: str, named: str) -> None:
    """A node that hit an error and stayed up (an exception in a callback) left only 'no progress' and the log tails:
    the timeout now names the node and its first error."""
    fake_nodes(slow=2.0, log_error=logged)
    assert _up(tmp_path, "--timeout", "0.8") == up.EXIT_FAILED
    err = capsys.readouterr().err
    assert f"(longer pauses need --timeout); the agent node logged an error: {named}\n" in err, err


def test_a_run_that_keeps_moving_outlasts_the_timeout(fake_nodes, tmp_path: Path, monkeypatch, capsys) -> None:
    """--timeout bounds a pause, not the run: 2.5 s of operations ending every 0.1 s with --timeout 1 is done."""
    monkeypatch.setattr(up, "PROGRESS_S", 0.2)
    fake_nodes(slow=2.5, steady=True)
    assert _up(tmp_path, "--timeout", "1") == up.EXIT_OK, capsys.readouterr().err


def test_time_scale_reaches_the_shop(fake_nodes, tmp_path: Path, monkeypatch) -> None:
    fake_nodes()
    seen = _record_params(monkeypatch)
    assert _up(tmp_path, "--time-scale", "0.02") == up.EXIT_OK
    assert seen["shop_node"]["time_scale"] == 0.02
    # the agent waits longer than the shop's longest paced wait before re-sending (with its 1 s every longer wait
    # re-sent the command, and the shop logged a stale_state error each time)
    assert seen["agent_node"]["resend_s"] == up.paced_resend_s(builtin("EX12"), 0.02) > 1.0
    seen.clear()
    (tmp_path / "out" / "t1.gantt.png").unlink()
    assert _up(tmp_path, "--db", str(tmp_path / "out" / "b.sqlite")) == up.EXIT_OK
    assert "time_scale" not in seen["shop_node"] and "resend_s" not in seen["agent_node"]  # unpaced: the defaults


def test_a_paced_agent_waits_past_the_longest_step() -> None:
    from fms_sim.disruptions import Breakdown, Scenario

    ex12 = builtin("EX12")
    longest = max([op.duration for job in ex12.jobs for op in job] + [t for row in ex12.agv_travel for t in row])
    assert up.paced_resend_s(ex12, 0.2) == round(1.0 + 3 * 0.2 * longest, 3)
    assert up.paced_resend_s(ex12, 0.2, Scenario((Breakdown(1, 0, 500),))) == round(1.0 + 3 * 0.2 * 500, 3)
    assert up.paced_resend_s(builtin("EX12").without_tools(), 0.0) == 1.0  # never below the agent's default


def test_an_invalid_schedule_still_fails_and_names_the_unclean_stop(fake_nodes, tmp_path: Path, capsys) -> None:
    fake_nodes(stuck="agent", bad_schedule=True)
    assert _up(tmp_path) == up.EXIT_FAILED
    err = capsys.readouterr().err
    assert "fms up: error: the schedule is infeasible" in err and "agent exit code -9" in err
    assert not (tmp_path / "out" / "s.json").exists()



def test_stop_all_sends_each_node_one_sigint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # a second SIGINT could reach a node while its interpreter finalises and kill it with -SIGINT
    sent: list[tuple[int, int]] = []
    real = up._signal_group
    monkeypatch.setattr(up, "_signal_group", lambda pid, sig: (sent.append((pid, sig)), real(pid, sig)))
    script = ("import signal, sys, time; signal.signal(signal.SIGINT, lambda *_: sys.exit(0)); "
              "print('ready', flush=True); time.sleep(60)")
    nodes = [up.NodeProcess(f"n{i}", [sys.executable, "-c", script], tmp_path / f"n{i}.log", dict(os.environ))
             for i in range(2)]
    for n in nodes:
        n.start()
    for n in nodes:  # the handlers are installed
        deadline = time.monotonic() + 30
        while "ready" not in n.log_path.read_text() and time.monotonic() < deadline:
            time.sleep(0.01)
    assert up.stop_all(nodes, 10.0) == {"n0": 0, "n1": 0}
    assert sorted(sent) == sorted((n.proc.pid, signal.SIGINT) for n in nodes)


def test_a_full_net_model_runs_the_shop_on_the_full_net(fake_nodes, tmp_path: Path, monkeypatch, capsys) -> None:
    """`fms up --solver ppo:full` (also in a disrupted shop) starts the shop on the full net with history, so the
    agent's twin follows it; a paper-net model under disruptions is refused before any node starts."""
    fake_nodes()
    seen = _record_params(monkeypatch)
    for extra, idle in (([], False), (["--noise", "0.1"], False)):
        seen.clear()
        (tmp_path / "out" / "t1.gantt.png").unlink(missing_ok=True)  # (the stand-in recorder's chart)
        code = up.main(["EX12", "--solver", "ppo:full", "--out", str(tmp_path / "out" / "s.json"), "--db",
                        str(tmp_path / "out" / "fms.sqlite"), "--run-id", "t1", "--timeout", "60", *extra])
        assert code == up.EXIT_OK
        shop, agent = seen["shop_node"], seen["agent_node"]
        assert shop["decisions"] == "full" and shop["history"] is True and shop["idle_stops"] is idle
        assert shop["history_delta"] is True and shop["features"] is False  # each state: the labels since the last
        assert agent["solver"] == "ppo:full" and "instance" in agent
        assert ("noise" in shop) is bool(extra)
    seen.clear()
    code = up.main(["EX12", "--solver", "ppo:bu", "--noise", "0.1", "--out", str(tmp_path / "out" / "b.json"),
                    "--db", str(tmp_path / "out" / "fms.sqlite")])
    assert code == 2 and not seen and "a full-net model such as ppo:full" in capsys.readouterr().err


def test_best_in_a_disrupted_run_compares_the_model_with_plan_rules(fake_nodes, tmp_path: Path, monkeypatch,
                                                                     capsys) -> None:
    """The paper net's rule pairs cannot run a disrupted shop: `best` with --noise weighs the model against
    plan:rules (the best full-net rule, simulated nominally) and never picks a pair that would then be refused."""
    from fms_dispatch.full_rules import solve_best_rules

    inst = load_instance("EX12")
    rules_span = solve_best_rules(inst, decisions="full").makespan
    name, span, reason = up.best_solver(inst, disrupted=True)
    assert name.startswith("ppo:guided") and span < rules_span and f"best full-net rule plan:rules: {rules_span}" \
        in reason
    import fms_dispatch.rl as rl

    def unavailable(name: str):
        def solve(*_: Any, **__: Any) -> Schedule:
            raise ValueError("instance EX12 does not fit model guided-dagger\n(details)")
        return solve

    monkeypatch.setattr(rl, "ppo_solver", unavailable)  # the model cannot run: the full-net rule, not a pair
    assert up.best_solver(inst, disrupted=True) == (
        "plan:rules", rules_span, f"best full-net rule on EX12: plan:rules (makespan {rules_span} in simulation; "
        "PPO not available: instance EX12 does not fit model guided-dagger)")
    # nominal: the better of the best rule pair (86) and the list schedule (84, executed as plan:list)
    assert up.best_rule(inst)[1] == 86 and up.best_solver(inst)[:2] == ("plan:list", 84)
    fake_nodes()
    seen = _record_params(monkeypatch)
    code = up.main(["EX12", "--solver", "best", "--noise", "0.1", "--out", str(tmp_path / "out" / "s.json"),
                    "--db", str(tmp_path / "out" / "fms.sqlite"), "--run-id", "t1", "--timeout", "60"])
    err = capsys.readouterr().err
    assert code == up.EXIT_OK, err
    assert "best full-net rule on EX12: plan:rules" in err and "(nominal simulations: the disruptions are not " \
        "known in advance)" in err
    assert seen["agent_node"]["solver"] == "plan:rules" and seen["shop_node"]["decisions"] == "full"
    assert seen["shop_node"]["noise"] == 0.1


def test_outputs_and_options_are_checked_before_any_node_starts(tmp_path: Path, monkeypatch, capsys) -> None:
    """What would make a finished run fail to deliver, or never end, is refused first: one line, exit 2, no node."""
    import sqlite3

    from fms_sim.recorder_store import RecorderStore

    def no_node(*_: Any, **__: Any) -> list[str]:
        raise AssertionError("a node was started")

    monkeypatch.setattr(up, "node_command", no_node)
    afile = tmp_path / "afile"
    afile.write_text("x")
    db = tmp_path / "fms.sqlite"
    RecorderStore(db).close()
    with sqlite3.connect(db) as con:  # a run of that id is already recorded there (its chart elsewhere)
        con.execute("INSERT INTO runs (run_id, instance, first_seen) VALUES ('t1', 'EX12', 0)")
    cases = [(["--gantt-dir", str(afile)], "--gantt-dir"), (["--log-dir", str(afile)], "--log-dir"),
             (["--out", str(afile / "s.json")], "is a file, not a folder"),
             (["--db", str(afile)], f"--db {afile} cannot be used as the recorder's database: "),
             (["--timeout", "nan"], "--timeout must be a positive number"),
             (["--timeout", "inf"], "--timeout must be a positive number"),
             (["--replan", "5"], "--replan applies to plan: solvers only"),
             (["--replan-wait"], "--replan-wait applies to plan: solvers and to guided ppo models that re-plan"),
             (["--solver", "ppo:bu", "--replan-wait"], "re-plan their guide, not to 'ppo:bu'"),
             (["--solver", "ppo", "--no-guide-replan", "--replan-wait"], "not to 'ppo' with --no-guide-replan"),
             (["--solver", "plan:list", "--replan", "0", "--replan-wait"], "--replan-wait needs re-planning"),
             (["--db", str(db)], "run id 't1' is already in"),
             (["--out", str(tmp_path / "x.sqlite"), "--db", str(tmp_path / "x.sqlite")],
              "--out and --db name the same file"),  # the schedule replaced the database: every run lost
             (["--scenario", ""], "--scenario names no file"),  # ran undisrupted
             *((["--" + flag, ""], f"--{flag} names nothing (an empty name)")  # a default, or the current folder
               for flag in ("out", "db", "run-id", "gantt-dir", "log-dir")),
             (["--run-id", "x" * 300], "--run-id is too long to name the run's files"),  # File name too long
             (["--seed", "3"], "--seed does not apply to first: it draws nothing at random"),  # as fms solve
             (["--solver", "ppo", "--seed", "3"], "a guided ppo model's plan search takes --guide-seed"),
             (["--solver", "ppo", "--guide-seed", "-2"], "--guide-seed: plan seed must be an integer >= 0"),
             (["--solver", "plan:list", "--guide-tabu", "0"],
              "applies to ppo solvers only, not to 'plan:list' (the default solver)"),
             (["--solver", "rule:MTWR+nearest+fifo"], "EX12 has no tools, so the tool rule 'fifo'"),  # as fms solve
             (["--solver", "random", "--seed", "-1"], "--seed must be an integer >= 0, got -1"),
             (["--time-scale", "inf"], "--time-scale must be a finite number >= 0 of seconds per time unit"),
             (["--time-scale", "nan"], "got nan")]
    for extra, msg in cases:
        code = up.main(["EX12", "--solver", "first", "--run-id", "t1", "--db", str(tmp_path / "new.sqlite"),
                        "--out", str(tmp_path / "s.json"), *extra])
        err = capsys.readouterr().err
        assert code == 2 and msg in err and len(err.strip().splitlines()) == 1, (extra, err)


def test_a_seed_is_taken_where_it_draws_something(fake_nodes, tmp_path: Path, monkeypatch) -> None:
    """--seed passes for a solver that draws (random), for the noise of any solver, and for best (which picks the
    solver: the seed applies if it picks one that draws); the agent and the shop get it."""
    fake_nodes()
    seen = _record_params(monkeypatch)
    for i, extra in enumerate((["--solver", "random"], ["--noise", "0.1"], ["--solver", "best"])):
        (tmp_path / "out" / "t1.gantt.png").unlink(missing_ok=True)
        assert _up(tmp_path, "--seed", "7", "--db", str(tmp_path / "out" / f"{i}.sqlite"), *extra) == up.EXIT_OK, extra
        assert seen["agent_node"]["seed"] == 7 and seen["shop_node"].get("noise_seed", 7) == 7, (extra, seen)
        assert seen["agent_node"]["run_id"] == "t1"  # it answers its own run's states only
        assert ("noise_seed" in seen["shop_node"]) == (extra[0] == "--noise")
    # a guided model's plan search takes --guide-seed (the agent's guide_seed parameter)
    (tmp_path / "out" / "t1.gantt.png").unlink(missing_ok=True)
    assert _up(tmp_path, "--solver", "ppo", "--guide-seed", "7", "--db", str(tmp_path / "out" / "g.sqlite")) == up.EXIT_OK
    assert seen["agent_node"]["guide_seed"] == 7


def test_ctrl_c_stops_the_run_with_exit_130_and_no_node_logs(fake_nodes, tmp_path: Path, capsys) -> None:
    """An interrupted run says so as the CLI does (exit 130; it was exit 1 or 130 by timing, with every node's log
    tail printed, tracebacks of a node still importing among them)."""
    import threading

    fake_nodes(slow=5.0)
    # Ctrl-C as a terminal delivers it (a process started in the background, as CI runs the tests, ignores SIGINT)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGINT)).start()
    t0 = time.monotonic()
    try:
        assert _up(tmp_path) == up.EXIT_INTERRUPTED == 130
    finally:
        signal.signal(signal.SIGINT, old)
    err = capsys.readouterr().err
    assert "\nfms: interrupted (logs: " in err and " log (" not in err, err  # after the start line
    assert time.monotonic() - t0 < 5.0 and not (tmp_path / "out" / "s.json").exists()


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP", "SIGQUIT"])
def test_sigterm_and_a_closed_terminal_stop_the_nodes_as_ctrl_c_does(sig: str) -> None:
    """While fms up waits for its nodes, SIGTERM, SIGHUP (a closed terminal, a dropped SSH session) and SIGQUIT
    raise KeyboardInterrupt (the nodes are then stopped as on Ctrl-C; each runs in its own session and would outlive
    fms up); afterwards the old handlers are back."""
    number = getattr(signal, sig)
    before = {s: signal.getsignal(s) for s in up.STOP_SIGNALS}
    guard = up._TermAsInterrupt()
    try:
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), number)
            time.sleep(1)  # the handler runs at the next bytecode boundary
    finally:
        guard.restore()
    assert {s: signal.getsignal(s) for s in up.STOP_SIGNALS} == before


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the kernel's parent-death signal is Linux's")
def test_a_node_stops_when_fms_up_is_killed(tmp_path: Path) -> None:
    """fms up killed outright (SIGKILL: no handler runs) still stops its nodes: the kernel sends them SIGTERM."""
    pid_file = tmp_path / "node.pid"
    parent = subprocess.Popen([sys.executable, "-c", f"""
import sys, time
from pathlib import Path
from fms_dispatch.up import NodeProcess
node = NodeProcess("sleeper", [sys.executable, "-c", "import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(60)"],
                   Path({str(tmp_path / 'node.log')!r}), dict(__import__('os').environ)).start()
time.sleep(60)
"""])
    try:
        for _ in range(100):
            if pid_file.exists() and pid_file.read_text():
                break
            time.sleep(0.1)
        child = int(pid_file.read_text())
        parent.kill()
        parent.wait()
        for _ in range(50):  # a KeyboardInterrupt ends the sleeper at once
            try:
                os.kill(child, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            os.kill(child, signal.SIGKILL)
            pytest.fail("the node outlived its killed parent")
    finally:
        parent.kill()


def test_replan_wait_reaches_the_agent_node(fake_nodes, tmp_path: Path, monkeypatch, capsys) -> None:
    fake_nodes()
    seen = _record_params(monkeypatch)
    assert _up(tmp_path, "--solver", "plan:list", "--replan-wait") == up.EXIT_OK, capsys.readouterr().err
    assert seen["agent_node"]["replan_wait"] is True and seen["agent_node"]["replan"] == 2.0
    # a guided model's guide re-plans wait too (no plan re-planning budget: it has none)
    shutil.rmtree(tmp_path / "out")  # (the stand-in nodes record run t1 there)
    assert _up(tmp_path, "--solver", "ppo", "--replan-wait") == up.EXIT_OK, capsys.readouterr().err
    assert seen["agent_node"]["replan_wait"] is True and "replan" not in seen["agent_node"]


@pytest.mark.parametrize("extra, waits", [
    (["--solver", "plan:list"], True),                           # a shop without a clock: waits by default
    (["--solver", "ppo"], True),                                 # a guided model's guide re-plans too
    (["--solver", "plan:list", "--time-scale", "0.01"], False),  # a shop kept to a clock runs on, as a real one
    (["--solver", "ppo", "--time-scale", "0.01", "--replan-wait"], True),
    (["--solver", "plan:list", "--no-replan-wait"], False),
    (["--solver", "plan:list", "--replan", "0"], False),         # nothing to wait for
    (["--solver", "ppo", "--no-guide-replan"], False),
    (["--solver", "ppo:bu"], False),                             # a paper-net model re-plans nothing
    (["--solver", "first"], False),
])
def test_an_unpaced_shop_waits_for_re_plans_by_default(extra, waits, fake_nodes, tmp_path: Path, monkeypatch,
                                                      capsys) -> None:
    """Without a clock the simulated shop would run on under the plan in force for as many states as the agent
    answers during a re-plan's search, which depends on this machine's speed (docs/benchmarks.md §8): by default
    it waits, so the live run is the offline one; with --time-scale it runs on, as a real shop does."""
    fake_nodes()
    seen = _record_params(monkeypatch)
    assert _up(tmp_path, *extra) == up.EXIT_OK, capsys.readouterr().err
    assert seen["agent_node"].get("replan_wait", False) is waits
    assert ("the shop waits for each re-plan" in capsys.readouterr().err) is waits


def test_progress_is_none_where_the_database_cannot_be_read(tmp_path):
    """A read that failed counted as "no operation done": flipping between it and the real figures reset the
    --timeout deadline, and a stuck run outlived its timeout by minutes."""
    from fms_sim.recorder_store import RecorderStore

    assert up._progress(tmp_path / "none.sqlite", "r") is None
    (tmp_path / "junk.sqlite").write_bytes(b"not a database at all" * 100)
    assert up._progress(tmp_path / "junk.sqlite", "r") is None
    RecorderStore(tmp_path / "db.sqlite").close()
    assert up._progress(tmp_path / "db.sqlite", "r") == (0, None, 0)


def test_an_interrupt_while_the_output_is_written_names_the_kept_output(fake_nodes, tmp_path: Path, capsys,
                                                                        monkeypatch) -> None:
    """After the nodes stopped, a signal (SIGTERM or Ctrl-C) while the schedule was checked and written said only
    'fms: interrupted' (from the CLI): the folder holding the shop's finished schedule was kept, unnamed."""
    import importlib

    validate_module = importlib.import_module("fms_sim.validate")  # (the package's name is the function)
    fake_nodes()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(validate_module, "validate", interrupted)  # (cmd_up imports it when it runs)
    assert _up(tmp_path) == up.EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert "fms: interrupted while the run's output was checked and written; the shop's output is kept in " in err
    kept = Path(err.rsplit("kept in ", 1)[1].strip())
    assert kept.is_dir() and list(kept.rglob("schedule.json")) and not (tmp_path / "out" / "s.json").exists()


@pytest.mark.parametrize("module", [["fms_dispatch.up"], ["fms_dispatch.cli", "up"]])
def test_a_bad_noise_is_bad_input_when_run_as_a_module(module, tmp_path: Path) -> None:
    # under python -m the CLI module is __main__ and up imported a second copy: its CliError for --noise 1.5 was not
    # the one main catches (a traceback, exit 1); refused before any node starts
    res = subprocess.run([sys.executable, "-m", *module, "EX12", "--noise", "1.5"], capture_output=True, text=True,
                         timeout=60, cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().endswith("error: --noise must be a spread from 0 to 1, got 1.5"), res.stderr
