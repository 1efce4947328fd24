"""Progress lines for long corpus jobs and the summary at the end.

Ray Data draws its own progress bars per stage; `Progress` adds one plain line every
``every`` seconds (logs of a job that runs for days keep it readable): videos finished out
of the total, failures, frames per second, and the time left at the rate so far.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass
class Summary:
    """What a corpus run did.

    Attributes:
        total: videos in the corpus; done: tracked now; skipped: complete from earlier
            runs with the same settings; failed: recorded as failed now (id → one-line
            error); failed_before: recorded as failed by earlier runs with the same
            settings, and left alone.
        retried: videos done now after their worker had died (killed, out of memory).
        frames: frames tracked now; seconds: the run's wall time.
        actor_seconds: time the actors spent on the videos done (decoding, tracking,
            writing), added over actors: per frame, what a frame costs an actor.
    """

    total: int
    done: int = 0
    skipped: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    failed_before: int = 0
    retried: int = 0
    frames: int = 0
    seconds: float = 0.0
    actor_seconds: float = 0.0

    @property
    def videos_per_second(self) -> float:
        """Videos tracked (done) per second of the run."""
        return self.done / self.seconds if self.seconds > 0 else 0.0

    @property
    def frames_per_second(self) -> float:
        """Frames tracked per second of the run, over all actors."""
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def line(self) -> str:
        """One line: counts, time and speeds."""
        before = f", {self.failed_before} failed before" if self.failed_before else ""
        retried = f" ({self.retried} after their worker died)" if self.retried else ""
        return (
            f"{self.total} videos: {self.done} done{retried}, {self.skipped} skipped (already "
            f"done), {len(self.failed)} failed{before} in {_duration(self.seconds)}; "
            f"{self.videos_per_second:.3g} videos/s, {self.frames_per_second:.3g} frames/s"
        )

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, with the speeds."""
        return {
            **asdict(self),
            "videos_per_second": self.videos_per_second,
            "frames_per_second": self.frames_per_second,
        }


class Progress:
    """Counts outcomes as they arrive and prints a line every ``every`` seconds.

    Args:
        summary: the run's summary, updated in place.
        todo: videos this run tracks (the total less the skipped ones).
        every: seconds between lines (0: a line per video).
        print_line: where lines go.
    """

    def __init__(self, summary: Summary, todo: int, every: float, print_line: Any = print) -> None:
        self.summary = summary
        self.todo = todo
        self.every = every
        self.print_line = print_line
        self.started = time.perf_counter()
        self.last = self.started
        self.finished = 0

    def update(self, outcome: dict[str, Any]) -> None:
        """Counts one video's outcome (`taptr.corpus.worker.OUTCOME_FIELDS`)."""
        self.finished += 1
        if outcome["status"] == "done":
            self.summary.done += 1
            self.summary.frames += int(outcome["frames"])
            self.summary.actor_seconds += float(outcome["seconds"])
            self.summary.retried += int(outcome.get("attempts", 1)) > 1
        else:
            self.summary.failed[str(outcome["video_id"])] = str(outcome["error"])
        now = time.perf_counter()
        if now - self.last >= self.every or self.finished == self.todo:
            self.last = now
            self.print_line(self.line(now - self.started), flush=True)

    def line(self, elapsed: float) -> str:
        """``corpus: 12/20 videos (1 failed), 41.2 frames/s, about 3m10s left``."""
        left = (self.todo - self.finished) * elapsed / max(self.finished, 1)
        rate = self.summary.frames / elapsed if elapsed > 0 else 0.0
        return (
            f"corpus: {self.finished}/{self.todo} videos ({len(self.summary.failed)} failed), "
            f"{rate:.3g} frames/s, about {_duration(left)} left"
        )


def _duration(seconds: float) -> str:
    """``42.0s``, ``3m10s``, ``2h05m``."""
    if seconds < 60:
        return f"{seconds:.1f}s"
    if seconds < 3600:
        return f"{int(seconds // 60)}m{int(seconds % 60):02d}s"
    return f"{int(seconds // 3600)}h{int(seconds % 3600 // 60):02d}m"
