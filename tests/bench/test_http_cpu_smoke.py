"""Smoke test of the side-by-side CPU benchmark: a short run end to end (not a timing test)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_http_cpu_benchmark_runs_both_servers_and_reports_every_figure() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "bench.http_cpu", str(REPO_ROOT), "--block", "5", "--rounds", "2"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout)
    shown = result.stdout
    assert report["block"] == 5 and report["rounds"] == 2
    for name in ("before", "after"):
        figures = report[name]
        assert figures["tree"] == str(REPO_ROOT)
        # every block costs the server some CPU; a localize answers with its solver's time
        for kind in ("healthz", "localize_omp", "localize_default"):
            assert figures[f"cpu_ms_{kind}"] >= 0, shown
        assert figures["solver_mean_ms_default"] > 0, shown
        # a block of 5 trivial requests can cost less than one clock tick: no ratio then
        ratio = figures["localize_omp_over_healthz"]
        assert (ratio is None) == (figures["cpu_ms_healthz"] == 0), shown
