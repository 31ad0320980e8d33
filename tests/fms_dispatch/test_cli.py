"""The fms command line: happy paths and one-line errors with exit code 2."""

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from fms_dispatch.cli import main
from fms_sim import Schedule, validate
from fms_sim.benchmarks import builtin


def run(args, capsys):
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_solve_writes_valid_schedule_and_gantt(tmp_path, capsys):
    out, png = tmp_path / "s.json", tmp_path / "g.png"
    code, stdout, _ = run(["solve", "EX12", "--solver", "rule:MTWR+nearest", "--out", str(out),
                           "--gantt", str(png), "-q"], capsys)
    assert code == 0 and "makespan" in stdout
    s = Schedule.load(out)
    assert validate(builtin("EX12"), s) == []
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert run(["validate", "EX12", str(out)], capsys)[0] == 0


def test_fleet_and_mode_overrides(tmp_path, capsys):
    out = tmp_path / "s.json"
    assert run(["solve", "sl00", "--agvs", "3", "--tool-transporters", "2", "--solver", "rule:LPT+nearest",
                "--out", str(out), "-q"], capsys)[0] == 0
    d = json.loads(out.read_text())
    assert d["n_agvs"] == 3 and d["n_tool_transporters"] == 2
    assert {t["agv"] for t in d["agv_trips"]} <= {0, 1, 2}
    assert run(["validate", "sl00", str(out), "--agvs", "3", "--tool-transporters", "2"], capsys)[0] == 0
    # validated against the default fleet it is wrong, and says why
    code, stdout, _ = run(["validate", "sl00", str(out)], capsys)
    assert code == 1 and "declares 3 AGVs, the instance has 10" in stdout
    assert run(["solve", "ra01", "--layout", "3", "--no-tools", "-q", "--out", str(out)], capsys)[0] == 0
    assert json.loads(out.read_text())["tool_trips"] == []
    assert run(["solve", "EX12", "--no-agvs", "-q", "--out", str(out)], capsys)[0] == 0
    assert json.loads(out.read_text())["agv_trips"] == []


@pytest.mark.parametrize("args, msg", [
    (["solve", "EX99"], "unknown built-in instance"),
    (["solve", "nosuchfile.json"], "no built-in instance or file"),
    (["solve", "EX12", "--solver", "magic"], "unknown solver"),
    (["solve", "EX12", "--solver", "rule:FOO"], "unknown job rule"),
    (["solve", "EX12", "--time-limit", "-1"], "time-limit"),
    (["solve", "EX12", "--agvs", "0"], "agvs must be an integer from 1 to 1000, got 0 (use --no-agvs to drop them)"),
    (["solve", "EX12", "--solver", "rule:"], "rule name 'rule:' has an empty part"),
    (["solve", "EX12", "--solver", "rule:MTWR+"], "rule name 'rule:MTWR+' has an empty part"),
    (["solve", "EX12", "--solver", "plan:cpsat:abc"], "bad plan solver 'plan:cpsat:abc': 'abc' is not a time budget"),
    (["solve", "EX12", "--solver", "ppo:nonexistent"], "no model named 'nonexistent'"),  # before the header line
    (["solve", "EX12", "--solver", "first", "--decisions", "paper", "--noise", "0.1"],
     "--scenario and --noise run on the full-decision net only: drop --decisions paper"),  # said decisions='full'
    (["solve", "EX12", "--solver", "ppo:bu", "--noise", "0.1", "-q"],
     "use a full-net model: ppo (the default, guided-dagger)"),  # it named only ppo:full, the weaker one
    (["solve", "EX42", "--solver", "ppo:full", "--no-guide-replan"],
     "model full reads no plan guide, so it takes no --[no-]guide-replan"),
    (["solve", "EX42", "--solver", "ppo:full", "--guide-tabu", "0"],
     "model full reads no plan guide, so it takes no plan search options (--guide-*)"),
    (["solve", "EX12", "--solver", "sos", "--time-limit", "nan"], "--time-limit must be a positive, finite number"),
    (["solve", "EX12", "--solver", "first", "--time-limit", "3"], "--time-limit does not apply to first"),
    (["solve", "EX12", "--solver", "list", "--time-limit", "3"], "--time-limit does not apply to list"),
    (["solve", "EX12", "--solver", "ppo", "--time-limit", "3"], "its plan search's limit is --guide-budget"),
    (["solve", "EX12", "--solver", "ppo", "--lookahead", "--lookahead-fast"], "give one of --lookahead"),
    (["solve", "EX42", "--solver", "ppo+lookahead-fast", "--lookahead-guide"],
     "ppo+lookahead-fast chooses its lookahead in its name; give no --lookahead flag with it"),
    (["solve", "sl30", "--solver", "plan:cpsat:8", "--time-limit", "1"],
     "plan:cpsat:8 gives its plan's budget in its name; give it without the seconds and --time-limit"),
    (["solve", "EX12", "--solver", "sos", "--decisions", "paper"], "rules:paper runs the paper net's rule pairs"),
    (["solve", "EX12", "--solver", "random", "--seed", "-3"], "--seed must be an integer >= 0, got -3"),  # ran as 3
    # a part of the name or of the plan search that decides nothing on the shop (they were taken without a word)
    (["solve", "EX12", "--solver", "rule:MTWR+nearest+same-machine-first"],
     "EX12 has no tools, so the tool rule 'same-machine-first' of rule:MTWR+nearest+same-machine-first decides "
     "nothing: give rule:MTWR+nearest"),
    (["solve", "EX12", "--solver", "plan:rule:MTWR+nearest+fifo"], "give plan:rule:MTWR+nearest"),
    (["solve", "ra01", "--no-agvs", "--no-tools", "--solver", "rule:MTWR+nearest"],
     "ra01 has no AGVs and no tool transporters, so the vehicle rule 'nearest' of rule:MTWR+nearest decides nothing: "
     "give rule:MTWR"),
    (["solve", "ra01", "--solver", "ppo", "--guide-rules"],
     "--guide-rules: ra01 has tools, and the plan search takes the rule pairs' schedules on shops without tools only"),
    (["solve", "sl70", "--solver", "ppo", "--guide-exact", "1"],
     "--guide-exact: sl70 is too large for CP-SAT's full model"),
    (["generate", "--jobs", "3", "--machines", "3", "--no-tools", "--tools", "4"], "contradict each other"),
    (["generate", "--jobs", "3", "--machines", "3", "--no-agvs", "--agvs", "4"], "contradict each other"),
    (["generate", "--jobs", "3", "--machines", "3", "--count", "0"], "--count must be >= 1"),
    (["generate", "--jobs", "3", "--machines", "3", "--prefix", "a/b"], "must be a plain name"),
])
def test_bad_input_one_line_exit_2(args, msg, capsys):
    code, _, err = run(args, capsys)
    assert code == 2
    assert err.startswith("fms: error:") and msg in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("args", [
    ["solve", "ra01", "--solver", "rule:MTWR+nearest+same-machine-first"],  # tools: the tool rule decides
    ["solve", "ra01", "--no-agvs", "--solver", "rule:MTWR+nearest"],  # the vehicle rule picks the transporter
    ["solve", "EX12", "--solver", "ppo", "--guide-rules"],  # no tools: the rule pairs' schedules are searched
    ["solve", "EX12", "--solver", "ppo", "--guide-exact", "0.1"],  # small enough for the polish
])
def test_every_part_of_a_name_or_search_that_can_decide_is_taken(args, capsys):
    code, out, err = run(args + ["-q"], capsys)
    assert code == 0 and "valid" in out and not err


