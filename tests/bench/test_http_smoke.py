"""Smoke test of the HTTP benchmark: a short run end to end (not a timing test)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_http_benchmark_runs_and_reports_every_figure() -> None:
    args = ["--sequential", "10", "--measurements", "10", "--seconds", "1", "--rounds", "2"]
    args += ["--batch", "5", "--batch-rounds", "2"]
    result = subprocess.run(
        [sys.executable, "-m", "bench.http", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout)
    shown = result.stdout  # the whole report, when an assertion below fails
    sequential = report["sequential_one_worker"]
    assert sequential["requests_each"] == 10
    assert sequential["healthz_p50_ms"] > 0 and sequential["localize_p50_ms"] > 0
    assert sequential["server_cpu_ms_per_localize"] > 0, shown
    for batch in (report["batch_vs_singles"], report["batch_vs_singles_omp"]):
        assert batch["measurements"] == 5 and batch["same_estimates"] is True, shown
    throughput = report["throughput_workers"]
    assert throughput["errors"] == 0, shown
    assert [len(throughput["rps_per_round"][w]) for w in ("1", "2")] == [2, 2]
    ratios = report["ratios"]
    # the service's own time around a solve is positive (the solve is timed inside it)
    assert sequential["localize_p50_ms"] > sequential["solver_p50_ms"], shown
    assert ratios["service_overhead_over_healthz"] > 0, shown
    # a batch's wall time holds its items' solves
    assert ratios["batch_over_item_solves"] > 1, shown
    assert ratios["workers_2_over_1"] == throughput["workers_2_over_1"]
    # an API process holds at least the interpreter and the web stack, and not gigabytes
    assert 50 < ratios["idle_api_process_peak_mib"] < 2048, shown
