"""Drawing tracks on frames: points, fading trails and whole trajectories.

Pure functions on numpy arrays; OpenCV does the antialiased drawing. Frames are (H, W, 3)
uint8 RGB, tracks are (x, y) pixels with pixel centres at integers (OpenCV's drawing
convention too), and visibility is True where a point is visible.

What a drawn point means:

- a filled disc: the point is visible on this frame;
- a ring (hollow circle): the point is occluded; the ring marks its predicted position;
- a trail: the point's path over the previous frames, more transparent the older it is.
  A trail segment is drawn only between two consecutive frames on which the point is
  visible, so a gap in a trail means the point was occluded there;
- nothing: the frame comes before the point's query frame, or its position is not finite.

Each point keeps one colour on every frame: by default a rainbow over the y coordinate of its
query position (red for the topmost point, violet for the lowest), as in CoTracker's
visualiser. Sizes scale with the shorter side of the image.
"""

from __future__ import annotations

import cv2
import numpy as np

SHIFT = 4
"""Fractional bits of OpenCV drawing coordinates: positions are drawn to 1/16 pixel."""

RADIUS_PER_PIXEL = 1 / 128
"""Default point radius as a fraction of the shorter image side (2 px at 256, 5.6 at 720)."""

MIN_RADIUS = 1.5
"""Smallest default radius in pixels, so points stay visible on tiny images."""

_SCALE = 1 << SHIFT


def point_colors(positions: np.ndarray, y_range: tuple[float, float] | None = None) -> np.ndarray:
    """Stable colours for points: a rainbow from the top point (red) to the bottom one (violet).

    Args:
        positions: (N, 2) (x, y) pixels, usually each point's query position.
        y_range: the (top, bottom) y in pixels that map to red and violet. None spreads the
            rainbow evenly over the points' order from top to bottom (ties left to right),
            so that a few points always get clearly different colours however close they
            are (three points: red, green, violet); pass (0, H - 1) when points are added
            over time and colours must not depend on them.

    Returns:
        (N, 3) uint8 RGB colours.
    """
    xy = np.nan_to_num(np.asarray(positions, dtype=np.float64).reshape(-1, 2))
    if len(xy) == 0:
        return np.zeros((0, 3), np.uint8)  # OpenCV rejects empty images
    if y_range is None:
        # by rank, not by y: two points with nearly the same y would get nearly one colour
        rank = np.empty(len(xy))
        rank[np.lexsort((xy[:, 0], xy[:, 1]))] = np.arange(len(xy))
        fraction = rank / max(len(xy) - 1, 1)
    else:
        top, bottom = y_range
        fraction = np.clip((xy[:, 1] - top) / max(bottom - top, 1e-6), 0.0, 1.0)
    # OpenCV's 8-bit hue runs over [0, 180); stop at 135 (violet) so both ends differ.
    hsv = np.empty((len(xy), 1, 3), np.uint8)
    hsv[:, 0, 0] = np.round(fraction * 135).astype(np.uint8)
    hsv[:, 0, 1:] = 255
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[:, 0]


def default_radius(height: int, width: int) -> float:
    """The point radius in pixels used when none is given, scaled with the image."""
    return max(MIN_RADIUS, min(height, width) * RADIUS_PER_PIXEL)


