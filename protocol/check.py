"""Small typed getters for decoded JSON; every failure is a ProtocolError naming the field."""

from __future__ import annotations

import math
import re
from typing import Any

from minority.protocol.errors import ProtocolError

# Safe inside one key-expression chunk and as one path component: 1-64 characters, the
# first a letter, digit or underscore (so never ".", ".." or an option-like "-x"); \Z, not $,
# so a trailing newline does not match.
NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}\Z")


def name(value: Any, where: str, error: type[ProtocolError] = ProtocolError) -> str:
    if not isinstance(value, str) or not NAME_RE.match(value):
        raise error(f"{where}: expected 1-64 characters of [A-Za-z0-9_.-] starting with a "
                    f"letter, digit or underscore, got {value!r:.80}")
    return value


def integer(value: Any, where: str, lo: int | None = None, hi: int | None = None,
            error: type[ProtocolError] = ProtocolError) -> int:
    if type(value) is not int:
        raise error(f"{where}: expected an integer, got {type(value).__name__} {value!r:.40}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise error(f"{where}: {value} is outside [{lo}, {hi}]")
    return value


def number(value: Any, where: str, lo: float | None = None, hi: float | None = None,
           error: type[ProtocolError] = ProtocolError) -> float:
    if type(value) not in (int, float) or not math.isfinite(value):
        raise error(f"{where}: expected a finite number, got {value!r:.40}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise error(f"{where}: {value} is outside [{lo}, {hi}]")
    return float(value)


def vector(value: Any, where: str, size: int = 3,
           error: type[ProtocolError] = ProtocolError) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != size:
        raise error(f"{where}: expected a list of {size} numbers, got {value!r:.60}")
    return tuple(number(v, f"{where}[{i}]", error=error) for i, v in enumerate(value))


def text(value: Any, where: str, max_len: int = 4096,
         error: type[ProtocolError] = ProtocolError) -> str:
    if not isinstance(value, str) or len(value) > max_len:
        raise error(f"{where}: expected a string of at most {max_len} characters")
    return value


def boolean(value: Any, where: str, error: type[ProtocolError] = ProtocolError) -> bool:
    if type(value) is not bool:
        raise error(f"{where}: expected true or false, got {value!r:.40}")
    return value


def keys(obj: Any, where: str, required: set[str], optional: set[str] = frozenset(),
         error: type[ProtocolError] = ProtocolError) -> dict:
    """Check that `obj` is an object with all `required` keys and nothing unknown."""
    if not isinstance(obj, dict):
        raise error(f"{where}: expected an object, got {type(obj).__name__}")
    missing = required - obj.keys()
    if missing:
        raise error(f"{where}: missing {', '.join(sorted(missing))}")
    unknown = obj.keys() - required - optional
    if unknown:
        raise error(f"{where}: unknown field(s) {', '.join(sorted(map(str, unknown)))}")
    return obj
