"""Tracking a video frame by frame: memory bounded by the window, not by the video.

`track_frames` feeds frames from any iterator (a decoder reading the file lazily) to an
`OnlineTracker` and yields each frame together with its tracks as soon as no later
window can change them (about one window behind the newest frame). Only the frames not
yet final are held. `draw_final` turns those batches into overlay frames with trails,
again holding only the last few rows of tracks, so a writer can encode the overlay while
the video is still being read.

With the video's length given (``num_frames``, the container's frame count), the tracks
equal `Predictor.track` on the whole video in memory (see `taptr.api.online`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from itertools import islice
from typing import NamedTuple

import numpy as np

from taptr.api.online import OnlineTracker, StreamUpdate
from taptr.api.predictor import Predictor
from taptr.task.both_ways import needs_backward, query_frames, reversed_queries


class FinalFrames(NamedTuple):
    """Frames whose tracks can no longer change.

    Attributes:
        first_frame: index of the first frame.
        frames: (F, H, W, 3) uint8 RGB frames.
        tracks: (F, N, 2) float32 (x, y) pixels, pixel centres at integers.
        visibility: (F, N) bool.
        visibility_logits: (F, N) float32; −inf before a point's query frame.
    """

    first_frame: int
    frames: np.ndarray
    tracks: np.ndarray
    visibility: np.ndarray
    visibility_logits: np.ndarray


def track_frames(
    predictor: Predictor,
    frames: Iterable[np.ndarray],
    queries: np.ndarray,
    *,
    num_frames: int | None = None,
    chunk: int = 4,
) -> Iterator[FinalFrames]:
    """Tracks queries through frames read one at a time.

    Args:
        predictor: the model and its settings.
        frames: (H, W, 3) uint8 RGB frames, in order.
        queries: (N, 3) (t, x, y) pixel queries, all known up front.
        num_frames: the video's length when known (makes long videos equal offline tracking).
        chunk: frames encoded at a time.

    Yields:
        `FinalFrames`, in order, covering every frame once.

    Raises:
        ValueError: no frames, bad queries, or fewer/more frames than ``num_frames``.
    """
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    source = iter(frames)
    first = next(source, None)
    if first is None:
        raise ValueError("the video has no frames")
    online = _online_tracker(predictor)
    state = online.start(num_frames=num_frames, frame_size=first.shape[:2])
    online.add_queries(state, queries)
    held: deque[np.ndarray] = deque()
    batch = [first, *islice(source, chunk - 1)]
    while batch:
        held.extend(batch)
        yield from _final(online.step(state, np.stack(batch)), held)
        batch = list(islice(source, chunk))
    yield from _final(online.finish(state), held)


def track_frames_both_ways(
    predictor: Predictor,
    read_forward: Callable[[], Iterable[np.ndarray]],
    read_reversed: Callable[[], Iterable[np.ndarray]],
    queries: np.ndarray,
    *,
    num_frames: int,
    chunk: int = 4,
    on_reversed: Callable[[int], object] | None = None,
) -> Iterator[FinalFrames]:
    """Tracks before and after each query frame, reading the video twice, never holding it.

    The first read goes backwards (``read_reversed``: frame T − 1 first) with every query at
    frame T − 1 − t and keeps only the tracks of the frames before each query frame; the
    second read goes forwards and yields each frame with those tracks before its points'
    query frames and the forward tracks from them on: `Predictor.track` with
    ``backward=True`` (`taptr.task.both_ways`), frame by frame.

    Args:
        predictor: the model and its settings.
        read_forward: opens the frames in order, (H, W, 3) uint8 RGB.
        read_reversed: opens the same frames last to first.
        queries: (N, 3) (t, x, y) pixel queries.
        num_frames: T, the video's length (required: it places the reversed queries).
        chunk: frames encoded at a time.
        on_reversed: called with the number of frames of each reversed batch (progress).

    Yields:
        `FinalFrames` in forward order, covering every frame once.
    """
    query = np.asarray(queries, dtype=np.float64)
    if not needs_backward(query):
        yield from track_frames(
            predictor, read_forward(), queries, num_frames=num_frames, chunk=chunk
        )
        return
    starts = query_frames(query)
    backward = None
    flipped = reversed_queries(query, num_frames)
    for batch in track_frames(
        predictor, read_reversed(), flipped, num_frames=num_frames, chunk=chunk
    ):
        if backward is None:  # (T, N, ...) of the reversed pass, in forward frame order
            backward = _empty_like(batch, num_frames)
        rows = num_frames - 1 - np.arange(batch.first_frame, batch.first_frame + len(batch.frames))
        for name in ("tracks", "visibility", "visibility_logits"):
            backward[name][rows] = getattr(batch, name)
        if on_reversed is not None:
            on_reversed(len(batch.frames))
    assert backward is not None
    for batch in track_frames(
        predictor, read_forward(), queries, num_frames=num_frames, chunk=chunk
    ):
        rows = slice(batch.first_frame, batch.first_frame + len(batch.frames))
        before = np.arange(num_frames)[rows, None] < starts[None]  # (F, N)
        yield batch._replace(
            tracks=np.where(before[..., None], backward["tracks"][rows], batch.tracks),
            visibility=np.where(before, backward["visibility"][rows], batch.visibility),
            visibility_logits=np.where(
                before, backward["visibility_logits"][rows], batch.visibility_logits
            ),
        )


def _online_tracker(predictor: Predictor) -> OnlineTracker:
    """The predictor's own streaming tracker where it has one, else PyTorch's.

    A graph engine's predictor has its own (`taptr.onnx.OnnxOnlineTracker`); both take the
    same calls and return the same updates.
    """
    own = getattr(predictor, "online_tracker", None)
    return own() if own is not None else OnlineTracker(predictor)


def _empty_like(batch: FinalFrames, num_frames: int) -> dict[str, np.ndarray]:
    """Zeroed (T, ...) arrays shaped and typed like the per-frame results of ``batch``."""
    return {
        name: np.zeros((num_frames, *value.shape[1:]), value.dtype)
        for name in ("tracks", "visibility", "visibility_logits")
        for value in [getattr(batch, name)]
    }


def _final(update: StreamUpdate, held: deque[np.ndarray]) -> Iterator[FinalFrames]:
    """Pairs an update with its frames, dropping them from ``held``."""
    count = update.tracks.shape[0]
    if count == 0:
        return
    frames = np.stack([held.popleft() for _ in range(count)])
    yield FinalFrames(
        update.first_frame,
        frames,
        # CPU tensors from PyTorch's tracker, arrays from the graph engines'
        np.asarray(update.tracks),
        np.asarray(update.visibility),
        np.asarray(update.visibility_logits),
    )


def draw_final(
    batches: Iterable[FinalFrames],
    queries: np.ndarray,
    *,
    trail_length: int = 12,
    radius: float | None = None,
    from_query_frames: bool = True,
) -> Iterator[np.ndarray]:
    """Overlay frames, one by one, as `taptr.viz.draw.draw_tracks` draws a whole video.

    Args:
        batches: `track_frames` (or `track_frames_both_ways`) output.
        queries: (N, 3) (t, x, y) the queries (colours come from their positions).
        trail_length: past frames each trail covers.
        radius: point radius in pixels; None scales it with the image.
        from_query_frames: draw each point from its query frame on (forward tracking);
            False draws it on every frame (tracked both ways).

    Yields:
        (H, W, 3) uint8 RGB frames with the points and their trails.
    """
    from taptr.viz.draw import draw_frame, point_colors

    colors = point_colors(queries[:, 1:])
    starts = queries[:, 0].astype(np.int64) if from_query_frames else np.zeros(len(queries), int)
    tracks: deque[np.ndarray] = deque(maxlen=trail_length + 1)
    visible: deque[np.ndarray] = deque(maxlen=trail_length + 1)
    indices: deque[int] = deque(maxlen=trail_length + 1)
    for batch in batches:
        for offset, frame in enumerate(batch.frames):
            tracks.append(batch.tracks[offset])
            visible.append(batch.visibility[offset])
            indices.append(batch.first_frame + offset)
            active = np.array(indices)[:, None] >= starts[None, :]  # (K, N)
            yield draw_frame(
                frame,
                np.stack(tracks),
                np.stack(visible),
                colors,
                active=active,
                radius=radius,
            )
