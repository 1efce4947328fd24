"""Checking a dataset folder in the Kubric layout before training or evaluating on it.

Every sequence is read with the same reader that training and evaluation use
(`taptr.data.kubric.read_sequence`), so a folder that passes here loads there. Beyond what
the reader refuses (missing or unreadable frames, a missing or malformed ``.npy``, a
``.npy`` header or frame header declaring more than the file holds or the limits of
`taptr.io.limits` allow, frames of different sizes, coordinate arrays of the wrong shape or
with non-finite values; each a one-line finding), the check warns about data that
loads but is probably wrong:

- coordinates that all lie in [0, 1]: normalised, where the layout wants pixels;
- most points flagged occluded: the ``visibility`` key must hold *occlusion* flags (True =
  occluded, CoTracker's convention); visibility flags stored there read inverted;
- tracks that are never visible, sequences without tracks or shorter than a window;
- folders without ``frames/``, which the reader skips.

Findings are plain data; the ``taptr check-data`` command prints them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from taptr.data.kubric import FRAMES_DIR, list_sequences, read_sequence

MIN_VISIBLE_FRACTION = 0.5
"""Below this fraction of visible (point, frame) pairs, the occlusion flags look inverted."""


@dataclass(frozen=True)
class Finding:
    """One problem found.

    Attributes:
        level: ``"error"`` (the sequence cannot be used) or ``"warning"`` (it loads, but
            something looks wrong).
        where: the sequence folder (or the root).
        message: what is wrong, in one line.
    """

    level: str
    where: str
    message: str


@dataclass
class SequenceStats:
    """Numbers of one readable sequence.

    Attributes:
        num_frames: T.
        size: (H, W) of the frames.
        num_points: N tracks.
        visible_fraction: fraction of the (T, N) entries that are visible.
    """

    num_frames: int
    size: tuple[int, int]
    num_points: int
    visible_fraction: float


@dataclass
class DataReport:
    """The outcome of `check_kubric_folder`.

    Attributes:
        root: the folder checked.
        num_sequences: sequence folders found (all of them, even beyond ``max_sequences``).
        stats: numbers of each readable sequence that was checked, by folder name.
        findings: errors and warnings, in folder order.
    """

    root: Path
    num_sequences: int = 0
    stats: dict[str, SequenceStats] = field(default_factory=dict)
    findings: list[Finding] = field(default_factory=list)

    @property
    def errors(self) -> list[Finding]:
        """The findings that make a sequence unusable."""
        return [f for f in self.findings if f.level == "error"]

    @property
    def warnings(self) -> list[Finding]:
        """The findings about data that loads but looks wrong."""
        return [f for f in self.findings if f.level == "warning"]

    def summary(self) -> list[str]:
        """A few lines describing the checked data."""
        lines = [f"{self.root}: {self.num_sequences} sequences, {len(self.stats)} readable"]
        if self.stats:
            values = list(self.stats.values())
            frames = [s.num_frames for s in values]
            points = [s.num_points for s in values]
            sizes = sorted({f"{s.size[1]}x{s.size[0]}" for s in values})
            visible = np.mean([s.visible_fraction for s in values])
            lines += [
                f"  frames per sequence: {min(frames)} to {max(frames)}",
                f"  tracks per sequence: {min(points)} to {max(points)}",
                f"  frame sizes (WxH): {', '.join(sizes[:5])}{' ...' if len(sizes) > 5 else ''}",
                f"  visible: {100 * visible:.1f}% of point-frames",
            ]
        return lines


def check_sequence(
    folder: Path, *, min_frames: int = 8
) -> tuple[SequenceStats | None, list[Finding]]:
    """Reads and checks one sequence folder.

    Args:
        folder: ``<root>/<seq>`` with ``frames/`` and ``<seq>.npy``.
        min_frames: fewer frames than this is a warning (a window spans 8 frames).

    Returns:
        The sequence's numbers (None when it cannot be read) and its findings.
    """
    where = str(folder)
    try:
        sample = read_sequence(folder)
    except (FileNotFoundError, ValueError, OSError) as error:
        return None, [Finding("error", where, str(error))]
    num_frames, num_points = sample.tracks.shape[:2]
    height, width = sample.video.shape[1:3]
    visible_fraction = float(sample.visible.mean()) if sample.visible.size else 0.0
    stats = SequenceStats(num_frames, (height, width), num_points, visible_fraction)
    findings = []

    def warn(message: str) -> None:
        findings.append(Finding("warning", where, message))

    if num_points == 0:
        return stats, [Finding("error", where, "no tracks (coords has N = 0)")]
    if num_frames < min_frames:
        warn(f"{num_frames} frames, fewer than {min_frames}")
    if max(width, height) > 2 and np.abs(sample.tracks).max() <= 1.0:
        warn("every coordinate lies in [0, 1]: coords must be pixels, not normalised values")
    never = int((~sample.visible.any(axis=0)).sum())
    if never == num_points:
        warn("no track is ever visible (inside the frame and not occluded)")
    elif never:
        warn(f"{never} of {num_points} tracks are never visible")
    if never < num_points and visible_fraction < MIN_VISIBLE_FRACTION:
        warn(
            f"only {100 * visible_fraction:.0f}% of point-frames are visible: the 'visibility' "
            "key must hold OCCLUSION flags (True = occluded); were visibility flags stored?"
        )
    return stats, findings


def check_kubric_folder(
    root: str | os.PathLike[str],
    *,
    max_sequences: int | None = None,
    min_frames: int = 8,
    progress: bool = False,
) -> DataReport:
    """Checks every sequence folder of a Kubric-layout dataset.

    Args:
        root: the folder holding ``<seq>/frames/*.png`` and ``<seq>/<seq>.npy``.
        max_sequences: check only the first sequences (numeric order).
        min_frames: sequences shorter than this get a warning.
        progress: show a progress bar (stderr).

    Raises:
        FileNotFoundError: ``root`` does not exist.
        ValueError: ``root`` holds no sequence folder (the message suggests a split folder
            when ``root`` is one level too high).
    """
    root = Path(root)
    folders = list_sequences(root)
    report = DataReport(root, num_sequences=len(folders))
    skipped = sorted(p.name for p in root.iterdir() if p.is_dir() and not (p / FRAMES_DIR).is_dir())
    if skipped:
        shown = ", ".join(skipped[:5]) + (" ..." if len(skipped) > 5 else "")
        report.findings.append(
            Finding(
                "warning",
                str(root),
                f"{len(skipped)} folders without {FRAMES_DIR}/ are ignored: {shown}",
            )
        )
    chosen = folders[:max_sequences] if max_sequences is not None else folders
    for folder in tqdm(chosen, desc="sequences", unit="seq", disable=not progress):
        stats, findings = check_sequence(folder, min_frames=min_frames)
        if stats is not None:
            report.stats[folder.name] = stats
        report.findings += findings
    return report
