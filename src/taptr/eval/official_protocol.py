"""TAPTR models run exactly as the authors' evaluations run them.

This reproduces the papers' numbers with the released checkpoints; it is a protocol for
those models, not a way to use them (`taptr.Predictor` is). Per video, on 256 × 256 frames
whose coordinates are TAP-Vid's normalised values × 255.

TAPTRv2 and TAPTR v1 (TAPTRv2-SPEC.md §4):

- frames are upsampled to the model's input size (512 × 512 for the released model),
  bilinear without antialiasing, and ImageNet-normalised;
- the query set is padded to 800 points with the official seed-0 recipe (`official_padding`),
  because points attend to each other and the padding changes the real points' outputs;
- ``first``: one pass over all queries; ``strided``: each query frame's points are padded
  separately and run forward and on the reversed video, fused at the query frame;
- a point is visible where sigmoid(visibility logit 1) > 0.5.

TAPTRv3 (TAPTRv3-DELTA.md §5, ``evaluate.sh`` with ``--streaming``):

- frames are resized to the model's input size (384 × 512 for ResNet-18) by torchvision's
  default bilinear resize, antialiased;
- 63 local support points around each real point and 36 grid points
  (`taptr.task.support_schemes`), the grid points' start frames drawn from numpy's
  generator seeded once with 42, one draw per video in dataset order (video k gets the
  (k + 1)-th draw); every point normalised with the official float32 steps (`official_normalised`);
- ``first`` only: the official v3 code runs ``strided`` through another path that fails
  with ``--streaming``; here ``strided`` pads each query frame's points the same way, with
  the video's draws continuing, as a convenience, not an official recipe;
- a point is visible where sigmoid(visibility logit 1) > 0.45 (the model config's
  threshold).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F

from taptr.api import TAPTR, normalize_frames
from taptr.api.context_points import PREFIX_FRAMES, ContextPoints, draw_context
from taptr.eval.query_sampling import QueryPoints
from taptr.eval.trackers import query_frames, track_both_ways
from taptr.geometry import normalized_to_pixels, pixels_to_normalized
from taptr.model.v3.taptr import TAPTRv3
from taptr.official.model_forward import official_forward
from taptr.task.support_schemes import (
    GRID_SEED,
    SupportPattern,
    grid_start_frames,
    support_scheme,
)

NUM_QUERIES = 800
"""Points per pass after padding (the official ``num_queries_per_video_eval``)."""

EVAL_FRAME = (256, 256)
"""(H, W) of the frames the evaluation pads in: padded points lie in [16, 239]."""


def official_padding(
    frame0_positions: np.ndarray, num_frames: int, num_queries: int = NUM_QUERIES
) -> ContextPoints:
    """The evaluation's padding of n real points to ``num_queries`` (TAPTRv2-SPEC.md §4.2).

    `taptr.api.context_points.draw_context` on the 256 × 256 frame with start frames drawn from
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


