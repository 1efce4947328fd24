"""TAPTRv2 run exactly as the authors' evaluation runs it (TAPTRv2-SPEC.md §4).

This reproduces the paper's numbers with the released checkpoint; it is a protocol for that
one model, not a way to use it (`taptr.Predictor` is). Per video, on 256 × 256 frames whose
coordinates are TAP-Vid's normalised values × 255:

- frames are upsampled to the model's input size (512 × 512 for the released model),
  bilinear, and ImageNet-normalised;
- the query set is padded to 800 points with the official seed-0 recipe (`official_padding`),
  because points attend to each other and the padding changes the real points' outputs;
- ``first``: one pass over all queries; ``strided``: each query frame's points are padded
  separately and run forward and on the reversed video, fused at the query frame;
- a point is visible where sigmoid(visibility logit 1) > 0.5.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F

from taptr.api import TAPTR, normalize_frames
from taptr.api.context import PREFIX_FRAMES, ContextPoints, draw_context
from taptr.eval.query_sampling import QueryPoints
from taptr.eval.trackers import query_frames, track_both_ways
from taptr.geometry import normalized_to_pixels, pixels_to_normalized
from taptr.official.model_forward import official_forward

NUM_QUERIES = 800
"""Points per pass after padding (the official ``num_queries_per_video_eval``)."""

EVAL_FRAME = (256, 256)
"""(H, W) of the frames the evaluation pads in: padded points lie in [16, 239]."""


def official_padding(
    frame0_positions: np.ndarray, num_frames: int, num_queries: int = NUM_QUERIES
) -> ContextPoints:
    """The evaluation's padding of n real points to ``num_queries`` (TAPTRv2-SPEC.md §4.2).

    `taptr.api.context.draw_context` on the 256 × 256 frame with start frames drawn from
    [0, 12). The official code fails on videos shorter than 12 frames, where a point can be
    occluded on every frame; here start frames are capped at T − 1, so each point is visible
    on its last frame at least. Videos of 12 frames or more get exactly the official padding.

    Args:
        frame0_positions: (n, 2) real points' (x, y) on frame 0, in 256-frame units.
        num_frames: T, frames in the video.
        num_queries: size of the padded set.
    """
    padding = draw_context(frame0_positions, num_queries, EVAL_FRAME, PREFIX_FRAMES)
    return padding._replace(start_frames=np.minimum(padding.start_frames, num_frames - 1))


class OfficialTAPTR:
    """A TAPTR model evaluated with the official recipe.

    Args:
        model: the network; its config's ``input_size`` is the resolution frames are
            upsampled to (512 × 512 for the released model).
        device: where to run it.
        num_queries: points per pass after padding (800 in the official protocol).
    """

    def __init__(
        self, model: TAPTR, *, device: str | torch.device = "cpu", num_queries: int = NUM_QUERIES
    ) -> None:
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.input_size = tuple(model.config.input_size) if model.config else (512, 512)
        self.num_queries = num_queries

    def _pass(
        self, video: np.ndarray, queries: np.ndarray, start_visible: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One forward-in-time pass.

        Args:
            video: (T, 256, 256, 3) uint8 frames.
            queries: (N, 3) (t, x, y) with x, y in 256-frame units (raster × 255).
            start_visible: (N,) bool visibility label on each query frame.

        Returns:
            tracks (T, N, 2) in 256-frame units and visible (T, N) bool.
        """
        height, width = video.shape[1:3]
        frames = torch.from_numpy(np.ascontiguousarray(video)).to(self.device)
        frames = frames.permute(0, 3, 1, 2).float() / 255  # (T, 3, H, W)
        if tuple(frames.shape[-2:]) != self.input_size:
            # torchvision's tensor resize as the official code calls it: bilinear,
            # align_corners=False, no antialiasing
            frames = F.interpolate(frames, size=self.input_size, mode="bilinear")
        query_xy = torch.as_tensor(queries[:, 1:], dtype=torch.float32)
        output = official_forward(
            self.model,
            normalize_frames(frames)[None],
            torch.as_tensor(query_frames(queries)),
            pixels_to_normalized(query_xy, height, width).to(self.device),
            torch.as_tensor(np.where(start_visible, 1, 2)).to(self.device),
        )
        tracks = normalized_to_pixels(output["positions"].float(), height, width)
        visible = output["visibility_logits"][..., 1].float().sigmoid() > 0.5
        return tracks.cpu().numpy(), visible.cpu().numpy()

    def predict(
        self, video: np.ndarray, points: QueryPoints, query_mode: str
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tracks the query points of one video as the official evaluation does.

        Args:
            video: (T, 256, 256, 3) uint8 frames.
            points: queries (N, 3) (t, x, y) and their ground truth, in 256-frame units.
            query_mode: ``"first"`` or ``"strided"``.

        Returns:
            tracks (T, N, 2) in 256-frame units and visible (T, N) bool.
        """
        num_frames, count = video.shape[0], len(points.queries)
        if query_mode == "first":
            padding = official_padding(points.tracks[0], num_frames, self.num_queries)
            queries = np.concatenate([points.queries, _padded_queries(padding, None)])
            # real and padded points are all queried on a frame where they are visible
            tracks, visible = self._pass(video, queries, np.ones(len(queries), dtype=bool))
            return tracks[:, :count], visible[:, :count]
        tracks = np.zeros((num_frames, count, 2))
        visible = np.zeros((num_frames, count), dtype=bool)
        frames = query_frames(points.queries)
        for frame in np.unique(frames):
            group = np.flatnonzero(frames == frame)
            padding = official_padding(points.tracks[0, group], num_frames, self.num_queries)
            queries = np.concatenate([points.queries[group], _padded_queries(padding, frame)])
            start_visible = np.concatenate(
                [np.ones(len(group), dtype=bool), padding.start_frames <= frame]
            )
            track = functools.partial(self._pass, start_visible=start_visible)
            group_tracks, group_visible = track_both_ways(track, video, queries)
            tracks[:, group] = group_tracks[:, : len(group)]
            visible[:, group] = group_visible[:, : len(group)]
        return tracks, visible


def _padded_queries(padding: ContextPoints, frame: int | None) -> np.ndarray:
    """(K, 3) (t, x, y) queries of padded points: on ``frame``, or (None) their first visible."""
    times = padding.start_frames if frame is None else np.full(len(padding.positions), frame)
    return np.concatenate([times[:, None].astype(np.float64), padding.positions], axis=1)
