"""The command line on unusual input (an audit of every subcommand with bad, odd or hostile files and options):
one line and exit code 2 for bad input, the verdict kept, nothing silently ignored."""

import json
import os
import subprocess
import sys

import pytest

from fms_dispatch.cli import main
from fms_sim import Schedule, validate
from fms_sim.benchmarks import builtin

DEEP = "[" * 5000 + "]" * 5000  # a 10 kB file: the JSON parser's RecursionError was a traceback


def run(args, capsys):
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def ex12(tmp_path, capsys):
    out = tmp_path / "s.json"
    assert run(["solve", "EX12", "--out", str(out), "-q"], capsys)[0] == 0
    return out


@pytest.mark.parametrize("argv", [["validate", "EX12", "{deep}"], ["solve", "{deep}"],
                                  ["solve", "EX12", "--scenario", "{deep}"], ["replay", "EX12", "{deep}"]])
def test_json_nested_too_deeply_is_bad_input(tmp_path, capsys, argv):
    deep = tmp_path / "deep.json"
    deep.write_text(DEEP)
    code, _, err = run([a.format(deep=deep) for a in argv], capsys)
    assert code == 2 and "nested too deeply" in err and len(err.strip().splitlines()) == 1  # (validate said 1)


def test_files_with_a_byte_order_mark_are_read(tmp_path, capsys, ex12):
    bom = b"\xef\xbb\xbf"
    sched = tmp_path / "bom.json"
    sched.write_bytes(bom + ex12.read_bytes())  # "Unexpected UTF-8 BOM (decode using utf-8-sig)"
    assert run(["validate", "EX12", str(sched)], capsys)[0] == 0
    inst = tmp_path / "shop.json"
    inst.write_bytes(bom + builtin("EX12").to_json().encode())
    assert run(["solve", str(inst), "-q"], capsys)[0] == 0
    text = tmp_path / "std.txt"
    text.write_bytes(bom + b"2 2\n0 3 1 4\n1 2 0 5\n")  # the header was read as a title
    code, out, err = run(["solve", str(text), "-q"], capsys)
    assert code == 0 and "makespan" in out, err


def test_a_header_skipped_as_a_title_is_named(tmp_path, capsys):
    text = tmp_path / "comma.txt"
    text.write_text("2,2\n0 3 1 4\n1 2 0 5\n")
    code, _, err = run(["solve", str(text), "-q"], capsys)
    assert code == 2 and "line 1, '2,2', was skipped as a title" in err  # it said only "got 0 and 3" of line 2


