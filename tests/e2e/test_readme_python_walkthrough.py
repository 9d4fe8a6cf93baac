"""The README's Python-client walkthrough, run verbatim against a live server."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

from scipy.optimize import linear_sum_assignment

from bench._server import ADMIN_KEY, TERMINAL_KEY, live_server

REPO = Path(__file__).resolve().parents[2]


def python_walkthrough() -> str:
    """The python block that follows the ``<!-- python-walkthrough -->`` marker in README.md."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    match = re.search(r"<!-- python-walkthrough -->\s*```python\n(.*?)```", readme, re.DOTALL)
    assert match, "README.md has no python walkthrough block"
    return match.group(1)


def _points(lines: list[str], label: str) -> list[tuple[float, float]]:
    prefix = f"{label} "
    return [
        tuple(json.loads(line.removeprefix(prefix))) for line in lines if line.startswith(prefix)
    ]


def test_readme_python_walkthrough_runs_and_localizes(tmp_path: Path) -> None:
    with live_server(tmp_path / "data", VLP_DEMO="0") as server:
        result = subprocess.run(
            [sys.executable, "-c", python_walkthrough()],
            cwd=REPO,
            env={
                "VLP": server.url,
                "ADMIN_KEY": ADMIN_KEY,
                "TERMINAL_KEY": TERMINAL_KEY,
                "OPENBLAS_NUM_THREADS": "1",
                "PATH": "/usr/local/bin:/usr/bin:/bin",
            },
            capture_output=True,
            text=True,
            timeout=120,
        )
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