def draw_frame(
    frame: np.ndarray,
    tracks: np.ndarray,
    visible: np.ndarray,
    colors: np.ndarray,
    *,
    active: np.ndarray | None = None,
    radius: float | None = None,
) -> np.ndarray:
    """Draws points with their trails on one frame; the building block of streaming drawing.

    Args:
        frame: (H, W, 3) uint8 RGB frame.
        tracks: (K, N, 2) (x, y) pixels on the last K frames, oldest first; the last row is
            this frame. The K - 1 earlier rows become the trail.
        visible: (K, N) bool visibility on the same frames.
        colors: (N, 3) uint8 RGB colour of each point.
        active: (K, N) bool, False on frames before a point's query frame, where it is not
            drawn at all; None means always active.
        radius: point radius in pixels; None scales it with the image (`default_radius`).

    Returns:
        (H, W, 3) uint8 RGB copy of the frame with the drawing.
    """
    _check_tracks(tracks, visible, colors)
    radius = default_radius(*frame.shape[:2]) if radius is None else radius
    drawn = np.isfinite(tracks).all(axis=-1)  # (K, N)
    if active is not None:
        if active.shape != drawn.shape:
            raise ValueError(f"active must be (K, N) = {drawn.shape}, got {active.shape}")
        drawn &= active
    shown = drawn & np.asarray(visible, dtype=bool)
    fixed = _fixed(tracks)
    color_list = colors.tolist()  # OpenCV draws into RGB frames, so colours stay RGB
    canvas = _draw_trails(frame.copy(), fixed, shown, color_list, _line_width(radius))
    for n in np.flatnonzero(drawn[-1]).tolist():
        # A ring for an occluded point keeps its centre free, so the frame shows through.
        thickness = cv2.FILLED if shown[-1, n] else _ring_width(radius)
        center = (fixed[-1][n][0], fixed[-1][n][1])
        cv2.circle(
            canvas, center, round(radius * _SCALE), color_list[n], thickness, cv2.LINE_AA, SHIFT
        )
    return canvas


def draw_tracks(
    video: np.ndarray,
    tracks: np.ndarray,
    visible: np.ndarray,
    *,
    query_frames: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    trail_length: int = 12,
    radius: float | None = None,
) -> np.ndarray:
    """Draws every point, with a fading trail, on every frame of a video.

    Args:
        video: (T, H, W, 3) uint8 RGB frames.
        tracks: (T, N, 2) (x, y) pixels.
        visible: (T, N) bool, True where a point is visible.
        query_frames: (N,) int frame index from which each point is drawn; None draws
            every point from frame 0.
        colors: (N, 3) uint8 RGB; None uses `point_colors` of each point's position on its
            query frame.
        trail_length: number of past frames each trail covers; 0 draws no trails.
        radius: point radius in pixels; None scales it with the image.

    Returns:
        (T, H, W, 3) uint8 RGB frames with the drawing.
    """
    _check_tracks(tracks, visible, colors)
    num_frames = tracks.shape[0]
    if video.shape[0] != num_frames:
        raise ValueError(f"video has {video.shape[0]} frames but tracks have {num_frames}")
    if trail_length < 0:
        raise ValueError(f"trail_length must be >= 0, got {trail_length}")
    starts = _starts(tracks, query_frames)
    if colors is None:
        colors = point_colors(_query_positions(tracks, starts))
    active = np.arange(num_frames)[:, None] >= starts[None, :]  # (T, N)
    out = np.empty_like(video)
    for t in range(num_frames):
        past = slice(max(0, t - trail_length), t + 1)
        out[t] = draw_frame(
            video[t], tracks[past], visible[past], colors, active=active[past], radius=radius
        )
    return out


def draw_trajectories(
    frame: np.ndarray,
    tracks: np.ndarray,
    visible: np.ndarray,
    *,
    query_frames: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    radius: float | None = None,
) -> np.ndarray:
    """Draws the whole trajectory of every point on one frame, as in the paper's figures.

    Each trajectory runs from the point's query frame, faint, to its last position, opaque,
    where the point is drawn as in `draw_tracks`; it is broken where the point is occluded.
    Drawing on frame t with ``tracks[: t + 1]`` shows the trajectories so far on every frame.

    Args:
        frame: (H, W, 3) uint8 RGB background, typically the last frame.
        tracks: (T, N, 2) (x, y) pixels.
        visible: (T, N) bool, True where a point is visible.
        query_frames: (N,) int query frame of each point; None means frame 0.
        colors: (N, 3) uint8 RGB; None uses `point_colors` of the query positions.
        radius: point radius in pixels; None scales it with the image.

    Returns:
        (H, W, 3) uint8 RGB copy of the frame with the drawing.
    """
    _check_tracks(tracks, visible, colors)
    starts = _starts(tracks, query_frames)
    if colors is None:
        colors = point_colors(_query_positions(tracks, starts))
    active = np.arange(tracks.shape[0])[:, None] >= starts[None, :]  # (T, N)
    return draw_frame(frame, tracks, visible, colors, active=active, radius=radius)


