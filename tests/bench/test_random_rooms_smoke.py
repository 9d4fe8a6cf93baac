"""bench/random_rooms.py: its rooms are valid layouts, and a short run through a real server
answers every request."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from bench.random_rooms import FORMS, Outcome, main, random_layout, summary

pytestmark = pytest.mark.slow


def test_random_layouts_are_valid_and_bounded() -> None:
    kinds = set()
    for seed in range(200):
        layout = random_layout(np.random.default_rng([7, seed]))  # validated on construction
        assert layout.n_cells <= 6000
        xs = {round(led.x, 9) for led in layout.leds}
        ys = {round(led.y, 9) for led in layout.leds}
        kinds.add("row" if len(ys) == 1 and len(xs) > 1 else "other")
    assert kinds == {"row", "other"}  # single rows of LEDs are among them


def test_summary_counts_per_form() -> None:
    outcomes = [
        Outcome(0, 4, "power", 1, True, 30.0, False, 200, 1, 0.1, 1.0, "ok"),
        Outcome(0, 4, "power", 2, True, 30.0, False, 200, 2, 2.0, 0.5, "ok", True, True),
        Outcome(0, 4, "terminals", 1, False, 10.0, True, 500),
    ]
    table = summary(outcomes)
    assert "| power | 2 | 0 | 0 | 0 | 105 | 105 | 0.750 | 1 |" in table
    assert "| terminals | 1 | - |" in table
    assert "| all | 3 | 1 | 0 | 0 | 105 | 105 | 0.750 | 1 |" in table


def test_a_short_run_answers_every_request(tmp_path: Path) -> None:
    """At noise levels outside the default draws too (0 and 60 dB)."""
    page = tmp_path / "results" / "random-rooms.md"
    page.parent.mkdir()
    page.write_text("# Random rooms\n\nhand-written\n")
    argv = ["--rooms", "2", "--trials", "3", "--snr-db", "0,60", "--out", str(tmp_path)]
    assert main(argv) == 0
    text = page.read_text()
    assert text.startswith("# Random rooms\n\nhand-written\n")
    with (tmp_path / "data" / "random_rooms.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 2 * 3
    assert {row["status"] for row in rows} == {"200"}  # no 4xx, no 5xx
    assert {float(row["snr_db"]) for row in rows} <= {0.0, 60.0}
    assert f"| {FORMS[0]} |" in text and "| all | 6 | 0 | 0 | 0 |" in text
    assert "--snr-db 0,60" in text  # the command that made the table


@pytest.mark.parametrize("value", ["", "ten", "10,nan", "10,,20"])
def test_snr_list_must_be_finite_numbers(value: str) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--snr-db", value])
    assert exit_info.value.code == 2  # argparse's usage error, before any server starts
