"""Checks of decoded JSON: small typed getters, and the constrained types the JSON documents
are built from; every failure is a ProtocolError naming the field."""

from __future__ import annotations

import math
import re
from typing import Annotated, Any

import msgspec

from minority.protocol.errors import ProtocolError

# Safe inside one key-expression chunk and as one path component: 1-64 characters, the
# first a letter, digit or underscore (so never ".", ".." or an option-like "-x"). The end is
# "(?![\s\S])", not $ (which matches before a trailing newline) nor \Z (which JavaScript's
# regular expressions, and so JSON Schema viewers, lack).
NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}(?![\s\S])")


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


# --- constrained types: the JSON documents (spec, JSON messages) are msgspec types built
# from these, so one definition gives the decoder's checks and the stored JSON Schemas.
FLOAT_MAX = 1.7976931348623157e308  # bounds that refuse NaN and +-inf
Finite = Annotated[float, msgspec.Meta(ge=-FLOAT_MAX, le=FLOAT_MAX)]
NonNegative = Annotated[float, msgspec.Meta(ge=0.0, le=FLOAT_MAX)]
Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
Vec3 = tuple[Finite, Finite, Finite]
RGB = tuple[Unit, Unit, Unit]
Name = Annotated[str, msgspec.Meta(pattern=NAME_RE.pattern)]
Count = Annotated[int, msgspec.Meta(ge=0, le=1 << 40)]  # steps, particles, bytes; larger: corrupt
Positive = Annotated[int, msgspec.Meta(ge=1, le=(1 << 63) - 1)]
Base64 = Annotated[str, msgspec.Meta(extra_json_schema={"contentEncoding": "base64"})]

_NOT_FINITE = re.compile(r"Expected `float` [<>]= -?1\.7976931348623157e\+308")
_BACKTICKS = re.compile(r"`([^`]*)`")


def convert(obj: Any, kind: type, where: str, error: type[ProtocolError] = ProtocolError,
            whole: str = "value"):
    """`obj` (decoded JSON) as a `kind` (a msgspec type built from the types above); an error
    `{where}.{path}: {problem}` otherwise, e.g. "views[0].width: expected int >= 1" (`whole`
    names obj itself when `where` is empty)."""
    try:
        return msgspec.convert(obj, kind)
    except msgspec.ValidationError as exc:
        text = str(exc)
        if ", got " not in text and "field `" not in text and not text.startswith("Invalid"):
            value = _at(obj, text.partition(" - at `")[2].rstrip("`"))
            if value is not _MISSING:
                text = text.replace(" - at `", f", got {value!r:.40} - at `", 1)
        raise error(validation_message(text, where, whole)) from None


def to_json(obj: Any) -> Any:
    """A msgspec value as plain JSON-ready Python (tuples become lists, fields their JSON
    names)."""
    return _lists(msgspec.to_builtins(obj))


def _lists(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_lists(v) for v in value]
    if isinstance(value, dict):
        return {k: _lists(v) for k, v in value.items()}
    return value


_MISSING = object()
_STEP = re.compile(r"\.([^.\[]+)|\[(\d+)\]")


def _at(obj: Any, path: str) -> Any:
    """The value at a msgspec error path ("$.views[0].width") of obj, or _MISSING."""
    for key, index in _STEP.findall(path.removeprefix("$")):
        try:
            obj = obj[key] if key else obj[int(index)]
        except (KeyError, IndexError, TypeError):
            return _MISSING
    return obj


def validation_message(text: str, where: str, whole: str = "value") -> str:
    """msgspec's "Expected `int` >= 1 - at `$.views[0].width`" in this package's form:
    "{where}.views[0].width: expected int >= 1"."""
    problem, _, path = text.partition(" - at `")
    path = path.rstrip("`").removeprefix("$").lstrip(".")
    if path.startswith("["):
        at = f"{where}{path}"
    else:
        at = ".".join(p for p in (where, path) if p) or whole
    problem = _NOT_FINITE.sub("expected a finite number", problem)
    for prefix, short in (("Object missing required field ", "missing "),
                          ("Object contains unknown field ", "unknown field(s) ")):
        if problem.startswith(prefix):
            problem = short + problem.removeprefix(prefix)
    problem = _BACKTICKS.sub(r"\1", problem)
    return f"{at}: {problem[:1].lower()}{problem[1:]}"