def test_validate_keeps_its_verdict_when_the_reader_leaves(tmp_path, capsys):
    out = tmp_path / "s.json"
    assert run(["solve", "sl00", "--solver", "first", "--out", str(out), "-q"], capsys)[0] == 0
    d = json.loads(out.read_text())
    for o in d["operations"]:
        o["start"] += 1  # hundreds of violations: more than a pipe holds
    out.write_text(json.dumps(d))
    proc = subprocess.Popen([sys.executable, "-m", "fms_dispatch.cli", "validate", "sl00", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout.readline().startswith(b"INVALID")
    proc.stdout.close()  # `| head -1`
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 1 and b"Traceback" not in err  # it exited 0: "valid" to a script


def test_a_malformed_recorded_scenario_is_bad_input_not_infeasible(tmp_path, capsys, ex12):
    d = json.loads(ex12.read_text())
    for bad in ({"foo": 1}, "x"):
        d["meta"] = {**d.get("meta", {}), "scenario": bad}
        ex12.write_text(json.dumps(d))
        code, out, err = run(["validate", "EX12", str(ex12)], capsys)
        assert code == 2 and "the schedule's recorded scenario is malformed" in err and "INVALID" not in out


def test_seed_replaces_the_seed_of_the_scenario_files_noise(tmp_path, capsys):
    def makespan(seed_in_file, *flags):
        f = tmp_path / f"n{seed_in_file}.json"
        f.write_text(json.dumps({"schema": "fms/scenario/v1", "noise": 0.3, "seed": seed_in_file}))
        code, _, _ = run(["solve", "EX42", "--scenario", str(f), "-q", "--out", str(tmp_path / "o.json"), *flags],
                         capsys)
        assert code == 0
        sched = Schedule.load(tmp_path / "o.json")
        return sched.meta["scenario"]["seed"], sched.to_dict()["operations"]  # (the same run: the same times)

    assert makespan(7)[0] == 7 and makespan(7, "--seed", "3")[0] == 3  # --seed was silently dropped
    assert makespan(7, "--seed", "3")[1] == makespan(3)[1]
    assert run(["solve", "EX42", "--solver", "random", "--seed", "3", "-q"], capsys)[0] == 0  # (its own seed)


@pytest.mark.parametrize("argv, needle", [
    (["solve", "EX12", "--scenario", ""], "--scenario names no file"),  # ran undisrupted
    (["validate", "EX12", "{s}", "--scenario", ""], "--scenario names no file"),  # used the recorded one
    (["generate", "--jobs", "3", "--machines", "3", "--out-dir", ""], "--out-dir names no folder"),  # cwd
    (["bench", "bu", "--instances", "1", "--methods", "first", "--results-dir", ""], "--results-dir names no folder"),
    (["experiment", "dynamic", "--quick", "--results-dir", ""], "--results-dir names no folder"),
    (["experiment", "dynamic", "--quick", "--results-dir", "/proc/fms-test"], "the folder /proc"),  # where no
    # folder can be made: found after the work (as root: "nothing can be written in"; else: "... may not be written")
    (["experiment", "dynamic", "--quick", "--sos-time", "inf", "--results-dir", "{d}"],
     "--sos-time must be positive and finite"),  # it ran forever
    (["experiment", "disruptions", "--quick", "--cpsat-time", "inf", "--results-dir", "{d}"],
     "--cpsat-time must be positive and finite"),
    (["experiment", "ablation", "--quick", "--studies", "masking", "--model", "nonexistent", "--results-dir", "{d}"],
     "--model is the lookahead study's model"),  # ignored, exit 0
    (["solve", "EX12", "--gantt", "{d}/g.txt"], "--gantt {d}/g.txt: name the chart's format by its suffix"),  # a PNG
    (["solve", "EX12", "--gantt", "{d}/g"], "name the chart's format by its suffix, one of ."),
    (["solve", "EX12", "--solver", "cpsat:5"], "give cpsat's time limit as --time-limit 5"),
    (["solve", "EX12", "--solver", "rules:ful"], "the rules solver's variants are rules:full (the default) and "
     "rules:paper"),  # "give rules's time limit as --time-limit ful"
    (["solve", "EX12", "--solver", "cpsat:fast"], "unknown solver 'cpsat:fast'; choose from first"),  # the same
    (["solve", "EX12", "--solver", "list:"], "'list:' names no list order"),  # ran as list
    (["solve", "EX12", "--seed", "5"], "--seed does not apply to list (the default solver): it draws nothing"),
    # a plan of a solver that draws nothing, and not re-planned: the seed was taken and ignored
    (["solve", "EX12", "--solver", "plan:list", "--seed", "5"], "--seed does not apply to plan:list: it draws nothing"),
    (["solve", "EX12", "--solver", "plan:rule:MTWR+nearest", "--seed", "5"], "--seed does not apply to plan:rule"),
    (["solve", "EX12", "--tool-transporters", "0"], "EX12 has no tool travel matrix"),  # "use --no-tools"
    (["bench", "bu", "--instances", "3..1", "--results-dir", "{d}/r"], "the range 3..1 runs backwards"),
    (["generate", "--jobs", "3", "--machines", "3", "--prefix", "sl", "--out-dir", "{d}/g"],
     "--prefix 'sl' names the files like built-in instances (sl00)"),  # shadowed the built-in sl00
])
def test_empty_names_and_ignored_values_are_refused(tmp_path, capsys, monkeypatch, ex12, argv, needle):
    monkeypatch.chdir(tmp_path)  # where an empty name wrote
    argv = [a.format(s=ex12, d=tmp_path) for a in argv]
    code, _, err = run(argv, capsys)
    assert code == 2 and needle.format(d=tmp_path) in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.json"]  # nothing written


def test_generate_checks_its_folder_before_writing(tmp_path, capsys, monkeypatch):
    locked = tmp_path / "ro"
    locked.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if os.fspath(p) == str(locked) else real(p, mode))
    code, _, err = run(["generate", "--jobs", "3", "--machines", "3", "--out-dir", str(locked)], capsys)
    assert code == 2 and f"the folder {locked} may not be written" in err and ".tmp" not in err  # (a temp's name)


def test_an_instance_file_with_a_travel_matrix_and_no_fleet_says_what_to_give(tmp_path, capsys):
    d = builtin("EX12").to_dict()
    del d["n_agvs"]
    f = tmp_path / "shop.json"
    f.write_text(json.dumps(d))
    code, _, err = run(["solve", str(f), "-q", "--agvs", "2"], capsys)  # "n_agvs = 0; use --no-agvs": no use
    assert code == 2 and "agv_travel is given but n_agvs is missing: give the number of AGVs (n_agvs)" in err


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d.update(tool_trip=d.pop("tool_trips")), "unknown schedule field 'tool_trip'"),  # dropped: no trips
    (lambda d: d["operations"][0].update(foo=1), "unknown field of operations 'foo'"),
    (lambda d: d["agv_trips"][0].update(agv_id=0), "unknown field of agv_trips 'agv_id'"),
])
def test_unknown_schedule_fields_are_refused_by_name(tmp_path, capsys, edit, needle):
    out = tmp_path / "s.json"
    assert run(["solve", "ra01", "--out", str(out), "-q"], capsys)[0] == 0
    d = json.loads(out.read_text())
    edit(d)
    out.write_text(json.dumps(d))
    code, _, err = run(["validate", "ra01", str(out)], capsys)
    assert code == 2 and needle in err, err


