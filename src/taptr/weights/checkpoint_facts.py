"""What a checkpoint is, read without building its model: `CheckpointFacts`.

A name resolves through `taptr.weights.registry.resolve_weights`, as loading resolves it, in
the same order and with the same warnings (an untrained preset, the bundled model standing
in for the default), and the file is checked as the loader checks it
(`taptr.weights.checkpoint.checkpoint_contents`). The corpus driver reads its settings
digests from these facts (`taptr.corpus.model_facts`), and the exported-graph engines their
export's key and the predictor's settings (`taptr.api.graph_predictor`): neither copies
weights into a model.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from taptr.config import ModelConfig


@dataclass(frozen=True)
class CheckpointFacts:
    """A resolved name: what it is called, its file, config and stored threshold.

    Attributes:
        name: the name or file it was asked as (``Predictor.source``).
        path: the file its weights come from (None: an untrained preset).
        config: its model config.
        threshold: the file's calibrated visibility threshold (None: the config's rules).
    """

    name: str
    path: Path | None
    config: ModelConfig
    threshold: float | None


def checkpoint_facts(name: str | None) -> CheckpointFacts:
    """The file, config and threshold of a checkpoint file or model name (None: the default).

    Raises:
        FileNotFoundError: neither a file nor a known name, or weights that cannot be had.
        CheckpointError: the file is not a checkpoint taptr loads.
    """
    from taptr.config import get_config
    from taptr.weights.registry import resolve_weights

    def untrained(asked: str, preset: str) -> CheckpointFacts:
        return CheckpointFacts(asked, None, get_config(preset), None)

    return resolve_weights(name, _from_file, untrained)[0]


def _from_file(path: Path, name: str, preset: str | None = None) -> CheckpointFacts:
    """A checkpoint file's config and stored threshold, checked as loading checks them."""
    from taptr.weights.checkpoint import (
        CheckpointError,
        check_architecture,
        checkpoint_contents,
        read_file,
        read_visibility_threshold,
    )
    from taptr.weights.safe_checks import named_failures

    with named_failures(path):
        data = read_file(path)
        if not isinstance(data, Mapping):
            raise CheckpointError(f"{path} holds a {type(data).__name__}, not a checkpoint dict")
        config, _ = checkpoint_contents(data, str(path))
        if preset is not None:
            check_architecture(config, path, name, preset)
    calibrated = data.get("visibility_threshold") is not None
    threshold = read_visibility_threshold(path) if calibrated else None
    return CheckpointFacts(name, path, config, threshold)
