"""`track_corpus`: a corpus tracked from Python, as ``taptr track-corpus`` tracks it.

    from taptr.api.spec import ModelSpec
    from taptr.corpus import CorpusOptions, QuerySpec, read_video_list, track_corpus

    videos = read_video_list("video list.csv", default=QuerySpec(grid=8))
    summary = track_corpus(videos, ModelSpec("taptr-small-synthetic"), CorpusOptions(out="res"))

The model is a `taptr.api.spec.ModelSpec`: a small picklable record each actor builds its
predictor from. The driver builds none: the settings digests and the memory each actor
reserves come from the spec and its checkpoint's config (`taptr.corpus.model_facts`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from taptr.api.spec import ModelSpec
from taptr.corpus.inputs import CorpusVideo
from taptr.corpus.pipeline import CorpusOptions, run_corpus
from taptr.corpus.progress import Summary


def track_corpus(
    videos: Sequence[CorpusVideo],
    model: ModelSpec | None = None,
    options: CorpusOptions | None = None,
    *,
    print_line: Callable[..., Any] = print,
) -> Summary:
    """Tracks every video of a corpus not already done in ``options.out``.

    Args:
        videos: the corpus: each video's id (unique), file and queries
            (`taptr.corpus.read_video_list` reads them from a CSV or Parquet video list). Their
            settings digests are set here, from the model and the options.
        model: the tracker (None: the default model, `ModelSpec()`), loaded once in each
            actor; its ``device`` is the actors' (None: a GPU where the actor has one).
        options: the output folder or URI and how the job runs (`CorpusOptions`; None:
            ``corpus-results`` with the defaults). Without ``memory_per_actor``, each
            actor reserves its process, the model's weights and the estimated peak of a
            10-second 720p clip with 256 points (`taptr.corpus.cluster.actor_memory`).
        print_line: where progress lines and the lines naming damaged parts go.

    Returns:
        The run's counts (also in ``OUT/summary.json``); ``summary.line()`` says them in
        one line.

    Raises:
        ValueError: ids given twice, bad values in the spec or options, a folder holding
            foreign files, an impossible request of the cluster, a store that does not
            answer, or a job that cannot go on (one line each).
        FileNotFoundError: the checkpoint cannot be found or had.
        ModuleNotFoundError: Ray is not installed (the message says how to install it).
        KeyboardInterrupt: Ctrl-C or SIGTERM (what the process's handler raised), after
            the summary is written.
    """
    from taptr.corpus.cluster import actor_memory, check_address, require_ray
    from taptr.corpus.model_facts import model_facts
    from taptr.corpus.settings import TrackSettings, with_digests

    model = ModelSpec() if model is None else model
    options = CorpusOptions(out="corpus-results") if options is None else options
    require_ray()  # before the checkpoint is read: say at once how to install it
    check_address(options.address)  # and that the cluster cannot be reached
    facts = model_facts(model)
    if model.engine != "torch":  # exported here once, not by every actor at the same time
        from taptr.export.cache import ExportRequest, cached_export

        assert facts.checkpoint_path is not None  # model_facts refuses untrained presets
        request = ExportRequest(facts.checkpoint_path, facts.source, facts.input_size)
        cached_export(request, model.engine)
    settings = TrackSettings(options.max_frames, options.backward)
    digested = with_digests(list(videos), model, facts, settings)
    if options.memory_per_actor is None:
        options = replace(options, memory_per_actor=actor_memory(facts))
    return run_corpus(digested, model, options, print_line)
