"""One place that turns a seed into a generator (no global seeding anywhere)."""

from __future__ import annotations

import numpy as np

__all__ = ["RandomState", "as_generator"]

RandomState = np.random.Generator | int | None


def as_generator(rng: RandomState) -> np.random.Generator:
    """A ``numpy.random.Generator`` from a generator, an integer seed or None (fresh)."""
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(rng)
