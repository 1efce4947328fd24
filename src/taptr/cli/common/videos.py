"""Many videos in one ``taptr track``: expanding the list, one folder each, resuming, sharding.

``taptr track a.mp4 clips/ "more/*.webm" --out results/`` tracks every video named, found in
a folder, or matched by a glob; each gets its own result folder ``results/<name>/``. A folder
that already holds a complete result (all of its files, written together at the end of a
run) made with the same settings (`taptr.cli.common.result_settings`) is skipped, so a crashed run
resumes where it stopped. Under ``torchrun`` each process takes every ``WORLD_SIZE``-th
video, and the first process prints one summary.
"""

from __future__ import annotations

import glob
import os
from pathlib import Path

from taptr.io.video import IMAGE_SUFFIXES, VIDEO_SUFFIXES

_GLOB_CHARACTERS = set("*?[")


def expand_videos(items: list[str]) -> list[Path]:
    """The videos that command-line items name, in order, without duplicates.

    Args:
        items: video files, image folders (one video), folders of video files, or glob
            patterns (quoted, so that taptr expands them).

    Raises:
        FileNotFoundError: an item names nothing, or a pattern matches no video (checked
            for every item before any video is tracked).
    """
    videos: list[Path] = []
    for item in items:
        if _GLOB_CHARACTERS & set(item):
            matched = [Path(p) for p in sorted(glob.glob(item)) if _is_video(Path(p))]
            if not matched:
                raise FileNotFoundError(f"no video matches {item!r}")
            videos += matched
        elif Path(item).is_dir() and not _is_image_folder(Path(item)):
            found = sorted(p for p in Path(item).iterdir() if _is_video(p))
            if not found:
                raise FileNotFoundError(f"{item} holds no video files or image frames")
            videos += found
        elif Path(item).exists():
            videos.append(Path(item))  # a file or an image folder; read errors come later
        else:  # a typo: said now, not after the model has loaded
            raise FileNotFoundError(f"video not found: {item}")
    return list(dict.fromkeys(videos))


def result_folders(videos: list[Path], out: Path) -> list[Path]:
    """One folder per video: ``out`` itself for a single video, else ``out/<name>``.

    Videos that share a name get the folder of their parent too (``out/<parent>-<name>``).
    """
    if len(videos) == 1:
        return [out]
    names = [
        video.stem if video.suffix.lower() in VIDEO_SUFFIXES else video.name for video in videos
    ]
    counts = {name: names.count(name) for name in names}
    return [
        out / (name if counts[name] == 1 else f"{video.parent.name}-{name}")
        for video, name in zip(videos, names, strict=True)
    ]


def is_complete(folder: Path, names: tuple[str, ...]) -> bool:
    """Whether ``folder`` holds every file of a finished run."""
    return all((folder / name).is_file() for name in names)


def my_share(count: int) -> list[int]:
    """Indices of the videos this process tracks: every ``WORLD_SIZE``-th from its ``RANK``."""
    rank = int(os.environ.get("RANK", "0"))
    world = int(os.environ.get("WORLD_SIZE", "1"))
    return list(range(rank, count, world))


def _is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def _is_image_folder(path: Path) -> bool:
    return any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir())
