"""Run a real ``vlp serve`` process on a free loopback port (end-to-end and process tests).

The server binds port 0 itself and writes the port it got to a file (``--port-file``), so no
other process can take the port between choosing and binding it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

__all__ = [
    "ADMIN_KEY",
    "TERMINAL_KEY",
    "VLP",
    "LiveServer",
    "bound_url",
    "live_server",
    "serve_args",
    "server_env",
    "wait_until_healthy",
]

REPO_ROOT = Path(__file__).resolve().parents[1]
ADMIN_KEY = "e2e-admin-key-0123456789"
TERMINAL_KEY = "e2e-terminal-key-0123456789"
VLP = Path(sys.executable).with_name("vlp")


@dataclass(frozen=True)
class LiveServer:
    """A running server: its base URL, data directory and process."""

    url: str
    data_dir: Path
    process: subprocess.Popen[bytes]


def serve_args(port_file: Path) -> list[str]:
    """Arguments of ``vlp serve`` for a loopback port of the kernel's choosing, reported in
    ``port_file``."""
    return ["--host", "127.0.0.1", "--port", "0", "--port-file", str(port_file)]


def bound_url(port_file: Path, process: subprocess.Popen[bytes], timeout_s: float) -> str:
    """The base URL of a server started with :func:`serve_args`, once it has bound.

    Raises
    ------
    RuntimeError
        When the process exits first.
    TimeoutError
        When no port is reported within ``timeout_s`` (a safety timeout).
    """
    deadline = time.monotonic() + timeout_s
    while not port_file.exists():
        if process.poll() is not None:
            raise RuntimeError(f"server exited early with code {process.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"the server reported no port in {port_file} after {timeout_s} s")
        time.sleep(0.05)
    return f"http://127.0.0.1:{int(port_file.read_text(encoding='utf-8'))}"


def server_env(data_dir: Path, **extra: str) -> dict[str, str]:
    """Environment for a server process with known keys and one-thread BLAS, importing the
    ``app`` of this source tree (the ``vlp`` command would else import the one installed in
    the environment, which may be another checkout's)."""
    env = dict(os.environ)
    env.update(
        PYTHONPATH=os.pathsep.join(
            part for part in (str(REPO_ROOT), os.environ.get("PYTHONPATH", "")) if part
        ),
        VLP_DATA_DIR=str(data_dir),
        VLP_ADMIN_KEYS=ADMIN_KEY,
        VLP_TERMINAL_KEYS=TERMINAL_KEY,
        OPENBLAS_NUM_THREADS="1",
        OMP_NUM_THREADS="1",
    )
    env.update(extra)
    return env


def wait_until_healthy(url: str, process: subprocess.Popen[bytes], timeout_s: float) -> None:
    """Poll ``/readyz`` until it answers 200; fail if the process exits first."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"server exited early with code {process.returncode}")
        try:
            if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise TimeoutError(f"server at {url} not ready after {timeout_s} s")


@contextmanager
def live_server(data_dir: Path, *, timeout_s: float = 120.0, **env: str) -> Iterator[LiveServer]:
    """Start ``vlp serve`` on a free port; stop it (SIGTERM, then SIGKILL) on exit."""
    port_file = data_dir / "serve.port"
    port_file.unlink(missing_ok=True)
    process = subprocess.Popen(
        [str(VLP), "serve", *serve_args(port_file)],
        env=server_env(data_dir, **env),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        url = bound_url(port_file, process, timeout_s)
        wait_until_healthy(url, process, timeout_s)
        yield LiveServer(url=url, data_dir=data_dir, process=process)
    finally:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
