"""bench/plots.py: Fig. 4 re-drawn from the stored summary keeps its legend inside the picture."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bench.plots import fig4, read_summary
from bench.results import SUMMARY_HEADER, summary_tuple

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
SUMMARY = REPO / "docs" / "data" / "accuracy_summary.csv"


def test_read_summary_round_trips_the_csv() -> None:
    with SUMMARY.open(newline="", encoding="utf-8") as handle:
        reader = csv.reader(handle)
        assert tuple(next(reader)) == SUMMARY_HEADER
        stored = [tuple(row) for row in reader]
    again = [tuple(str(value) for value in summary_tuple(s)) for s in read_summary(SUMMARY)]
    assert again == stored


@pytest.mark.parametrize("room", ["hall", "paper"])
def test_fig4_draws_nothing_on_its_edges(room: str, tmp_path: Path) -> None:
    """A legend cut off by the canvas leaves ink on the picture's outermost pixels."""
    path = fig4(read_summary(SUMMARY), room, tmp_path / "fig4.png")
    pixels = np.asarray(Image.open(io.BytesIO(path.read_bytes())).convert("L"))
    edges = np.concatenate([pixels[:, :2].ravel(), pixels[:, -2:].ravel(), pixels[-2:, :].ravel()])
    assert edges.min() >= 250, f"ink on the edge of {room}'s figure"
