"""Tracking a corpus of videos on a Ray cluster (or a local Ray instance): ``taptr track-corpus``.

The driver (`taptr.corpus.pipeline`) reads the output folder's index to leave out what is
done (`taptr.corpus.layout`), checks what it asks of the cluster before Ray could wait on
it (`taptr.corpus.cluster`), and hands batches of videos to tracker actors
(`taptr.corpus.scheduler`), each holding one `taptr.api.predictor.Predictor`
(`taptr.corpus.worker`). Actors write the rows of many videos at once as parts of a
Parquet dataset (`taptr.corpus.parts`, schema in `taptr.corpus.schema`), in a local
folder or an object store (`taptr.corpus.storage`); a video counts once its part is
published and read back. docs/CORPUS.md describes the job, the layout and the limits.

Ray and pyarrow are the optional extra ``pip install -e ".[ray]"``; nothing here imports
them at package import.
"""

from __future__ import annotations

from taptr.corpus.inputs import CorpusVideo, QuerySpec

__all__ = ["CorpusVideo", "QuerySpec"]
