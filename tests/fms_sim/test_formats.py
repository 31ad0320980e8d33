"""Text job-shop formats, instance files and load_instance with its overrides."""

from __future__ import annotations

from pathlib import Path

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.formats import format_standard, format_taillard, load_instance, parse_text_jobshop
from fms_sim.instance import Instance, InstanceError, Operation

STANDARD = """\
# a 3x3 example in OR-Library standard format
3 3
0 3 1 2 2 2
0 2 2 1 1 4
1 4 2 3 0 1
"""
STANDARD_JOBS = (
    (Operation(1, None, 3), Operation(2, None, 2), Operation(3, None, 2)),
    (Operation(1, None, 2), Operation(3, None, 1), Operation(2, None, 4)),
    (Operation(2, None, 4), Operation(3, None, 3), Operation(1, None, 1)),
)

TAILLARD = """\
Nb of jobs, Nb of Machines, Time seed, Machine seed, Upper bound, Lower bound :
2 3 840612802 398197754 25 20
Times
 5 7 9
 1 2 3
Machines
 2 3 1
 3 1 2
"""
TAILLARD_JOBS = (
    (Operation(2, None, 5), Operation(3, None, 7), Operation(1, None, 9)),
    (Operation(3, None, 1), Operation(1, None, 2), Operation(2, None, 3)),
)


def test_standard_format() -> None:
    inst = parse_text_jobshop(STANDARD, "tiny")
    assert inst.name == "tiny" and inst.jobs == STANDARD_JOBS
    assert inst.mode == "jobshop" and inst.n_machines == 3 and inst.n_agvs == 0
    assert parse_text_jobshop(format_standard(inst), "tiny") == inst


def test_orlib_title_lines_are_skipped() -> None:
    text = " instance tiny\n +++++++++++++++\n A made-up 3x3 instance\n" + STANDARD.split("\n", 1)[1]
    assert parse_text_jobshop(text, "t").jobs == STANDARD_JOBS


def test_taillard_format_labelled_with_extra_header_numbers() -> None:
    inst = parse_text_jobshop(TAILLARD, "tai")
    assert inst.jobs == TAILLARD_JOBS and inst.n_machines == 3
    assert parse_text_jobshop(format_taillard(inst), "tai") == inst


def test_taillard_format_unlabelled() -> None:
    text = "2 3\n5 7 9\n1 2 3\n2 3 1\n3 1 2\n"
    assert parse_text_jobshop(text, "x").jobs == TAILLARD_JOBS


def test_taillard_text_of_ta01_round_trips() -> None:
    ta01 = builtin("ta01")
    text = format_taillard(ta01)
    assert text.splitlines()[2].split() == "94 66 10 53 26 15 65 82 10 27 93 92 96 70 83".split()
    assert parse_text_jobshop(text, "ta01").jobs == ta01.jobs
    assert parse_text_jobshop(format_standard(ta01), "ta01").jobs == ta01.jobs


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "no header"),
        ("# only a comment\n", "no header"),
        ("3\n", "line 1: the header needs"),
        ("0 3\n", "line 1: n_jobs and n_machines must be >= 1"),
        ("2 x\n", "line 1: expected integers, got 'x'"),
        ("2 2\n0 3 1 4\n1 2 0 x\n", "line 3: expected integers, got 'x'"),
        ("2 2\n0 3 1 4\n1 2 0 2.5\n", "line 3: expected integers, got '2.5'"),
        ("2 2\n0 3 1 4\n1 2 0\n", "line 3: expected 4 numbers"),
        ("2 2\n0 3 1 4\n", "expected 2 lines after the header"),
        ("2 2\n0 3 1 4\n1 2 0 5\n1 2 0 5\n", "line 4: unexpected extra line"),
        ("2 2\n0 3 1 -4\n1 2 0 5\n", "line 2: negative processing time -4"),
        ("2 2\n0 3 2 4\n1 2 0 5\n", "line 2: machine 2 out of range 0..1"),
        ("2 2\n3 4\n5 -6\n1 2\n2 1\n", "line 3: negative processing time -6"),
        ("2 2\n3 4\n5 6\n1 2\n2 0\n", "line 5: machine 0 out of range 1..2"),
        ("2 2\n3 4\n5 6\n1 2\n", "expected 4 lines after the header"),
        ("2 2\nTimes\n3 4\nMachines\n1 2\n2 1\n", "expected 2 times rows"),
        ("2 2\nTimes\n3 4\n5 6\n7 8\nMachines\n1 2\n2 1\n", "line 5: more than 2 times rows"),
        ("2 2\nTimes\n3 4 5\n", "line 3: expected 2 numbers"),
        ("2 2\nTimes\n3 4\n5 6\nMachines\n1 2\n2 1\nMachines\n", "line 8: a second 'Machines' section"),
        # int() alone took these, which no such file holds; a huge token is shown cut; a time above the largest
        # (10**9) was refused without its line
        ("2 2\n0 3 1 4\n1 2 0 1_000\n", "line 3: expected integers, got '1_000'"),
        ("2 2\n0 3 1 4\n1 2 0 \u0663\n", "line 3: expected integers, got '\u0663'"),
        ("2 2\n0 3 1 4\n1 2 0 --5\n", "line 3: expected integers, got '--5'"),
        ("2 2\n0 3 1 4\n1 2 0 x" + "9" * 5000 + "\n",
         r"line 3: expected integers, got 'x9{19}\.\.\.9{8} \(5001 characters\)'$"),
        ("2 2\n0 3 1 4\n1 2 0 1000000001\n", "line 3: processing time 1000000001 is above the largest, 1,000,000,000"),
        ("2 2\n3 4\n5 2000000000\n1 2\n2 1\n", "line 3: processing time 2000000000 is above the largest"),
    ],
)
def test_malformed_text(text: str, match: str) -> None:
    with pytest.raises(InstanceError, match=match):
        parse_text_jobshop(text, "bad")


