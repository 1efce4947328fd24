"""The driver's bookkeeping of dead actors, on a scripted Ray (no processes, no timing).

Each fake actor runs the real `TrackerWorker.run` protocol on paper: a video it may "die
on" ends its process either while tracking (after `Started`) or while reading the header
(before it); everything it had not yet reported, written or not, is judged by the
`Scheduler` alone. Checked: a death is charged to the video being tracked and to no
other; a death between videos sends the batch back one video per call until the culprit
is found; finished but unwritten videos are tracked again unless their part was written;
no video is written twice; a video that kills every actor becomes a failure row.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from taptr.corpus.layout import ResultLayout
from taptr.corpus.parts import PartLimits, PartWriter
from taptr.corpus.records import DONE, FAILED, Committed, Failure, Finished, Started, VideoTask
from taptr.corpus.scheduler import JobError, Scheduler, SchedulerOptions

pytest.importorskip("pyarrow")


class ActorDiedError(Exception):
    """Stands for ``ray.exceptions.RayActorError``."""

    actor_init_failed = False


class TaskFailedError(Exception):
    """Stands for ``ray.exceptions.RayTaskError``."""


@dataclass
class Script:
    """What the fake actors do: ``kill`` maps a video id to (deaths, 'track' or 'read')."""

    kill: dict[str, tuple[int, str]] = field(default_factory=dict)
    deaths: dict[str, int] = field(default_factory=dict)
    part_videos: int = 2
    layout: ResultLayout | None = None
    written: list[str] = field(default_factory=list)  # video ids, once per part row


class Ref:
    def __init__(self, value=None, error=None):
        self.value, self.error = value, error


class Generator:
    """A streaming call: its items are computed up front, its death is the last item."""

    def __init__(self, items):
        self.items = list(items)

    def __next__(self):
        if not self.items:
            raise StopIteration
        return self.items.pop(0)


class Actor:
    def __init__(self, script: Script, tasks: list[VideoTask]):
        self.script, self.tasks = script, tasks
        self.parts = PartWriter(script.layout, "20261207T000000000000Z", PartLimits(videos=10**6))
        self.dead = False
        self.ready = _Method(lambda: Ref(self.parts.writer))
        self.run = _Method(lambda batch: Generator(self._run(batch)))
        self.flush = _Method(lambda: Generator(self._flush()))
        self.stop = _Method(lambda: None)  # its calls are computed up front: nothing to end

    def _run(self, batch):
        events = []
        for task in batch:
            if self.dead:
                return
            deaths, where = self.script.kill.get(task.video_id, (0, ""))
            dies = self.script.deaths.get(task.video_id, 0) < deaths
            if dies and where == "read":
                self.script.deaths[task.video_id] = self.script.deaths.get(task.video_id, 0) + 1
                yield Ref(events) if events else None
                yield Ref(error=ActorDiedError())
                return
            yield Ref(events + [Started(task.index)])
            events = []
            if dies:
                self.script.deaths[task.video_id] = self.script.deaths.get(task.video_id, 0) + 1
                yield Ref(error=ActorDiedError())
                return
            failure = Failure(task.video_id, task.path, "x", task.attempt, None, None, "d")
            self.parts.add_failure(task.index, failure)  # rows of either kind count alike
            events.append(Finished(task.index, DONE, frames=1, points=1))
            if self.parts.pending >= self.script.part_videos:
                events.append(self._commit())
        if events:
            yield Ref(events)

    def _flush(self):
        yield Ref([self._commit()] if self.parts.pending else [])

    def _commit(self) -> Committed:
        ids = [failure.video_id for failure in self.parts._failures]
        committed = self.parts.flush()
        self.script.written += ids
        return committed


class _Method:
    def __init__(self, call):
        self.call = call

    def remote(self, *args):
        return self.call(*args)


class FakeRay:
    """The part of Ray the scheduler uses, run in order."""

    class exceptions:  # noqa: N801 - as ray.exceptions
        RayActorError = ActorDiedError
        RayTaskError = TaskFailedError

    @staticmethod
    def wait(items, num_returns, timeout):
        return items[:1], items[1:]

    @staticmethod
    def get(ref):
        if ref is None:
            return []
        if ref.error is not None:
            raise ref.error
        return ref.value

    @staticmethod
    def kill(handle, no_restart):
        handle.dead = True


def _run(tmp_path, ids, script: Script, actors=2, max_attempts=3):
    layout = ResultLayout.at(str(tmp_path / "out"))
    layout.prepare()
    script.layout = layout
    tasks = [VideoTask(i, video_id, f"{video_id}.mp4", "{}", "d") for i, video_id in enumerate(ids)]
    committed: dict[str, tuple[str, int]] = {}

    def on_commit(finished: Finished, attempts: int) -> None:
        video_id = tasks[finished.index].video_id
        assert video_id not in committed, f"{video_id} counted twice"
        committed[video_id] = (finished.status, attempts)

    scheduler = Scheduler(
        tasks,
        lambda: Actor(script, tasks),
        layout,
        PartWriter(layout, "20261207T000000000000Z"),
        SchedulerOptions(actors, max_attempts, start_timeout=60),
        on_commit,
    )
    scheduler.ray = FakeRay
    while scheduler.step():
        pass
    assert scheduler.close() == []
    return committed, scheduler, layout


@pytest.fixture(autouse=True)
def _fake_ray(monkeypatch):
    import sys
    import types

    fake = types.ModuleType("ray")
    fake.exceptions = FakeRay.exceptions
    fake.wait, fake.get, fake.kill = FakeRay.wait, FakeRay.get, FakeRay.kill
    monkeypatch.setitem(sys.modules, "ray", fake)


def test_a_death_while_tracking_is_charged_to_that_video_alone(tmp_path):
    ids = [f"v{i:02d}" for i in range(30)]
    script = Script(kill={"v07": (1, "track")})
    committed, scheduler, layout = _run(tmp_path, ids, script)
    assert set(committed) == set(ids)
    assert committed["v07"] == (DONE, 2)
    assert scheduler.charged == [7]  # nobody else charged
    assert sorted(script.written) == sorted(ids)  # every video written once
    assert sorted(layout.read_index()["video_id"].to_pylist()) == sorted(ids)


def test_a_video_that_kills_every_attempt_becomes_a_failure_row(tmp_path):
    ids = [f"v{i:02d}" for i in range(12)]
    script = Script(kill={"v03": (99, "track")})
    committed, scheduler, layout = _run(tmp_path, ids, script, max_attempts=2)
    assert committed["v03"] == (FAILED, 2)
    assert all(status == DONE for video, (status, _) in committed.items() if video != "v03")
    failures = layout.read_failures().to_pylist()
    (row,) = [row for row in failures if row["video_id"] == "v03"]
    assert row["error"] == "its worker died in each of 2 attempts (killed or out of memory)"
    assert row["attempts"] == 2
    assert scheduler.charged == [3, 3]


def test_a_death_between_videos_finds_the_culprit_alone(tmp_path):
    ids = [f"v{i:02d}" for i in range(40)]
    script = Script(kill={"v05": (99, "read")}, part_videos=100)
    committed, scheduler, layout = _run(tmp_path, ids, script, max_attempts=2)
    assert committed["v05"][0] == FAILED
    assert all(status == DONE for video, (status, _) in committed.items() if video != "v05")
    assert scheduler.charged == [5, 5]  # only the culprit was ever charged
    assert sorted(script.written) == sorted(set(ids) - {"v05"})  # the driver wrote its row
    assert sorted(layout.read_index()["video_id"].to_pylist()) == sorted(ids)


def test_finished_unwritten_videos_are_tracked_again_and_written_once(tmp_path):
    # parts of 100: every video before the death waits unwritten in the dead actor
    ids = [f"v{i:02d}" for i in range(20)]
    script = Script(kill={"v15": (1, "track")}, part_videos=100)
    committed, _, _ = _run(tmp_path, ids, script, actors=1)
    assert set(committed) == set(ids) and all(s == DONE for s, _ in committed.values())
    assert sorted(script.written) == sorted(ids)


def test_an_actor_that_cannot_load_its_model_stops_the_job(tmp_path):
    layout = ResultLayout.at(str(tmp_path / "out"))
    layout.prepare()

    class Broken:
        def __init__(self):
            error = ActorDiedError()
            error.actor_init_failed = True
            error.args = (
                "The actor died because of an error raised in its creation task\n"
                "ValueError: cannot read checkpoint x.pth",
            )
            self.ready = _Method(lambda: Ref(error=error))

    tasks = [VideoTask(0, "v", "v.mp4", "{}", "d")]
    scheduler = Scheduler(
        tasks,
        Broken,
        layout,
        PartWriter(layout, "20261207T000000000000Z"),
        SchedulerOptions(1),
        lambda f, a: None,
    )
    scheduler.ray = FakeRay
    with pytest.raises(JobError, match="could not start: ValueError: cannot read checkpoint"):
        while scheduler.step():
            pass


def _pipeline_run(tmp_path, ids, script: Script, progress_lines: list[str]):
    """`taptr.corpus.pipeline._run` (the driver's loop, progress lines included) on the fakes."""
    from taptr.corpus.pipeline import CorpusOptions, _run
    from taptr.corpus.progress import Summary

    layout = ResultLayout.at(str(tmp_path / "out"))
    layout.prepare()
    script.layout = layout
    tasks = [VideoTask(i, v, f"{v}.mp4", "{}", "d" * 16) for i, v in enumerate(ids)]
    summary = Summary(total=len(ids), run="20261207T000000000000Z")
    options = CorpusOptions(out=str(tmp_path / "out"), progress_every=0)

    def print_line(text, **_):
        progress_lines.append(text)

    context = (layout, summary, 2)
    _run(tasks, lambda: Actor(script, tasks), options, context, print_line)
    return summary


def test_progress_counts_written_videos_once_and_never_passes_the_total(tmp_path):
    import re

    ids = [f"v{i:02d}" for i in range(20)]
    # parts of 100: the videos finished before the death were never written, and run again
    script = Script(kill={"v15": (1, "track")}, part_videos=100)
    lines: list[str] = []
    summary = _pipeline_run(tmp_path, ids, script, lines)
    counts = [tuple(map(int, re.match(r"corpus: (\d+)/(\d+)", line).groups())) for line in lines]
    assert counts and all(total == 20 and done <= 20 for done, total in counts), lines
    assert [done for done, _ in counts] == sorted(done for done, _ in counts)  # never back
    assert lines[-1].startswith("corpus: 20/20 videos (0 failed)") and lines[-1].endswith("done")
    assert "-" not in " ".join(lines)  # no negative time left
    assert summary.done == 20


def test_a_sigterm_while_the_driver_waits_on_ray_stops_as_sigterm(tmp_path, monkeypatch):
    import signal

    from taptr.cli.main import Terminated, sigterm_raises
    from taptr.corpus.signals import remembered_stop

    calls = {"wait": 0}

    def wait_like_ray(items, num_returns, timeout):
        calls["wait"] += 1
        if calls["wait"] == 4:
            try:
                signal.raise_signal(signal.SIGTERM)  # its handler runs inside the wait
            except BaseException:
                raise KeyboardInterrupt from None  # what Ray raises in its place
        return items[:1], items[1:]

    monkeypatch.setattr(FakeRay, "wait", staticmethod(wait_like_ray))
    import sys

    monkeypatch.setattr(sys.modules["ray"], "wait", wait_like_ray)
    ids = [f"v{i:02d}" for i in range(12)]
    lines: list[str] = []
    with sigterm_raises(), pytest.raises(Terminated), remembered_stop():
        _pipeline_run(tmp_path, ids, Script(), lines)
    assert calls["wait"] > 4  # the actors were given their grace to write