@pytest.mark.parametrize("content, msg", [
    ("{broken", "malformed"),
    ('{"name": "x", "jobs": [[{"machine": 1, "tool": null, "duration": -3}]]}', "non-negative"),
    ('{"name": "x", "jobs": [[{"machine": 1, "tool": null, "duration": 3}]], "agv_travel": [[0, 1], [1, 0], [1, 1]],'
     ' "n_agvs": 1}', "agv_travel row 0 must have 3 entries"),
    ('{"name": "x", "jobs": [[{"machine": 3, "tool": null, "duration": 3}]], "agv_travel": [[0, 1], [1, 0]],'
     ' "n_agvs": 1}', "machine 3"),
])
def test_bad_instance_files(tmp_path, content, msg, capsys):
    f = tmp_path / "bad.json"
    f.write_text(content)
    code, _, err = run(["solve", str(f), "-q"], capsys)
    assert code == 2 and msg in err and len(err.strip().splitlines()) == 1


def test_validate_reports_violations_and_bad_files(tmp_path, capsys):
    out = tmp_path / "s.json"
    run(["solve", "EX12", "--out", str(out), "-q"], capsys)
    d = json.loads(out.read_text())
    d["operations"][0]["end"] += 5
    out.write_text(json.dumps(d))
    code, stdout, _ = run(["validate", "EX12", str(out)], capsys)
    assert code == 1 and "INVALID" in stdout
    out.write_text("[]")
    assert run(["validate", "EX12", str(out)], capsys)[0] == 2
    assert run(["validate", "EX12", str(tmp_path / "missing.json")], capsys)[0] == 2


def test_instances_and_generate(tmp_path, capsys):
    code, out, _ = run(["instances"], capsys)
    names = out.split()
    assert code == 0 and {"EX12", "EX104", "ra20", "sl79", "ta01"} <= set(names)
    code, out, _ = run(["generate", "--jobs", "6", "--machines", "4", "--count", "2", "--out-dir", str(tmp_path),
                        "--prefix", "t"], capsys)
    assert code == 0
    files = sorted(tmp_path.glob("t*.json"))
    assert [f.name for f in files] == ["t00.json", "t01.json"]
    assert run(["solve", str(files[1]), "--solver", "rule:SPT+nearest", "-q"], capsys)[0] == 0
    assert run(["generate", "--jobs", "0", "--machines", "4", "--out-dir", str(tmp_path)], capsys)[0] == 2