def test_format_needs_rectangular_jobs() -> None:
    with pytest.raises(InstanceError, match="job 0 has 3 operations; the text formats need exactly 4 per job"):
        format_standard(builtin("EX12"))


# ---------------------------------------------------------------------------------------------- load_instance
def test_load_builtin_and_layout() -> None:
    assert load_instance("ex12") == builtin("EX12")
    assert load_instance("ra01", layout=3).name == "ra01L3"
    with pytest.raises(InstanceError, match="unknown built-in instance 'sl99'"):
        load_instance("sl99")


def test_load_files(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_text(STANDARD)
    (tmp_path / "tai").write_text(TAILLARD)
    inst = load_instance(str(tmp_path / "a.txt"))
    assert inst.name == "a" and inst.jobs == STANDARD_JOBS
    assert load_instance(str(tmp_path / "tai")).jobs == TAILLARD_JOBS
    ra = builtin("ra02")
    ra.save(tmp_path / "r.json")
    assert load_instance(str(tmp_path / "r.json")) == ra
    (tmp_path / "r.inst").write_text(ra.to_json())  # JSON detected by content
    assert load_instance(str(tmp_path / "r.inst")) == ra


def test_a_folder_named_like_a_builtin_does_not_hide_it(tmp_path: Path, monkeypatch) -> None:
    # "fms solve EX12" in a folder holding an EX12/ folder (e.g. results written per instance) read
    # "'EX12' is a directory"; a folder is never an instance, and a file of that name still wins
    monkeypatch.chdir(tmp_path)
    (tmp_path / "EX12").mkdir()
    assert load_instance("EX12") == builtin("EX12")
    (tmp_path / "sl00").write_text(builtin("ra02").to_json())
    assert load_instance("sl00") == builtin("ra02")


def test_load_file_errors(tmp_path: Path) -> None:
    with pytest.raises(InstanceError, match="no built-in instance or file named 'missing.txt'"):
        load_instance("missing.txt")
    with pytest.raises(InstanceError, match="is a directory"):
        load_instance(str(tmp_path))
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InstanceError, match="bad.json: malformed JSON"):
        load_instance(str(tmp_path / "bad.json"))
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InstanceError, match="cannot read"):
        load_instance(str(tmp_path / "bin.txt"))
    (tmp_path / "ok.txt").write_text(STANDARD)
    with pytest.raises(InstanceError, match="layout applies only to built-in ra"):
        load_instance(str(tmp_path / "ok.txt"), layout=2)
    with pytest.raises(InstanceError, match="no built-in instance or file named 'ra01.json'"):
        load_instance("ra01.json")
    with pytest.raises(InstanceError, match="must be named"):
        load_instance("  ")


def test_file_takes_precedence_over_builtin_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "ta01").write_text(STANDARD)
    monkeypatch.chdir(tmp_path)
    assert load_instance("ta01").jobs == STANDARD_JOBS


