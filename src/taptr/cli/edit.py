"""``taptr edit VIDEO``: paste an image onto a tracked region (the paper's video editing)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from taptr.cli.common.model_options import (
    add_model_arguments,
    check_model_arguments,
    load_predictor,
)
from taptr.cli.common.options import check_at_least, check_output_file
from taptr.cli.common.run_memory import check_run_memory

if TYPE_CHECKING:
    from collections.abc import Iterator

    import numpy as np

    from taptr.api.predictor import Predictor
    from taptr.io.video import VideoInfo

logger = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "edit",
        help="track a painted region and paste an image onto it in every frame",
        description="Samples points densely inside --mask on --query-frame, tracks them forwards "
        "and backwards, fits the region's motion per frame (RANSAC, outliers dropped) and warps "
        "--overlay onto it, hidden where the region is occluded. The video is decoded, tracked, "
        "edited and encoded frame by frame (memory flat in its length); with a later "
        "--query-frame the file is first read backwards to track the frames before it.",
    )
    parser.add_argument("video", help="video file or folder of images")
    parser.add_argument(
        "--mask",
        required=True,
        help="mask of the region on --query-frame (an image of the video's size; inside = "
        "pixels neither black nor transparent)",
    )
    parser.add_argument(
        "--overlay", required=True, help="image (RGB or RGBA) to paste on the region"
    )
    parser.add_argument(
        "--query-frame", type=int, default=0, help="frame the mask was drawn on (default 0)"
    )
    parser.add_argument(
        "--stride", type=int, default=6, help="pixel spacing of the tracked points (default 6)"
    )
    parser.add_argument(
        "--opacity", type=float, default=1.0, help="overlay opacity in [0, 1] (default 1)"
    )
    parser.add_argument("--out", default="edited.mp4", help="output mp4 (default: edited.mp4)")
    add_model_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Tracks the region and writes the edited video."""
    from taptr.apps.editing import overlay_region
    from taptr.io.video import read_video, write_video

    info, mask, overlay, queries = _checked_inputs(args)
    predictor = load_predictor(args)
    from taptr.api.online import FrameCountError  # imports torch: after every cheap check

    if info.num_frames is not None:
        check_run_memory(
            args,
            predictor,
            num_frames=min(info.num_frames, args.max_frames or info.num_frames),
            num_points=len(queries),
            frame_size=(info.height, info.width),
            whole_video=False,
        )
        # frame by frame; frames before a later query frame come from a backward read
        try:
            edited = _edited_frames(args, predictor, queries, mask, overlay, info.num_frames)
            path = write_video(args.out, edited, info.fps or 24.0)
            print(f"tracked {len(queries)} region point{_s(len(queries))}; wrote {path}")
            return 0
        except FrameCountError as error:  # the container's frame count was wrong
            logger.warning("%s: %s; editing it in memory instead", args.video, error)
    video = read_video(args.video, max_frames=args.max_frames)
    num_frames = video.shape[0]
    if not args.query_frame < num_frames:
        raise ValueError(f"--query-frame {args.query_frame} outside [0, {num_frames})")
    result = predictor.track(video, queries, backward=True, progress=True)
    edited = overlay_region(
        video,
        overlay,
        mask,
        result.tracks[0].numpy(),
        result.visibility[0].numpy(),
        args.query_frame,
        opacity=args.opacity,
    )
    path = write_video(args.out, edited, info.fps or 24.0)
    print(f"tracked {len(queries)} region point{_s(len(queries))}; wrote {path}")
    return 0


def _checked_inputs(
    args: argparse.Namespace,
) -> tuple[VideoInfo, np.ndarray, np.ndarray, np.ndarray]:
    """Checks every argument and input file, before torch and the model load.

    Returns:
        The video's header, the region mask, the overlay image and the region's queries.
    """
    from taptr.api.regions import read_mask, sample_region_queries
    from taptr.io.video import read_video, video_info
    from taptr.task.query_checks import check_num_points

    check_output_file(args.out, suffixes=(".mp4",))
    check_model_arguments(args)
    check_at_least(args.query_frame, 0, "--query-frame")
    check_at_least(args.stride, 1, "--stride")
    if not 0 <= args.opacity <= 1:
        raise ValueError(f"--opacity must lie in [0, 1], got {args.opacity}")
    info = video_info(args.video)
    mask = read_mask(args.mask, name="--mask", size=(info.height, info.width))
    overlay = (
        read_video(args.overlay, max_frames=1)[0]
        if Path(args.overlay).is_dir()
        else _read_overlay(args.overlay)
    )
    queries = sample_region_queries(mask, args.query_frame, stride=args.stride)
    check_num_points(len(queries), f"--mask {args.mask} with --stride {args.stride}")
    if info.num_frames is not None:
        declared = min(info.num_frames, args.max_frames or info.num_frames)
        if not args.query_frame < declared:
            raise ValueError(f"--query-frame {args.query_frame} outside [0, {declared})")
    return info, mask, overlay, queries


def _edited_frames(
    args: argparse.Namespace,
    predictor: Predictor,
    queries: np.ndarray,
    mask: np.ndarray,
    overlay: np.ndarray,
    declared: int,
) -> Iterator[np.ndarray]:
    """Edited frames, decoded, tracked and edited one window at a time (memory flat in T).

    Points given on a later frame are tracked backwards first, on a second, reversed read
    of the file (`taptr.api.streaming.track_frames_both_ways`).
    """
    from tqdm.auto import tqdm

    from taptr.api.streaming import track_frames_both_ways
    from taptr.apps.editing import apply_overlay, prepare_overlay
    from taptr.io.reverse_frames import iter_frames_reversed
    from taptr.io.video import iter_frames

    num_frames = min(declared, args.max_frames or declared)
    prepared = prepare_overlay(overlay, mask, queries[:, 1:])
    passes = 2 if queries[:, 0].max() > 0 else 1
    with tqdm(total=passes * num_frames, desc="editing", unit="frame") as bar:
        batches = track_frames_both_ways(
            predictor,
            lambda: iter_frames(args.video, max_frames=args.max_frames),
            lambda: iter_frames_reversed(args.video, max_frames=args.max_frames),
            queries,
            num_frames=num_frames,
            on_reversed=bar.update,
        )
        for batch in batches:
            for frame, positions, visible in zip(
                batch.frames, batch.tracks, batch.visibility, strict=True
            ):
                yield apply_overlay(frame, prepared, positions, visible, opacity=args.opacity)[0]
            bar.update(len(batch.frames))


def _read_overlay(path: str) -> np.ndarray:
    import numpy as np

    from taptr.io.file_kind import kind, require_file
    from taptr.io.image_guard import read_image_channels

    if kind(path, "--overlay") is None:
        raise FileNotFoundError(f"--overlay {path}: file not found")
    require_file(path, "--overlay")  # a FIFO would block, a device never end
    image = read_image_channels(path, f"--overlay {path}")  # header checked before decoding
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
        raise ValueError(f"--overlay {path}: not an RGB or RGBA image with 8 bits a channel")
    return image


def _s(count: int) -> str:
    """The plural ending of a count: "1 point", "2 points"."""
    return "" if count == 1 else "s"
