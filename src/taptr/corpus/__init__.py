"""Tracking a corpus of videos on a Ray cluster (or a local Ray instance): ``taptr track-corpus``.

From Python, `track_corpus` (`taptr.corpus.job`) takes the videos (`CorpusVideo`, or
`read_video_list`), the tracker as a `taptr.api.spec.ModelSpec` and `CorpusOptions`, and
returns the run's `Summary`; `read_tracks` and `read_failures` read the results back
with their columns, failures or not.

The driver (`taptr.corpus.pipeline`) reads the output folder's index, removing the
parts that do not hold what it says (`taptr.corpus.damage`), to leave out what is done
(`taptr.corpus.layout`), checks what it asks of the cluster before Ray could wait on it
(`taptr.corpus.cluster`), and hands batches of videos to tracker actors
(`taptr.corpus.scheduler`), each holding one `taptr.api.predictor.Predictor`
(`taptr.corpus.worker`). Actors write the rows of many videos at once as parts of a
Parquet dataset (`taptr.corpus.parts`, schema in `taptr.corpus.schema`), in a local
folder or an object store (`taptr.corpus.storage`); a video counts once its part is
published and read back. docs/CORPUS.md describes the job, the layout and the limits.

Ray and pyarrow are the optional extra ``pip install -e ".[ray]"``; nothing here imports
them, or torch, at package import.
"""

from __future__ import annotations

from taptr.corpus.inputs import CorpusVideo, QuerySpec
from taptr.lazy import lazy_names

_EXPORTS = {
    "track_corpus": "taptr.corpus.job",
    "CorpusOptions": "taptr.corpus.pipeline",
    "Summary": "taptr.corpus.progress",
    "PartLimits": "taptr.corpus.parts",
    "read_video_list": "taptr.corpus.video_list",
    "read_tracks": "taptr.corpus.results",
    "read_failures": "taptr.corpus.results",
}

__all__ = ["CorpusVideo", "QuerySpec", *sorted(_EXPORTS)]

__getattr__ = lazy_names(__name__, _EXPORTS)