def test_console_script_runs_as_a_process():
    r = subprocess.run([sys.executable, "-m", "fms_dispatch.cli", "solve", "EX99"], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("fms: error:")


def test_ppo_solver_names(capsys):
    from fms_dispatch.solvers import UnknownSolver, get_solver, solve

    inst = builtin("EX22")
    plain, ahead = solve(inst, "ppo"), solve(inst, "ppo+lookahead")
    assert validate(inst, plain) == [] and validate(inst, ahead) == []
    assert ahead.makespan <= plain.makespan
    with pytest.raises(UnknownSolver, match="only \\+lookahead, \\+lookahead-fast or \\+lookahead-guide"):
        get_solver("ppo+magic")
    code, out, _ = run(["solve", "EX22", "--solver", "ppo", "--lookahead", "-q"], capsys)
    # the summary names the model and the lookahead that ran, as the schedule's meta does
    assert code == 0 and f"makespan {ahead.makespan} (ppo:guided-dagger+lookahead, " in out
    assert ahead.meta["solver"] == "ppo:guided-dagger+lookahead"
    fast = solve(inst, "ppo+lookahead-fast")
    assert validate(inst, fast) == [] and fast.makespan <= plain.makespan
    assert fast.meta["lookahead_fast"] is True and ahead.meta["lookahead_fast"] is False
    assert fast.meta["solver"].endswith("+lookahead-fast") and "lookahead_fast" not in plain.meta
    code, out, _ = run(["solve", "EX22", "--solver", "ppo", "--lookahead-fast", "-q"], capsys)
    assert code == 0 and f"makespan {fast.makespan} (ppo:guided-dagger+lookahead-fast, " in out
    code, out, _ = run(["solve", "EX22", "--solver", "ppo:full", "-q"], capsys)
    assert code == 0 and "(ppo:full, " in out
    code, _, err = run(["solve", "EX22", "--solver", "first", "--lookahead-fast", "-q"], capsys)
    assert code == 2 and "--lookahead, --lookahead-fast and --lookahead-guide apply to the ppo solver only" in err
    with pytest.raises(ValueError, match="lookahead must be False, True, 'fast' or 'guide'"):
        solve(inst, "ppo", lookahead="quick")


def test_a_guided_runs_plan_search_is_timed_apart(tmp_path, capsys, monkeypatch):
    """The summary line and the schedule say how much of a guided model's run was its plan search at the start
    (within its budget; most of it on sl00, where the search takes the whole budget), or how long it took beside
    the run and what came of it, and nothing for a model without a plan."""
    from fms_dispatch.rl import beside

    out = tmp_path / "s.json"
    with monkeypatch.context() as m:
        m.setattr(beside, "FORK_AVAILABLE", False)  # the search before the run
        code, line, _ = run(["solve", "sl00", "--solver", "ppo", "--guide-budget", "0.3", "--out", str(out), "-q"],
                            capsys)
    meta = json.loads(out.read_text())["meta"]
    assert code == 0 and 0.2 <= meta["guide_search_time"] <= 0.8 and meta["guide_search_time"] < meta["wall_time"]
    assert f"{meta['wall_time']:.3f} s, {meta['guide_search_time']:.3f} s of it the plan search, valid)" in line
    if beside.FORK_AVAILABLE:  # beside the run (sl00: the search ends after the run and finds a better plan)
        monkeypatch.setattr(beside, "_cpus", lambda: 2)
        monkeypatch.setattr(beside, "BESIDE_LISTS", 10**9)  # (by default only a 100-job shop's search runs beside)
        code, line, _ = run(["solve", "sl00", "--solver", "ppo", "--guide-budget", "0.3", "--out", str(out), "-q"],
                            capsys)
        meta = json.loads(out.read_text())["meta"]
        # (sl00's run ends before the 0.3 s search, which nearly always finds a better plan: the run starts over;
        # on a loaded machine it may find none in its budget, and the first plan stands)
        outcome = meta["guide_search_beside"]
        assert code == 0 and outcome in ("kept", "restarted") and 0.2 <= meta["guide_search_time"] <= 3
        said = "which started over with its plan" if outcome == "restarted" else "its first plan kept"
        t = f"{meta['guide_search_time']:.3f}"
        assert f"{meta['wall_time']:.3f} s, plan search {t} s beside the run, {said}, valid)" in line
    code, line, _ = run(["solve", "EX22", "--solver", "ppo:full", "--out", str(out), "-q"], capsys)
    assert code == 0 and "plan search" not in line and "guide_search_time" not in json.loads(out.read_text())["meta"]


def test_replay_writes_a_schedule_no_later_than_the_given_one(tmp_path, capsys):
    given, out, png = tmp_path / "given.json", tmp_path / "out.json", tmp_path / "r.png"
    assert run(["solve", "ra01", "--solver", "rule:MTWR+nearest", "--out", str(given), "-q"], capsys)[0] == 0
    code, stdout, _ = run(["replay", "ra01", str(given), "--out", str(out), "--gantt", str(png)], capsys)
    assert code == 0 and "replayed makespan" in stdout
    s, g = Schedule.load(out), Schedule.load(given)
    assert validate(builtin("ra01"), s) == [] and s.makespan <= g.makespan
    assert s.meta["solver"] == "replay" and s.meta["given_makespan"] == g.makespan
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_replay_of_a_run_with_live_orders_says_its_jobs_are_there_from_time_0(tmp_path, capsys):
    # the replay has every job of the final instance from time 0, so an ordered job can start before its order
    # came: said, as for a disrupted run's schedule (it was silent)
    import random

    from fms_sim.full_shop import FullShop
    from fms_sim.instance import Operation

    rng = random.Random(3)
    shop = FullShop(builtin("ra01"))
    for _ in range(25):
        shop.act(rng.choice(shop.legal_actions()))
    shop.add_jobs([[Operation(1, 1, 3), Operation(2, 2, 4)]])
    while not shop.done:
        shop.act(rng.choice(shop.legal_actions()))
    inst, given = tmp_path / "i.json", tmp_path / "given.json"
    shop.instance.save(inst)
    shop.schedule().save(given)
    code, stdout, err = run(["replay", str(inst), str(given), "--out", str(tmp_path / "r.json")], capsys)
    assert code == 0 and "replayed makespan" in stdout
    assert "note: the schedule's run took live orders (meta.arrivals); the replay has every job from time 0" in err
    assert "arrivals" not in Schedule.load(tmp_path / "r.json").meta


def test_replay_refuses_an_invalid_schedule_and_writes_nothing(tmp_path, capsys):
    given, out = tmp_path / "given.json", tmp_path / "out.json"
    assert run(["solve", "EX12", "--solver", "rule:FIFO+first", "--out", str(given), "-q"], capsys)[0] == 0
    code, stdout, err = run(["replay", "EX13", str(given), "--out", str(out)], capsys)  # other travel times
    assert code == 2 and "not a valid schedule for EX13" in err and "travel time is" in err
    # the schedule was made for another shop: said first, as fms validate says it (the violations alone hid it)
    assert err.startswith("note: the schedule names instance 'EX12', replaying it in 'EX13'\n")
    assert not out.exists()
    code, _, err = run(["replay", "EX12", str(tmp_path / "missing.json")], capsys)
    assert code == 2 and "cannot read schedule" in err


def test_solve_under_disruptions_and_bad_scenarios(tmp_path, capsys):
    sc, out = tmp_path / "sc.json", tmp_path / "s.json"
    sc.write_text(json.dumps({"schema": "fms/scenario/v1", "noise": 0.1, "seed": 2,
                              "breakdowns": [{"machine": 2, "start": 30, "duration": 20}],
                              "outages": [{"kind": "agv", "vehicle": 1, "start": 10, "duration": 15}]}))
    assert run(["solve", "EX12", "--solver", "plan:list", "--scenario", str(sc), "--out", str(out), "-q"],
               capsys)[0] == 0
    s = Schedule.load(out)
    assert s.meta["scenario"]["breakdowns"] == [{"machine": 2, "start": 30, "duration": 20}]
    assert run(["validate", "EX12", str(out)], capsys)[0] == 0  # checked against the recorded scenario
    assert run(["solve", "EX12", "--solver", "rule:MTWR+nearest", "--noise", "0.2", "--seed", "5", "--out", str(out),
                "-q"], capsys)[0] == 0
    assert Schedule.load(out).meta["scenario"]["noise"] == 0.2
    for bad, msg in [({"breakdowns": [{"machine": 9, "start": 0, "duration": 3}]}, "machine 9"),
                     ({"outages": [{"kind": "agv", "vehicle": 0, "start": 0, "duration": -3}]},
                      "duration from 1 to 1,000,000,000"), ({"storms": []}, f"scenario {sc}: unknown scenario field")]:
        sc.write_text(json.dumps(bad))
        code, _, err = run(["solve", "EX12", "--scenario", str(sc), "-q"], capsys)
        assert code == 2 and msg in err
    sc.write_text("{not json")
    code, _, err = run(["solve", "EX12", "--scenario", str(sc), "-q"], capsys)
    assert code == 2 and "not valid JSON" in err
    code, _, err = run(["solve", "EX12", "--solver", "cpsat", "--noise", "0.1", "-q"], capsys)
    assert code == 2 and "does not run in a disrupted shop" in err
    code, _, err = run(["solve", "EX12", "--solver", "rule:MTWR+nearest", "--decisions", "paper", "--noise", "0.1",
                        "-q"], capsys)
    assert code == 2 and "full-decision net only" in err
    code, _, err = run(["solve", "EX12", "--solver", "plan:list", "--noise", "0.3", "--replan", "inf", "-q"], capsys)
    assert code == 2 and "--replan must be positive and finite" in err  # ran a search with no deadline
    for noise in ("1000", "50", "-1", "nan"):  # 1000 was an OverflowError, 50 a "valid" makespan of 3e47
        code, _, err = run(["solve", "EX12", "--noise", noise, "-q"], capsys)
        assert code == 2 and "--noise must be a spread from 0 to 1" in err
    code, _, err = run(["solve", "EX12", "--noise", "1.0000001", "-q"], capsys)
    assert code == 2 and err.strip().endswith("got 1.0000001")  # it said "got 1"
    sc.write_text(json.dumps({"breakdowns": [{"machine": 2, "start": 30, "durarion": 20}]}))
    code, _, err = run(["solve", "EX12", "--scenario", str(sc), "-q"], capsys)
    assert code == 2 and "breakdown 0: unknown field(s) 'durarion'" in err


def test_solve_runs_a_full_net_ppo_model_under_disruptions(tmp_path, capsys):
    from fms_dispatch.experiments import _timed_run
    from fms_dispatch.rl.lookahead import run_agent
    from fms_dispatch.rl.models import load_agent
    from fms_sim.disruptions import Scenario
    from fms_sim.full_shop import FullShop
    from fms_sim.snapshot import nominal_copy

    out = tmp_path / "s.json"
    inst = builtin("EX12")
    agent = load_agent("full")
    sc = Scenario(noise=0.2, seed=5)
    for extra, lookahead in (([], False), (["--lookahead"], True)):
        assert run(["solve", "EX12", "--solver", "ppo:full", "--noise", "0.2", "--seed", "5", "--out", str(out), "-q"]
                   + extra, capsys)[0] == 0
        s = Schedule.load(out)
        assert s.meta["scenario"]["noise"] == 0.2 and s.meta["lookahead"] is lookahead
        assert run(["validate", "EX12", str(out)], capsys)[0] == 0  # against the realised times
        # the run the experiments measure: the model deciding in the disrupted shop (twins: nominal copies)
        ref = (run_agent(FullShop(inst, scenario=sc), agent.act, lookahead=True, twin=nominal_copy) if lookahead
               else _timed_run(inst, sc, None, agent.act)[0])
        assert s.makespan == ref.makespan
    code, _, err = run(["solve", "EX12", "--solver", "ppo:bu", "--noise", "0.1", "-q"], capsys)
    assert code == 2 and "paper's net, which runs no disruptions" in err


def test_solve_replans_a_plan_under_disruptions_and_refuses_bad_replan_options(tmp_path, capsys):
    out = tmp_path / "s.json"
    code, stdout, _ = run(["solve", "sl00", "--solver", "plan:list", "--noise", "0.2", "--seed", "3", "--replan", "0.3",
                           "--out", str(out), "-q"], capsys)
    assert code == 0 and "re-plans (" in stdout
    s = Schedule.load(out)
    assert validate(builtin("sl00"), s) == []
    events = s.meta["replans"]  # 20 % noise makes the shop late: it re-plans (first at the same state every run)
    assert events and events[0]["reason"] == "late" and f", {len(events)} re-plan{'s' * (len(events) != 1)} (" in stdout
    for e in events:  # a new plan is adopted exactly when it ends earlier (the search is on the clock: either way)
        assert e["status"] in ("adopted", "kept") and e["budget"] == 0.3
        assert (e["status"] == "adopted") == (e["after"] < e["before"]), e
    assert run(["validate", "sl00", str(out)], capsys)[0] == 0
    code, _, err = run(["solve", "EX12", "--solver", "rule:MTWR+nearest", "--replan", "1", "-q"], capsys)
    assert code == 2 and "plan: solvers only" in err
    code, _, err = run(["solve", "EX12", "--solver", "plan:list", "--replan", "0", "-q"], capsys)
    assert code == 2 and "--replan must be positive" in err


def test_an_infeasible_schedule_from_a_solver_is_refused_and_not_written(tmp_path, capsys, monkeypatch):
    """The CLI validates every schedule before writing it: a solver bug gives exit 1 and no file."""
    import fms_dispatch.solvers as solvers

    real = solvers.solve

    def broken(inst, name, **opts):
        s = real(inst, name, **opts)
        s.operations[0] = replace(s.operations[0], start=s.operations[0].start - 1)
        return s

    monkeypatch.setattr(solvers, "solve", broken)
    out = tmp_path / "s.json"
    code, stdout, err = run(["solve", "EX12", "--solver", "list", "--out", str(out), "-q"], capsys)
    assert code == 1 and err.startswith("fms: internal error: the list schedule is infeasible: op (")
    assert not out.exists() and "makespan" not in stdout


def test_solve_re_plans_a_guided_models_guide_at_a_breakdown(tmp_path, capsys):
    """A guided model re-plans its guide when the breakdown begins (adopted here: 126 against 135 kept), the
    re-plans in the schedule's meta; --no-guide-replan acts the start's plan out; only ppo solvers take it."""
    sc, out = tmp_path / "sc.json", tmp_path / "s.json"
    sc.write_text(json.dumps({"schema": "fms/scenario/v1", "noise": 0.1, "seed": 5,
                              "breakdowns": [{"machine": 2, "start": 20, "duration": 40}]}))
    base = ["solve", "ra01", "--solver", "ppo", "--scenario", str(sc), "--guide-tabu", "0", "--out", str(out), "-q"]
    code, stdout, _ = run(base, capsys)
    assert code == 0 and "1 re-plan (1 adopted)" in stdout
    s = Schedule.load(out)
    (ev,) = s.meta["replans"]
    assert (ev["reason"], ev["time"], ev["status"], ev["method"]) == ("breakdown", 20, "adopted", "guide")
    assert ev["after"] < ev["before"] * (1 - 0.02)
    assert run(["validate", "ra01", str(out)], capsys)[0] == 0
    code, stdout, _ = run(base + ["--no-guide-replan"], capsys)
    kept = Schedule.load(out)
    assert code == 0 and "re-plans" not in stdout and "replans" not in kept.meta
    assert kept.makespan > s.makespan  # on this run the re-planned guide ends earlier (126 against 137)
    code, _, err = run(["solve", "ra01", "--solver", "list", "--no-guide-replan", "-q"], capsys)
    assert code == 2 and "--[no-]guide-replan applies to the ppo solver only" in err


def test_output_paths_are_checked_before_the_work(tmp_path, capsys):
    """A folder named as the output file, or a file named as a folder, is refused before solving (nothing is
    computed and then lost), as one line with exit code 2."""
    (tmp_path / "f").write_text("x")
    for args, msg in [(["solve", "EX12", "--out", str(tmp_path)], "is a folder; name a file"),
                      (["solve", "EX12", "--gantt", str(tmp_path / "f" / "g.png")], "is a file, not a folder"),
                      (["generate", "--jobs", "3", "--machines", "3", "--out-dir", str(tmp_path / "f")],
                       "is a file, not a folder")]:
        code, out, err = run(args, capsys)
        assert code == 2 and msg in err and len(err.strip().splitlines()) == 1 and "makespan" not in out, args
    # an error of several lines (the offending training specs) is printed whole, on one line
    code, _, err = run(["train", "EX12", "notapattern", "--steps", "256", "--out", str(tmp_path / "m")], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "'EX12' gives EX12" in err and "'notapattern' does not expand" in err


def test_rules_time_limit_and_search_summary(capsys):
    code, out, _ = run(["solve", "sl00", "--solver", "rules", "--time-limit", "0.01", "-q"], capsys)
    assert code == 0 and ", best list, 1 of " in out and "rule combinations within the time limit" in out
    code, out, _ = run(["solve", "EX12", "--solver", "cpsat", "--time-limit", "20", "-q"], capsys)
    assert code == 0 and "makespan 82 " in out and ", optimal," in out  # EX12's known optimum, proven
    # and what the search added to its start schedule (84: the list schedule's), or that it added nothing
    assert ", from a start schedule of 84," in out
    code, out, _ = run(["solve", "sl70", "--solver", "cpsat", "--time-limit", "1", "-q"], capsys)
    assert code == 0 and "no better than its start schedule (a list schedule)" in out  # 1 s: the start's 7777


def test_instances_lists_the_heldout_shops(capsys):
    code, out, _ = run(["instances"], capsys)
    names = out.split()
    assert code == 0 and names[-50:] == [f"ho{k:02d}" for k in range(50)]
    code, out, _ = run(["instances", "--details"], capsys)
    assert out.splitlines()[-1].startswith("ho49: 100 jobs x 20 machines") and "(held out)" in out


def test_outputs_that_would_clobber_an_input_or_each_other_are_refused(tmp_path, capsys):
    # the chart overwrote the schedule, --out overwrote the instance, and an empty name was silently ignored
    shop = tmp_path / "shop.json"
    shop.write_text(builtin("EX12").to_json())
    same = tmp_path / "same.json"
    for args, needle in [(["solve", "EX12", "--out", str(same), "--gantt", str(same)], "name the same file"),
                         (["solve", str(shop), "--out", str(shop)], "is an input of this command"),
                         (["solve", "EX12", "--out", ""], "--out names no file"),
                         (["solve", "EX12", "--gantt", " "], "--gantt names no file")]:
        code, _, err = run(args + ["-q"], capsys)
        assert code == 2 and needle in err, (args, err)
    assert not same.exists() and json.loads(shop.read_text())["name"] == "EX12"
    sched = tmp_path / "s.json"
    assert run(["solve", "EX12", "--out", str(sched), "-q"], capsys)[0] == 0
    code, _, err = run(["replay", "EX12", str(sched), "--out", str(sched)], capsys)
    assert code == 2 and "is an input of this command" in err


def test_a_chart_that_cannot_be_written_names_itself_and_keeps_the_schedule(tmp_path, capsys, monkeypatch):
    # the chart is rendered after the schedule is saved; its failure read "No such file or directory: x.png" with
    # nothing saying which output failed or that the schedule had been written
    import fms_sim.gantt

    def fail(*args, **kwargs):
        raise FileNotFoundError(2, "No such file or directory")

    monkeypatch.setattr(fms_sim.gantt, "save_gantt", fail)
    out, png = tmp_path / "s.json", tmp_path / "g.png"
    code, _, err = run(["solve", "EX12", "--solver", "list", "--out", str(out), "--gantt", str(png), "-q"], capsys)
    assert code == 2
    assert f"cannot write --gantt {png}: No such file or directory (the schedule was saved to {out})" in err
    assert validate(builtin("EX12"), Schedule.load(out)) == []


def test_an_output_folder_without_write_permission_is_refused_before_solving(tmp_path, capsys, monkeypatch):
    # a folder this user may not write was found only after the solve; access is denied through os.access so the
    # test holds for root too (who may write anywhere)
    locked = tmp_path / "locked"
    locked.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if os.fspath(p) == str(locked) else real(p, mode))
    code, stdout, err = run(["solve", "EX12", "--out", str(locked / "sub" / "s.json"), "-q"], capsys)
    assert code == 2 and f"the folder {locked} may not be written (permission denied)" in err
    assert "makespan" not in stdout and not (locked / "sub").exists()
    (locked / "s.json").write_text("{}")
    monkeypatch.setattr(os, "access", lambda p, mode: False if os.fspath(p) == str(locked / "s.json")
                        else real(p, mode))
    code, _, err = run(["solve", "EX12", "--out", str(locked / "s.json"), "-q"], capsys)
    assert code == 2 and "the file may not be written (permission denied)" in err


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_an_output_where_nothing_can_be_written_is_refused_before_solving_also_for_root(capsys):
    # root passes os.access everywhere, so the check let the solve run and failed only on writing its result
    code, stdout, err = run(["solve", "EX12", "--out", "/proc/fms-test/s.json", "-q"], capsys)
    assert code == 2 and "the folder /proc" in err and "makespan" not in stdout  # (as another user: permission bits)


def test_generate_checks_every_flag_by_name_before_writing(tmp_path, capsys):
    # --no-agvs took a bad --agv-seed while --no-tools refused a bad --tool-seed; --tools 0 was reported as
    # "n_tools ..."; a folder in the way of the second file left the first one written
    base = ["generate", "--jobs", "3", "--machines", "2", "--out-dir", str(tmp_path / "g")]
    for extra, needle in ((["--no-agvs", "--agv-seed", "0"], "--agv-seed must be a Taillard seed in 1..2147483646"),
                          (["--no-tools", "--tool-seed", "0"], "--tool-seed must be a Taillard seed"),
                          (["--tools", "0"], "--tools must be >= 1 and at most 1000, got 0"),
                          (["--machines", "100000"], "--machines must be >= 1 and at most 1000")):
        code, _, err = run(base + extra, capsys)
        assert code == 2 and needle in err, (extra, err)
    (tmp_path / "g" / "gen01.json").mkdir(parents=True)
    code, _, err = run(base + ["--count", "2", "--prefix", "gen"], capsys)
    assert code == 2 and "is a folder; nothing was written" in err
    assert not (tmp_path / "g" / "gen00.json").exists()


def test_sigterm_stops_a_command_as_ctrl_c_does(tmp_path):
    """SIGTERM (kill, a supervisor) ended fms solve without a word and left the Gantt chart's hidden temporary;
    it is an interrupt now: exit 130, 'fms: interrupted', temporaries removed."""
    import signal
    import subprocess
    import time

    # (a plan: solver: an interrupted cpsat, tabu, sos or rules search keeps its best schedule:
    # test_an_interrupted_search_keeps_its_best_schedule)
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "solve", "sl70", "--solver", "plan:tabu:600",
                             "--out", str(tmp_path / "s.json")], stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    time.sleep(3)  # past the start, into the search
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err.strip().endswith("fms: interrupted"), err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("closed, unbuffered, read", [("stdout", True, 1), ("stderr", True, 1), ("both", True, 1),
                                                     ("both", False, 1), ("stderr", True, 0), ("both", True, 0)])
