"""Query points typed on the command line (``--points``) or listed in a file (``--points-file``).

The rules, as ``taptr track --help`` states them:

- ``--points "t,x,y;t,x,y"``: the three numbers of a point are separated by commas (spaces
  around them are allowed), points by ``;`` or newlines. Numbers separated by spaces only,
  as in ``"0 100 100"``, are refused: it is not clear whether that is one point or a typo
  for several, and a silently wrong reading would track the wrong points.
- ``--points-file``: UTF-8 text with one point per line, its numbers separated by commas,
  spaces or tabs (the output of ``numpy.savetxt`` reads as is); ``#`` starts a comment, and
  the first line may be a header such as ``t,x,y``. Any other line that is not three
  numbers is an error naming its line number, and so is a NaN or infinite number.
- Frames are whole numbers, as Python reads the text into a double: ``47.0000001`` is an
  error naming the value (queries are float32, which would round it to 47 silently), and
  ``47.0`` or ``4.7e1`` is frame 47.

Both stop at the limit of `taptr.task.query_checks.max_points` before building the array.
`build_queries` turns any of ``taptr track``'s query options (these two, ``--grid``,
``--mask``) into (N, 3) queries.
"""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from taptr.task.query_checks import check_num_points, check_query_values, max_points

if TYPE_CHECKING:
    from taptr.io.video import VideoInfo

MAX_LINE_CHARS = 4096
"""Longest line of a points file; a longer one is not a list of points."""

FLOAT32_MAX = float(np.finfo(np.float32).max)
"""Largest magnitude of a query number (queries are float32)."""


def add_query_arguments(parser: argparse.ArgumentParser, *, required: bool) -> None:
    """The query options of ``taptr track`` (and ``track-corpus``, where they are defaults)."""
    queries = parser.add_mutually_exclusive_group(required=required)
    queries.add_argument(
        "--points",
        help='queries "t,x,y;t,x,y;..." in pixels of the input video: commas between the '
        "numbers of a point, ';' between points",
    )
    queries.add_argument(
        "--points-file",
        help="UTF-8 text/csv file with one t,x,y query per line (commas or spaces; '#' "
        "comments and a header line allowed)",
    )
    queries.add_argument("--grid", type=int, metavar="N", help="track an N×N grid on --query-frame")
    queries.add_argument(
        "--mask",
        help="track points sampled inside this mask (an image of the video's size; inside = "
        "pixels neither black nor transparent)",
    )
    parser.add_argument(
        "--query-frame", type=int, default=0, help="frame of --grid and --mask (default 0)"
    )
    parser.add_argument(
        "--mask-stride", type=int, default=8, help="pixel spacing of --mask points (default 8)"
    )


def parse_points(text: str, flag: str = "--points") -> np.ndarray:
    """``"t,x,y;t,x,y"`` → (N, 3) float32; every point has three comma-separated numbers.

    Raises:
        ValueError: naming ``flag`` and the point, for anything that is not three finite
            numbers, and for more points than `max_points`.
    """
    chunks = [chunk.strip() for chunk in re.split(r"[;\n]", text) if chunk.strip()]
    if not chunks:
        raise ValueError(f"{flag} {text!r} holds no points; write t,x,y;t,x,y;...")
    check_num_points(len(chunks), flag)
    rows = []
    for number, chunk in enumerate(chunks, 1):
        fields = [field.strip() for field in chunk.split(",")]
        if any(re.search(r"\s", field) for field in fields):
            raise ValueError(
                f"{flag}: point {number} {chunk!r} has numbers separated by spaces; separate "
                "the numbers of a point by commas and points by ';', as in '0,100,100;5,20,30'"
            )
        rows.append(_triple(fields, f"{flag}: point {number} {chunk!r}"))
    return np.array(rows, np.float32)


