"""Smoke test of the accuracy benchmark: it runs end to end on 2 trials (not a timing test)."""

from __future__ import annotations

import csv
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[2]
TRIAL_COLUMNS = [
    "room",
    "snr_db",
    "n_targets",
    "trial",
    "method",
    "model",
    "error_m",
    "time_ms",
    "status",
]
SUMMARY_COLUMNS = [
    "room",
    "snr_db",
    "n_targets",
    "method",
    "model",
    "trials",
    "failures",
    "median_error_m",
    "mean_error_m",
    "p90_error_m",
    "median_time_ms",
    "grid_floor_m",
    "crlb_m",
    "crlb_single_m",
]


def _read(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        return list(reader.fieldnames or []), list(reader)


def test_accuracy_benchmark_runs_end_to_end(tmp_path: Path) -> None:
    handwritten = "# Accuracy\n\nHand-written discussion that a rerun must keep.\n"
    page = tmp_path / "results" / "accuracy.md"
    page.parent.mkdir()
    page.write_text(handwritten, encoding="utf-8")
    args = [
        "--trials",
        "2",
        "--ks",
        "1,3",
        "--snrs",
        "30",
        "--rooms",
        "paper",
        "--solvers",
        "omp",
        "--jobs",
        "1",
        "--out",
        str(tmp_path),
    ]
    done = subprocess.run(
        [sys.executable, "-m", "bench.accuracy", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr

    columns, trials = _read(tmp_path / "data" / "accuracy_trials.csv")
    assert columns == TRIAL_COLUMNS
    # Per trial: grid floor, single-target CRLB, two aggregated CRLBs, RSS, omp x 2 models.
    assert len(trials) == 2 * 2 * 7
    assert {r["status"] for r in trials} == {"ok"}
    assert all(math.isfinite(float(r["error_m"])) and float(r["error_m"]) >= 0 for r in trials)
    floors = [float(r["error_m"]) for r in trials if r["method"] == "grid_floor"]
    assert all(f <= 0.2 * math.sqrt(2) / 2 + 1e-12 for f in floors)  # within half a diagonal
    assert all(float(r["error_m"]) > 0 for r in trials if r["method"].startswith("crlb"))
    # One placement per trial: every method of a trial saw the same K targets.
    assert {(r["n_targets"], r["trial"]) for r in trials} == {
        ("1", "0"),
        ("1", "1"),
        ("3", "0"),
        ("3", "1"),
    }

    columns, summary = _read(tmp_path / "data" / "accuracy_summary.csv")
    assert columns == SUMMARY_COLUMNS
    assert sorted((r["n_targets"], r["method"], r["model"]) for r in summary) == [
        (k, m, model)
        for k in ("1", "3")
        for m, model in (("omp", "correlation"), ("omp", "power"), ("rss", "-"))
    ]
    for row in summary:
        assert row["trials"] == "2" and row["failures"] == "0"
        assert math.isfinite(float(row["mean_error_m"]))
        per_trial = [
            float(r["error_m"])
            for r in trials
            if (r["n_targets"], r["method"], r["model"])
            == (row["n_targets"], row["method"], row["model"])
        ]
        assert math.isclose(float(row["mean_error_m"]), sum(per_trial) / 2, rel_tol=1e-5)
        assert float(row["crlb_single_m"]) > 0
        if row["method"] == "omp":
            assert float(row["crlb_m"]) > 0

    for name in ("fig3_estimates_k8.png", "fig4_error_vs_k_paper.png"):
        assert (tmp_path / "figures" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    markdown = page.read_text(encoding="utf-8")
    assert markdown.startswith(handwritten)
    assert "<!-- accuracy-results:start -->" in markdown
    assert "python -m bench.accuracy --trials 2" in markdown
    assert "### Room `paper`, 30 dB" in markdown
    # The page sits in results/ beside data/ and figures/: its image links must resolve.
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", markdown)
    assert images and all((page.parent / image).resolve().is_file() for image in images)
