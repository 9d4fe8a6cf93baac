"""Smoke test of bench/hall_refinement.py: it runs on the medium room (not a timing test)."""

from __future__ import annotations

import pytest

from bench.hall_refinement import run

pytestmark = pytest.mark.slow


def test_local_and_full_refinements_are_both_reported() -> None:
    """Two seeds, three targets in the 40 m room at 30 dB: both ways report every figure
    and find every target (these seeds' targets are found by either)."""
    report = run("medium", 3, range(1, 3), 30.0)
    assert report["seeds"] == "1-2"
    for way in ("local", "full"):
        figures = report[way]
        assert set(figures) == {
            "misplaced",
            "median_mean_error_cm",
            "worst_mean_error_cm",
            "median_solve_s",
            "max_solve_s",
        }
        assert figures["misplaced"] == "0 of 6"
        assert 0.0 < figures["median_mean_error_cm"] <= figures["worst_mean_error_cm"] < 5.0
