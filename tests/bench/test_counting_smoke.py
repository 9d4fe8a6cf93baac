"""bench/counting.py runs end to end and writes its section."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.counting import count_cell, main

pytestmark = pytest.mark.slow


def test_counting_cell_counts_every_placement() -> None:
    cell = count_cell("paper", 1, 1.0, 3)
    assert sum(cell.counts.values()) == 3
    # One target as modelled is always counted (the solver's counting tests cover more).
    assert cell.right == 1.0 and cell.counts == {1: 3}
    assert 0.0 < cell.error < 0.2


def test_counting_writes_its_section(tmp_path: Path) -> None:
    page = tmp_path / "results" / "counting.md"
    page.parent.mkdir()
    page.write_text(
        "# Counting\n\nbefore\n<!-- counting:start -->\nold\n<!-- counting:end -->\nafter\n"
    )
    assert main(["--ks", "1", "--scales", "1.0", "--trials", "2", "--out", str(tmp_path)]) == 0
    text = page.read_text()
    assert "old" not in text and text.startswith("# Counting\n\nbefore\n")
    assert text.rstrip().endswith("after")
    assert "| paper | ideal | 1 | 1 | 1.00 | 1: 2 |" in text