def test_a_reader_that_leaves_costs_no_result(tmp_path, closed, unbuffered, read):
    """`fms solve ... | head -1`: the search's progress lines went to stdout and the first one after the reader left
    ended the solve, exit 0, without its --out file; a result line on a closed stdout did the same (at once under
    PYTHONUNBUFFERED, else exit 120 at Python's flush). Progress goes to stderr now, and a reader that leaves either
    stream (or both: 2>&1), at once or after a line, costs nothing but the lines it would have read (any note on
    stderr after it left, such as a guided model's plan hint, ended the solve before its --out file, exit 0)."""
    import subprocess

    out = tmp_path / "s.json"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if unbuffered:
        env["PYTHONUNBUFFERED"] = "1"
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "solve", "sl00", "--solver", "tabu",
                             "--time-limit", "1", "--out", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT if closed == "both" else subprocess.PIPE, text=True, env=env,
                            cwd=tmp_path)
    gone, kept = (proc.stdout, proc.stderr) if closed in ("stdout", "both") else (proc.stderr, proc.stdout)
    assert gone is not None
    for _ in range(read):
        assert gone.readline()  # the first line (the header or, on stdout, the result), then gone
    gone.close()
    rest = kept.read() if kept is not None else ""
    assert proc.wait(timeout=60) == 0
    assert validate(builtin("sl00"), Schedule.load(out)) == []
    if closed == "stderr":  # stdout holds only the result
        assert rest.splitlines()[0].startswith("sl00: makespan ") and rest.splitlines()[1] == f"schedule: {out}"
    if closed == "stdout":
        assert "  tabu: list schedule " in rest


