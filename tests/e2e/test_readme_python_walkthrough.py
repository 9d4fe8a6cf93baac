"""The Python-client tutorial's walkthrough, run verbatim against a live server."""

from __future__ import annotations

import json
import math

import pytest
from scipy.optimize import linear_sum_assignment

from .readme_blocks import PYTHON_WALKTHROUGH_FILE, Checkout, readme_blocks

pytestmark = pytest.mark.slow


def _points(lines: list[str], label: str) -> list[tuple[float, float]]:
    prefix = f"{label} "
    return [
        tuple(json.loads(line.removeprefix(prefix))) for line in lines if line.startswith(prefix)
    ]


def _run_line() -> str:
    """The tutorial's shell block that runs the saved walkthrough."""
    found = [
        block.code
        for block in readme_blocks()
        if block.language == "bash" and PYTHON_WALKTHROUGH_FILE in block.code
    ]
    assert len(found) == 1, found
    return found[0]


def test_readme_python_walkthrough_runs_and_localizes(checkout: Checkout) -> None:
    result = checkout.run(_run_line(), timeout_s=180)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[-17] == "fingerprint: ready" and lines[-18] == "build 100%", lines
    truth, estimates = _points(lines, "truth"), _points(lines, "estimate")
    assert len(truth) == 8 and len(estimates) == 8
    # The same simulation as the curl walkthrough, so the same bound (see that test).
    distances = [[math.hypot(tx - ex, ty - ey) for ex, ey in estimates] for tx, ty in truth]
    rows, cols = linear_sum_assignment(distances)
    errors = [distances[r][c] for r, c in zip(rows, cols, strict=True)]
    assert sum(errors) / len(errors) < 0.25