def test_replay_shows_the_fleet_the_schedule_was_made_for_first(tmp_path, capsys):
    out = tmp_path / "s.json"
    assert run(["solve", "ra01", "--no-agvs", "--no-tools", "--out", str(out), "-q"], capsys)[0] == 0
    assert validate(builtin("ra01"), Schedule.load(out))[:2] == [
        "schedule declares 0 AGVs, the instance has 2", "schedule declares 0 tool transporters, the instance has 1"]
    code, _, err = run(["replay", "ra01", str(out)], capsys)  # they were the 28th and 47th of 46 lines, unshown
    assert code == 2 and "schedule declares 0 AGVs" in err.splitlines()[1]


def test_outputs_go_through_links_into_their_targets(tmp_path, capsys):
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    target.write_text("old")
    link.symlink_to(target.name)
    assert run(["solve", "EX12", "--out", str(link), "-q"], capsys)[0] == 0
    assert link.is_symlink() and Schedule.load(target).instance == "EX12"  # the link became a file


def test_a_schedule_given_as_the_instance_and_the_other_way_round_say_so(tmp_path, capsys, ex12):
    shop = tmp_path / "shop.json"
    shop.write_text(builtin("EX12").to_json())
    code, _, err = run(["solve", str(ex12), "-q"], capsys)  # "instance is missing the field 'name'"
    assert code == 2 and "this is a schedule, not an instance" in err
    code, _, err = run(["validate", "EX12", str(shop)], capsys)  # "field 'operations' must be a list"
    assert code == 2 and "this is an instance, not a schedule" in err


def test_a_text_file_is_named_once_in_its_errors(tmp_path, capsys):
    text = tmp_path / "std.txt"
    text.write_text("2 2\n0 3 1 4\n")
    code, _, err = run(["solve", str(text), "-q"], capsys)
    assert code == 2 and "fms: error: std.txt: expected 2 lines after the header" in err  # "std.txt: std: expected"
