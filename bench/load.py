"""Load test: localize at rising concurrency against a real ``vlp serve`` on loopback.

Starts its own server on a free 127.0.0.1 port (demo room: the paper's 4 x 4 m room,
16 LEDs), simulates one K = 8 correlation measurement at 30 dB and posts it to localize from
an async httpx client at each concurrency level for an equal share of ``--seconds``. Every
level is bounded in time (no new request after its deadline, 30 s per request), so the whole
run ends by itself. Reports per level: requests, throughput, p50/p99 latency and errors
(non-200 answers and transport failures). Other work on the machine changes the figures: run it
on a quiet machine.

    python -m bench.load --seconds 60 [--levels 1,2,4,8,16] [--solver gridless]
        [--update-doc docs/results/load.md]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path

import httpx
import numpy as np

from bench._common import machine_markdown, machine_record, replace_section
from bench._server import ADMIN_KEY, TERMINAL_KEY, live_server, ready_demo_room

__all__ = ["LevelResult", "LoadReport", "main", "markdown", "run"]

REQUEST_TIMEOUT_S = 30.0
_PREAMBLE = "# Results: load\n"


@dataclass(frozen=True)
class LevelResult:
    """What one concurrency level did (latencies in ms, throughput in answered requests/s)."""

    concurrency: int
    seconds: float
    requests: int
    ok: int
    throughput_rps: float
    p50_ms: float
    p99_ms: float
    max_ms: float
    errors: dict[str, int]


async def _drive(
    client: httpx.AsyncClient, path: str, body: dict[str, object], concurrency: int, seconds: float
) -> LevelResult:
    latencies: list[float] = []
    errors: Counter[str] = Counter()
    stop_at = time.monotonic() + seconds

    async def user() -> None:
        while time.monotonic() < stop_at:
            started = time.perf_counter()
            try:
                response = await client.post(path, json=body)
            except httpx.HTTPError as exc:
                errors[type(exc).__name__] += 1
                continue
            if response.status_code == 200:
                latencies.append((time.perf_counter() - started) * 1000.0)
            else:
                errors[f"HTTP {response.status_code}"] += 1

    start = time.monotonic()
    await asyncio.gather(*(user() for _ in range(concurrency)))
    elapsed = time.monotonic() - start
    ok = len(latencies)
    return LevelResult(
        concurrency=concurrency,
        seconds=round(elapsed, 1),
        requests=ok + sum(errors.values()),
        ok=ok,
        throughput_rps=round(ok / elapsed, 2),
        p50_ms=round(statistics.median(latencies), 1) if latencies else float("nan"),
        p99_ms=round(float(np.percentile(latencies, 99)), 1) if latencies else float("nan"),
        max_ms=round(max(latencies), 1) if latencies else float("nan"),
        errors=dict(errors),
    )


def _measurement(url: str, solver: str) -> tuple[str, dict[str, object]]:
    """The demo room's id (once ready) and a K = 8 measurement body for it."""
    room_id = ready_demo_room(url)
    admin = {"X-API-Key": ADMIN_KEY}
    with httpx.Client(base_url=url, headers=admin, timeout=REQUEST_TIMEOUT_S) as client:
        simulated = client.post(
            f"/v1/rooms/{room_id}/simulate",
            json={"targets": 8, "snr_db": 30, "seed": 1, "solver": solver},
        )
        simulated.raise_for_status()
    body: dict[str, object] = simulated.json()["measurement"]
    return room_id, body


async def _levels(
    url: str, room_id: str, body: dict[str, object], levels: list[int], seconds: float
) -> list[LevelResult]:
    path = f"/v1/rooms/{room_id}/localize"
    limits = httpx.Limits(max_connections=max(levels))
    headers = {"X-API-Key": TERMINAL_KEY}
    async with httpx.AsyncClient(
        base_url=url, limits=limits, timeout=REQUEST_TIMEOUT_S, headers=headers
    ) as client:
        for _ in range(5):  # load the fingerprint and prepare the solver before timing
            (await client.post(path, json=body)).raise_for_status()
        return [await _drive(client, path, body, level, seconds) for level in levels]


@dataclass(frozen=True)
class LoadReport:
    """One run: where, under what background load, and each level's figures."""

    machine: dict[str, str]
    solver: str
    seconds: float
    levels: list[LevelResult]


def run(seconds: float, levels: list[int], solver: str) -> LoadReport:
    """Start a server, drive each level for ``seconds / len(levels)``, return the figures."""
    with tempfile.TemporaryDirectory() as tmp, live_server(Path(tmp)) as server:
        room_id, body = _measurement(server.url, solver)
        results = asyncio.run(_levels(server.url, room_id, body, levels, seconds / len(levels)))
    return LoadReport(
        machine=machine_record(),
        solver=solver,
        seconds=seconds,
        levels=results,
    )


def markdown(report: LoadReport, command: str) -> str:
    """The report as the load results block of docs/results/load.md."""
    rows = [
        "| concurrency | seconds | requests | ok | throughput (req/s) | p50 (ms) | p99 (ms) "
        "| max (ms) | errors |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for level in report.levels:
        errors = ", ".join(f"{kind}: {count}" for kind, count in level.errors.items()) or "0"
        rows.append(
            f"| {level.concurrency} | {level.seconds} | {level.requests} | {level.ok} | "
            f"{level.throughput_rps} | {level.p50_ms} | {level.p99_ms} | {level.max_ms} | "
            f"{errors} |"
        )
    return (
        f"Command: `{command}` (solver `{report.solver}`, paper room, K = 8, correlation "
        f"at 30 dB, one uvicorn worker, loopback).\n\n{machine_markdown(report.machine)}\n\n"
        + "\n".join(rows)
        + "\n"
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.load``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="total, split over levels")
    parser.add_argument("--levels", default="1,2,4,8,16", help="comma-separated concurrencies")
    parser.add_argument("--solver", default="gridless")
    parser.add_argument("--update-doc", type=Path, help="rewrite the load block of this file")
    args = parser.parse_args(argv)
    levels = [int(level) for level in args.levels.split(",")]
    if not levels or min(levels) < 1 or max(levels) > 256 or args.seconds <= 0:
        parser.error("--levels must be integers in 1..256 and --seconds positive")
    report = run(args.seconds, levels, args.solver)
    print(json.dumps(asdict(report), indent=2))
    if args.update_doc is not None:
        command = "python -m bench.load " + " ".join(argv if argv is not None else sys.argv[1:])
        replace_section(args.update_doc, "load", markdown(report, command), preamble=_PREAMBLE)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
