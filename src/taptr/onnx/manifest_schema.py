"""What a manifest's keys may hold, checked before anything uses them.

Each key of ``taptr-export.json`` has a `Check`: a function of the value read that
returns it converted (lists to tuples) or raises `ManifestError`, one line naming the
file and the key (``support.local_offsets``) and what is wrong with it. A `record` takes
exactly its keys: a missing key and an unknown one are errors alike. Sizes are bounded
here, so that no value read can ask the loop for gigabytes or negative dimensions.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

Check = Callable[[Any, str], Any]
"""(value, key) → the value converted; raises `_RefusedError` naming the key."""


class ManifestError(ValueError):
    """A manifest that does not hold what its version says; the message names file and key."""


class _RefusedError(Exception):
    """A key's value refused (turned into a `ManifestError` with the file's name)."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(key, problem)
        self.key = key
        self.problem = problem


def _kind(value: Any) -> str:
    """What a JSON value is, for messages."""
    names = {bool: "a boolean", int: "a number", float: "a number", str: "text"}
    names |= {list: "a list", dict: "an object", type(None): "null"}
    return names.get(type(value), type(value).__name__)


def integer(low: int, high: int) -> Check:
    """A whole number in [low, high] (JSON booleans are not numbers here)."""

    def check(value: Any, key: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _RefusedError(key, f"must be a whole number, got {_kind(value)}")
        if not low <= value <= high:
            raise _RefusedError(key, f"must lie in [{low:,}, {high:,}], got {value:,}")
        return value

    return check


def real(low: float = -math.inf, high: float = math.inf, *, strict: bool = False) -> Check:
    """A finite number in [low, high], or in (low, high) when ``strict``."""

    def check(value: Any, key: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise _RefusedError(key, f"must be a number, got {_kind(value)}")
        inside = low < value < high if strict else low <= value <= high
        if not math.isfinite(value) or not inside:
            bounds = f"({low}, {high})" if strict else f"[{low}, {high}]"
            raise _RefusedError(key, f"must be a finite number in {bounds}, got {value}")
        return float(value)

    return check


def boolean(value: Any, key: str) -> bool:
    """True or false."""
    if not isinstance(value, bool):
        raise _RefusedError(key, f"must be true or false, got {_kind(value)}")
    return value


def choice(*options: Any) -> Check:
    """One of ``options`` exactly."""

    def check(value: Any, key: str) -> Any:
        if isinstance(value, bool) or value not in options or type(value) is float:
            listed = ", ".join(repr(option) for option in options)
            raise _RefusedError(key, f"must be one of {listed}, got {_shown(value)}")
        return value

    return check


def text(most: int) -> Check:
    """Text of at most ``most`` characters."""

    def check(value: Any, key: str) -> str:
        if not isinstance(value, str) or len(value) > most:
            raise _RefusedError(key, f"must be text of at most {most} characters")
        return value

    return check


def sequence(item: Check, *, length: int | None = None, most: int = 64) -> Check:
    """A list of ``length`` (or at most ``most``) items, each checked; returned as a tuple."""

    def check(value: Any, key: str) -> tuple[Any, ...]:
        if not isinstance(value, list):
            raise _RefusedError(key, f"must be a list, got {_kind(value)}")
        if length is not None and len(value) != length:
            raise _RefusedError(key, f"must hold {length} entries, got {len(value):,}")
        if len(value) > most:
            raise _RefusedError(key, f"must hold at most {most:,} entries, got {len(value):,}")
        return tuple(item(entry, f"{key}[{index}]") for index, entry in enumerate(value))

    return check


def record(fields: dict[str, Check]) -> Check:
    """An object with exactly the keys of ``fields``, each checked; returned as a dict."""

    def check(value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise _RefusedError(key, f"must be an object, got {_kind(value)}")
        prefix = f"{key}." if key else ""
        missing = [name for name in fields if name not in value]
        if missing:
            raise _RefusedError(prefix + missing[0], "is missing")
        unknown = [name for name in value if name not in fields]
        if unknown:
            raise _RefusedError(prefix + str(unknown[0])[:40], "is not a key of this manifest")
        return {name: fields[name](value[name], prefix + name) for name in fields}

    return check


def checked(data: Any, fields: dict[str, Check], where: str) -> dict[str, Any]:
    """``data`` checked as a record of ``fields``.

    Args:
        data: what the manifest's JSON held.
        fields: each key's check.
        where: the manifest file, for messages.

    Raises:
        ManifestError: the first key that does not hold what it must.
    """
    try:
        return record(fields)(data, "")
    except _RefusedError as refused:
        raise ManifestError(f"{where}: {refused.key!r} {refused.problem}") from None


def refuse(where: str, key: str, problem: str) -> ManifestError:
    """A `ManifestError` for a check made outside the schema (values that disagree)."""
    return ManifestError(f"{where}: {key!r} {problem}")


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."
