"""Tracking a corpus of videos on a Ray cluster (or a local Ray instance): ``taptr track-corpus``.

A corpus is a Ray Data job (docs/CORPUS.md). CPU tasks read each video's header and check
it (`taptr.corpus.probe`); actors that each hold one `taptr.api.predictor.Predictor` (one GPU
each where there are GPUs) stream the frames through the tracker (`taptr.corpus.worker`);
every video's rows appear in a Parquet dataset at once or not at all, failures are rows
with their one-line error (`taptr.corpus.results`); a rerun skips what is done with the
same settings; `taptr.corpus.pipeline` ties it together and prints progress and a summary
(`taptr.corpus.progress`).

Ray and pyarrow are the optional extra ``pip install "taptr[ray]"``; nothing here imports
them at package import.
"""

from __future__ import annotations

from taptr.corpus.inputs import CorpusVideo, QuerySpec

__all__ = ["CorpusVideo", "QuerySpec"]
