"""``taptr track VIDEO``: track points and write tracks.npz, tracks.csv and overlay.mp4."""

from __future__ import annotations

import argparse
import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from taptr.cli.common.model_options import (
    add_model_arguments,
    check_model_arguments,
    load_predictor,
)
from taptr.cli.common.options import (
    check_at_least,
    check_output_folder,
)
from taptr.cli.common.points import (
    add_query_arguments,
    build_queries,
    check_listed_points,
    listed_points,
)
from taptr.cli.common.result_settings import (
    SETTINGS_NAME,
    made_with,
    track_settings,
    write_settings,
)
from taptr.cli.common.run_memory import check_run_memory
from taptr.io.atomic import check_result_names
from taptr.io.frame_count import ACCEPT_TRUNCATED, check_decoded

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor
    from taptr.api.streaming import FinalFrames
    from taptr.io.video import VideoInfo

logger = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Registers the subcommand."""
    parser = subparsers.add_parser(
        "track",
        help="track points through a video",
        description="Tracks points given as (t, x, y) pixel queries (pixel centres at integers), "
        "a grid, or a region mask, and writes tracks.npz, tracks.csv and overlay.mp4 to --out "
        "(replacing an earlier run's files together, or not at all if interrupted). Frames are "
        "decoded, tracked, drawn and encoded as they go, so memory does not grow with the "
        "video (--backward reads the file twice, backwards first). Under torchrun, the videos "
        "are shared out among the processes (for large corpora, with retries and a Parquet "
        "dataset of results, see taptr track-corpus). One run tracks at most 100,000 points; the "
        "environment variable TAPTR_MAX_POINTS raises that.",
    )
    parser.add_argument(
        "video",
        nargs="+",
        help="video files (mp4, webm, avi, gif, ...), folders of images, folders of videos, "
        "or quoted glob patterns; several videos get one result folder each under --out, "
        "and videos whose folder already holds a finished run with the same settings are "
        "skipped (see --overwrite)",
    )
    add_query_arguments(parser, required=True)
    parser.add_argument(
        "--backward", action="store_true", help="also track before each query frame"
    )
    parser.add_argument("--trajectories", action="store_true", help="also write trajectories.png")
    parser.add_argument("--out", default="outputs", help="output folder (default: outputs)")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="track every video again, even those whose folder already holds a run with "
        "the same settings (recorded in its settings.json)",
    )
    parser.add_argument(
        ACCEPT_TRUNCATED,
        action="store_true",
        help="track a video that decodes to fewer frames than its container declares (cut "
        "short or damaged) through the frames that decode; by default it is an error",
    )
    add_model_arguments(parser, engines=True)
    parser.set_defaults(func=run)


OUTPUT_NAMES = ("tracks.npz", "tracks.csv", "overlay.mp4", "trajectories.png", SETTINGS_NAME)
"""Every file track writes to --out; a new run replaces them as a set."""


def check_track_arguments(args: argparse.Namespace) -> None:
    """Checks every option that can be checked without reading the video."""
    from taptr.task.query_checks import check_num_points

    check_output_folder(args.out)
    check_model_arguments(args)
    check_at_least(args.query_frame, 0, "--query-frame")
    check_at_least(args.mask_stride, 1, "--mask-stride")
    if args.grid is not None:
        check_at_least(args.grid, 1, "--grid")
        check_num_points(args.grid * args.grid, f"--grid {args.grid}")


def run(args: argparse.Namespace) -> int:
    """Tracks every video named and writes its outputs; prints one summary."""
    from taptr.cli.common.videos import expand_videos, is_complete, my_share, result_folders
    from taptr.process_group import gather_objects, join_process_group

    # Everything that can fail on the arguments fails here, before torch and the model load.
    check_track_arguments(args)
    listed = listed_points(args)
    videos = expand_videos(args.video)
    folders = result_folders(videos, Path(args.out))
    if len(videos) == 1:
        check_result_names(folders[0], OUTPUT_NAMES)
        info = {0: check_video(args, videos[0], listed)}
    predictor = load_predictor(args)
    settings = track_settings(args, predictor, listed)
    finished = {
        i for i in my_share(len(videos)) if len(videos) > 1 and is_complete(folders[i], FINISHED)
    }
    done = set() if args.overwrite else {i for i in finished if made_with(folders[i], settings)}
    mine = [i for i in my_share(len(videos)) if i not in done]
    joined = join_process_group(predictor.device.type == "cuda")
    outcomes: list[tuple[str, str, tuple[int, int] | None]] = [
        (str(videos[i]), "skipped: already done", None) for i in sorted(done)
    ]
    try:
        for index in mine:
            video, folder = videos[index], folders[index]
            if index in finished and not args.overwrite:
                print(f"{video}: {folder} was made with other settings; tracking it again")
            try:
                checked = info[index] if len(videos) == 1 else check_video(args, video, listed)
                counts = track_video(args, predictor, video, folder, listed, checked, settings)
            except (ValueError, FileNotFoundError) as error:
                if len(videos) == 1:
                    raise
                outcomes.append((str(video), f"failed: {error}", None))
                continue
            outcomes.append((str(video), "tracked", counts))
        everyone = [o for part in gather_objects(outcomes) for o in part]
    finally:
        if joined:
            import torch.distributed as dist

            dist.destroy_process_group()
    if int(os.environ.get("RANK", "0")) == 0 and len(videos) > 1:
        _print_summary(everyone, Path(args.out))
    return 0 if not any(status.startswith("failed") for _, status, _ in everyone) else 2


FINISHED = ("tracks.npz", "tracks.csv", "overlay.mp4", SETTINGS_NAME)
"""The files every finished run leaves (written together at its end)."""


def check_video(args: argparse.Namespace, video: Path, listed: np.ndarray | None) -> VideoInfo:
    """Reads a video's header and checks the queries and mask against it."""
    from taptr.api.regions import read_mask
    from taptr.io.video import video_info

    info = video_info(video)
    if listed is not None:
        flag = "--points" if args.points is not None else f"--points-file {args.points_file}"
        check_listed_points(listed, info, args.max_frames, flag)
    if args.mask is not None:
        read_mask(args.mask, name="--mask", size=(info.height, info.width))
    return info


