"""Fixtures shared by the default solver's tests."""

from __future__ import annotations

import pytest

from app.vlp.fingerprints import Fingerprint
from app.vlp.solvers.gridless import GridlessSolver


@pytest.fixture(scope="module")
def paper_solver(paper_fingerprint: Fingerprint) -> GridlessSolver:
    return GridlessSolver(paper_fingerprint, "correlation")
