"""Smoke test of the bounded-work benchmark: one short run end to end (not a timing test)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_bounded_work_benchmark_runs_and_rewrites_only_its_block(tmp_path: Path) -> None:
    doc = tmp_path / "bounded-work.md"
    doc.write_text("# Results: bounded work\n\n## Reading it\n\nKept.\n")
    result = subprocess.run(
        [sys.executable, "-m", "bench.bounded_work", "--repeat", "1", "--update-doc", str(doc)],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    figures = json.loads(result.stdout)
    assert set(figures["room_map_s"]) == {"coverage", "crlb"}
    assert all(seconds > 0 for seconds in figures["room_map_s"].values())
    assert figures["tiny_grid_ms"] > 0 and figures["worker_stop_s"] > 0
    text = doc.read_text()
    assert "Kept." in text
    block = text.split("<!-- bounded-work:start -->")[1].split("<!-- bounded-work:end -->")[0]
    assert "python -m bench.bounded_work --repeat 1" in block
    assert block.count("\n|") == 6  # header, rule and four figures