def test_overrides() -> None:
    inst = load_instance("ra01", agvs=3, tool_transporters=2)
    assert (inst.n_agvs, inst.n_tool_transporters) == (3, 2)
    assert inst.tool_travel == builtin("ra01").tool_travel
    no_tools = load_instance("ra01", no_tools=True)
    assert no_tools.mode == "agvs" and no_tools.n_tools == 0
    assert all(o.tool is None for ops in no_tools.jobs for o in ops)
    assert load_instance("ra01", no_agvs=True).mode == "tools"
    plain = load_instance("sl00", no_agvs=True, no_tools=True)
    assert plain.mode == "jobshop" and plain.jobs == builtin("ta01").jobs
    assert load_instance("sl00", agvs=1, no_tools=True).n_agvs == 1


@pytest.mark.parametrize(
    "spec, kwargs, match",
    [
        ("ta01", {"agvs": 2}, "ta01 has no AGV travel matrix"),
        ("EX12", {"tool_transporters": 2}, "EX12 has no tool travel matrix"),
        ("ra01", {"agvs": 0}, r"agvs must be an integer from 1 to 1000, got 0 \(use --no-agvs"),
        ("ra01", {"tool_transporters": -1}, "tool_transporters must be an integer from 1 to 1000"),
        # the keywords and the command line's flags named (the message serves both)
        ("ra01", {"agvs": 2, "no_agvs": True}, r"AGVs or drop them, not both \(agvs / no_agvs: --agvs / --no-agvs\)"),
        ("ra01", {"tool_transporters": 2, "no_tools": True},
         r"not both \(tool_transporters / no_tools: --tool-transporters / --no-tools\)"),
    ],
)
def test_override_errors(spec: str, kwargs: dict, match: str) -> None:
    with pytest.raises(InstanceError, match=match):
        load_instance(spec, **kwargs)


def test_json_instance_with_plain_jobshop(tmp_path: Path) -> None:
    inst = Instance(name="js", jobs=STANDARD_JOBS)
    inst.save(tmp_path / "js.json")
    with pytest.raises(InstanceError, match="js has no AGV travel matrix"):
        load_instance(str(tmp_path / "js.json"), agvs=2)


def test_an_error_in_a_text_file_names_the_file(tmp_path) -> None:
    path = tmp_path / "shop.txt"
    path.write_text("2 2\n0 3 1 4\n1 2 0 x\n")
    with pytest.raises(InstanceError, match=r"^shop\.txt: line 3: expected integers, got 'x'$"):
        load_instance(str(path))


def test_the_drop_flags_take_booleans_only():
    with pytest.raises(InstanceError, match="no_tools must be True or False, got 'yes'"):
        load_instance("ra01", no_tools="yes")  # type: ignore[arg-type]
    with pytest.raises(InstanceError, match="no_agvs must be True or False, got 1"):
        load_instance("ra01", no_agvs=1)  # type: ignore[arg-type]


def test_an_instance_file_is_loaded_from_a_path(tmp_path: Path) -> None:
    # a pathlib.Path was refused as "an instance must be named" (Schedule.load, Instance.save take one)
    path = tmp_path / "shop.json"
    builtin("ra01").save(path)
    assert load_instance(path) == builtin("ra01") and load_instance(path, agvs=3).n_agvs == 3
    with pytest.raises(InstanceError, match="is a directory"):
        load_instance(tmp_path)


def test_a_number_too_long_for_any_field_names_its_line() -> None:
    # beyond Python's conversion limit (4,300 digits) a raw ValueError named no file nor line
    with pytest.raises(InstanceError, match=r"line 2: the number '9{20}\.\.\.9{8} \(5000 characters\)' is too large"):
        parse_text_jobshop("1 1\n0 " + "9" * 5000 + "\n", "big")
    with pytest.raises(InstanceError, match="line 2: the number '99999999999999999999' is too large"):
        parse_text_jobshop("1 1\n0 " + "9" * 20 + "\n", "big")


@pytest.mark.parametrize("data", ['{"name": "t\xe9", "jobs": []}'.encode("latin-1"),
                                  '{"name": "t", "jobs": []}'.encode("utf-16")])
def test_a_file_not_in_utf8_says_so_and_what_to_do(tmp_path: Path, data: bytes) -> None:
    # it showed the codec's message alone: "'utf-8' codec can't decode byte 0xff in position 0: invalid start byte"
    (tmp_path / "x.json").write_bytes(data)
    with pytest.raises(InstanceError, match=r"x.json': not UTF-8 text \(byte 0x.. at offset \d+\).*save it"):
        load_instance(str(tmp_path / "x.json"))
