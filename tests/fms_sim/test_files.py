"""Output files are replaced only by complete ones: a failed write leaves the old file and no temporary."""

import errno
import os
import stat
from pathlib import Path

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.files import folder_problem, output_problem, replacing, write_atomically

from .conftest import run_first


def _full_disk(monkeypatch):
    """Make every Path.write_text write half its text, then fail as a full disk does."""
    real = Path.write_text

    def half(self, data, *args, **kwargs):
        real(self, data[:len(data) // 2], *args, **kwargs)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Path, "write_text", half)


def test_a_complete_write_replaces_the_file_with_the_usual_permissions(tmp_path):
    out = tmp_path / "sub" / "s.json"
    assert write_atomically(out, "one\n") == out and out.read_text() == "one\n"  # folders made
    write_atomically(out, "two\n")
    assert out.read_text() == "two\n" and [p.name for p in out.parent.iterdir()] == ["s.json"]
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~mask  # not mkstemp's 0600


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    inst = builtin("EX12")
    sched = run_first(inst)
    out, spec = tmp_path / "s.json", tmp_path / "i.json"
    out.write_text("the old schedule\n")
    spec.write_text("the old instance\n")
    _full_disk(monkeypatch)
    with pytest.raises(OSError, match="No space left"):
        sched.save(out)
    with pytest.raises(OSError, match="No space left"):
        inst.save(spec)
    assert out.read_text() == "the old schedule\n" and spec.read_text() == "the old instance\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["i.json", "s.json"]


def test_an_error_while_writing_removes_the_temporary(tmp_path):
    out = tmp_path / "x.bin"
    with pytest.raises(RuntimeError):
        with replacing(out) as tmp:
            tmp.write_bytes(b"part")
            raise RuntimeError("interrupted")
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_an_existing_file_keeps_its_permissions(tmp_path):
    out = tmp_path / "s.json"
    out.write_text("old\n")
    out.chmod(0o640)
    write_atomically(out, "new\n")
    assert out.read_text() == "new\n" and stat.S_IMODE(out.stat().st_mode) == 0o640


def test_through_a_link_the_target_is_replaced_and_the_link_stays(tmp_path):
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    target.write_text("old\n")
    link.symlink_to(target.name)
    write_atomically(link, "new\n")  # it replaced the link by a file and left the target as it was
    assert link.is_symlink() and target.read_text() == "new\n"
    write_atomically(tmp_path / "dangling.json", "x\n")  # (a plain new file still works beside them)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dangling.json", "link.json", "target.json"]


def test_a_pipe_is_written_into_not_replaced_by_a_file(tmp_path):
    import threading

    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    got: list[str] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    write_atomically(fifo, "through the pipe\n")  # (/dev/null, /dev/stdout: the same path)
    reader.join(timeout=10)
    assert got == ["through the pipe\n"] and stat.S_ISFIFO(fifo.stat().st_mode)


def test_a_writable_file_in_a_folder_that_is_not_is_written_in_place(tmp_path, monkeypatch):
    import tempfile

    out = tmp_path / "s.json"
    out.write_text("old\n")

    def refused(*args, **kwargs):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))

    monkeypatch.setattr(tempfile, "mkstemp", refused)  # as in a folder this user may not write (tests run as root)
    write_atomically(out, "new\n")
    assert out.read_text() == "new\n"
    with pytest.raises(PermissionError, match=f"the folder {tmp_path} may not be written"):
        write_atomically(tmp_path / "new.json", "x\n")  # (it named the temporary file it could not make)


def test_json_with_a_byte_order_mark_or_nested_too_deeply_is_read_or_refused_as_json(tmp_path):
    import json

    from fms_sim.files import loads, read_text
    from fms_sim.instance import Instance, InstanceError
    from fms_sim.schedule import Schedule, ScheduleError

    sched = run_first(builtin("EX12"))
    path = tmp_path / "bom.json"
    path.write_bytes(b"\xef\xbb\xbf" + sched.to_json().encode())  # "Unexpected UTF-8 BOM (decode using utf-8-sig)"
    assert Schedule.load(path).makespan == sched.makespan and not read_text(path).startswith("\ufeff")
    assert loads("\ufeff[1]") == [1]
    deep = "[" * 5000 + "]" * 5000
    with pytest.raises(json.JSONDecodeError, match="nested too deeply"):  # a RecursionError
        loads(deep)
    path.write_text(deep)
    with pytest.raises(ScheduleError, match="nested too deeply"):
        Schedule.load(path)
    # a number longer than Python converts was a plain ValueError (not the reader's error), with no position
    long = '{"instance": "EX12", "makespan": 1' + "0" * 5000 + "}"
    with pytest.raises(json.JSONDecodeError, match=r"a number has more than 4300 digits: line 1 column 34 "):
        loads(long)
    with pytest.raises(ScheduleError, match="a number has more than 4300 digits"):
        Schedule.from_json(long)
    with pytest.raises(InstanceError, match="a number has more than 4300 digits"):
        Instance.from_json(long.replace('"instance"', '"name"'))
    with pytest.raises(ValueError, match="the hook's"):  # a hook's own error is its own
        loads("{}", object_pairs_hook=lambda pairs: (_ for _ in ()).throw(ValueError("the hook's")))