def _progress_line(proc, prefix: str) -> str:
    """The first line of ``proc``'s standard error that starts with ``prefix`` (progress goes there, past the header
    line), or the last line read before the stream ended."""
    assert proc.stderr is not None
    line = proc.stderr.readline()
    while line and not line.startswith(prefix):
        line = proc.stderr.readline()
    return line


def test_an_interrupted_search_keeps_its_best_schedule(tmp_path):
    """Ctrl-C (here SIGTERM, which fms takes as Ctrl-C) in a long cpsat, tabu, sos or rules search lost all it found;
    the best schedule so far is now printed, validated and written, and the exit code still says 'interrupted'."""
    import signal
    import subprocess
    import time

    out, chart = tmp_path / "s.json", tmp_path / "s.png"
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "solve", "ra20", "--solver", "cpsat",
                             "--time-limit", "120", "--out", str(out), "--gantt", str(chart)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    first = _progress_line(proc, "  cpsat: makespan ")  # CP-SAT's first solution: the search is under way
    assert first.startswith("  cpsat: makespan "), first
    proc.send_signal(signal.SIGTERM)
    rest, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    line = [ln for ln in rest.splitlines() if ln.startswith("ra20: makespan ")]
    assert line and ", interrupted, valid)" in line[0], rest
    assert err.strip().endswith(f"fms: interrupted: the search stopped early; its best schedule so far is above and "
                                f"in {out} and {chart}"), err
    sched = Schedule.load(out)
    assert validate(builtin("ra20"), sched) == [] and chart.stat().st_size > 0
    assert sched.meta["status"] == "INTERRUPTED" and sched.meta["lower_bound"] <= sched.makespan
    assert f"makespan {sched.makespan} " in line[0]
    start = sched.meta["start_makespan"]  # what the search had added when it was stopped (it was not said)
    assert start >= sched.makespan and (f"from a start schedule of {start}" in line[0] if start > sched.makespan
                                        else "no better than its start schedule" in line[0]), line[0]
    # cpsat interrupted in its start schedules (on a large shop they take up to 10 s of the limit: nothing was kept)
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "solve", "sl70", "--solver", "cpsat",
                             "--time-limit", "200", "--out", str(tmp_path / "c.json")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    time.sleep(3)
    proc.send_signal(signal.SIGTERM)
    rest, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and ", interrupted, valid)" in rest, (rest, err)
    assert validate(builtin("sl70"), Schedule.load(tmp_path / "c.json")) == []
    assert Schedule.load(tmp_path / "c.json").meta["start_makespan"] is None and "start schedule" not in rest
    # the tabu search too (interrupted in the search, or before it: then its start schedule), and sos
    for solver, first, wait in (("tabu", "  tabu: list schedule ", 1.0), ("tabu", "  tabu: list schedule ", 0.0),
                                ("sos", "  sos: ", 0.5)):
        proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "solve", "sl30", "--solver", solver,
                                 "--time-limit", "600", "--out", str(tmp_path / "t.json")], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, cwd=tmp_path)
        line = _progress_line(proc, first)
        assert line.startswith(first), line
        time.sleep(wait)
        proc.send_signal(signal.SIGTERM)
        rest, err = proc.communicate(timeout=60)
        assert proc.returncode == 130 and ", interrupted, valid)" in rest, (rest, err)
        sched = Schedule.load(tmp_path / "t.json")
        assert validate(builtin("sl30"), sched) == [] and sched.meta["status"] == "INTERRUPTED"
        assert f"sl30: makespan {sched.makespan} ({solver}, " in rest and sched.meta["wall_time"] > 0
    # the rule combinations (no progress line: a few seconds in, many have run on sl00)
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "solve", "sl00", "--solver", "rules",
                             "--out", str(tmp_path / "r.json")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=tmp_path)
    time.sleep(5)
    proc.send_signal(signal.SIGTERM)
    rest, err = proc.communicate(timeout=60)
    sched = Schedule.load(tmp_path / "r.json")
    assert proc.returncode == 130 and validate(builtin("sl00"), sched) == [], (rest, err)
    assert f"rules, {sched.meta['wall_time']:.3f} s, best {sched.meta['rule']}, {sched.meta['tried']} of " \
           f"{sched.meta['combinations']} rule combinations, interrupted, valid)" in rest, rest
    # another solver's interrupt is an interrupt as before: nothing written
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "solve", "ra20", "--solver", "plan:cpsat:120",
                             "--out", str(tmp_path / "p.json")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=tmp_path)
    assert _progress_line(proc, "  cpsat: makespan ").startswith("  cpsat: makespan ")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip().endswith("fms: interrupted"), err
    assert not (tmp_path / "p.json").exists()


