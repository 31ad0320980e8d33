"""Reading and writing the project's files safely.

Writing: into a temporary file beside the target, then renamed over it. A schedule, an instance, a scenario or a
chart written straight into its target is destroyed by a failed write (a full disk, a quota, an interrupt): the old
content is gone and half a file is left. Written here, the target is replaced only by a complete file
(``os.replace`` is atomic on one file system), a failed write leaves the old file as it was and removes its
temporary, and a watcher of the folder never sees half a file. A symbolic link stays a link (its target is
replaced), and a device or a pipe (``/dev/null``, a FIFO) is written straight into, never replaced by a file.

Reading: :func:`read_text` and :func:`loads` take a UTF-8 file with or without a byte-order mark (editors on Windows
write one) and turn JSON nested too deeply for the parser into a JSON error, not a crash. :func:`loads` refuses an
object that holds one key twice (Python's parser keeps the last value without a word, so a file's reader saw
another value than its writer meant); :func:`unique_pairs` is that check as a hook, for the message decoder.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import stat
import sys
import tempfile
from json.decoder import scanstring  # type: ignore[attr-defined]  # (the stubs leave them out)
from json.scanner import py_make_scanner  # type: ignore[attr-defined]
from pathlib import Path
from typing import Any, Callable, Iterator

__all__ = ["replacing", "write_atomically", "read_text", "loads", "DuplicateKeyError", "unique_pairs", "file_above",
           "output_problem", "folder_problem", "drop_instance_beside", "instance_beside"]


def read_text(path: str | Path) -> str:
    """The text of a UTF-8 file, a leading byte-order mark dropped. Raises OSError and UnicodeDecodeError."""
    return Path(path).read_text(encoding="utf-8-sig")


class _NotJson(ValueError):
    """A value Python's parser takes but JSON has not (``NaN``, ``Infinity``, a number too large for a float)."""


def _constant(name: str) -> Any:
    raise _NotJson(f"{name} is not a JSON number")


def _finite(text: str) -> float:
    value = float(text)
    if value in (math.inf, -math.inf):  # 1e400: infinity after decoding, written back as Infinity
        raise _NotJson(f"{text} is too large for a number")
    return value


#: a JSON string (skipped) or a token that JSON has not
_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"|(-?Infinity|NaN|-?\d+(?:\.\d+)?[eE][+-]?\d+|-?\d+\.\d+)')


def _where(text: str) -> int:
    """Where in ``text`` the first token :func:`_constant` or :func:`_finite` refused stands (0 if none is found)."""
    for m in _TOKEN.finditer(text):
        tok = m.group(1)
        if tok and (tok[-1] in "yN" or not math.isfinite(float(tok))):
            return m.start(1)
    return 0


class DuplicateKeyError(ValueError):
    """A JSON object holds ``key`` twice. JSON leaves the meaning open and Python keeps the last value without a
    word: ``{"noise": 0.1, "noise": 0.5}`` ran with 0.5, whatever its writer meant."""

    def __init__(self, key: str) -> None:
        super().__init__(f"duplicate key {key[:60]!r} in an object")
        self.key = key


def unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """An ``object_pairs_hook`` for :func:`json.loads`: the object's dict, or :class:`DuplicateKeyError` naming the
    first key it holds twice. :func:`loads` uses it; the message decoder (``fms_msgs_json``) too, so that a file and
    a message refuse the same objects."""
    out = dict(pairs)
    if len(out) != len(pairs):  # (one dict and a length: the check costs next to nothing on a large file)
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise DuplicateKeyError(key)
            seen.add(key)
    return out


def _skip_space(s: str, i: int) -> int:
    """The index of the first character from ``i`` on that is not JSON white space."""
    while i < len(s) and s[i] in " \t\n\r":
        i += 1
    return i


