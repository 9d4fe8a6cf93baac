"""The test side of the build gate: ``VLP_TEST_BUILD_GATE`` (``app.jobs.build._BuildGate``).

A fault test shuts the gate, lets a real build run into it, learns from the marker file that
the build is held at the chosen progress, does its harm (``kill -9``, a second worker, a
stepped clock) and opens the gate. What happens when no longer depends on the machine's speed.
"""

from __future__ import annotations

from pathlib import Path

from tests.waiting import SAFETY_TIMEOUT_S, wait_for

__all__ = ["BuildGate"]


class BuildGate:
    """A gate file and its ``.held`` marker.

    Parameters
    ----------
    path : Path
        The gate file (created by :meth:`shut`, deleted by :meth:`open`).
    at : float, default=0.0
        The progress fraction at which the held build waits.
    """

    def __init__(self, path: Path, at: float = 0.0) -> None:
        self.path = path
        self.at = at
        self.marker = path.with_name(f"{path.name}.held")

    def env(self) -> dict[str, str]:
        """The environment that arms the hook in a ``vlp`` process or a build pool."""
        return {"VLP_TEST_BUILD_GATE": str(self.path), "VLP_TEST_BUILD_GATE_AT": repr(self.at)}

    def shut(self) -> None:
        """Hold the next build that reaches ``at`` (one build per shutting)."""
        self.marker.unlink(missing_ok=True)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.touch()

    def wait_held(self, timeout_s: float = SAFETY_TIMEOUT_S) -> str:
        """Wait until a build is held at the gate; the id of its job."""
        wait_for(self.marker.exists, f"a build to be held at {self.path}", timeout_s)
        return self.marker.read_text(encoding="utf-8")

    def open(self) -> None:
        """Let the held build go on (and every later build pass)."""
        self.path.unlink(missing_ok=True)