def test_the_default_solver_is_the_list_schedule_and_its_plan_under_disruptions(tmp_path, capsys):
    """Without --solver, fms solve runs the earliest-start list schedule (``first``, the lowest enabled action,
    ended several times later on shops with tools), and in a disrupted run that schedule's plan executed under the
    disruptions (the list solver plans on the shop it is given, which a disrupted run must not know ahead)."""
    from fms_dispatch import solve
    from fms_sim.disruptions import Scenario

    out = tmp_path / "s.json"
    inst = builtin("sl00")
    code, stdout, _ = run(["solve", "sl00", "--out", str(out), "-q"], capsys)
    listed = solve(inst, "list")
    assert code == 0 and f"makespan {listed.makespan} (list, " in stdout
    assert Schedule.load(out) == listed and listed.makespan < solve(inst, "first", decisions="full").makespan
    code, stdout, _ = run(["solve", "sl00", "--noise", "0.1", "--seed", "3", "--out", str(out), "-q"], capsys)
    noisy = solve(inst, "plan:list", scenario=Scenario((), (), 0.1, 3))
    assert code == 0 and f"makespan {noisy.makespan} (plan:list, " in stdout
    assert Schedule.load(out) == noisy and validate(inst, noisy) == []
    # options the default does not take name it as the default, and the way on
    code, _, err = run(["solve", "EX12", "--time-limit", "3"], capsys)
    assert code == 2 and "--time-limit does not apply to list (the default solver)" in err
    code, _, err = run(["solve", "EX12", "--decisions", "paper"], capsys)
    assert code == 2 and "not list (the default solver)" in err and "name one of them with --solver" in err
    code, _, err = run(["solve", "EX12", "--replan", "1"], capsys)
    assert code == 2 and "--solver plan:list re-plans the list schedule's plan" in err
    # an empty disruption is no disruption: the paper net takes it (it was refused as a disrupted run)
    code, stdout, _ = run(["solve", "EX12", "--solver", "first", "--decisions", "paper", "--noise", "0", "-q"], capsys)
    assert code == 0 and f"makespan {solve(builtin('EX12'), 'first').makespan} (first, " in stdout