def _duplicate_at(text: str, key: str) -> int:
    """Where in ``text`` an object's second ``key`` stands (0 if it is not found). Python's fast parser calls the
    hook once an object is read, without its position: found here by reading ``text`` again with the slow parser,
    only once a duplicate was found, so that the error names the line."""

    class Found(Exception):
        pass

    def parse_object(s_and_end: tuple[str, int], strict: bool, scan_once: Any, *_: Any) -> tuple[dict, int]:
        s, end = s_and_end  # (just after the "{"; the text is JSON up to the duplicate: the fast parser read it)
        seen: set[str] = set()
        end = _skip_space(s, end)
        if s[end] == "}":
            return {}, end + 1
        while True:
            name, after = scanstring(s, end + 1, strict)
            if name in seen and name == key:
                raise Found(end)
            seen.add(name)
            _, end = scan_once(s, _skip_space(s, _skip_space(s, after) + 1))  # (past the ":")
            end = _skip_space(s, end)
            if s[end] == "}":
                return {}, end + 1
            end = _skip_space(s, end + 1)  # (past the ",")

    decoder = json.JSONDecoder()
    decoder.parse_object = parse_object  # type: ignore[attr-defined]
    try:
        py_make_scanner(decoder)(text, _skip_space(text, 0))
    except Found as found:
        return int(found.args[0])
    except (ValueError, IndexError, StopIteration, RecursionError):  # not found: the start of the text
        pass
    return 0


def loads(text: str | bytes, object_pairs_hook: Callable[[list[tuple[str, Any]]], Any] | None = None) -> Any:
    """``json.loads(text)`` (with ``object_pairs_hook``), a leading byte-order mark dropped; JSON nested too deeply for
    the parser (a crash with a RecursionError), a number with more digits than Python converts (a plain
    ValueError), what JSON has not but Python's parser takes (``NaN``, ``Infinity``, ``1e400``, which became
    infinity: a file read so was written back with them, which other JSON readers refuse) and, unless another
    ``object_pairs_hook`` is given, an object holding one key twice (:func:`unique_pairs`; the last value was taken
    without a word) raise :class:`json.JSONDecodeError` like any other malformed JSON, naming where they stand.
    Bytes are read as UTF-8 (they failed with "a bytes-like object is required, not 'str'", the reverse of the
    truth); another type is a TypeError."""
    if isinstance(text, (bytes, bytearray)):
        try:
            text = bytes(text).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise json.JSONDecodeError(f"not UTF-8 text ({exc.reason})", "", 0) from None
    elif not isinstance(text, str):
        raise TypeError(f"JSON text must be a str or bytes, got {type(text).__name__}")
    text = text.removeprefix("\ufeff")
    try:
        return json.loads(text, object_pairs_hook=unique_pairs if object_pairs_hook is None else object_pairs_hook,
                          parse_constant=_constant, parse_float=_finite)
    except RecursionError:
        raise json.JSONDecodeError("nested too deeply", text, 0) from None
    except json.JSONDecodeError:
        raise
    except DuplicateKeyError as exc:  # (before ValueError: a key may hold the word "digits")
        raise json.JSONDecodeError(str(exc), text, _duplicate_at(text, exc.key)) from None
    except _NotJson as exc:
        raise json.JSONDecodeError(str(exc), text, _where(text)) from None
    except ValueError as exc:
        if "digits" not in str(exc):  # the hook's own error
            raise
        limit = sys.get_int_max_str_digits()
        where = re.search(r"\d{%d,}" % (limit + 1), text)
        raise json.JSONDecodeError(f"a number has more than {limit} digits", text,
                                   where.start() if where else 0) from None


