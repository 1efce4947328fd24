"""Paths and loaders shared by the tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

FIXTURES = Path(__file__).parent / "fixtures"
SHARED_MEDIA = Path(__file__).resolve().parents[2] / "shared" / "media"


def load_golden(case: str) -> dict[str, np.ndarray]:
    """A compact golden fixture (see scripts/compact_golden.py)."""
    with np.load(FIXTURES / f"{case}.npz") as data:
        return {k: data[k] for k in data.files}