def test_fms_up_defaults_to_the_list_plan_executed_live(capsys):
    from fms_dispatch.cli import DEFAULT_DISRUPTED_SOLVER, build_parser

    assert build_parser().parse_args(["up", "EX12"]).solver == DEFAULT_DISRUPTED_SOLVER == "plan:list"
    with pytest.raises(SystemExit):
        main(["up", "--help"])
    up_help = " ".join(capsys.readouterr().out.split())
    assert "(default: plan:list: the earliest-start list schedule" in up_help  # it printed {DEFAULT_DISRUPTED_SOLVER}


@pytest.mark.parametrize("fleet", [["--agvs", "3"], ["--no-agvs"], ["--no-tools"], ["--tool-transporters", "2"]])
def test_a_schedule_of_an_overridden_fleet_checked_without_it_names_the_option(tmp_path, capsys, fleet):
    out = tmp_path / "s.json"
    assert run(["solve", "ra01", *fleet, "--out", str(out), "-q"], capsys)[0] == 0
    code, stdout, err = run(["validate", "ra01", str(out)], capsys)
    assert code == 1 and "INVALID" in stdout
    assert f"if it was solved with {' '.join(fleet)}, give the same here" in err
    code, _, err = run(["replay", "ra01", str(out)], capsys)
    assert code == 2 and f"if it was solved with {' '.join(fleet)}, give the same here" in err
    code, stdout, err = run(["validate", "ra01", str(out), *fleet], capsys)
    assert code == 0 and "hint" not in err
    # another shop's schedule: no option of this one makes it fit, so no hint
    code, _, err = run(["validate", "EX62", str(out)], capsys)
    assert code == 1 and "hint" not in err


def test_guide_seed_seeds_a_guided_models_plan_search(tmp_path, capsys):
    """A guided model's plan search restarts at random (seed 0): --guide-seed seeds it (--seed keeps to the noise and
    is refused for ppo in a nominal run, naming --guide-seed); a model without a guide takes no --guide-* option."""
    from fms_dispatch import solve
    from fms_dispatch.rl.guide import effort_from

    out = tmp_path / "s.json"
    assert run(["solve", "EX42", "--solver", "ppo", "--guide-seed", "5", "--guide-tabu", "0", "--out", str(out), "-q"],
               capsys)[0] == 0
    got = Schedule.load(out)
    assert got.meta["guide_effort"]["seed"] == 5
    assert got == solve(builtin("EX42"), "ppo", guide_effort=effort_from(tabu=0, seed=5))
    assert got.makespan != solve(builtin("EX42"), "ppo", guide_effort=effort_from(tabu=0)).makespan  # it matters
    for argv, needle in ((["--solver", "ppo", "--seed", "5"], "plan search takes --guide-seed"),
                         (["--solver", "ppo:bu", "--guide-seed", "5"], "reads no plan guide"),
                         (["--solver", "ppo", "--guide-seed", "-1"], "--guide-seed: plan seed must be an integer >= 0"),
                         (["--solver", "list", "--guide-seed", "1"], "apply to the ppo solver only")):
        code, _, err = run(["solve", "EX42", *argv, "-q"], capsys)
        assert code == 2 and needle in err, (argv, err)


def test_generate_with_the_default_seeds_writes_the_large_benchmarks_first_group(tmp_path, capsys):
    """What fms generate --help says of its default seeds: 15 jobs, 15 machines, 10 shops are sl00-sl09."""
    from fms_sim.formats import load_instance

    assert run(["generate", "--jobs", "15", "--machines", "15", "--count", "10", "--out-dir", str(tmp_path)],
               capsys)[0] == 0
    for k in range(10):
        got, sl = load_instance(str(tmp_path / f"gen{k:02d}.json")), builtin(f"sl{k:02d}")
        assert (got.jobs, got.agv_travel, got.tool_travel, got.n_agvs, got.n_tool_transporters) == (
            sl.jobs, sl.agv_travel, sl.tool_travel, sl.n_agvs, sl.n_tool_transporters), k


def test_noise_over_a_scenario_files_seeded_noise_says_it_replaces_the_seed(tmp_path, capsys):
    path = tmp_path / "sc.json"
    path.write_text(json.dumps({"schema": "fms/scenario/v1", "breakdowns": [], "outages": [], "noise": 0.1,
                                "seed": 7}))
    code, _, err = run(["solve", "ra01", "--scenario", str(path), "--noise", "0.1", "-q"], capsys)
    assert code == 0 and f"--noise replaces the noise of {path} and its seed 7 (now 0" in err
    for extra in (["--seed", "7"], []):  # a seed given, or the file's kept (no --noise): nothing to say
        code, _, err = run(["solve", "ra01", "--scenario", str(path), *(["--noise", "0.1"] if extra else []),
                            *extra, "-q"], capsys)
        assert code == 0 and "replaces" not in err


def test_validate_a_schedule_alone_checks_it_against_the_instance_it_names(tmp_path, capsys):
    out = tmp_path / "s.json"
    for args, name in ((["EX12"], "EX12"), (["ra01", "--layout", "3"], "ra01L3"), (["ho03"], "ho03")):
        assert run(["solve", *args, "--out", str(out), "-q"], capsys)[0] == 0
        code, stdout, err = run(["validate", str(out)], capsys)
        assert code == 0 and stdout.startswith(f"valid: {name}, ") and "the instance the schedule was made for" in err
    # a shop of a file: the final instance a live run writes beside its schedule (OUT.instance.json), else refused
    shop = tmp_path / "shop.json"
    shop.write_text(builtin("EX21").to_json().replace('"EX21"', '"myshop"'))
    assert run(["solve", str(shop), "--out", str(out), "-q"], capsys)[0] == 0
    code, _, err = run(["validate", str(out)], capsys)
    assert code == 2 and "made for instance 'myshop', which is no built-in shop and has no s.instance.json" in err
    (tmp_path / "s.instance.json").write_text(shop.read_text())
    code, stdout, _ = run(["validate", str(out)], capsys)
    assert code == 0 and stdout.startswith("valid: myshop, ")
    # an instance file of another shop beside it is not this run's: passed over
    (tmp_path / "s.instance.json").write_text(builtin("EX31").to_json())
    code, _, err = run(["validate", str(out)], capsys)
    assert code == 2 and "made for instance 'myshop', which is no built-in shop" in err