@contextlib.contextmanager
def replacing(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary path (ending in ``suffix``: ``".tmp.png"`` for a writer that reads the format from the name) to
    write ``path``'s new content to; on leaving without an error it replaces ``path``
    (an existing file keeps its permissions, a new one gets the usual ones), on an error it is removed and ``path``
    is left as it was. The parent folders are created. Through a symbolic link the link's target is replaced; a
    device or a pipe is given as it is (written straight into); and an existing file that this user may write in a
    folder they may not is written in place (no temporary can be made beside it)."""
    given = Path(path)
    if given.exists() and not given.is_file() and not given.is_dir():  # /dev/null, /dev/stdout, a FIFO
        yield given
        return
    out = Path(os.path.realpath(given))  # a link stays a link: its target gets the content
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=suffix, dir=str(out.parent))
    except PermissionError:
        if out.is_file() and os.access(out, os.W_OK):
            yield out
            return
        raise PermissionError(f"the folder {out.parent} may not be written (permission denied)") from None
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        if out.is_file():
            mode = stat.S_IMODE(out.stat().st_mode)
        else:
            mask = os.umask(0)
            os.umask(mask)
            mode = 0o666 & ~mask
        os.chmod(tmp, mode)  # mkstemp makes 0600
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_atomically(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`replacing`; returns the path."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def file_above(path: Path) -> Path | None:
    """The file that ``path`` would have to lie inside (its nearest existing ancestor, when that is not a folder):
    no output can be written there. None when ``path`` can be made."""
    parent = next((q for q in path.parents if q.exists()), None)
    return parent if parent is not None and not parent.is_dir() else None


def output_problem(path: str | Path) -> str | None:
    """Why an output file cannot be written at ``path`` (None: it can), found before any work: a folder, a path
    inside a file, an existing file or a folder to write in that this user may not write (or where writing fails when
    tried: a read-only file system, ``/proc``; the file is opened without being changed)."""
    p = Path(path)
    if p.is_dir():
        return "is a folder; name a file"
    above = file_above(p)
    if above is not None:
        return f"{above} is a file, not a folder"
    if p.exists():
        if not os.access(p, os.W_OK):
            return "the file may not be written (permission denied)"
        return _open_problem(p) if p.is_file() else None
    return folder_problem(p.parent)


def folder_problem(folder: str | Path) -> str | None:
    """Why files cannot be written in ``folder`` (None: they can): it is a file, lies inside one, or it (or, where
    it does not exist yet, the nearest folder above it, in which it would be made) may not be written by this
    user, or no file can be made there when tried (one is made and removed)."""
    folder = Path(folder).absolute()
    if folder.exists() and not folder.is_dir():
        return f"{folder} is a file, not a folder"
    above = file_above(folder)
    if above is not None:
        return f"{above} is a file, not a folder"
    where = next((q for q in (folder, *folder.parents) if q.exists()), None)
    if where is None:
        return None
    if not os.access(where, os.W_OK | os.X_OK):
        return f"the folder {where} may not be written (permission denied)"
    return _probe_problem(where)


def _probe_problem(folder: Path) -> str | None:
    """Why no file can be made in the existing ``folder`` (None: one was made and removed). ``os.access`` answers
    from the permission bits, which root passes everywhere: a read-only file system or ``/proc`` is found only by
    trying."""
    try:
        fd, name = tempfile.mkstemp(prefix=".fms-check.", dir=str(folder))
    except OSError as exc:
        return f"nothing can be written in the folder {folder} ({exc.strerror or exc})"
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(name)
    return None


def _open_problem(path: Path) -> str | None:
    """Why the existing file ``path`` cannot be opened for writing (None: it can), tried without changing it (opened
    to append, nothing written): root passes ``os.access`` on a read-only file system too."""
    try:
        with open(path, "ab"):
            pass
    except OSError as exc:
        return f"the file may not be written ({exc.strerror or exc})"
    return None


def drop_instance_beside(schedule: str | Path, instance: str, source: str | Path | None = None) -> Path | None:
    """Remove the final instance of shop ``instance`` beside ``schedule`` (:func:`instance_beside`), left by an
    earlier run to the same file, once a run without live orders has written a schedule of that shop there; returns
    its path if one was removed. ``fms validate SCHEDULE`` reads such a file first: the new run's valid schedule was
    called INVALID against the earlier run's ordered jobs. A file of another shop (which ``fms validate`` passes
    over), one that cannot be read, and the run's own instance file ``source`` are left alone."""
    beside = instance_beside(schedule)
    if not beside.is_file() or (source is not None and Path(source).is_file()
                                and Path(source).resolve() == beside.resolve()):
        return None
    try:
        named = loads(read_text(beside)).get("name")
    except (OSError, ValueError, AttributeError):
        return None
    if named != instance:
        return None
    beside.unlink()
    return beside


def instance_beside(schedule: str | Path) -> Path:
    """Where a run's final instance goes beside its schedule file (a run that took live orders has jobs its instance
    has not): ``OUT.instance.json`` for ``OUT.json``, ``NAME.instance.json`` for a schedule file ``NAME`` without the
    ``.json`` suffix. ``fms up`` writes it there and ``fms validate SCHEDULE`` reads it from there."""
    p = Path(schedule)
    return p.with_name(f"{p.name[:-5] if p.name.endswith('.json') else p.name}.instance.json")