def _draw_trails(
    canvas: np.ndarray,
    fixed: list[list[list[int]]],
    shown: np.ndarray,
    colors: list[list[int]],
    thickness: int,
) -> np.ndarray:
    """Draws segments between consecutive shown positions, fading with age, onto ``canvas``.

    The segment ending at row k of K rows has opacity k / (K - 1): the newest is opaque.
    Segments of one age are drawn together on a copy and blended in once, oldest first, so
    the cost is one blend per age rather than one per segment.
    """
    num_rows = len(fixed)
    segments = shown[1:] & shown[:-1]  # (K - 1, N): both ends visible
    for k in range(1, num_rows):
        points = np.flatnonzero(segments[k - 1]).tolist()
        if not points:
            continue
        layer = canvas.copy()
        for n in points:
            start, end = fixed[k - 1][n], fixed[k][n]
            cv2.line(
                layer,
                (start[0], start[1]),
                (end[0], end[1]),
                colors[n],
                thickness,
                cv2.LINE_AA,
                SHIFT,
            )
        opacity = k / (num_rows - 1)
        cv2.addWeighted(layer, opacity, canvas, 1.0 - opacity, 0.0, dst=canvas)
    return canvas


def _starts(tracks: np.ndarray, query_frames: np.ndarray | None) -> np.ndarray:
    """(N,) int query frame of each point, frame 0 by default."""
    if query_frames is None:
        return np.zeros(tracks.shape[1], np.int64)
    starts = np.asarray(query_frames).astype(np.int64)
    if starts.shape != tracks.shape[1:2]:
        raise ValueError(f"query_frames must be (N,) = ({tracks.shape[1]},), got {starts.shape}")
    if starts.size and not (0 <= starts.min() <= starts.max() < len(tracks)):
        raise ValueError(f"query_frames must lie in [0, {len(tracks) - 1}]")
    return starts


def _query_positions(tracks: np.ndarray, query_frames: np.ndarray) -> np.ndarray:
    """(N, 2) position of each point on its query frame."""
    return tracks[query_frames, np.arange(tracks.shape[1])]


def _check_tracks(tracks: np.ndarray, visible: np.ndarray, colors: np.ndarray | None) -> None:
    if tracks.ndim != 3 or tracks.shape[2] != 2:
        raise ValueError(f"tracks must be (T, N, 2), got {tracks.shape}")
    if visible.shape != tracks.shape[:2]:
        raise ValueError(f"visible must be (T, N) = {tracks.shape[:2]}, got {visible.shape}")
    if colors is not None and colors.shape != (tracks.shape[1], 3):
        raise ValueError(f"colors must be (N, 3) = ({tracks.shape[1]}, 3), got {colors.shape}")


def _fixed(tracks: np.ndarray) -> list[list[list[int]]]:
    """(..., 2) (x, y) pixels to OpenCV's fixed-point coordinates (``SHIFT`` fractional bits).

    Returned as nested Python lists: OpenCV wants Python ints, and converting the whole
    array at once is far cheaper than one point at a time.
    """
    # Non-finite positions become 0 (they are never drawn); far ones are clipped so the
    # fixed-point integers cannot overflow.
    scaled = np.nan_to_num(np.asarray(tracks, np.float64) * _SCALE, nan=0.0)
    return np.clip(np.round(scaled), -(2**24), 2**24).astype(np.int64).tolist()


def _line_width(radius: float) -> int:
    return max(1, round(radius / 2))


def _ring_width(radius: float) -> int:
    # Thinner than a trail, so the ring's hole stays clearly open on small points.
    return max(1, round(radius / 3))
