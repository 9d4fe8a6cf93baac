"""Smoke test of the tracking benchmark: it runs end to end on seconds of walking (not a
timing or accuracy test)."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import pytest

from bench.tracking import COLUMNS

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_tracking_benchmark_runs_end_to_end(tmp_path: Path) -> None:
    args = [
        "--quick",
        "--duration",
        "4",
        "--repeats",
        "3",
        "--sizes",
        "10,100",
        "--out",
        str(tmp_path),
    ]
    done = subprocess.run(
        [sys.executable, "-m", "bench.tracking", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    with (tmp_path / "data" / "tracking.csv").open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        assert reader.fieldnames == COLUMNS
        rows = list(reader)
    # Paper room: labelled K = 4, correlation K = 4 and 8, with and without shadowing; crossing.
    assert len(rows) == 8
    labelled = [r for r in rows if r["mode"] == "terminals"]
    assert all(math.isfinite(float(r["tracked_rmse_standing_m"])) for r in labelled)
    assert all(0.0 <= float(r["coverage_95"]) <= 1.0 for r in labelled)
    page = (tmp_path / "results" / "tracking.md").read_text(encoding="utf-8")
    assert page.startswith("# Tracking results")
    assert "python -m bench.tracking --quick --duration 4" in page
    assert "## Targets" in page and "| 100 |" in page
