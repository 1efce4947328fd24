"""The driver's side of a corpus job: hands videos to tracker actors and keeps count.

Each actor gets a batch of videos at a time (one call in flight, a Ray streaming
generator of events, `taptr.corpus.records`) and is asked to flush its part when the
work runs out. Because an actor announces each video it starts tracking, the driver
knows what a dead actor was doing:

- the video it was tracking has its death counted; after ``max_attempts`` deaths it is
  recorded as failed ("its worker died in each of N attempts") instead of tried again;
- the videos of its batch it had not reached go back to the queue, uncharged; when it
  died between videos (reading a header, or its node was lost), they go back one per
  call, so that a video that kills its reader is found alone;
- its finished but unwritten videos go back to the queue, unless an index it published
  names them (it died after writing them): no video is written twice.

A dead actor is replaced; an actor that cannot start within ``start_timeout`` seconds
(its node is gone and the cluster cannot hold another) is dropped and the others go on.
When none is left, the videos still to do are recorded as failed with the reason.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from taptr.corpus.layout import INDEX, ResultLayout
from taptr.corpus.parts import PartWriter
from taptr.corpus.records import (
    FAILED,
    Committed,
    Event,
    Failure,
    Finished,
    Started,
    VideoTask,
)

MAX_BATCH = 64
"""Most videos in one call (short calls balance the actors at the end of the job)."""

WAIT_SECONDS = 1.0
"""Longest wait for an event before the driver looks at the clock (progress, timeouts)."""


@dataclass(frozen=True)
class SchedulerOptions:
    """How the driver runs the actors.

    Attributes:
        actors: actors to run.
        max_attempts: deaths while tracking a video before it is recorded as failed.
        start_timeout: seconds an actor may take to start (load its model) before it
            is dropped.
        max_restarts: actor deaths outside any video (model loading) before the job
            stops.
    """

    actors: int
    max_attempts: int = 3
    start_timeout: float = 300.0
    max_restarts: int = 10


@dataclass
class Slot:
    """One actor as the driver sees it.

    Attributes:
        handle: the actor (None once dropped); ready: its start, until it has loaded its
            model (then None); since: when it was started; writer: its writer id.
        call: the streaming call in flight; batch: that call's videos, in order;
            current: the video it announced and has not finished; finished: those it did.
        uncommitted: finished videos waiting in its part; parts: the parts it reported.
        flushing: the call in flight is a flush.
    """

    handle: Any
    ready: Any
    since: float
    writer: str | None = None
    call: Any = None
    batch: list[int] = field(default_factory=list)
    current: int | None = None
    finished: set[int] = field(default_factory=set)
    uncommitted: dict[int, Finished] = field(default_factory=dict)
    parts: set[str] = field(default_factory=set)
    flushing: bool = False


class JobError(RuntimeError):
    """The job cannot go on (an actor's model cannot load, the output cannot be written)."""


class Scheduler:
    """Runs the tasks on actors; reports committed outcomes through ``on_commit``.

    Args:
        tasks: the videos to track, indexed by `VideoTask.index` (``tasks[i].index == i``).
        start_actor: starts one actor; returns its handle.
        layout: the output folder (to reconcile a dead actor's parts).
        driver_parts: where the driver writes the failures it decides.
        options: see `SchedulerOptions`.
        on_commit: called with each `Finished` once it is written (its part published),
            and its tracking attempts: what the summary and the progress lines count.
    """

    def __init__(
        self,
        tasks: list[VideoTask],
        start_actor: Callable[[], Any],
        layout: ResultLayout,
        driver_parts: PartWriter,
        options: SchedulerOptions,
        on_commit: Callable[[Finished, int], None],
    ) -> None:
        import ray

        self.ray = ray
        self.tasks = tasks
        self.start_actor = start_actor
        self.layout = layout
        self.driver_parts = driver_parts
        self.options = options
        self.on_commit = on_commit
        self.queue: deque[int] = deque(range(len(tasks)))
        self.alone: deque[int] = deque()  # suspects of a death between videos
        self.tries: dict[int, int] = {}
        self.deaths: dict[int, int] = {}
        self.charged: list[int] = []  # every death, by the video it was charged to
        self.restarts = 0
        self.slots = [self._start() for _ in range(options.actors)]
        self.first_ready: float | None = None
        self.stopping = False
        self.driver_pending: dict[int, Finished] = {}  # failures the driver decided

    def step(self) -> bool:
        """Hands out work and handles what arrived within `WAIT_SECONDS`; False when done."""
        self._hand_out()
        # an actor still starting matters only while there is work it could take
        starting = not self.stopping and bool(self.queue or self.alone)
        waiting = {}
        for slot in self.slots:
            if slot.call is not None:
                waiting[slot.call] = slot
            elif slot.ready is not None and starting:
                waiting[slot.ready] = slot
        if not waiting:
            return False
        ready, _ = self.ray.wait(list(waiting), num_returns=1, timeout=WAIT_SECONDS)
        for item in ready:
            slot = waiting[item]
            if item is slot.ready:
                self._on_ready(slot)
            else:
                self._on_call(slot)
        self._drop_stalled()
        return True

    def stop(self) -> None:
        """Hands out nothing more; actors end their calls and write what they hold.

        A call ends after the video in progress (`TrackerWorker.stop`).
        """
        self.stopping = True
        for slot in self.slots:
            if slot.call is not None and not slot.flushing:
                slot.handle.stop.remote()

    def close(self) -> list[int]:
        """Ends the actors and writes the driver's failures; returns the videos left undone.

        Videos left undone were neither committed nor recorded as failed (the job was
        stopped): the next run tracks them.
        """
        left = list(self.queue) + list(self.alone)
        for slot in self.slots:
            left += [i for i in slot.batch if i not in slot.finished] + list(slot.uncommitted)
            if slot.handle is not None:
                self.ray.kill(slot.handle, no_restart=True)
        committed = self.driver_parts.flush()
        if committed is not None:
            self._commit_driver(committed)
        return sorted(set(left))

    def fail_remaining(self, reason: str) -> None:
        """Records every video not yet done as failed with ``reason`` (no actor is left)."""
        for index in list(self.queue) + list(self.alone):
            self._fail(index, reason)
        self.queue.clear()
        self.alone.clear()

    # -- actors -------------------------------------------------------------------------

    def _start(self) -> Slot:
        handle = self.start_actor()
        return Slot(handle, handle.ready.remote(), time.monotonic())

    def _on_ready(self, slot: Slot) -> None:
        try:
            slot.writer = self.ray.get(slot.ready)
        except self.ray.exceptions.RayActorError as error:
            if getattr(error, "actor_init_failed", False):
                raise JobError(f"a tracker actor could not start: {_cause(error)}") from None
            self._restart(slot, charge=None)
            return
        slot.ready = None
        if self.first_ready is None:
            self.first_ready = time.monotonic()

    def _drop_stalled(self) -> None:
        """Drops actors that could not start in time (their node is gone, say)."""
        now = time.monotonic()
        for slot in self.slots:
            if slot.ready is not None and now - slot.since > self.options.start_timeout:
                self.ray.kill(slot.handle, no_restart=True)
                slot.handle = slot.ready = None
        self.slots = [slot for slot in self.slots if slot.handle is not None]
        if not self.slots and not self.stopping and (self.queue or self.alone):
            self.fail_remaining(
                f"no tracker actor could start within {self.options.start_timeout:g} s "
                "(the cluster cannot hold one now)"
            )

    def _restart(self, slot: Slot, charge: int | None) -> None:
        """Replaces a dead actor (``charge``: the video it was tracking, if any)."""
        if self.stopping:
            slot.handle = slot.ready = None
            return
        if charge is None:
            self.restarts += 1
            if self.restarts > self.options.max_restarts:
                raise JobError(
                    f"tracker actors died {self.restarts} times outside any video (out of "
                    "memory while loading the model?); see Ray's logs"
                )
        fresh = self._start()
        slot.handle, slot.ready, slot.since = fresh.handle, fresh.ready, fresh.since
        slot.writer, slot.parts = None, set()

    # -- work ---------------------------------------------------------------------------

    def _hand_out(self) -> None:
        for slot in self.slots:
            if slot.call is not None or slot.ready is not None:
                continue
            batch = [] if self.stopping else self._next_batch()
            if batch:
                slot.batch, slot.finished = batch, set()
                slot.call = slot.handle.run.remote([self._task(i) for i in batch])
            elif slot.uncommitted and not slot.flushing:
                slot.flushing = True
                slot.call = slot.handle.flush.remote()

    def _next_batch(self) -> list[int]:
        if self.alone:
            return [self.alone.popleft()]
        live = max(1, sum(slot.ready is None for slot in self.slots))
        size = max(1, min(MAX_BATCH, len(self.queue) // (2 * live)))
        return [self.queue.popleft() for _ in range(min(size, len(self.queue)))]

    def _task(self, index: int) -> VideoTask:
        task = self.tasks[index]
        attempt = self.tries.get(index, 0) + 1
        return task if task.attempt == attempt else _with_attempt(task, attempt)

    def _on_call(self, slot: Slot) -> None:
        try:
            reference = next(slot.call)
        except StopIteration:
            self._call_ended(slot)
            return
        except self.ray.exceptions.RayActorError:
            self._on_death(slot)
            return
        try:
            events = self.ray.get(reference)
        except self.ray.exceptions.RayActorError:
            self._on_death(slot)
            return
        except self.ray.exceptions.RayTaskError as error:
            raise JobError(f"a tracker actor failed: {_cause(error)}") from None
        for event in events:
            self._on_event(slot, event)

    def _call_ended(self, slot: Slot) -> None:
        """The call's stream ended: what it did not reach goes back to the queue."""
        untouched = [i for i in slot.batch if i not in slot.finished and i != slot.current]
        self.queue.extendleft(reversed(untouched))
        slot.call, slot.batch, slot.finished, slot.current = None, [], set(), None
        slot.flushing = False

    def _on_event(self, slot: Slot, event: Event) -> None:
        if isinstance(event, Started):
            slot.current = event.index
            self.tries[event.index] = self.tries.get(event.index, 0) + 1
        elif isinstance(event, Finished):
            slot.current = None
            slot.finished.add(event.index)
            slot.uncommitted[event.index] = event
        elif isinstance(event, Committed):
            slot.parts.add(event.part)
            for index in event.indices:
                self._commit(slot.uncommitted.pop(index))

    def _on_death(self, slot: Slot) -> None:
        """Sorts out a dead actor's videos (see the module docstring), then replaces it."""
        self._recover_written(slot)
        if slot.writer is not None:
            self.layout.remove_orphans(slot.writer)
        self.queue.extendleft(reversed(list(slot.uncommitted)))
        slot.uncommitted = {}
        current = slot.current
        untouched = [i for i in slot.batch if i not in slot.finished and i != current]
        if current is not None:
            self.queue.extendleft(reversed(untouched))
            self._charge(current)
        elif len(slot.batch) == 1 and untouched:  # alone, and it died: that video did it
            self._charge(untouched[0])
        else:
            self.alone.extend(untouched)
        slot.batch = []  # sorted out above
        self._call_ended(slot)
        self._restart(slot, charge=current)

    def _recover_written(self, slot: Slot) -> None:
        """Commits what a dead actor published without telling (its indexes say)."""
        if slot.writer is None or not slot.uncommitted:
            return
        unseen = [p for p in self.layout.parts(INDEX, slot.writer) if p not in slot.parts]
        if not unseen:
            return
        by_id = {self.tasks[i].video_id: i for i in slot.uncommitted}
        for video_id in self.layout.read_index(unseen)["video_id"].to_pylist():
            index = by_id.get(video_id)
            if index is not None:
                self._commit(slot.uncommitted.pop(index))

    def _charge(self, index: int) -> None:
        """Counts a death against a video; fails it after ``max_attempts`` of them."""
        self.deaths[index] = self.deaths.get(index, 0) + 1
        self.charged.append(index)
        self.tries[index] = max(self.tries.get(index, 0), self.deaths[index])
        if self.deaths[index] >= self.options.max_attempts:
            count = self.deaths[index]
            self._fail(
                index, f"its worker died in each of {count} attempts (killed or out of memory)"
            )
        else:
            self.queue.appendleft(index)

    def _fail(self, index: int, reason: str) -> None:
        task = self.tasks[index]
        tries = self.tries.get(index, 0)
        failure = Failure(task.video_id, task.path, reason, tries, None, None, task.digest)
        self.driver_parts.add_failure(index, failure)
        self.driver_pending[index] = Finished(index, FAILED, reason)
        if self.driver_parts.due():
            committed = self.driver_parts.flush()
            if committed is not None:
                self._commit_driver(committed)

    def _commit_driver(self, committed: Committed) -> None:
        for index in committed.indices:
            self._commit(self.driver_pending.pop(index))

    def _commit(self, finished: Finished) -> None:
        """Reports a written video; its counts are no longer needed (a corpus is long)."""
        self.deaths.pop(finished.index, None)
        self.on_commit(finished, self.tries.pop(finished.index, 0))


def _with_attempt(task: VideoTask, attempt: int) -> VideoTask:
    from dataclasses import replace

    return replace(task, attempt=attempt)


def _cause(error: BaseException) -> str:
    """The last line of a Ray error: the original exception's type and message."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else type(error).__name__
