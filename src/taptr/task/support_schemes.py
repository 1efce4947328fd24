"""Support points: the extra points a model tracks around the user's, never returned.

Points attend to each other in every decoder layer, so whatever else a model is given
changes the user's tracks. Each way of surrounding the queries is one `SupportScheme` in
`SCHEMES`, which says everything a tracker needs of it:

- ``count``: how many support points N queries bring (the model tracks N + count);
- ``points``: those points for given queries: start frames, positions, and each point's
  parent (the query a local point surrounds, −1 for the others), local points first in
  query order;
- ``added``: what points added to a stream after its support was drawn bring (they leave
  with their parent);
- ``fallback`` and ``fits``: the scheme used instead when this one does not fit N queries.

Adding a scheme is one `register_scheme` call (tests/test_support_schemes.py registers
one and runs it through the predictor, its stream and the exported loop).

The official patterns (TAPTRv3-DELTA.md §5.2), in 256 × 256 pixels where a normalised
coordinate is x / 255:

1. 63 local points per query: its position plus the offsets of an 8 × 8 grid spanning
   ±24 px (``linspace(−24, 24, 8)``, x fastest) without entry 32, which the official code
   removes as if it were the centre: (−24, +3.43). Each starts on its query's frame; they
   may lie outside the frame.
2. 36 grid points on ``linspace(16, 239, 6)``², x fastest, each starting on a frame drawn
   from [0, 12) (``randint(0, 12, 36)``) by a numpy generator seeded with 42: the official
   evaluation draws them from numpy's global generator, seeded once, one draw per video in
   dataset order (`taptr.eval.official_protocol` replays that order); a tracker takes the
   first draw for every video.

A `SupportPattern` holds those numbers in the unit and float type a caller computes in:
normalised (the predictor in its dtype, the exported loop in the manifest's float32
values) or the evaluation's 256 × 256 pixels in float64, so each caller gets exactly what
its own arithmetic gave before this registry existed.

``random`` (TAPTRv2's seeded context points) is drawn per video from the model's input
size by `taptr.api.context_points` (`SupportScheme.drawn`); its count and fallback are here.

Shapes: N queries, K support points, L local offsets, G grid points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

LOCAL_SPAN = 24.0
"""Half the side of the local pattern, in 256 × 256 pixels."""
LOCAL_SIDE = 8
GRID_SIDE = 6
GRID_POINTS = GRID_SIDE * GRID_SIDE
GRID_MARGIN = 16
GRID_SEED = 42
PREFIX_FRAMES = 12
"""Grid points start on a frame drawn from [0, 12)."""
EVAL_SCALE = 255.0
"""A normalised coordinate is a 256 × 256 pixel divided by 255."""

LOCAL_SUPPORT_BUDGET = 2048
"""With ``local_and_grid``, queries get their 63 local points only while each query and its
local points together stay within this many points (32 queries); more queries get the 36
grid points alone and support each other. docs/RESULTS.md ("Support points for TAPTRv3's
queries") measures what the local points cost per frame and what they bring."""


def local_offsets() -> np.ndarray:
    """(63, 2) float64 local (dx, dy) in 256 × 256 pixels, x fastest, entry 32 removed."""
    line = np.linspace(-LOCAL_SPAN, LOCAL_SPAN, LOCAL_SIDE)
    xs, ys = np.meshgrid(line, line)
    grid = np.stack((xs.ravel(), ys.ravel()), axis=-1)  # (64, 2)
    return np.delete(grid, LOCAL_SIDE * LOCAL_SIDE // 2, axis=0)


LOCAL_OFFSETS = local_offsets()
"""(63, 2) the local pattern, in 256 × 256 pixels."""


def grid_positions() -> np.ndarray:
    """(36, 2) float64 grid (x, y) in 256 × 256 pixels, x fastest."""
    line = np.linspace(GRID_MARGIN, 256 - 1 - GRID_MARGIN, GRID_SIDE)
    xs, ys = np.meshgrid(line, line)
    return np.stack((xs.ravel(), ys.ravel()), axis=-1)


def grid_start_frames(rng: np.random.RandomState) -> np.ndarray:
    """(36,) int64 the grid points' start frames: one official draw from ``rng``.

    A video shorter than a draw never starts that point, which then influences nothing
    (the official code requires 12 frames), so streams of unknown length agree with it.
    """
    return rng.randint(0, PREFIX_FRAMES, GRID_POINTS).astype(np.int64)


def first_grid_draw() -> np.ndarray:
    """(36,) the grid start frames every tracker uses: the first draw seeded with 42."""
    return grid_start_frames(np.random.RandomState(GRID_SEED))


@dataclass(frozen=True, eq=False)
class SupportPattern:
    """The numbers of the support schemes, in one unit and float type.

    Attributes:
        local_offsets: (L, 2) (dx, dy) added to a query's position.
        grid_positions: (G, 2) (x, y) of the grid points.
        grid_start_frames: (G,) int64 their start frames.
        local_budget: `LOCAL_SUPPORT_BUDGET`, or a manifest's.
        context_points: ``random``: the points the query set is padded to.
    """

    local_offsets: np.ndarray
    grid_positions: np.ndarray
    grid_start_frames: np.ndarray
    local_budget: int = LOCAL_SUPPORT_BUDGET
    context_points: int = 0

    @classmethod
    def normalised(
        cls, dtype: type | np.dtype = np.float32, *, context_points: int = 0
    ) -> SupportPattern:
        """The patterns in the model's normalised units (x / 255), rounded to ``dtype``."""
        return cls(
            (LOCAL_OFFSETS / EVAL_SCALE).astype(dtype),
            (grid_positions() / EVAL_SCALE).astype(dtype),
            first_grid_draw(),
            context_points=context_points,
        )

    @classmethod
    def pixels_256(cls, grid_starts: np.ndarray) -> SupportPattern:
        """The patterns in the evaluation's 256 × 256 pixels (float64), with a grid draw."""
        return cls(local_offsets(), grid_positions(), np.asarray(grid_starts, np.int64))


class SupportPoints(NamedTuple):
    """Support points of some queries.

    Attributes:
        start_frames: (K,) int64.
        positions: (K, 2) (x, y) in the pattern's unit and type.
        parents: (K,) int64 index (among the queries given) of the query a local point
            surrounds, −1 for points that belong to no query.
    """

    start_frames: np.ndarray
    positions: np.ndarray
    parents: np.ndarray


def no_points(positions: np.ndarray) -> SupportPoints:
    """No support points, positions typed as ``positions``."""
    return SupportPoints(
        np.zeros(0, np.int64), np.zeros((0, 2), positions.dtype), np.zeros(0, np.int64)
    )


def local_points(starts: np.ndarray, xy: np.ndarray, pattern: SupportPattern) -> SupportPoints:
    """The local pattern of each query, in query order: (N·L,) points."""
    offsets = pattern.local_offsets  # (L, 2)
    positions = (xy[:, None] + offsets).reshape(-1, 2)  # (N·L, 2)
    parents = np.repeat(np.arange(len(starts), dtype=np.int64), len(offsets))
    return SupportPoints(np.repeat(np.asarray(starts, np.int64), len(offsets)), positions, parents)


def grid_points(pattern: SupportPattern) -> SupportPoints:
    """The G grid points, in the pattern's type, belonging to no query."""
    count = len(pattern.grid_positions)
    return SupportPoints(
        pattern.grid_start_frames.astype(np.int64),
        pattern.grid_positions,
        np.full(count, -1, np.int64),
    )


def joined(*parts: SupportPoints) -> SupportPoints:
    """Support points one after the other."""
    return SupportPoints(*(np.concatenate(column) for column in zip(*parts, strict=True)))


def _nothing(starts: np.ndarray, xy: np.ndarray, pattern: SupportPattern) -> SupportPoints:
    return no_points(xy)


def _always(num_queries: int, pattern: SupportPattern) -> bool:
    return True


@dataclass(frozen=True)
class SupportScheme:
    """One way of surrounding the queries (module docstring).

    Attributes:
        name: what options and configs call it.
        count: (N, pattern) → support points N queries bring.
        points: (starts (N,), xy (N, 2), pattern) → their `SupportPoints`.
        added: the same for points added to a stream after its support was drawn.
        fallback: the scheme used instead where ``fits`` says no.
        fits: (N, pattern) → whether N queries get this scheme.
        drawn: its points are drawn per video by `taptr.api.context_points` (``random``), not by
            ``points``.
    """

    name: str
    count: Callable[[int, SupportPattern], int]
    points: Callable[[np.ndarray, np.ndarray, SupportPattern], SupportPoints]
    added: Callable[[np.ndarray, np.ndarray, SupportPattern], SupportPoints] = _nothing
    fallback: str | None = None
    fits: Callable[[int, SupportPattern], bool] = _always
    drawn: bool = False


def _random_points(starts: np.ndarray, xy: np.ndarray, pattern: SupportPattern) -> SupportPoints:
    if pattern.context_points <= len(starts):
        return no_points(xy)
    raise ValueError(
        "this model pads its queries with random context points, drawn by "
        "taptr.api.context_points, which needs torch: pass support_points='grid' or 'none'"
    )


SCHEMES: dict[str, SupportScheme] = {}
"""Every support scheme by name, in the order options list them."""


def register_scheme(scheme: SupportScheme) -> SupportScheme:
    """Adds ``scheme`` to `SCHEMES` (replacing one of the same name) and returns it."""
    SCHEMES[scheme.name] = scheme
    return scheme


register_scheme(
    SupportScheme(
        "random",
        count=lambda n, pattern: max(0, pattern.context_points - n),
        points=_random_points,
        drawn=True,
    )
)
register_scheme(
    SupportScheme(
        "local_and_grid",
        count=lambda n, pattern: n * len(pattern.local_offsets) + len(pattern.grid_positions),
        points=lambda starts, xy, pattern: joined(
            local_points(starts, xy, pattern), grid_points(pattern)
        ),
        added=local_points,
        fallback="grid",
        # each query with its local points within the budget: the grid alone beyond
        fits=lambda n, pattern: n * (1 + len(pattern.local_offsets)) <= pattern.local_budget,
    )
)
register_scheme(
    SupportScheme(
        "grid",
        count=lambda n, pattern: len(pattern.grid_positions),
        points=lambda starts, xy, pattern: grid_points(pattern),
    )
)
register_scheme(
    SupportScheme("none", count=lambda n, pattern: 0, points=_nothing),
)


def support_scheme(name: str, what: str = "support_points") -> SupportScheme:
    """The registered scheme called ``name``.

    Raises:
        ValueError: no scheme has that name (the message lists them, naming ``what``).
    """
    scheme = SCHEMES.get(name) if isinstance(name, str) else None
    if scheme is None:
        raise ValueError(f"{what} must be one of {', '.join(SCHEMES)}, got {name!r}")
    return scheme


def choose_scheme(
    configured: str, num_queries: int, pattern: SupportPattern, asked: str | None = None
) -> SupportScheme:
    """The scheme ``num_queries`` user points get.

    Args:
        configured: the model's scheme (its config's ``support_points``).
        num_queries: N.
        pattern: the numbers the schemes count with.
        asked: a scheme asked for instead (an option): used as it is, never replaced.
    """
    if asked is not None:
        return support_scheme(asked)
    scheme = support_scheme(configured)
    while scheme.fallback is not None and not scheme.fits(num_queries, pattern):
        scheme = support_scheme(scheme.fallback)
    return scheme


def model_points(scheme: SupportScheme, num_queries: int, pattern: SupportPattern) -> int:
    """Points the model tracks for ``num_queries`` user points under ``scheme``."""
    return num_queries + scheme.count(num_queries, pattern)
