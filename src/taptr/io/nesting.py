"""How deeply unpickled data nests, measured without recursion.

A pickle can hold a list nested 100,000 levels deep in a few hundred kilobytes. The
unpicklers build it without recursing, but anything that later walks it recursively (a
``repr`` in an error message, ``str`` of a key, a config check, numpy's array discovery)
dies with RecursionError. Readers of files measure the depth of what they loaded with
`check_nesting`, which walks it with an explicit stack, and refuse data nested deeper than
any file taptr reads needs.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from typing import Any

MAX_DEPTH = 64
"""Deepest nesting accepted in a loaded file: taptr's checkpoints nest about 6 levels
(training state: optimizer → state → parameter → buffers), datasets 4."""


class NestingError(ValueError):
    """Loaded data nests deeper than allowed; one line, without the data."""


def _children(value: Any) -> Iterator[Any]:
    if isinstance(value, dict):
        yield from value.keys()
        yield from value.values()
    elif isinstance(value, (list, tuple, set, frozenset)):
        yield from value
    elif isinstance(value, argparse.Namespace):
        yield from vars(value).values()


def nesting_depth(value: Any, stop_after: int = MAX_DEPTH) -> int:
    """Levels of containers (dict, list, tuple, set, Namespace) in ``value``; a scalar is 0.

    Args:
        value: the data.
        stop_after: stop counting once this depth is exceeded (returns ``stop_after + 1``).
    """
    deepest = 0
    # the deepest level each container was reached at: a container shared by several
    # parents is walked again only when reached deeper (at most stop_after times), and a
    # container that holds itself is reached ever deeper until the count stops
    reached: dict[int, int] = {}
    stack: list[tuple[Any, int]] = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if not isinstance(item, (dict, list, tuple, set, frozenset, argparse.Namespace)):
            continue
        if reached.get(id(item), 0) >= depth:
            continue
        reached[id(item)] = depth
        deepest = max(deepest, depth)
        if deepest > stop_after:
            return stop_after + 1
        stack.extend((child, depth + 1) for child in _children(item))
    return deepest


def check_nesting(value: Any, what: str, limit: int = MAX_DEPTH) -> None:
    """Raises `NestingError` naming ``what`` when ``value`` nests deeper than ``limit``."""
    if nesting_depth(value, limit) > limit:
        raise NestingError(f"{what} holds data nested more than {limit} levels deep")