def support_points_256(queries: np.ndarray, draws: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TAPTRv3's 'local_and_grid' support of real queries, in 256 × 256 pixels.

    The registry's scheme (`taptr.task.support_schemes`) on the evaluation's pixels, in
    float64 as the official code adds them.

    Args:
        queries: (n, 3) real (t, x, y), each on its first visible frame.
        draws: (36,) the grid points' start frames (this video's draw).

    Returns:
        (n + 63·n + 36, 3) (t, x, y) in float64: the real points, 63 local points per real
        point (its query position plus the offsets, from its query frame), the grid
        points; and (K,) their kind: 0 real, 1 local, 2 grid.
    """
    starts = np.rint(queries[:, 0]).astype(np.int64)
    pattern = SupportPattern.pixels_256(draws)
    support = support_scheme("local_and_grid").points(starts, queries[:, 1:], pattern)
    added = np.c_[support.start_frames.astype(np.float64), support.positions]
    points = np.concatenate([queries, added])
    kind = np.concatenate([np.zeros(len(queries), np.int64), np.where(support.parents >= 0, 1, 2)])
    return points, kind


def official_normalised(xy_256: np.ndarray, input_size: tuple[int, int]) -> torch.Tensor:
    """(K, 2) 256-pixel (x, y) → the model's normalised float32 values, as TAPTRv3's code.

    Its transforms scale by float32((W − 1) / 255), (H − 1) / 255 to the model input's
    pixels, then divide by (W − 1, H − 1), each step in float32: within 1e-7 of x / 255.
    """
    height, width = input_size
    spans = np.array([width - 1, height - 1], dtype=np.float32)
    scaled = xy_256.astype(np.float32) * (spans / np.float32(255)).astype(np.float32)
    return torch.from_numpy((scaled / spans).astype(np.float32))


def grid_draws(index: int, count: int = 1) -> list[np.ndarray]:
    """The grid start frames of video ``index``'s first ``count`` paddings.

    The official evaluation seeds numpy's global generator with 42 once and each video's
    padding draws from it in turn: video k's first draw is the (k + 1)-th.
    """
    rng = np.random.RandomState(GRID_SEED)
    draws = [grid_start_frames(rng) for _ in range(index + count)]
    return draws[index:]


class OfficialTAPTR:
    """A TAPTR model evaluated with the official recipe.

    Args:
        model: the network; its config's ``input_size`` is the resolution frames are
            resized to (512 × 512 for TAPTRv2, 384 × 512 for TAPTRv3-R18).
        device: where to run it.
        num_queries: points per pass after padding (800 in the official TAPTRv2 protocol;
            TAPTRv3 adds support points instead).
    """

    def __init__(
        self, model: TAPTR, *, device: str | torch.device = "cpu", num_queries: int = NUM_QUERIES
    ) -> None:
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        height, width = model.config.input_size if model.config else (512, 512)
        self.input_size = (height, width)
        self.num_queries = num_queries
        self.threshold = model.config.visibility_threshold if model.config else 0.5
        self.per_frame = isinstance(model, TAPTRv3)

    def model_input(self, video: np.ndarray) -> torch.Tensor:
        """(T, 256, 256, 3) uint8 → the (1, T, 3, H_m, W_m) ImageNet-normalised model input."""
        frames = torch.from_numpy(np.ascontiguousarray(video)).to(self.device)
        frames = frames.permute(0, 3, 1, 2).float() / 255  # (T, 3, H, W)
        if tuple(frames.shape[-2:]) != self.input_size:
            # torchvision's tensor resize as each official evaluation calls it: bilinear,
            # align_corners=False; TAPTRv3's torchvision antialiases (its default since 0.17)
            frames = F.interpolate(
                frames, size=self.input_size, mode="bilinear", antialias=self.per_frame
            )
        return normalize_frames(frames)[None]

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
        if self.per_frame:
            query_xy = official_normalised(queries[:, 1:], self.input_size)
        else:
            query_xy = pixels_to_normalized(
                torch.as_tensor(queries[:, 1:], dtype=torch.float32), height, width
            )
        output = official_forward(
            self.model,
            self.model_input(video),
            torch.as_tensor(query_frames(queries)),
            query_xy.to(self.device),
            torch.as_tensor(np.where(start_visible, 1, 2)).to(self.device),
        )
        tracks = normalized_to_pixels(output["positions"].float(), height, width)
        visible = output["visibility_logits"][..., 1].float().sigmoid() > self.threshold
        return tracks.cpu().numpy(), visible.cpu().numpy()

    def predict(
        self, video: np.ndarray, points: QueryPoints, query_mode: str, index: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tracks the query points of one video as the official evaluation does.

        Args:
            video: (T, 256, 256, 3) uint8 frames.
            points: queries (N, 3) (t, x, y) and their ground truth, in 256-frame units.
            query_mode: ``"first"`` or ``"strided"``.
            index: the video's position in the dataset (TAPTRv3's grid draws follow it).

        Returns:
            tracks (T, N, 2) in 256-frame units and visible (T, N) bool.
        """
        if self.per_frame:
            return self._predict_v3(video, points, query_mode, index)
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

    def _predict_v3(
        self, video: np.ndarray, points: QueryPoints, query_mode: str, index: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """TAPTRv3: support points, one forward pass per padding (see the module docstring)."""
        count = len(points.queries)
        frames = query_frames(points.queries)
        groups = (
            [np.arange(count)]
            if query_mode == "first"
            else [np.flatnonzero(frames == frame) for frame in np.unique(frames)]
        )
        tracks = np.zeros((video.shape[0], count, 2))
        visible = np.zeros((video.shape[0], count), dtype=bool)
        for group, draws in zip(groups, grid_draws(index, len(groups)), strict=True):
            queries, kind = support_points_256(points.queries[group], draws)
            start_visible = np.ones(len(queries), dtype=bool)
            if query_mode == "first":
                group_tracks, group_visible = self._pass(video, queries, start_visible)
            else:
                queries[kind < 2, 0] = frames[group[0]]  # real and local points
                track = functools.partial(self._pass, start_visible=start_visible)
                group_tracks, group_visible = track_both_ways(track, video, queries)
            tracks[:, group] = group_tracks[:, : len(group)]
            visible[:, group] = group_visible[:, : len(group)]
        return tracks, visible


def _padded_queries(padding: ContextPoints, frame: int | None) -> np.ndarray:
    """(K, 3) (t, x, y) queries of padded points: on ``frame``, or (None) their first visible."""
    times = padding.start_frames if frame is None else np.full(len(padding.positions), frame)
    return np.concatenate([times[:, None].astype(np.float64), padding.positions], axis=1)
