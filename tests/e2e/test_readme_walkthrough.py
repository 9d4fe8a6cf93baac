"""The README's curl walkthrough, run verbatim against a live server."""

from __future__ import annotations

import json
import math
import re
import subprocess
from pathlib import Path

from scipy.optimize import linear_sum_assignment

from bench._server import ADMIN_KEY, TERMINAL_KEY, live_server

REPO = Path(__file__).resolve().parents[2]


def walkthrough_script() -> str:
    """The bash block that follows the ``<!-- walkthrough -->`` marker in README.md."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    match = re.search(r"<!-- walkthrough -->\s*```bash\n(.*?)```", readme, re.DOTALL)
    assert match, "README.md has no walkthrough block"
    return match.group(1)


def test_readme_walkthrough_runs_and_localizes(tmp_path: Path) -> None:
    script = walkthrough_script()
    with live_server(tmp_path / "data", VLP_DEMO="0") as server:
        result = subprocess.run(
            ["bash", "-euo", "pipefail", "-c", script],
            cwd=REPO,
            env={
                "VLP": server.url,
                "ADMIN_KEY": ADMIN_KEY,
                "TERMINAL_KEY": TERMINAL_KEY,
                "PATH": "/usr/local/bin:/usr/bin:/bin",
            },
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0] == "build: succeeded"
    truth = [json.loads(line) for line in lines[1:9]]
    estimates = [json.loads(line) for line in lines[9:]]
    assert len(truth) == 8 and len(estimates) == 8
    # Hungarian-matched mean error, computed here independently of the service's metrics:
    # at 30 dB and K = 8 the default solver's median is ~5 cm (docs/accuracy.md), but seed 7
    # places a close pair and gives 16.5 cm (the in-process solver gives the same); 0.25 m
    # still fails when an estimate is missing or lands on the wrong terminal.
    rows, cols = linear_sum_assignment(
        [[math.hypot(tx - ex, ty - ey) for ex, ey in estimates] for tx, ty in truth]
    )
    errors = [
        math.hypot(truth[r][0] - estimates[c][0], truth[r][1] - estimates[c][1])
        for r, c in zip(rows, cols, strict=True)
    ]
    assert sum(errors) / len(errors) < 0.25