@pytest.mark.parametrize("n_agvs", [-1, 10**12])
def test_a_schedule_declaring_a_fleet_no_option_gives_is_infeasible_without_a_hint(n_agvs, tmp_path, capsys):
    """A schedule declaring -1 or 10**12 AGVs got 'solved with --agvs -1? give the same here' (an option that cannot
    be given), and checked alone ('fms validate s.json') an error about that --agvs, which the user never gave: it
    is infeasible, and says why."""
    out = tmp_path / "s.json"
    run(["solve", "EX12", "--out", str(out), "-q"], capsys)
    d = json.loads(out.read_text())
    d["n_agvs"] = n_agvs
    out.write_text(json.dumps(d))
    for args in (["validate", "EX12", str(out)], ["validate", str(out)]):
        code, text, err = run(args, capsys)
        assert code == 1 and f"schedule declares {n_agvs} AGVs, the instance has 2" in text + err, args
        assert "--agvs" not in text + err


def test_validate_alone_checks_the_fleet_the_schedule_records_and_takes_the_schedule_after_options(tmp_path, capsys):
    # `fms solve EX12 --agvs 3 --out s.json; fms validate s.json` called the tool's own valid schedule INVALID (the
    # shop it names, with its own fleet); and `fms validate EX12 --agvs 3 s.json` was refused by argparse
    out = tmp_path / "s.json"
    for args, shown in ((["EX12", "--agvs", "3"], "EX12 with --agvs 3"), (["EX12", "--no-agvs"], "EX12 with --no-agvs"),
                        (["ra01", "--layout", "3", "--no-tools"], "ra01 (layout 3) with --no-tools"),
                        (["sl00", "--agvs", "2", "--tool-transporters", "1"],
                         "sl00 with --agvs 2 --tool-transporters 1")):
        assert run(["solve", *args, "--out", str(out), "-q"], capsys)[0] == 0
        code, stdout, err = run(["validate", str(out)], capsys)
        assert code == 0 and stdout.startswith("valid: ") and f"checking against {shown}, the instance" in err, err
        code, stdout, _ = run(["validate", args[0], *args[1:], str(out)], capsys)  # the options before the file
        assert code == 0 and stdout.startswith("valid: ")
    # an instance named, or a fleet given, is checked as given: the hint says what differs
    assert run(["solve", "EX12", "--agvs", "3", "--out", str(out), "-q"], capsys)[0] == 0
    code, _, err = run(["validate", "EX12", str(out)], capsys)
    assert code == 1 and "if it was solved with --agvs 3, give the same here" in err
    code, _, err = run(["validate", str(out), "--agvs", "2"], capsys)
    assert code == 1 and "if it was solved with --agvs 3, give the same here" in err
    # only the fleet it records: a schedule without its fleet sizes read as having none, and one that never moved a
    # part passed against the shop without AGVs
    assert run(["solve", "EX12", "--out", str(out), "-q"], capsys)[0] == 0
    data = json.loads(out.read_text())
    for key in ("n_agvs", "n_tool_transporters", "agv_trips", "tool_trips"):
        data.pop(key, None)
    out.write_text(json.dumps(data))
    code, stdout, _ = run(["validate", str(out)], capsys)
    assert code == 1 and stdout.startswith("INVALID")
    with pytest.raises(SystemExit) as exc:  # a second file is still refused
        main(["validate", "EX12", str(out), str(out)])
    assert exc.value.code == 2 and "unrecognized arguments" in capsys.readouterr().err


def test_a_run_to_an_earlier_runs_schedule_removes_the_instance_it_left_beside(tmp_path, capsys):
    # fms up --out s.json with live orders writes s.instance.json; a later run to s.json without orders left it, and
    # `fms validate s.json` checked the new, valid schedule against the earlier run's ordered jobs: INVALID, exit 1
    out, beside = tmp_path / "s.json", tmp_path / "s.instance.json"
    ordered = builtin("EX12")
    ordered = replace(ordered, jobs=ordered.jobs + ordered.jobs[:1])
    ordered.save(beside)
    assert run(["solve", "EX12", "--out", str(out), "-q"], capsys)[0] == 0
    assert not beside.exists()
    code, stdout, _ = run(["validate", str(out)], capsys)
    assert code == 0 and stdout.startswith("valid: EX12")
    ordered.save(beside)  # solving that final instance itself keeps it (it is the run's input)
    code, _, err = run(["solve", str(beside), "--out", str(out), "-q"], capsys)
    assert code == 0 and beside.is_file() and "removed" not in err
    builtin("EX21").save(beside)  # another shop's file (fms validate passes it over): kept (it was removed)
    code, _, err = run(["solve", "EX12", "--out", str(out), "-q"], capsys)
    assert code == 0 and beside.is_file() and "removed" not in err


def test_validate_alone_refuses_what_it_cannot_resolve(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "s.json"
    assert run(["solve", "EX12", "--out", str(out), "-q"], capsys)[0] == 0
    code, _, err = run(["validate", "EX12"], capsys)  # the schedule forgotten: not "cannot read schedule EX12"
    assert code == 2 and "give the schedule file too: fms validate EX12 SCHEDULE" in err
    (tmp_path / "EX12").write_text("junk")  # a file of the shop's name would be read instead of the built-in
    code, _, err = run(["validate", str(out)], capsys)
    assert code == 2 and "a file named EX12 in the working folder hides the built-in shop EX12" in err
    (tmp_path / "EX12").unlink()
    # a layout given overrides the one the schedule names, and the notes say which was checked
    assert run(["solve", "ra01", "--layout", "3", "--out", str(out), "-q"], capsys)[0] == 0
    code, _, err = run(["validate", str(out), "--layout", "2"], capsys)
    assert code == 1 and "the schedule names instance 'ra01L3', checking against 'ra01'" in err  # layout 2
    assert "made for" not in err


def test_a_plans_seed_is_taken_where_its_search_or_its_re_plans_draw(tmp_path, capsys):
    # (plan:list --seed was taken and ignored: refused now, tests/fms_dispatch/test_cli_inputs.py; these draw)
    for argv in (["--solver", "plan:sos:0.5", "--seed", "3"], ["--solver", "plan:list", "--replan", "1", "--seed", "3"],
                 ["--solver", "plan:list", "--noise", "0.1", "--seed", "3"]):
        code, out, err = run(["solve", "EX12", *argv, "--out", str(tmp_path / "s.json")], capsys)
        assert code == 0 and "valid" in out, err