def track_video(
    args: argparse.Namespace,
    predictor: Predictor,
    video: Path,
    out: Path,
    listed: np.ndarray | None,
    info: VideoInfo,
    settings: dict,
) -> tuple[int, int]:
    """Tracks one video into ``out`` with the run's ``settings``; returns (frames, points)."""
    from taptr.api.online import FrameCountError

    check_result_names(out, OUTPUT_NAMES)  # before tracking: a failed rerun mixes nothing
    declared = info.num_frames
    if declared is not None and args.max_frames is not None:
        declared = min(declared, args.max_frames)
    if declared is not None:
        queries = (
            listed if listed is not None else build_queries(args, declared, info.height, info.width)
        )
        try:
            return _track_streaming(
                args, predictor, (video, out), queries, info, declared, settings
            )
        except FrameCountError as error:  # the container's frame count was wrong
            if error.short:  # cut short: an error unless asked to keep what decodes
                check_decoded(
                    video, error.seen, info.num_frames, args.max_frames, args.accept_truncated
                )
            logger.warning("%s: %s; tracking it in memory instead", video, error)
    return _track_in_memory(args, predictor, (video, out), listed, info, settings)


def _track_streaming(
    args: argparse.Namespace,
    predictor: Predictor,
    paths: tuple[Path, Path],
    queries: np.ndarray,
    info: VideoInfo,
    num_frames: int,
    settings: dict,
) -> tuple[int, int]:
    """Decodes, tracks, draws and encodes frame by frame; holds about one window of frames.

    With ``--backward`` the file is read twice, backwards first (`taptr.io.reverse_frames`).
    ``paths`` is (video, result folder).
    """
    from tqdm.auto import tqdm

    from taptr.api.inputs import query_tensor
    from taptr.api.streaming import draw_final, track_frames, track_frames_both_ways
    from taptr.io.atomic import result_folder
    from taptr.io.reverse_frames import iter_frames_reversed
    from taptr.io.video import iter_frames, write_video

    video, out = paths
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    last_frame: list[np.ndarray] = [np.zeros(0, np.uint8)]
    # checked before the first frame is decoded, with the predictor's own messages
    queries = query_tensor(queries, 1, num_frames, info.height, info.width)[0].numpy()
    check_run_memory(
        args,
        predictor,
        num_frames=num_frames,
        num_points=len(queries),
        frame_size=(info.height, info.width),
        whole_video=False,
    )

    def read() -> Iterator[np.ndarray]:
        return iter_frames(video, max_frames=args.max_frames)

    def batches(bar: tqdm) -> Iterator[FinalFrames]:
        if not args.backward:
            return track_frames(predictor, read(), queries, num_frames=num_frames)
        return track_frames_both_ways(
            predictor,
            read,
            lambda: iter_frames_reversed(video, max_frames=args.max_frames),
            queries,
            num_frames=num_frames,
            on_reversed=bar.update,
        )

    def tracked():
        total = num_frames * (2 if args.backward else 1)
        with tqdm(total=total, desc="tracking", unit="frame") as bar:
            for batch in batches(bar):
                # tracks only, and a copy of the newest frame: a view would keep the
                # whole batch of frames alive
                kept.append((batch.tracks, batch.visibility))
                last_frame[0] = batch.frames[-1].copy()
                bar.update(len(batch.frames))
                yield batch

    with result_folder(out, OUTPUT_NAMES) as staging:
        overlay = draw_final(tracked(), queries, from_query_frames=not args.backward)
        write_video(staging / "overlay.mp4", overlay, info.fps or 24.0)
        tracks = np.concatenate([part[0] for part in kept])
        visibility = np.concatenate([part[1] for part in kept])
        _write_tracks(args, predictor, video, staging, tracks, visibility, queries, info)
        if args.trajectories:
            starts = None if args.backward else queries[:, 0].astype(np.int64)
            _write_trajectories(staging, last_frame[0], tracks, visibility, starts)
        write_settings(staging, settings)
    _print_done(out, len(queries), len(tracks), args.trajectories)
    return len(tracks), len(queries)