def test_a_key_twice_in_one_object_is_refused_naming_the_key_the_line_and_the_file(tmp_path):
    """Python's parser keeps the last of two values of one key without a word: a scenario with its noise twice ran
    with the second, an instance file named twice took the second name, a schedule file's second instance was
    validated. Every file read through loads() refuses it now, naming the key, where it stands and the file."""
    import json

    from fms_sim.disruptions import Scenario, ScenarioError
    from fms_sim.files import DuplicateKeyError, loads, unique_pairs
    from fms_sim.formats import load_instance
    from fms_sim.instance import InstanceError
    from fms_sim.schedule import Schedule, ScheduleError

    with pytest.raises(json.JSONDecodeError, match=r"duplicate key 'name' in an object: line 4 column 2 \(char 30\)"):
        loads('{\n "name": "x",\n "jobs": [],\n "name": "y"\n}')
    # the inner object's key, where the second one stands (not the outer object's first key of that name)
    with pytest.raises(json.JSONDecodeError, match=r"duplicate key 'b' in an object: line 1 column 27 "):
        loads('{"x": [1, {"b": {"c": 1}, "b" :2}], "b": 3}')
    with pytest.raises(json.JSONDecodeError, match="duplicate key 'digits'"):  # (not taken for a number's error)
        loads('{"digits": 1, "digits": 2}')
    assert loads('{"a": {"k": 1}, "b": {"k": 2}}') == {"a": {"k": 1}, "b": {"k": 2}}  # one key per object
    assert unique_pairs([("a", 1), ("b", 2)]) == {"a": 1, "b": 2}
    with pytest.raises(DuplicateKeyError, match="duplicate key 'a' in an object") as info:
        unique_pairs([("a", 1), ("b", 2), ("a", 3)])
    assert info.value.key == "a"

    inst = builtin("EX12")
    path = tmp_path / "shop.json"
    path.write_text(inst.to_json(indent=1).replace('"name": "EX12"', '"name": "EX12",\n "name": "mine"', 1))
    with pytest.raises(InstanceError, match=r"shop.json: malformed JSON: duplicate key 'name' in an object: line 3 "):
        load_instance(str(path))
    path = tmp_path / "plan.json"
    path.write_text('{"instance": "EX12", "makespan": 0, "operations": [], "instance": "EX11"}')
    with pytest.raises(ScheduleError, match=r"plan.json: malformed JSON: duplicate key 'instance' in an object"):
        Schedule.load(path)
    path = tmp_path / "scenario.json"
    path.write_text('{"breakdowns": [],\n "noise": 0.1,\n "noise": 0.5}')
    with pytest.raises(ScenarioError, match=r"scenario .*scenario.json is not valid JSON: duplicate key 'noise' in "
                                            r"an object \(line 3\)"):
        Scenario.load(path)


def test_what_json_has_not_is_refused_on_reading_and_on_writing(tmp_path):
    """Python's parser takes NaN, Infinity and 1e400 (infinity after decoding) and its writer writes them back as
    NaN/Infinity, which other JSON readers refuse: a schedule whose meta held one was read, then written, as
    non-JSON. Both directions refuse them now, naming where they stand."""
    import json
    import re

    import numpy as np

    from fms_sim.files import loads
    from fms_sim.schedule import Schedule, ScheduleError

    for text, what, col in (('{"a": NaN}', "NaN is not a JSON number", 7),
                            ('{"s": "NaN", "a": [1.5, -Infinity]}', "-Infinity is not a JSON number", 25),
                            ('{"s": "1e400", "a": 1e400}', "1e400 is too large for a number", 21)):
        with pytest.raises(json.JSONDecodeError, match=f"{what}: line 1 column {col} "):
            loads(text)
    assert loads('{"a": [1.5, -2e3, "NaN"]}') == {"a": [1.5, -2000.0, "NaN"]}
    sched = run_first(builtin("EX12"))
    with pytest.raises(ScheduleError, match="malformed JSON: NaN is not a JSON number"):
        Schedule.from_json(sched.to_json().replace('"instance"', '"meta": {"gap": NaN}, "instance"'))
    out = tmp_path / "s.json"
    sched.save(out)
    for meta, where in (({"gap": float("nan")}, "meta['gap']"),
                        ({"runs": [1, {"t": float("inf")}]}, "meta['runs'][1]['t']"),
                        ({"seen": {1, 2}}, "meta['seen']"), ({"t": np.float32(0.5)}, "meta['t']")):
        sched.meta = meta
        with pytest.raises(ScheduleError, match="^" + re.escape(where) + " cannot be written as JSON"):
            sched.save(out)
        assert Schedule.load(out).meta == {}  # the file written before is kept


def test_a_runs_final_instance_lies_beside_its_schedule_under_one_name():
    """fms up writes it there and fms validate SCHEDULE reads it there: the two used different names for a schedule
    file without the .json suffix (run.sched: run.sched.instance.json against run.instance.json)."""
    from fms_sim.files import instance_beside

    assert instance_beside("out/run.json") == Path("out/run.instance.json")
    assert instance_beside(Path("run.sched")) == Path("run.sched.instance.json")
    assert instance_beside("run") == Path("run.instance.json")


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_an_output_where_nothing_can_be_written_is_found_by_trying_also_for_root():
    # os.access answers from the permission bits, which root passes everywhere: run as root (a container, a robot
    # computer), a schedule_out under /proc or on a read-only file system passed the check and the run was lost
    # when the file was written at its end
    # (another user is refused by the permission bits already: "the folder /proc may not be written")
    for problem in (output_problem("/proc/fms-test/s.json"), folder_problem("/proc/fms-test/charts")):
        assert problem is not None and "the folder /proc" in problem, problem
    assert output_problem("/proc/version").startswith("the file may not be written (")


def test_checking_an_output_leaves_nothing_behind(tmp_path):
    old = tmp_path / "s.json"
    old.write_text("old\n")
    before = old.stat().st_mtime_ns
    assert output_problem(old) is None and output_problem(tmp_path / "new" / "s.json") is None
    assert folder_problem(tmp_path / "charts") is None
    assert old.read_text() == "old\n" and old.stat().st_mtime_ns == before
    assert sorted(q.name for q in tmp_path.iterdir()) == ["s.json"]  # no probe left, no folder made
