"""A small table-driven checker for JSON-shaped values (dicts, lists, str, int, bool, None).

Every message kind in :mod:`fms_msgs_json.schemas` is described by a tuple of :class:`Field` rows; one generic
function, :func:`check_object`, walks such a table. Keeping the rules as data (instead of one hand-written
validator per kind) keeps the kinds consistent and the error messages uniform: each failure names the dotted
path of the offending field (``jobs[0][1].machine``), what was expected and what was found.

The checks are strict in the way JSON consumers in other languages need: ``true`` is not an integer, ``1.0`` is
not an integer, a JSON object's keys are strings.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Protocol

__all__ = [
    "FieldError", "Check", "Field", "Int", "Bool", "Str", "OneOf", "Nullable", "ListOf", "MapOf", "Obj",
    "json_type", "show", "check_object", "join_path",
]


class FieldError(ValueError):
    """One field breaks its rule; ``path`` is the dotted/indexed path, ``str(exc)`` a one-line explanation."""

    def __init__(self, path: str, reason: str) -> None:
        super().__init__(reason)
        self.path = path
        self.reason = reason


def json_type(value: Any) -> str:
    """The JSON type name of a Python value (``bool`` → ``boolean``), or its Python type name if not JSON."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "number"
    if isinstance(value, str):
        return "string"
    if isinstance(value, list):
        return "array"
    if isinstance(value, dict):
        return "object"
    return type(value).__name__


def show(value: Any, limit: int = 40) -> str:
    """A short one-line rendering of ``value`` for error messages: ``'abc' (string)``, ``true (boolean)``."""
    if isinstance(value, (dict, list)):
        unit = "item" if isinstance(value, list) else "key"
        return f"an {json_type(value)} with {len(value)} {unit}{'' if len(value) == 1 else 's'}"
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif value is None:
        text = "null"
    else:
        text = repr(value)
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return f"{text} ({json_type(value)})"


def _fail(path: str, expected: str, value: Any) -> FieldError:
    return FieldError(path, f"field {path!r} must be {expected}, got {show(value)}")


def join_path(path: str, key: str) -> str:
    """The path of field ``key`` of the object at ``path`` (``""``: the message itself): ``history.at``, ``at``."""
    return f"{path}.{key}" if path else key


class Check(Protocol):
    """A rule for one value: raises :class:`FieldError` naming ``path`` if ``value`` breaks it."""

    @property
    def expected(self) -> str:
        """What the rule accepts, in words ("an integer >= 0"), for error messages."""
        ...

    def __call__(self, value: Any, path: str) -> None: ...


#: the integers a message may carry: 64-bit, as SQLite (the recorder) and most JSON readers store them (a larger
#: time was accepted, run by the shop and then failed every insert of the recorder)
INT64 = (-2**63, 2**63 - 1)


@dataclass(frozen=True)
class Int:
    """An integer (never a bool, never a float) that fits 64 bits (:data:`INT64`), at least ``minimum`` if
    given."""

    minimum: int | None = None

    @property
    def expected(self) -> str:
        return "an integer" if self.minimum is None else f"an integer >= {self.minimum}"

    def __call__(self, value: Any, path: str) -> None:
        if not isinstance(value, int) or isinstance(value, bool):
            raise _fail(path, self.expected, value)
        if self.minimum is not None and value < self.minimum:
            raise _fail(path, self.expected, value)
        if not INT64[0] <= value <= INT64[1]:
            raise _fail(path, f"{self.expected} of 64 bits (at most {INT64[1]:,})", value)


@dataclass(frozen=True)
class Bool:
    """``true`` or ``false`` (never 0/1)."""

    expected: str = "a boolean"

    def __call__(self, value: Any, path: str) -> None:
        if not isinstance(value, bool):
            raise _fail(path, self.expected, value)


@dataclass(frozen=True)
class Str:
    """A string; non-empty if ``nonempty``; at most ``max_len`` characters if given."""

    nonempty: bool = True
    max_len: int | None = None
    what: str = ""
    """Optional extra wording for the message, e.g. ``"an action label, not an index"``."""

    @property
    def expected(self) -> str:
        base = "a non-empty string" if self.nonempty else "a string"
        if self.max_len is not None:
            base += f" of at most {self.max_len} characters"
        return f"{base} ({self.what})" if self.what else base

    def __call__(self, value: Any, path: str) -> None:
        if not isinstance(value, str):
            raise _fail(path, self.expected, value)
        if self.nonempty and not value:
            raise _fail(path, self.expected, value)
        if self.max_len is not None and len(value) > self.max_len:
            raise FieldError(path, f"field {path!r} must be {self.expected}, got {len(value)} characters")


@dataclass(frozen=True)
class OneOf:
    """One of a fixed set of strings."""

    values: tuple[str, ...]

    @property
    def expected(self) -> str:
        return "one of " + ", ".join(repr(v) for v in self.values)

    def __call__(self, value: Any, path: str) -> None:
        if not isinstance(value, str) or value not in self.values:
            raise _fail(path, self.expected, value)


