"""Real ``vlp serve`` and ``vlp worker`` processes for fault, concurrency and scale-out tests.

:class:`ProcessFleet` starts processes, each in its own process group with its JSON
log on a file, and on exit ends every group it started, build children included, even when
the test failed. ``kill -9`` in a test hits one process only (:meth:`VlpProcess.kill9`), as
the OOM killer or a crash would; the fleet still sweeps the group afterwards.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from tests.live_server import (
    ADMIN_KEY,
    TERMINAL_KEY,
    VLP,
    bound_url,
    serve_args,
    server_env,
    wait_until_healthy,
)
from tests.waiting import SAFETY_TIMEOUT_S

__all__ = [
    "ADMIN",
    "TERMINAL",
    "ProcessFleet",
    "VlpProcess",
    "child_pids",
    "peak_rss_bytes",
    "pid_alive",
    "process_fleet",
]

ADMIN = {"X-API-Key": ADMIN_KEY}
TERMINAL = {"X-API-Key": TERMINAL_KEY}

# A dead worker's job is reclaimed in seconds, not the production 30 s; a live worker renews
# its lease 20 times per lease, so a loaded machine does not lose it a job by a late beat.
FAST_JOBS = {
    "VLP_JOB_LEASE_SECONDS": "10",
    "VLP_JOB_HEARTBEAT_SECONDS": "0.5",
    "VLP_JOB_POLL_SECONDS": "0.1",
}


def child_pids(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux ``/proc``; empty once the process is gone)."""
    children: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            children += [int(n) for n in (task / "children").read_text().split()]
        except OSError:
            continue
    return children


def peak_rss_bytes(pid: int) -> int:
    """The peak resident memory of a live process so far (``VmHWM``), in bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"process {pid} reports no VmHWM")


def pid_alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in status


@dataclass
class VlpProcess:
    """One started ``vlp`` process: its command, log file and (for ``serve``) base URL."""

    kind: str
    process: subprocess.Popen[bytes]
    log_path: Path
    data_dir: Path
    url: str = ""

    @property
    def pid(self) -> int:
        """The process id."""
        return self.process.pid

    def build_children(self) -> list[int]:
        """The live child processes (build pool, resource tracker)."""
        return child_pids(self.pid)

    def kill9(self) -> None:
        """SIGKILL this process only (not its children) and reap it."""
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=30)

    def log(self) -> list[dict[str, Any]]:
        """The JSON log lines written so far (other lines skipped)."""
        entries = []
        for line in self.log_path.read_text(encoding="utf-8", errors="replace").splitlines():
            if line.startswith("{"):
                try:
                    entries.append(json.loads(line))
                except json.JSONDecodeError:  # a line cut by a kill
                    continue
        return entries

    def client(self) -> httpx.Client:
        """An HTTP client for this server (admin key by default)."""
        return httpx.Client(base_url=self.url, headers=ADMIN, timeout=30.0)


class ProcessFleet:
    """Starts ``vlp`` processes on one data directory and ends them all on :meth:`close`."""

    def __init__(self, data_dir: Path, **env: str) -> None:
        self.data_dir = data_dir
        self.env = {**FAST_JOBS, **env}
        self.processes: list[VlpProcess] = []

    def _start(self, kind: str, args: list[str], env: dict[str, str]) -> VlpProcess:
        index = len(self.processes)
        log_path = self.data_dir.parent / f"{kind}-{index}.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with log_path.open("ab") as log:
            process = subprocess.Popen(
                [str(VLP), kind, *args],
                env=server_env(self.data_dir, **{**self.env, **env}),
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        started = VlpProcess(kind=kind, process=process, log_path=log_path, data_dir=self.data_dir)
        self.processes.append(started)
        return started

    def serve(
        self, env: Mapping[str, str] | None = None, *, timeout_s: float = SAFETY_TIMEOUT_S
    ) -> VlpProcess:
        """Start ``vlp serve`` (with ``env`` on top of the fleet's) on a loopback port it picks
        and wait until ``/readyz`` is 200."""
        port_file = self.data_dir.parent / f"serve-{len(self.processes)}.port"
        server = self._start("serve", serve_args(port_file), dict(env or {}))
        server.url = bound_url(port_file, server.process, timeout_s)
        wait_until_healthy(server.url, server.process, timeout_s)
        return server

    def worker(self, **env: str) -> VlpProcess:
        """Start ``vlp worker`` (it claims jobs as soon as it has migrated)."""
        return self._start("worker", [], env)

    def close(self) -> None:
        """SIGTERM every process group, SIGKILL what is left after 10 s, reap everything.

        A group outlives its leader, so build children orphaned by a ``kill -9`` (they keep
        their process group when re-parented) are reached too.
        """
        for started in self.processes:
            _signal_group(started.pid, signal.SIGTERM)
        deadline = time.monotonic() + 10.0
        for started in self.processes:
            with suppress(subprocess.TimeoutExpired):
                started.process.wait(timeout=max(deadline - time.monotonic(), 0.1))
            _signal_group(started.pid, signal.SIGKILL)
            if started.process.poll() is None:
                started.process.kill()
                started.process.wait(timeout=10)


def _signal_group(pgid: int, signum: signal.Signals) -> None:
    try:
        os.killpg(pgid, signum)
    except (ProcessLookupError, PermissionError):
        return


@contextmanager
def process_fleet(data_dir: Path, **env: str) -> Iterator[ProcessFleet]:
    """A :class:`ProcessFleet` that is always cleaned up."""
    fleet = ProcessFleet(data_dir, **env)
    try:
        yield fleet
    finally:
        fleet.close()
