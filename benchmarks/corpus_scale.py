"""The corpus pipeline's own cost per video at 10⁴ to 10⁶ videos, with a stand-in tracker.

What is measured is taptr's pipeline, not the model: reading a Parquet video list, the
settings digests, the plan (the skip set read from the parts' index), handing videos to
actors, writing parts, a rerun over everything done, and opening the dataset in pandas.
To reach 10⁶ videos in minutes on 2 cores the model is replaced by a stand-in, named as
such everywhere it is reported: ``StandInWorker`` is the real `TrackerWorker` (the same
driver, batches, events, parts, index and compaction) whose header reading is cached
per file (every row names one of a few 3-frame clips) and whose "tracking" returns
zeros of the declared length instead of running a model.

Scenarios, each in its own process (its peak RSS is the driver's memory):

- ``failures``: N rows naming files that do not exist (every video a failure row);
- ``done``: N rows over 3-frame clips with --grid 1 through the stand-in, then a rerun
  over the N done videos (the time until it would start tracking: it has nothing to
  track, so the whole rerun), then ``pd.read_parquet(OUT/tracks)``.

    python benchmarks/corpus_scale.py --videos 10000 100000 1000000 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import ClassVar

import numpy as np

from taptr.api.spec import ModelSpec
from taptr.apps.benchmark import machine
from taptr.corpus.probe import Probed
from taptr.corpus.records import VideoTask, VideoTracks
from taptr.corpus.worker import TrackerWorker

CLIPS = 4
"""Distinct tiny clips the rows name."""

STAND_IN = ModelSpec("tiny")
"""The spec the actors get (the stand-in loads nothing; the digests are given)."""


class StandInWorker(TrackerWorker):
    """`TrackerWorker` with a cached header read and fabricated tracks (no model)."""

    headers: ClassVar[dict[str, Probed]] = {}  # per actor process: its own copy

    def load(self, model: ModelSpec) -> None:  # type: ignore[override]
        return None  # its `_track` runs no model

    def _probe(self, task: VideoTask) -> Probed:
        known = self.headers.get(task.path)
        if known is None:
            known = self.headers[task.path] = super()._probe(task)
        return Probed(known.info, known.queries)

    def _track(self, task: VideoTask, probed: Probed) -> VideoTracks:
        frames, points = probed.info.num_frames or 1, len(probed.queries)
        return VideoTracks(
            task.video_id, task.path, probed.queries, np.zeros((frames, points, 2), np.float32),
            np.ones((frames, points), bool), (probed.info.height, probed.info.width),
            probed.info.fps, probed.info.num_frames, "stand-in", task.digest,
        )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--videos", type=int, nargs="+", default=[10_000])
    parser.add_argument("--scenarios", nargs="+", default=["failures", "done"])
    parser.add_argument("--actors", type=int, default=2)
    parser.add_argument("--json", help="also write the results here")
    parser.add_argument(
        "--one", nargs=3, metavar=("SCENARIO", "N", "FOLDER"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.one:
        scenario, count, folder = args.one
        print(json.dumps(_scenario(scenario, int(count), Path(folder), args.actors)))
        return
    results = {
        "command": "python benchmarks/corpus_scale.py " + " ".join(sys.argv[1:]),
        "machine": machine(),
        "stand_in": StandInWorker.__doc__,
        "load_average_before": os.getloadavg(),
        "runs": [],
    }
    for count in args.videos:
        for scenario in args.scenarios:
            folder = Path(tempfile.mkdtemp(prefix=f"corpus-scale-{scenario}-{count}-"))
            command = [sys.executable, __file__, "--one", scenario, str(count), str(folder),
                       "--actors", str(args.actors)]  # fmt: skip
            done = subprocess.run(command, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                raise SystemExit(done.stderr[-3000:])
            run = json.loads(done.stdout.strip().splitlines()[-1])
            print(json.dumps(run), flush=True)
            results["runs"].append(run)
    results["load_average_after"] = os.getloadavg()
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


def _scenario(scenario: str, count: int, folder: Path, actors: int) -> dict:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from taptr.corpus.damage import sound_index
    from taptr.corpus.inputs import QuerySpec
    from taptr.corpus.layout import ResultLayout
    from taptr.corpus.pipeline import CorpusOptions, plan, run_corpus
    from taptr.corpus.progress import Summary
    from taptr.corpus.video_list import read_video_list

    paths = _clips(folder) if scenario == "done" else [str(folder / "missing.mp4")]
    table = pa.table({"path": [paths[i % len(paths)] for i in range(count)],
                      "id": [f"v{i:07d}" for i in range(count)]})  # fmt: skip
    pq.write_table(table, folder / "video list.parquet")
    del table
    timings: dict[str, float] = {}
    started = time.perf_counter()
    videos = read_video_list(folder / "video list.parquet", QuerySpec(grid=1))
    timings["read_manifest_s"] = time.perf_counter() - started
    videos = [
        video.__class__(video.video_id, video.path, video.queries, "0" * 16) for video in videos
    ]
    out = str(folder / "out")
    options = CorpusOptions(out=out, actors=actors, progress_every=3600, memory_per_actor=2**30)
    started = time.perf_counter()
    summary = run_corpus(videos, STAND_IN, options, print_line=_quiet, worker=StandInWorker)
    timings["job_s"] = time.perf_counter() - started
    expected = count if scenario == "done" else 0
    assert summary.done == expected and summary.done + summary.failed == count, summary.line()
    result = {"scenario": scenario, "videos": count, **timings,
              "job_per_video_ms": 1000 * timings["job_s"] / count,
              "driver_peak_rss_job_mib": _peak_mib()}  # fmt: skip
    if scenario == "done":
        started = time.perf_counter()
        layout = ResultLayout.at(out)
        rerun = Summary(total=count)
        assert plan(videos, sound_index(layout), CorpusOptions(out=out), rerun) == []
        result["rerun_plan_s"] = time.perf_counter() - started
        started = time.perf_counter()
        again = run_corpus(videos, STAND_IN, options, print_line=_quiet, worker=StandInWorker)
        result["rerun_s"] = time.perf_counter() - started
        assert again.skipped == count
        result["driver_peak_rss_rerun_mib"] = _peak_mib()
        import pandas as pd

        started = time.perf_counter()
        frame = pd.read_parquet(folder / "out" / "tracks")
        result["pandas_open_s"] = time.perf_counter() - started
        assert len(frame) == count
        result["parts"] = len(list((folder / "out" / "tracks").iterdir()))
    result["peak_rss_with_pandas_mib"] = _peak_mib()  # the benchmark's own frame included
    return result


def _peak_mib() -> float:
    """This process's peak resident memory so far (the driver's, plus the benchmark's)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _clips(folder: Path) -> list[str]:
    from taptr.io.video import write_video

    rng = np.random.default_rng(0)
    paths = []
    for index in range(CLIPS):
        frames = rng.integers(0, 256, (3, 32, 48, 3), np.uint8)
        paths.append(str(write_video(folder / f"clip{index}.mp4", frames, fps=10)))
    return paths


def _quiet(*_args: object, **_kwargs: object) -> None:
    return None


if __name__ == "__main__":
    main()