@dataclass(frozen=True)
class Nullable:
    """``null`` or whatever ``inner`` accepts."""

    inner: Check

    @property
    def expected(self) -> str:
        return f"null or {self.inner.expected}"

    def __call__(self, value: Any, path: str) -> None:
        if value is None:
            return
        try:
            self.inner(value, path)
        except FieldError as exc:
            if exc.path != path:  # a nested field failed: keep its precise message
                raise
            reason = exc.reason.replace(f"must be {self.inner.expected}", f"must be {self.expected}", 1)
            raise FieldError(path, reason) from None


@dataclass(frozen=True)
class ListOf:
    """A JSON array whose items all pass ``item``; optionally non-empty and with unique (hashable) items."""

    item: Check
    nonempty: bool = False
    unique: bool = False

    @property
    def expected(self) -> str:
        return ("a non-empty array" if self.nonempty else "an array") + f" of ({self.item.expected})"

    def __call__(self, value: Any, path: str) -> None:
        if not isinstance(value, list):
            raise _fail(path, "a non-empty array" if self.nonempty else "an array", value)
        if self.nonempty and not value:
            raise FieldError(path, f"field {path!r} must be a non-empty array, got an empty one")
        if not _all_plain(self.item, value):  # the fast path failed: find (and name) the offending item
            for i, x in enumerate(value):
                self.item(x, f"{path}[{i}]")
        if self.unique:
            seen: set[Any] = set()
            for i, x in enumerate(value):
                if x in seen:
                    raise FieldError(f"{path}[{i}]", f"field {path}[{i}] repeats {show(x)}; items must be unique")
                seen.add(x)


def _all_plain(item: Check, value: list[Any]) -> bool:
    """Fast path for long arrays of scalars (state masks, feature columns): True if every item certainly
    passes ``item`` (exact ``int``/``bool``/``str`` items within the rule); False means "check one by one",
    which also produces the precise error. It never accepts what the item rule rejects."""
    kind = type(item)
    if kind is Int:  # (the 64-bit bound too: a feature column of 2**64 passed, where one such field was refused)
        return not value or (set(map(type, value)) == {int} and max(value) <= INT64[1]
                             and min(value) >= (INT64[0] if item.minimum is None else max(item.minimum, INT64[0])))
    if kind is Bool:
        return not value or set(map(type, value)) == {bool}
    if kind is Str and item.max_len is None:
        return not value or (set(map(type, value)) == {str} and (not item.nonempty or all(value)))
    return False


@dataclass(frozen=True)
class MapOf:
    """A JSON object with non-empty string keys and values that pass ``value``."""

    value: Check

    @property
    def expected(self) -> str:
        return f"an object of string -> ({self.value.expected})"

    def __call__(self, value: Any, path: str) -> None:
        if not isinstance(value, dict):
            raise _fail(path, "an object", value)
        for key, x in value.items():
            if not isinstance(key, str) or not key:
                raise FieldError(path, f"field {path!r} must have non-empty string keys, got key {show(key)}")
            self.value(x, f"{path}.{key}")


@dataclass(frozen=True)
class Field:
    """One row of a table: a key, its rule, and whether it must be present.

    An optional field may be absent; if present it must pass ``check`` (wrap it in :class:`Nullable` to allow
    ``null`` too).
    """

    name: str
    check: Check
    required: bool = True


@dataclass(frozen=True)
class Obj:
    """A JSON object checked against a table of :class:`Field` rows (then the cross-field rule ``extra``, called
    with the object and its path, if any: an object nested in a message keeps the rules it has as a message of its
    own); keys not in the table are allowed."""

    fields: tuple[Field, ...]
    expected: str = "an object"
    extra: Callable[[dict[str, Any], str], None] | None = None

    def __call__(self, value: Any, path: str) -> None:
        check_object(value, self.fields, path, self.extra, expected=self.expected)


def check_object(value: Any, fields: Iterable[Field], path: str = "",
                 extra: Callable[[dict[str, Any], str], None] | None = None, expected: str = "an object") -> None:
    """Check ``value`` against the table ``fields`` (then the cross-field rule ``extra``, if any).

    Raises :class:`FieldError` for the first failure, in table order. Keys that are not in the table are
    ignored (forward compatibility: a newer sender may add fields). ``expected`` words the failure when
    ``value`` is not an object at all.
    """
    if not isinstance(value, dict):
        if path:
            raise _fail(path, expected, value)
        raise FieldError(path, f"a message must be a JSON object, got {show(value)}")
    for f in fields:
        where = join_path(path, f.name)
        if f.name not in value:
            if f.required:
                raise FieldError(where, f"missing required field {where!r} ({f.check.expected})")
            continue
        f.check(value[f.name], where)
    if extra is not None:
        extra(value, path)
