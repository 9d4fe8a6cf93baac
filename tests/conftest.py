"""Fixtures shared by the whole suite (the database fixtures come from a plugin)."""

from __future__ import annotations

import fcntl
import os
from collections import Counter

import numpy as np
import pytest

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout
from app.vlp.presets import paper_layout

# database_url, postgres_url, sqlite_url, clock and registry, for every test directory;
# small_room for the benchmarks' smoke runs.
pytest_plugins = ["tests.db_fixtures", "tests.bench_rooms"]


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
    """Fingerprint of the paper's room (built once per test run; treat as read-only)."""
    return build_fingerprint(paper_room)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Under ``./test``: wait, once collected, until the script releases its lock on
    ``VLP_TEST_START_LOCK`` (lint and type checks passed, the solver's kernels compiled into
    their disk cache), so collecting overlaps the kernels' compile but no test runs before."""
    path = os.environ.get("VLP_TEST_START_LOCK")
    if not path or not session.items or not os.path.exists(path):
        return
    with open(path, "rb") as lock:
        fcntl.flock(lock, fcntl.LOCK_SH)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under pytest-xdist (``./test``): hand out the modules that hold slow tests first, and
    refuse tests that share a node id.

    Workers take whole modules in collection order (``--dist loadfile``); a long module
    taken last keeps one worker busy while the other idles, so the long ones go first
    (longest first balances best). Tests that share a node id: the workers run tests by id,
    so all but the first of them would silently not run. Such a module is marked ``serial``
    and ``./test`` runs it in a plain pass
    (docs/explanation/architecture.md#tests-and-their-lanes).
    """
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    _slow_modules_first(items)
    counts = Counter(item.nodeid for item in items)
    shared = sorted(nodeid for nodeid, count in counts.items() if count > 1)
    if shared:
        raise pytest.UsageError(
            f"{len(shared)} node ids are shared by several tests ({shared[0]}, ...): under "
            "pytest-xdist only the first of each would run; mark the module `serial`"
        )


def _slow_modules_first(items: list[pytest.Item]) -> None:
    """Reorder ``items`` in place: modules with a ``slow`` test first, each module's tests in
    their order (every worker collects the same order, as xdist requires)."""
    slow_modules = {item.nodeid.split("::")[0] for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.nodeid.split("::")[0] not in slow_modules)
