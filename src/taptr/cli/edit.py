"""``taptr edit VIDEO``: paste an image onto a tracked region (the paper's video editing)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from taptr.cli.track import add_model_arguments, load_predictor

if TYPE_CHECKING:
    import numpy as np


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "edit",
        help="track a painted region and paste an image onto it in every frame",
        description="Samples points densely inside --mask on --query-frame, tracks them forwards "
        "and backwards, fits the region's motion per frame (RANSAC, outliers dropped) and warps "
        "--overlay onto it, hidden where the region is occluded.",
    )
    parser.add_argument("video", help="video file or folder of images")
    parser.add_argument("--mask", required=True, help="PNG mask of the region on --query-frame")
    parser.add_argument(
        "--overlay", required=True, help="image (RGB or RGBA) to paste on the region"
    )
    parser.add_argument("--query-frame", type=int, default=0, help="frame the mask was drawn on")
    parser.add_argument("--stride", type=int, default=6, help="pixel spacing of the tracked points")
    parser.add_argument("--opacity", type=float, default=1.0, help="overlay opacity in [0, 1]")
    parser.add_argument("--out", default="edited.mp4", help="output mp4 (default: edited.mp4)")
    add_model_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Tracks the region and writes the edited video."""
    from taptr.editing import overlay_region, read_mask, sample_region_queries
    from taptr.viz.video_io import read_video, video_info, write_video

    info = video_info(args.video)
    video = read_video(args.video, max_frames=args.max_frames)
    num_frames, height, width = video.shape[:3]
    if not 0 <= args.query_frame < num_frames:
        raise ValueError(f"--query-frame {args.query_frame} outside [0, {num_frames})")
    mask = read_mask(args.mask)
    if mask.shape != (height, width):
        raise ValueError(
            f"mask {args.mask} is {mask.shape[1]}x{mask.shape[0]}, the video is {width}x{height}"
        )
    overlay = (
        read_video(args.overlay)[0] if Path(args.overlay).is_dir() else _read_overlay(args.overlay)
    )
    queries = sample_region_queries(mask, args.query_frame, stride=args.stride)
    result = load_predictor(args).track(video, queries, backward=True, progress=True)
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
    print(f"tracked {len(queries)} region points; wrote {path}")
    return 0


def _read_overlay(path: str) -> np.ndarray:
    import cv2

    if not Path(path).is_file():
        raise FileNotFoundError(f"overlay image not found: {path}")
    image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"cannot read {path} as an RGB or RGBA image")
    code = cv2.COLOR_BGRA2RGBA if image.shape[2] == 4 else cv2.COLOR_BGR2RGB
    return cv2.cvtColor(image, code)
