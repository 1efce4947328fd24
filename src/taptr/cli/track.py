"""``taptr track VIDEO``: track points and write tracks.npz, tracks.csv and overlay.mp4."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

logger = logging.getLogger(__name__)


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by the commands that run a model."""
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="checkpoint file or model name (default: the bundled taptr-small-synthetic model)",
    )
    parser.add_argument(
        "--device", default=None, help="cpu, cuda, cuda:1, mps (default: cuda if available)"
    )
    parser.add_argument(
        "--input-size",
        type=int,
        nargs=2,
        metavar=("HEIGHT", "WIDTH"),
        default=None,
        help="resolution the model sees (default: the model's, 512 512 for the paper model)",
    )
    parser.add_argument(
        "--max-frames", type=int, default=None, help="read at most this many frames"
    )


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "track",
        help="track points through a video",
        description="Tracks points given as (t, x, y) pixel queries (pixel centres at integers), "
        "a grid, or a region mask, and writes tracks.npz, tracks.csv and overlay.mp4 to --out.",
    )
    parser.add_argument("video", help="video file (mp4, webm, avi, gif, ...) or folder of images")
    queries = parser.add_mutually_exclusive_group(required=True)
    queries.add_argument("--points", help='queries "t,x,y;t,x,y;..." in pixels of the input video')
    queries.add_argument("--points-file", help="text/csv file with one t,x,y query per line")
    queries.add_argument("--grid", type=int, metavar="N", help="track an N×N grid on --query-frame")
    queries.add_argument(
        "--mask", help="track points sampled inside this mask (PNG, same size as the video)"
    )
    parser.add_argument(
        "--query-frame", type=int, default=0, help="frame of --grid and --mask (default 0)"
    )
    parser.add_argument("--mask-stride", type=int, default=8, help="pixel spacing of --mask points")
    parser.add_argument(
        "--backward", action="store_true", help="also track before each query frame"
    )
    parser.add_argument("--trajectories", action="store_true", help="also write trajectories.png")
    parser.add_argument("--out", default="outputs", help="output folder (default: outputs)")
    add_model_arguments(parser)
    parser.set_defaults(func=run)


def parse_points(text: str) -> np.ndarray:
    """``"t,x,y;t,x,y"`` → (N, 3) float32."""
    rows = [chunk for chunk in text.replace("\n", ";").split(";") if chunk.strip()]
    try:
        points = np.array(
            [[float(v) for v in row.replace(" ", ",").split(",") if v] for row in rows]
        )
    except ValueError:
        raise ValueError(f"cannot read points {text!r}: expected 't,x,y;t,x,y;...'") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be triples t,x,y; got {text!r}")
    return points.astype(np.float32)


def read_points_file(path: str) -> np.ndarray:
    """Queries from a file with one ``t,x,y`` per line (``#`` comments and a header allowed)."""
    file = Path(path)
    if not file.is_file():
        raise FileNotFoundError(f"points file not found: {file}")
    lines = [ln.split("#", 1)[0].strip() for ln in file.read_text().splitlines()]
    lines = [ln for ln in lines if ln and not ln[0].isalpha()]
    if not lines:
        raise ValueError(f"{file} holds no t,x,y lines")
    return parse_points(";".join(lines))


def build_queries(args: argparse.Namespace, video: np.ndarray) -> np.ndarray:
    """The (N, 3) queries the arguments ask for."""
    from taptr.api.inputs import grid_queries
    from taptr.editing import read_mask, sample_region_queries

    num_frames, height, width = video.shape[:3]
    if args.points is not None:
        return parse_points(args.points)
    if args.points_file is not None:
        return read_points_file(args.points_file)
    if not 0 <= args.query_frame < num_frames:
        raise ValueError(f"--query-frame {args.query_frame} outside [0, {num_frames})")
    if args.grid is not None:
        return grid_queries(args.grid, args.query_frame, height, width).numpy()
    mask = read_mask(args.mask)
    if mask.shape != (height, width):
        raise ValueError(
            f"mask {args.mask} is {mask.shape[1]}x{mask.shape[0]}, the video is {width}x{height}"
        )
    return sample_region_queries(mask, args.query_frame, stride=args.mask_stride)


def load_predictor(args: argparse.Namespace) -> Predictor:
    """The predictor the model arguments describe."""
    from taptr.api.predictor import Predictor

    size = tuple(args.input_size) if args.input_size else None
    return Predictor.from_pretrained(args.checkpoint, device=args.device, input_size=size)


def run(args: argparse.Namespace) -> int:
    """Tracks and writes the three outputs."""
    from taptr.viz.draw import draw_tracks, draw_trajectories
    from taptr.viz.export import save_tracks_csv, save_tracks_npz
    from taptr.viz.video_io import read_video, video_info, write_video

    info = video_info(args.video)
    video = read_video(args.video, max_frames=args.max_frames)
    queries = build_queries(args, video)
    predictor = load_predictor(args)
    result = predictor.track(video, queries, backward=args.backward, progress=True)
    tracks = result.tracks[0].numpy()
    visibility = result.visibility[0].numpy()
    out = Path(args.out)
    metadata = {
        "video": str(args.video),
        "num_frames": int(video.shape[0]),
        "height": int(video.shape[1]),
        "width": int(video.shape[2]),
        "fps": info.fps,
        "model": args.checkpoint or "taptr-small-synthetic",
        "input_size": list(predictor.input_size),
        "backward": bool(args.backward),
        "coordinates": "(x, y) pixels, pixel centres at integers",
    }
    save_tracks_npz(out / "tracks.npz", tracks, visibility, queries, metadata)
    save_tracks_csv(out / "tracks.csv", tracks, visibility)
    query_frames = None if args.backward else queries[:, 0].astype(np.int64)
    overlay = draw_tracks(video, tracks, visibility, query_frames=query_frames)
    write_video(out / "overlay.mp4", overlay, info.fps or 24.0)
    if args.trajectories:
        from taptr.viz.video_io import write_image

        write_image(
            out / "trajectories.png",
            draw_trajectories(video[-1], tracks, visibility, query_frames=query_frames),
        )
    print(
        f"tracked {len(queries)} points through {video.shape[0]} frames; wrote "
        f"{out / 'tracks.npz'}, {out / 'tracks.csv'}, {out / 'overlay.mp4'}"
    )
    logger.info("metadata: %s", json.dumps(metadata))
    return 0
