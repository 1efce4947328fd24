"""The videos of a corpus and the queries each one asks for.

A corpus is a list of `CorpusVideo`: an id (unique in the corpus; the result rows carry it),
the file or image folder, and a `QuerySpec` (listed points, a grid, or a mask). Video lists
(CSV or Parquet) are read by `taptr.corpus.video_list`; folders and globs become videos whose
id is their path as found.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from taptr.task.query_checks import grid_points


@dataclass(frozen=True)
class QuerySpec:
    """The queries of one video: exactly one of ``points``, ``grid`` or ``mask``.

    Attributes:
        points: ((t, x, y), ...) pixel queries, pixel centres at integers.
        grid: a grid × grid grid of points on ``query_frame``.
        mask: an image of the video's size; points are sampled inside it on ``query_frame``
            every ``mask_stride`` pixels.
        query_frame: frame of the grid or mask points.
        mask_stride: pixel spacing of mask points.
    """

    points: tuple[tuple[float, float, float], ...] | None = None
    grid: int | None = None
    mask: str | None = None
    query_frame: int = 0
    mask_stride: int = 8

    def __post_init__(self) -> None:
        given = sum(value is not None for value in (self.points, self.grid, self.mask))
        if given != 1:
            raise ValueError("give exactly one of points, grid or mask for each video")

    def to_json(self) -> str:
        """The spec as JSON text (how it travels through Ray Data rows)."""
        return json.dumps(
            {
                "points": None if self.points is None else [list(p) for p in self.points],
                "grid": self.grid,
                "mask": self.mask,
                "query_frame": self.query_frame,
                "mask_stride": self.mask_stride,
            }
        )

    @classmethod
    def from_json(cls, text: str) -> QuerySpec:
        """The spec `to_json` wrote."""
        fields = json.loads(text)
        points = fields.pop("points")
        return cls(points=None if points is None else points_tuple(points), **fields)


@dataclass(frozen=True, slots=True)
class CorpusVideo:
    """One video of a corpus.

    Attributes:
        video_id: unique in the corpus; names the video in every result row.
        path: a video file or a folder of images.
        queries: what to track.
        digest: the settings digest its result is made with (set by the caller from the
            run's settings and these queries; a rerun skips a video whose result has it).
    """

    video_id: str
    path: str
    queries: QuerySpec
    digest: str = ""


def points_tuple(points: object) -> tuple[tuple[float, float, float], ...]:
    """(N, 3) numbers as a tuple of (t, x, y) float tuples (hashable; N ≥ 1).

    Raises:
        ValueError: not N rows of three finite numbers.
    """
    try:
        array = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"points must be rows of three numbers t,x,y, got {points!r:.60}"
        ) from None
    if array.ndim != 2 or array.shape[1] != 3 or len(array) == 0:
        raise ValueError(f"points must be rows of three numbers t,x,y, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError("points hold a NaN or infinite number")
    return tuple((float(t), float(x), float(y)) for t, x, y in array.astype(np.float32))


def build_queries(
    spec: QuerySpec,
    num_frames: int,
    height: int,
    width: int,
    *,
    option: Callable[[str], str] = str,
) -> np.ndarray:
    """The (N, 3) float32 (t, x, y) queries ``spec`` asks for on a video of this size.

    Args:
        spec: the queries.
        num_frames: T, the video's length.
        height: H, its frame height in pixels.
        width: W, its frame width in pixels.
        option: how messages name a field (``taptr track`` passes ``"--" + name``).

    Raises:
        ValueError: a query frame outside the video, a bad grid or mask, or too many points.
    """
    from taptr.task.query_checks import check_num_points

    if spec.points is not None:
        return np.asarray(spec.points, np.float32)
    if not 0 <= spec.query_frame < num_frames:
        frame = option("query-frame")
        raise ValueError(f"{frame} {spec.query_frame} outside [0, {num_frames})")
    if spec.grid is not None:
        return grid_points(spec.grid, spec.query_frame, height, width, name=option("grid"))
    from taptr.api.regions import read_mask, sample_region_queries

    assert spec.mask is not None  # exactly one of points, grid and mask is given
    inside = read_mask(spec.mask, name=option("mask"), size=(height, width))
    sampled = sample_region_queries(inside, spec.query_frame, stride=spec.mask_stride)
    stride = option("mask-stride")
    check_num_points(len(sampled), f"{option('mask')} {spec.mask} with {stride} {spec.mask_stride}")
    return sampled
