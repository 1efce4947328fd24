"""The evaluation sets by name: the four TAP-Vid sets and the Kubric layout.

``kubric`` reads any folder of sequences in the Kubric MOVi-F layout of CoTracker
(`taptr.data.kubric`), which is also the layout of taptr's synthetic data.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator

from taptr.data.tapvid import TAPVID_DATASETS, PendingVideo, iter_tapvid

DATASETS = (*TAPVID_DATASETS, "kubric")


def iter_kubric(root: str | os.PathLike[str]) -> Iterator[PendingVideo]:
    """The sequences of a Kubric-layout folder, in numeric order, loaded one at a time."""
    from taptr.data.kubric import list_sequences, read_sequence

    folders = list_sequences(root)
    return (PendingVideo(f.name, functools.partial(read_sequence, f)) for f in folders)


def open_dataset(dataset: str, root: str | os.PathLike[str]) -> Iterator[PendingVideo]:
    """The videos of an evaluation set, not yet loaded.

    Args:
        dataset: one of `DATASETS`.
        root: the dataset file or folder (see `taptr.data.tapvid.find_tapvid_files`), or
            for ``kubric`` the folder holding the sequence folders.

    Raises:
        ValueError: unknown dataset name.
        FileNotFoundError: nothing to read at ``root``.
    """
    if dataset == "kubric":
        return iter_kubric(root)
    if dataset in TAPVID_DATASETS:
        return iter_tapvid(dataset, root)
    raise ValueError(f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")
