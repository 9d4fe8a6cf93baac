"""Every shell and Python block of the README and the pages it sends a reader to first (the
tutorials, the keys how-to) runs verbatim, or says why it cannot.

The curl and Python walkthroughs have their own tests (they also check the positions); this
module runs every other shell block and checks that no block is left out.
"""

from __future__ import annotations

import json

import pytest

from app.schemas.calibrations import calibration_example

from .readme_blocks import (
    PYTHON_WALKTHROUGH_FILE,
    REPO,
    RUN_PAGES,
    SHELL_LANGUAGES,
    Block,
    Checkout,
    readme_blocks,
)

pytestmark = pytest.mark.slow

# Blocks run by test_readme_walkthrough.py and test_readme_python_walkthrough.py.
_RUN_ELSEWHERE = ("walkthrough", "python-walkthrough")
# What each marked block must print (beyond exiting 0).
_EXPECTED_OUTPUT = {
    "keys-walkthrough": ["lobby kiosk", "revoked "],
    "batch-walkthrough": ["3 answers", "\n422\n"],
    "cli-walkthrough": [
        "estimates (gridless",
        '"status": "ready"',
        "LEDs flagged: 5 dimmed, 10 dead",
        "masked: [10]",
    ],
}


def _runs_elsewhere(block: Block) -> bool:
    return block.marker in _RUN_ELSEWHERE or PYTHON_WALKTHROUGH_FILE in block.code


def _run_here() -> list[Block]:
    return [
        block
        for block in readme_blocks()
        if block.language in SHELL_LANGUAGES
        and block.not_run_reason is None
        and not _runs_elsewhere(block)
    ]


def test_no_block_is_left_out() -> None:
    blocks = readme_blocks()
    assert {block.page for block in blocks} == set(RUN_PAGES), "a page without code blocks"
    for block in blocks:
        where = block.where
        assert block.language, f"{where}: a fenced block without a language"
        reason = block.not_run_reason
        if reason is not None:
            assert len(reason) >= 20, f"{where}: `not-run` needs a real reason, got {reason!r}"
            continue
        if block.language == "python":
            assert block.marker == "python-walkthrough", f"{where}: a Python block no test runs"
        elif block.language not in SHELL_LANGUAGES:
            assert block.language in ("json", "text"), f"{where}: unexpected {block.language}"
    # The one block that cannot run: `./run`/`./test` (it serves until stopped, and runs the
    # suite that runs this test).
    assert len([b for b in blocks if b.not_run_reason is not None]) <= 1
    assert {marker for marker in _EXPECTED_OUTPUT} <= {b.marker for b in _run_here()}


@pytest.mark.parametrize("block", _run_here(), ids=lambda block: block.name)
def test_block_runs_verbatim(block: Block, checkout: Checkout) -> None:
    result = checkout.run(block.code)
    assert result.returncode == 0, f"stdout:\n{result.stdout}\nstderr:\n{result.stderr}"
    for expected in _EXPECTED_OUTPUT.get(block.marker or "", []):
        assert expected in result.stdout, (expected, result.stdout)


def test_example_survey_is_the_documented_simulation() -> None:
    """examples/survey.json is calibration_example() (README: how the file was made)."""
    stored = json.loads((REPO / "examples" / "survey.json").read_text(encoding="utf-8"))
    assert stored == calibration_example()
