"""Background fingerprint builds: durable jobs claimed by workers, built in child processes."""

from __future__ import annotations

from .build import BuildTask, build_and_store
from .worker import EmbeddedWorkers, run_worker

__all__ = ["BuildTask", "EmbeddedWorkers", "build_and_store", "run_worker"]
