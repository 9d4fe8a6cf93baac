"""Fixtures shared by the whole suite (the database fixtures come from a plugin)."""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
import pytest

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout
from app.vlp.presets import paper_layout

# database_url, postgres_url, sqlite_url, clock and registry, for every test directory.
pytest_plugins = ["tests.db_fixtures"]


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh, seeded generator per test."""
    return np.random.default_rng(20261122)


@pytest.fixture(scope="session")
def paper_room() -> Layout:
    """The paper's 4 x 4 x 3 m room (16 LEDs, 0.2 m grid)."""
    return paper_layout()


@pytest.fixture(scope="session")
def paper_fingerprint(paper_room: Layout) -> Fingerprint:
    """Fingerprint of the paper's room (built once per session; treat as read-only)."""
    return build_fingerprint(paper_room)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under pytest-xdist (``./test``), refuse tests that share a node id: the workers run
    tests by id, so all but the first of them would silently not run. Such a module is
    marked ``serial`` and ``./test`` runs it in a plain pass (docs/architecture.md, "Tests
    and their lanes")."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    counts = Counter(item.nodeid for item in items)
    shared = sorted(nodeid for nodeid, count in counts.items() if count > 1)
    if shared:
        raise pytest.UsageError(
            f"{len(shared)} node ids are shared by several tests ({shared[0]}, ...): under "
            "pytest-xdist only the first of each would run; mark the module `serial`"
        )
