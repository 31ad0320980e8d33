"""Output files are replaced only by complete ones: a failed write leaves the old file and no temporary."""

import errno
import os
import stat
from pathlib import Path

import pytest

from fms_sim.benchmarks import builtin
from fms_sim.files import replacing, write_atomically

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
