"""The fenced code blocks of the README and the pages it sends a reader to first, and running
one verbatim in a fresh shell.

The pages (:data:`RUN_PAGES`) are the README, the tutorials and the keys how-to: every shell
block there is meant to be pasted as it is. A block is run in a scratch checkout
(``examples/``, ``.venv`` and ``./vlp`` linked from this repository) whose ``var/`` is the data
directory of a live ``vlp serve`` started with no keys, so ``source var/credentials`` reads the
file that server generated. Shell blocks run with ``bash -e -o pipefail``: stricter than a
terminal, so any failing line fails the test.

Every shell or Python block of those pages must run in some test or carry
``<!-- not-run: REASON -->`` right before it (tests/e2e/test_readme_blocks.py checks that none
is left out).
"""

from __future__ import annotations

import re
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from tests.live_server import LiveServer, live_server

__all__ = [
    "PYTHON_WALKTHROUGH_FILE",
    "REPO",
    "RUN_PAGES",
    "SHELL_LANGUAGES",
    "Block",
    "Checkout",
    "block_with_marker",
    "readme_blocks",
    "readme_checkout",
]

REPO = Path(__file__).resolve().parents[2]
# The pages whose blocks a reader pastes as they are: each block runs verbatim in a test.
RUN_PAGES = (
    "README.md",
    "docs/tutorials/first-room-with-curl.md",
    "docs/tutorials/python-client.md",
    "docs/tutorials/survey-calibration.md",
    "docs/how-to/manage-keys.md",
)
SHELL_LANGUAGES = ("bash", "sh", "shell", "console")
# The README says to save its Python walkthrough under this name.
PYTHON_WALKTHROUGH_FILE = "walkthrough.py"
_FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```\s*$", re.DOTALL | re.MULTILINE)
_MARKER = re.compile(r"<!--\s*(.*?)\s*-->\s*$", re.DOTALL)


@dataclass(frozen=True)
class Block:
    """One fenced block: its language, code, the ``<!-- marker -->`` just before it, and
    where it is (page and line)."""

    language: str
    code: str
    marker: str | None
    line: int
    page: str = "README.md"

    @property
    def not_run_reason(self) -> str | None:
        """The reason given by a ``<!-- not-run: REASON -->`` marker, else None."""
        if self.marker is None or not self.marker.startswith("not-run:"):
            return None
        return self.marker.removeprefix("not-run:").strip()

    @property
    def name(self) -> str:
        """A test id: the marker, else the page, language and line."""
        if self.marker:
            return self.marker.split(":")[0]
        return f"{Path(self.page).stem}-{self.language}-line{self.line}"

    @property
    def where(self) -> str:
        """``page line N``, for messages."""
        return f"{self.page} line {self.line}"


def readme_blocks() -> list[Block]:
    """Every fenced block of the pages in :data:`RUN_PAGES`, in order."""
    blocks = []
    for page in RUN_PAGES:
        text = (REPO / page).read_text(encoding="utf-8")
        for match in _FENCE.finditer(text):
            before = text[: match.start()].rstrip("\n")
            last_line = before.rsplit("\n", 1)[-1]
            marker = _MARKER.search(last_line)
            blocks.append(
                Block(
                    language=match.group(1).strip(),
                    code=match.group(2),
                    marker=marker.group(1) if marker else None,
                    line=text.count("\n", 0, match.start()) + 1,
                    page=page,
                )
            )
    return blocks


def block_with_marker(marker: str) -> Block:
    """The one block whose marker is ``marker``."""
    found = [block for block in readme_blocks() if block.marker == marker]
    assert len(found) == 1, f"{len(found)} blocks are marked <!-- {marker} --> in {RUN_PAGES}"
    return found[0]


@dataclass(frozen=True)
class Checkout:
    """A scratch checkout next to a live server; ``run`` runs a shell block in it."""

    root: Path
    server: LiveServer

    def run(self, code: str, *, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
        """Run shell code verbatim in a fresh ``bash -e -o pipefail`` (no inherited env)."""
        return subprocess.run(
            ["bash", "-e", "-o", "pipefail", "-c", code],
            cwd=self.root,
            env={
                "PATH": "/usr/local/bin:/usr/bin:/bin",
                "HOME": str(self.root),
                "LANG": "C.UTF-8",
                "OPENBLAS_NUM_THREADS": "1",
                "COLUMNS": "200",
            },
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )


@contextmanager
def readme_checkout(root: Path) -> Iterator[Checkout]:
    """A scratch checkout whose ``var/`` is a live server's data dir (keys generated)."""
    root.mkdir(parents=True)
    for name in ("examples", ".venv", "vlp"):
        (root / name).symlink_to(REPO / name)
    python_walkthrough = block_with_marker("python-walkthrough")
    (root / PYTHON_WALKTHROUGH_FILE).write_text(python_walkthrough.code, encoding="utf-8")
    with live_server(root / "var", VLP_ADMIN_KEYS="", VLP_TERMINAL_KEYS="", VLP_DEMO="0") as server:
        yield Checkout(root=root, server=server)
