"""Progress lines for long corpus jobs and the summary at the end.

One plain line every ``every`` seconds (logs of a job that runs for days stay readable):
videos done or failed out of those to do, failures, frames per second, and the time
left. A video counts once its part is published (committed), as in the summary: one
tracked but not yet written, or tracked by a worker that then died, does not count, so
the count never passes the videos to do and never runs ahead of OUT. The rate and the
estimate count from the moment the first actor was ready, so that model loading does not
make the first estimate long. The last line is printed from the summary's own numbers.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from taptr.corpus.records import DONE, Finished
from taptr.messages import printable

MAX_LISTED_FAILURES = 20
"""Failed videos named in the summary (all are in OUT/failures)."""


@dataclass
class Summary:
    """What a corpus run did.

    Attributes:
        total: videos in the corpus.
        run: the run's id (the parts it wrote carry it).
        state: ``running``, ``finished``, ``interrupted`` (Ctrl-C, SIGTERM) or ``failed``.
        done: videos tracked and written now; skipped: done by earlier runs with the same
            settings; failed: recorded as failed now; failed_before: recorded as failed by
            earlier runs with the same settings, and left alone.
        left: videos this run did not finish (stopped or failed): the next run tracks them.
        retried: videos done now after more than one tracking attempt (a worker died).
        frames: frames of the videos done now.
        seconds: the run's wall time; tracking_seconds: from the first actor ready to the
            last result (the rates' time).
        actor_seconds: time actors spent on the videos done, added over actors.
        failures: the first `MAX_LISTED_FAILURES` failed ids and their errors.
        error: why the job stopped, when it failed.
    """

    total: int
    run: str = ""
    state: str = "running"
    done: int = 0
    skipped: int = 0
    failed: int = 0
    failed_before: int = 0
    left: int = 0
    retried: int = 0
    frames: int = 0
    seconds: float = 0.0
    tracking_seconds: float = 0.0
    actor_seconds: float = 0.0
    failures: dict[str, str] = field(default_factory=dict)
    error: str = ""

    @property
    def frames_per_second(self) -> float:
        """Frames tracked per second of tracking, over all actors."""
        return self.frames / self.tracking_seconds if self.tracking_seconds > 0 else 0.0

    @property
    def videos_per_second(self) -> float:
        """Videos done per second of tracking."""
        return self.done / self.tracking_seconds if self.tracking_seconds > 0 else 0.0

    def commit(self, finished: Finished, attempts: int, video_id: str) -> None:
        """Counts a video written as done or failed."""
        if finished.status == DONE:
            self.done += 1
            self.frames += finished.frames
            self.actor_seconds += finished.seconds
            self.retried += attempts > 1
            return
        self.failed += 1
        if len(self.failures) < MAX_LISTED_FAILURES:
            self.failures[video_id] = finished.error

    def line(self) -> str:
        """One line: counts, time and speeds."""
        before = f", {self.failed_before} failed before" if self.failed_before else ""
        retried = f" ({self.retried} after their worker died)" if self.retried else ""
        left = f", {self.left} left for the next run" if self.left else ""
        return (
            f"{self.total} videos: {self.done} done{retried}, {self.skipped} skipped (already "
            f"done), {self.failed} failed{before}{left} in {duration(self.seconds)}; "
            f"{self.videos_per_second:.3g} videos/s, {self.frames_per_second:.3g} frames/s"
        )

    def failure_lines(self, out: str) -> list[str]:
        """The failed videos, ids escaped, and where the rest are."""
        lines = [f"  failed: {printable(vid)}: {error}" for vid, error in self.failures.items()]
        if self.failed > len(self.failures):
            lines.append(f"  ... and {self.failed - len(self.failures)} more in {out}")
        return lines

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, with the speeds."""
        return {
            **asdict(self),
            "videos_per_second": self.videos_per_second,
            "frames_per_second": self.frames_per_second,
        }


class Progress:
    """Counts videos as actors finish them and prints a line every ``every`` seconds.

    Args:
        summary: the run's summary (its counts are the committed ones).
        todo: videos this run tracks.
        every: seconds between lines (0: a line per video).
        print_line: where lines go.
    """

    def __init__(
        self, summary: Summary, todo: int, every: float, print_line: Callable[..., Any] = print
    ) -> None:
        self.summary = summary
        self.todo = todo
        self.every = every
        self.print_line = print_line
        self.started: float | None = None  # the first actor's readiness
        self.last = time.monotonic()
        self.finished = self.failed = self.frames = 0
        self.printed = 0  # videos finished when the last line was printed

    def start(self, when: float) -> None:
        """The first actor is ready (``time.monotonic`` time): the rates count from here."""
        if self.started is None:
            self.started = when

    def update(self, finished: Finished) -> None:
        """Counts a video whose part is published (done or failed for good)."""
        self.finished += 1
        self.failed += finished.status != DONE
        self.frames += finished.frames
        if self.every == 0:
            self.tick()

    def tick(self) -> None:
        """Prints a line when one is due (with ``every`` 0: when a video was finished)."""
        now = time.monotonic()
        if self.every == 0 and self.finished == self.printed:
            return
        if now - self.last >= self.every and self.started is not None:
            self.printed = self.finished
            self.last = now
            self.print_line(self.line(now - self.started), flush=True)

    def line(self, elapsed: float) -> str:
        """``corpus: 12/20 videos (1 failed), 41.2 frames/s, about 3m10s left``."""
        rate = self.frames / elapsed if elapsed > 0 else 0.0
        if self.finished:
            left_over = max(0, self.todo - self.finished)
            left = f"about {duration(left_over * elapsed / self.finished)} left"
        else:
            left = "estimating the time left"
        return (
            f"corpus: {self.finished}/{self.todo} videos ({self.failed} failed), "
            f"{rate:.3g} frames/s, {left}"
        )

    def final(self) -> None:
        """The last line, from the summary's numbers (what was written)."""
        summary = self.summary
        finished = summary.done + summary.failed
        self.print_line(
            f"corpus: {finished}/{self.todo} videos ({summary.failed} failed), "
            f"{summary.frames_per_second:.3g} frames/s, "
            + ("done" if finished == self.todo else f"{self.todo - finished} not finished"),
            flush=True,
        )


def duration(seconds: float) -> str:
    """``42.0s``, ``3m10s``, ``2h05m``."""
    if seconds < 60:
        return f"{seconds:.1f}s"
    if seconds < 3600:
        return f"{int(seconds // 60)}m{int(seconds % 60):02d}s"
    return f"{int(seconds // 3600)}h{int(seconds % 3600 // 60):02d}m"
