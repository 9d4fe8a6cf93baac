"""HTTP benchmark: localize latency and throughput of one uvicorn worker on loopback.

Paper room, K = 8, correlation measurements at 30 dB, default solver. Reports sequential
localize latency (p50, p99) and concurrent throughput of localize against a trivial endpoint
(`/healthz`) measured in the same run, and their ratio.

    python -m bench.http [--seconds 10] [--concurrency 8]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from bench._server import TERMINAL_KEY, live_server, ready_demo_room


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


async def _throughput(
    url: str, path: str, body: dict[str, object] | None, seconds: float, concurrency: int
) -> tuple[float, int]:
    headers = {"X-API-Key": TERMINAL_KEY}
    done = 0
    errors = 0
    stop_at = time.monotonic() + seconds

    async def worker(client: httpx.AsyncClient) -> None:
        nonlocal done, errors
        while time.monotonic() < stop_at:
            if body is None:
                response = await client.get(path, headers=headers)
            else:
                response = await client.post(path, headers=headers, json=body)
            if response.status_code == 200:
                done += 1
            else:
                errors += 1

    limits = httpx.Limits(max_connections=concurrency)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=30.0) as client:
        start = time.monotonic()
        await asyncio.gather(*(worker(client) for _ in range(concurrency)))
        elapsed = time.monotonic() - start
    return done / elapsed, errors


def run(seconds: float, concurrency: int, sequential: int) -> dict[str, object]:
    """Start a server, measure, and return the figures."""
    with tempfile.TemporaryDirectory() as tmp, live_server(Path(tmp)) as server:
        url = server.url
        with httpx.Client(timeout=30.0) as client:
            room_id = ready_demo_room(url)
            headers = {"X-API-Key": TERMINAL_KEY}
            sim = client.post(
                f"{url}/v1/rooms/{room_id}/simulate",
                headers=headers,
                json={"targets": 8, "snr_db": 30, "seed": 1},
            ).json()
            body = sim["measurement"]
            path = f"/v1/rooms/{room_id}/localize"
            for _ in range(20):  # warm the fingerprint and solver caches
                client.post(f"{url}{path}", headers=headers, json=body).raise_for_status()
            latencies = []
            for _ in range(sequential):
                start = time.perf_counter()
                client.post(f"{url}{path}", headers=headers, json=body).raise_for_status()
                latencies.append((time.perf_counter() - start) * 1000.0)
        trivial_rps, trivial_errors = asyncio.run(
            _throughput(url, "/healthz", None, seconds, concurrency)
        )
        localize_rps, localize_errors = asyncio.run(
            _throughput(url, path, body, seconds, concurrency)
        )
    return {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": f"{platform.processor() or platform.machine()}, {_cpu_model()}",
        "sequential_requests": sequential,
        "localize_p50_ms": round(statistics.median(latencies), 2),
        "localize_p99_ms": round(_percentile(latencies, 99), 2),
        "concurrency": concurrency,
        "seconds_per_phase": seconds,
        "trivial_rps": round(trivial_rps, 1),
        "localize_rps": round(localize_rps, 1),
        "throughput_ratio": round(localize_rps / trivial_rps, 3),
        "errors": trivial_errors + localize_errors,
    }


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.http`` and ``vlp bench http``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="per throughput phase")
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--sequential", type=int, default=300)
    args = parser.parse_args(argv)
    print(json.dumps(run(args.seconds, args.concurrency, args.sequential), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
