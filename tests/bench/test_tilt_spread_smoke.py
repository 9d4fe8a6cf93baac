"""``bench/tilt_spread.py`` runs end to end and writes its section."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench import tilt_spread

pytestmark = pytest.mark.slow


def test_one_placement_per_case_writes_the_section(tmp_path: Path, small_room: str) -> None:
    argv = ["--trials", "1", "--rooms", small_room, "--out", str(tmp_path)]
    assert tilt_spread.main(argv) == 0
    text = (tmp_path / "results" / "tilt-spread.md").read_text(encoding="utf-8")
    rows = [line for line in text.splitlines() if line.startswith(f"| {small_room} |")]
    assert [row.split(" | ")[1] for row in rows] == [case.name for case in tilt_spread.CASES]


def test_the_declared_spread_refits_tilted_terminals() -> None:
    outcome = tilt_spread.run_case("paper", tilt_spread.Case("tilt 0-20 deg"), 1)
    for name in ("as given", "declared"):
        assert outcome.errors[name].shape == (tilt_spread.COUNT,)
        assert np.all(np.isfinite(outcome.radii[name]) & (outcome.radii[name] > 0))
    # The same draws: the declared spread refits the tilts, so the answers differ.
    assert not np.array_equal(outcome.errors["as given"], outcome.errors["declared"])