def _track_in_memory(
    args: argparse.Namespace,
    predictor: Predictor,
    paths: tuple[Path, Path],
    listed: np.ndarray | None,
    info: VideoInfo,
    settings: dict,
) -> tuple[int, int]:
    """Reads the whole video first (for unknown frame counts); ``paths``: (video, folder)."""
    from taptr.io.atomic import result_folder
    from taptr.io.video import read_video, write_video
    from taptr.viz.draw import draw_tracks, point_colors

    video, out = paths
    frames = read_video(video, max_frames=args.max_frames)
    check_decoded(video, len(frames), info.num_frames, args.max_frames, args.accept_truncated)
    queries = listed if listed is not None else build_queries(args, *frames.shape[:3])
    check_run_memory(
        args,
        predictor,
        num_frames=len(frames),
        num_points=len(queries),
        frame_size=frames.shape[1:3],
        whole_video=False,  # already read: the check is about what tracking adds
    )
    result = predictor.track(frames, queries, backward=args.backward, progress=True)
    tracks = result.tracks[0].numpy()
    visibility = result.visibility[0].numpy()
    query_frames = None if args.backward else queries[:, 0].astype(np.int64)
    with result_folder(out, OUTPUT_NAMES) as staging:
        _write_tracks(args, predictor, video, staging, tracks, visibility, queries, info)
        # coloured by where each point was given, as the streamed overlay is
        colors = point_colors(queries[:, 1:])
        overlay = draw_tracks(frames, tracks, visibility, query_frames=query_frames, colors=colors)
        write_video(staging / "overlay.mp4", overlay, info.fps or 24.0)
        if args.trajectories:
            _write_trajectories(staging, frames[-1], tracks, visibility, query_frames)
        write_settings(staging, settings)
    _print_done(out, len(queries), len(frames), args.trajectories)
    return len(frames), len(queries)


def _write_tracks(
    args: argparse.Namespace,
    predictor: Predictor,
    video: Path,
    staging: Path,
    tracks: np.ndarray,
    visibility: np.ndarray,
    queries: np.ndarray,
    info: VideoInfo,
) -> None:
    from taptr.io.tracks import save_tracks_csv, save_tracks_npz

    metadata = {
        "video": str(video),
        "num_frames": int(tracks.shape[0]),
        "height": int(info.height),
        "width": int(info.width),
        "fps": info.fps,
        "model": predictor.source,
        "input_size": list(predictor.input_size),
        "context_points": predictor.context_points,
        "backward": bool(args.backward),
        "coordinates": "(x, y) pixels, pixel centres at integers",
    }
    save_tracks_npz(staging / "tracks.npz", tracks, visibility, queries, metadata)
    save_tracks_csv(staging / "tracks.csv", tracks, visibility)
    logger.info("metadata: %s", json.dumps(metadata))


def _write_trajectories(
    staging: Path,
    frame: np.ndarray,
    tracks: np.ndarray,
    visibility: np.ndarray,
    query_frames: np.ndarray | None,
) -> None:
    from taptr.io.video import write_image
    from taptr.viz.draw import draw_trajectories

    starts = None if query_frames is None else np.asarray(query_frames).astype(np.int64)
    write_image(
        staging / "trajectories.png",
        draw_trajectories(frame, tracks, visibility, query_frames=starts),
    )


def _print_done(out: Path, points: int, frames: int, trajectories: bool) -> None:
    names = ["tracks.npz", "tracks.csv", "overlay.mp4", *["trajectories.png"] * trajectories]
    print(
        f"tracked {_count(points, 'point')} through {_count(frames, 'frame')}; wrote "
        f"{', '.join(str(out / name) for name in [*names, SETTINGS_NAME])}",
        flush=True,
    )


def _count(number: int, noun: str) -> str:
    """``1 frame``, ``2 frames``."""
    return f"{number} {noun}{'' if number == 1 else 's'}"


def _print_summary(outcomes: list, out: Path) -> None:
    tracked = sum(status == "tracked" for _, status, _ in outcomes)
    skipped = sum(status.startswith("skipped") for _, status, _ in outcomes)
    failed = [(video, status) for video, status, _ in outcomes if status.startswith("failed")]
    print(
        f"{len(outcomes)} videos: {tracked} tracked, {skipped} already done, {len(failed)} "
        f"failed; results in {out}/<video name>/ (--overwrite tracks finished ones again)"
    )
    for video, status in failed:
        print(f"  {video}: {status}")
