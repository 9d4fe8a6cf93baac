"""Smoke test of the load benchmark: a short run end to end (not a timing test)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_load_benchmark_runs_and_rewrites_only_its_block(tmp_path: Path) -> None:
    doc = tmp_path / "load.md"
    doc.write_text("# Results: load\n\n## Load\n\nKept.\n\n## Reading it\n\nAlso kept.\n")
    args = ["--seconds", "2", "--levels", "1,2", "--solver", "nnls", "--update-doc", str(doc)]
    result = subprocess.run(
        [sys.executable, "-m", "bench.load", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert [level["concurrency"] for level in report["levels"]] == [1, 2]
    for level in report["levels"]:
        assert level["ok"] > 0 and level["errors"] == {}
        assert level["requests"] == level["ok"]
        assert 0 < level["p50_ms"] <= level["p99_ms"] <= level["max_ms"]
    text = doc.read_text()
    assert "Kept." in text and "Also kept." in text
    block = text.split("<!-- load:start -->")[1].split("<!-- load:end -->")[0]
    assert block.count("\n| 1 |") == 1 and block.count("\n| 2 |") == 1
    assert "python -m bench.load --seconds 2" in block