def read_points_file(path: str, flag: str = "--points-file") -> np.ndarray:
    """Queries from a text file with one ``t,x,y`` per line (see the module's rules).

    Reads line by line, so a huge file fails at the point limit instead of filling memory.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line, for a line that is not three finite
            numbers, text that is not UTF-8, or more points than `max_points`.
    """
    from taptr.io.file_kind import kind, require_file

    file = Path(path)
    if kind(file, flag) is None:
        raise FileNotFoundError(f"{flag} {file}: file not found")
    require_file(file, flag)  # a FIFO would block, /dev/zero never end
    rows: list[tuple[float, float, float]] = []
    limit = max_points()
    try:
        with file.open(encoding="utf-8-sig", newline=None) as stream:
            for number, line in enumerate(iter(lambda: stream.readline(MAX_LINE_CHARS + 1), ""), 1):
                if len(line.rstrip("\n")) > MAX_LINE_CHARS:
                    raise ValueError(
                        f"{flag} {file} line {number}: longer than {MAX_LINE_CHARS} characters"
                    )
                row = _file_line(line, number, header_allowed=not rows, where=f"{flag} {file}")
                if row is not None:
                    rows.append(row)
                    if len(rows) > limit:
                        check_num_points(len(rows), f"{flag} {file} (at line {number})")
    except UnicodeDecodeError as error:
        raise ValueError(
            f"{flag} {file}: not UTF-8 text (byte {error.start}); give a text file of t,x,y lines"
        ) from None
    if not rows:
        raise ValueError(f"{flag} {file} holds no t,x,y lines")
    return np.array(rows, np.float32)


def listed_points(args: argparse.Namespace) -> np.ndarray | None:
    """The queries of --points or --points-file (read before the video), else None."""
    if args.points is not None:
        return parse_points(args.points)
    if args.points_file is not None:
        return read_points_file(args.points_file)
    return None


def check_listed_points(
    points: np.ndarray, info: VideoInfo, max_frames: int | None, flag: str
) -> None:
    """Checks listed queries against the video's size, before decoding the video.

    Containers may state a wrong frame count, so queries at or beyond it are left to the
    predictor, which checks them on the decoded frames.
    """
    if info.num_frames is None:
        return
    num_frames = min(info.num_frames, max_frames or info.num_frames)
    if float(points[:, 0].max()) >= num_frames:
        return
    try:
        check_query_values(points.astype(np.float64), num_frames, info.height, info.width)
    except ValueError as error:
        raise ValueError(f"{flag}: {error}") from None


def build_queries(args: argparse.Namespace, num_frames: int, height: int, width: int) -> np.ndarray:
    """The (N, 3) queries the arguments ask for, on a video of that many frames and size."""
    from taptr.corpus.inputs import QuerySpec
    from taptr.corpus.inputs import build_queries as queries_of

    listed = listed_points(args)
    if listed is not None:
        return listed
    spec = QuerySpec(
        grid=args.grid, mask=args.mask, query_frame=args.query_frame, mask_stride=args.mask_stride
    )
    return queries_of(spec, num_frames, height, width, option=lambda name: f"--{name}")


def _file_line(
    line: str, number: int, *, header_allowed: bool, where: str
) -> tuple[float, float, float] | None:
    """One line of a points file: a point, or None for blanks, comments and the header."""
    content = line.split("#", 1)[0].strip()
    if not content:
        return None
    fields = [field for field in re.split(r"[,\s]+", content) if field]
    if header_allowed and not any(_is_number(field) for field in fields):
        return None  # a header such as "t,x,y" or "frame x y"
    return _triple(fields, f"{where} line {number} {content!r}")


def _triple(fields: list[str], where: str) -> tuple[float, float, float]:
    """Three finite numbers, or a ValueError that starts with ``where``."""
    if len(fields) != 3 or not all(_is_number(field) for field in fields):
        raise ValueError(f"{where}: points must be triples t,x,y of numbers")
    values = tuple(float(field) for field in fields)
    if not all(math.isfinite(value) for value in values):
        raise ValueError(f"{where}: NaN or infinite number")
    if not all(abs(value) <= FLOAT32_MAX for value in values):
        # queries are float32: a larger number would become inf (numpy warns, then NaN)
        raise ValueError(f"{where}: a number beyond float32's range (±{FLOAT32_MAX:.3g})")
    if values[0] != round(values[0]):
        # checked before float32, which would read 47.0000001 as frame 47 without a word
        raise ValueError(f"{where}: frame {fields[0]} is not a whole frame index")
    return values  # type: ignore[return-value]


def _is_number(field: str) -> bool:
    try:
        float(field)
    except ValueError:
        return False
    return True
