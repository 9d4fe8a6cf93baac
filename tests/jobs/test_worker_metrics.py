"""Metrics of a standalone worker: process and jobs-by-status, on a port of their own."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from app.jobs.telemetry import serve_worker_metrics


def test_worker_metrics_endpoint_serves_process_and_job_metrics() -> None:
    counts = {"queued": 3, "running": 1, "succeeded": 7, "failed": 0}
    server = serve_worker_metrics(host="127.0.0.1", port=0, count_jobs=lambda: counts, workers=2)
    try:
        text = httpx.get(f"http://127.0.0.1:{server.port}/metrics", timeout=10).text
    finally:
        server.stop()
    assert 'vlp_jobs{status="queued"} 3.0' in text
    assert 'vlp_jobs{status="succeeded"} 7.0' in text
    assert "vlp_worker_threads 2.0" in text
    assert "process_cpu_seconds_total" in text and "process_resident_memory_bytes" in text
    with pytest.raises(httpx.TransportError):
        httpx.get(f"http://127.0.0.1:{server.port}/metrics", timeout=2)


def test_unreachable_registry_gives_no_job_sample() -> None:
    server = serve_worker_metrics(host="127.0.0.1", port=0, count_jobs=lambda: None, workers=1)
    try:
        text = httpx.get(f"http://127.0.0.1:{server.port}/metrics", timeout=10).text
    finally:
        server.stop()
    assert "vlp_jobs{" not in text and "process_cpu_seconds_total" in text


@pytest.mark.slow
def test_vlp_worker_metrics_port(tmp_path: Path) -> None:
    """A real `vlp worker --metrics-port 0`: it binds a port itself, logs it, and its
    /metrics answers there while it runs."""
    env = {**os.environ, "VLP_DATA_DIR": str(tmp_path), "OPENBLAS_NUM_THREADS": "1"}
    env.pop("VLP_DATABASE_URL", None)
    vlp = Path(sys.executable).with_name("vlp")
    log = tmp_path / "worker.log"
    with log.open("wb") as sink:
        process = subprocess.Popen(
            [str(vlp), "worker", "--metrics-port", "0"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=sink,
        )
    try:
        deadline = time.monotonic() + 60.0  # a safety net only
        port = _logged_metrics_port(process, log, deadline)
        while True:
            assert process.poll() is None, log.read_text()
            try:
                text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=2).text
                break
            except httpx.TransportError:
                assert time.monotonic() < deadline, "worker metrics never answered"
                time.sleep(0.1)
        assert 'vlp_jobs{status="queued"} 0.0' in text
        assert "process_cpu_seconds_total" in text
    finally:
        process.terminate()
        process.wait(timeout=30)


def _logged_metrics_port(process: subprocess.Popen[bytes], log: Path, deadline: float) -> int:
    """The port the worker's JSON log says its metrics server bound."""
    while True:
        assert process.poll() is None, log.read_text()
        for line in log.read_text(encoding="utf-8", errors="replace").splitlines():
            if '"metrics_port"' in line:
                return int(json.loads(line)["metrics_port"])
        assert time.monotonic() < deadline, "the worker never logged its metrics port"
        time.sleep(0.1)
