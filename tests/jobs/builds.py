"""Build functions the worker tests run in the pool's child processes (importable by name)."""

from __future__ import annotations

import os
import threading

from app.jobs.build import BuildTask
from app.registry.queue import StoredBuild

__all__ = ["crash_build", "endless_build"]


def crash_build(task: BuildTask) -> StoredBuild:
    """A build whose process dies."""
    del task
    os._exit(3)


def endless_build(task: BuildTask) -> StoredBuild:
    """A build that never ends: only stopping the pool ends its process."""
    del task
    threading.Event().wait()
    raise AssertionError("unreachable")
