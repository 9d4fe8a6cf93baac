"""A real ``vlp serve`` process for the benchmarks that measure through HTTP.

The server binds a free loopback port itself and reports it in a file; it imports the
``app`` of this source tree and knows two keys, one per role.
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

from ._common import REPO_ROOT

__all__ = ["ADMIN_KEY", "TERMINAL_KEY", "LiveServer", "live_server", "ready_demo_room"]

ADMIN_KEY = "bench-admin-key-0123456789"
TERMINAL_KEY = "bench-terminal-key-0123456789"


@dataclass(frozen=True)
class LiveServer:
    """A running server: its base URL, data directory and process."""

    url: str
    data_dir: Path
    process: subprocess.Popen[bytes]


@contextmanager
def live_server(
    data_dir: Path, *, timeout_s: float = 120.0, source: Path = REPO_ROOT, **env: str
) -> Iterator[LiveServer]:
    """Start ``vlp serve`` (BLAS on one thread, ``env`` added) until it is ready; stop it on
    exit. The server imports the ``app`` of the source tree ``source`` (default: this one).

    Raises
    ------
    RuntimeError
        When the server exits before it is ready.
    TimeoutError
        When it is not ready within ``timeout_s``.
    """
    port_file = data_dir / "serve.port"
    port_file.unlink(missing_ok=True)
    python_path = os.pathsep.join(filter(None, (str(source), os.environ.get("PYTHONPATH"))))
    vlp = Path(sys.executable).with_name("vlp")
    process = subprocess.Popen(
        [str(vlp), "serve", "--host", "127.0.0.1", "--port", "0", "--port-file", str(port_file)],
        env={
            **os.environ,
            "PYTHONPATH": python_path,
            "VLP_DATA_DIR": str(data_dir),
            "VLP_ADMIN_KEYS": ADMIN_KEY,
            "VLP_TERMINAL_KEYS": TERMINAL_KEY,
            "OPENBLAS_NUM_THREADS": "1",
            "OMP_NUM_THREADS": "1",
            **env,
        },
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        url = _wait_until_ready(port_file, process, time.monotonic() + timeout_s)
        yield LiveServer(url=url, data_dir=data_dir, process=process)
    finally:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _wait_until_ready(port_file: Path, process: subprocess.Popen[bytes], deadline: float) -> str:
    url = None
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"server exited early with code {process.returncode}")
        if url is None and port_file.exists():
            url = f"http://127.0.0.1:{int(port_file.read_text(encoding='utf-8'))}"
        try:
            if url is not None and httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                return url
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise TimeoutError(f"the server was not ready in time (port file {port_file})")


def ready_demo_room(url: str, *, timeout_s: float = 120.0) -> str:
    """The id of the server's demo room once its fingerprint is ready.

    Raises
    ------
    TimeoutError
        When it is not ready within ``timeout_s``.
    """
    with httpx.Client(base_url=url, headers={"X-API-Key": ADMIN_KEY}, timeout=30.0) as client:
        room_id = str(client.get("/v1/rooms").json()["items"][0]["id"])
        deadline = time.monotonic() + timeout_s
        while client.get(f"/v1/rooms/{room_id}").json()["fingerprint"]["status"] != "ready":
            if time.monotonic() > deadline:
                raise TimeoutError(f"the demo room was not built within {timeout_s:g} s")
            time.sleep(0.1)
    return room_id
