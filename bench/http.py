"""HTTP benchmark: the localize path over loopback, real ``vlp serve`` processes.

Paper room (the demo room), K = 8 correlation measurements at 30 dB (seeds 0..N-1, cycled),
default solver unless said otherwise, BLAS one thread. Each figure is a ratio measured in
one run (``ratios`` in the output collects them):

(a) sequential client, one API process: localize p50 against ``/healthz`` p50, the two
    requests interleaved so both see the same load; the service's own cost around a solve,
    ``(localize p50 - solver p50) / healthz p50`` (the solver's time is each answer's
    ``elapsed_ms``); also localize with the ``omp`` solver (the path with an almost free
    solver), and the server process's CPU time per request of each kind, which a loaded
    shared machine does not stretch as it does latency;
(b) throughput at concurrency C (default 8) of ``vlp serve --workers 2`` against
    ``--workers 1``: both servers run for the whole benchmark, phases alternate between them
    (W1, W2, W2, W1, ...), medians over the rounds;
(c) a batch of B (default 100) measurements in one ``localize/batch`` request: its wall time
    against the sum of its items' solver times (``elapsed_ms``), and against the same B sent
    as single requests one after another (one keep-alive connection), alternating, medians;
    again with the ``omp`` solver, where the solve is nearly free and what a batch saves
    (HTTP, key check, lookups per request) shows;
(d) the one-worker API process's peak resident memory (``VmHWM``) once it is ready, before
    any request.

Bodies are encoded to JSON once, before any timing: the client's own encoding (tens of
milliseconds for a batch of 100 matrices) is not what the service adds around a solve.

    python -m bench.http [--sequential 300] [--seconds 5] [--rounds 5] [--concurrency 8]
                         [--batch 100] [--batch-rounds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench._server import TERMINAL_KEY, LiveServer, live_server, ready_demo_room

_HEADERS = {"X-API-Key": TERMINAL_KEY}
_JSON = {"Content-Type": "application/json"}
# Seconds of load that warm each server before its throughput phases (at most a phase).
_WARM_S = 2.0


def _measurements(url: str, room_id: str, count: int) -> list[dict[str, Any]]:
    """``count`` K = 8 correlation measurements at 30 dB (seeds 0..count-1), current version."""
    bodies = []
    with httpx.Client(base_url=url, headers=_HEADERS, timeout=60.0) as client:
        for seed in range(count):
            simulation = client.post(
                f"/v1/rooms/{room_id}/simulate", json={"targets": 8, "snr_db": 30, "seed": seed}
            )
            simulation.raise_for_status()
            body = simulation.json()["measurement"]
            body.pop("fingerprint_version", None)
            bodies.append(body)
    return bodies


def _encoded(body: Any) -> bytes:
    """``body`` as the JSON bytes a client would send (encoded once, outside any timing)."""
    return json.dumps(body, separators=(",", ":")).encode("utf-8")


def _post(client: httpx.Client, path: str, content: bytes) -> httpx.Response:
    return client.post(path, content=content, headers=_JSON)


def _peak_rss_mib(pid: int) -> float:
    """A process's peak resident memory so far (``VmHWM``), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text(encoding="utf-8").splitlines():
        key, _, rest = line.partition(":")
        if key == "VmHWM":
            return int(rest.split()[0]) / 1024
    raise RuntimeError(f"no VmHWM in /proc/{pid}/status")


def _ratio(numerator: float, denominator: float) -> float | None:
    return round(numerator / denominator, 2) if denominator > 0 else None


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (all its threads), from ``/proc``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _server_cpu_ms(
    client: httpx.Client, pid: int, requests: int, send: Callable[[httpx.Client, int], object]
) -> float:
    """The server's CPU milliseconds per request over ``requests`` requests made by ``send``:
    unlike latency, what a loaded, shared machine does not stretch."""
    before = _cpu_seconds(pid)
    for index in range(requests):
        send(client, index)
    return (_cpu_seconds(pid) - before) / requests * 1e3


def _sequential(
    server: LiveServer, room_id: str, bodies: list[dict[str, Any]], requests: int
) -> dict[str, float | None]:
    """(a): interleaved healthz / localize / localize(omp), one connection; then the server's
    CPU time per request of each kind."""
    url = server.url
    path = f"/v1/rooms/{room_id}/localize"
    healthz, default, omp, solver = [], [], [], []
    encoded = [_encoded(body) for body in bodies]
    encoded_omp = [_encoded({**body, "solver": "omp"}) for body in bodies]
    with httpx.Client(base_url=url, headers=_HEADERS, timeout=60.0) as client:
        for index in range(min(20, len(bodies))):  # warm the fingerprint and solver caches
            _post(client, path, encoded[index]).raise_for_status()
            _post(client, path, encoded_omp[index]).raise_for_status()
        for index in range(requests):
            start = time.perf_counter()
            client.get("/healthz").raise_for_status()
            healthz.append(time.perf_counter() - start)
            start = time.perf_counter()
            answer = _post(client, path, encoded[index % len(bodies)])
            default.append(time.perf_counter() - start)
            answer.raise_for_status()
            solver.append(float(answer.json()["elapsed_ms"]))
            start = time.perf_counter()
            _post(client, path, encoded_omp[index % len(bodies)]).raise_for_status()
            omp.append(time.perf_counter() - start)
        pid = server.process.pid
        cpu_healthz = _server_cpu_ms(
            client, pid, requests, lambda c, _i: c.get("/healthz").raise_for_status()
        )
        cpu_omp = _server_cpu_ms(
            client,
            pid,
            requests,
            lambda c, i: _post(c, path, encoded_omp[i % len(bodies)]).raise_for_status(),
        )
        cpu_default = _server_cpu_ms(
            client,
            pid,
            requests,
            lambda c, i: _post(c, path, encoded[i % len(bodies)]).raise_for_status(),
        )
    healthz_ms = statistics.median(healthz) * 1e3
    localize_ms = statistics.median(default) * 1e3
    omp_ms = statistics.median(omp) * 1e3
    solver_ms = statistics.median(solver)
    # Each request's own time around its solve, for the spread of the figure below.
    around = [wall * 1e3 - solve for wall, solve in zip(default, solver, strict=True)]
    return {
        "requests_each": requests,
        "healthz_p50_ms": round(healthz_ms, 3),
        "localize_p50_ms": round(localize_ms, 3),
        "localize_p99_ms": round(float(np.percentile(np.asarray(default) * 1e3, 99)), 3),
        "localize_over_healthz": round(localize_ms / healthz_ms, 2),
        "solver_p50_ms": round(solver_ms, 3),
        "service_overhead_over_healthz": round((localize_ms - solver_ms) / healthz_ms, 2),
        "around_solve_p50_ms": round(statistics.median(around), 3),
        "localize_omp_p50_ms": round(omp_ms, 3),
        "localize_omp_over_healthz": round(omp_ms / healthz_ms, 2),
        "server_cpu_ms_per_healthz": round(cpu_healthz, 3),
        "server_cpu_ms_per_localize": round(cpu_default, 3),
        "server_cpu_ms_per_localize_omp": round(cpu_omp, 3),
        # None when too few requests for the kernel's CPU clock ticks (10 ms) to see healthz.
        "server_cpu_localize_over_healthz": _ratio(cpu_default, cpu_healthz),
        "server_cpu_localize_omp_over_healthz": _ratio(cpu_omp, cpu_healthz),
    }


async def _throughput(
    url: str, path: str, bodies: list[dict[str, Any]], seconds: float, concurrency: int
) -> tuple[float, int]:
    encoded = [_encoded(body) for body in bodies]
    done = 0
    errors = 0
    stop_at = time.monotonic() + seconds

    async def worker(client: httpx.AsyncClient, offset: int) -> None:
        nonlocal done, errors
        index = offset
        while time.monotonic() < stop_at:
            response = await client.post(path, content=encoded[index % len(encoded)], headers=_JSON)
            index += concurrency
            if response.status_code == 200:
                done += 1
            else:
                errors += 1

    limits = httpx.Limits(max_connections=concurrency)
    async with httpx.AsyncClient(
        base_url=url, headers=_HEADERS, limits=limits, timeout=60.0
    ) as client:
        start = time.monotonic()
        await asyncio.gather(*(worker(client, offset) for offset in range(concurrency)))
        elapsed = time.monotonic() - start
    return done / elapsed, errors


def _scaling(
    servers: dict[int, tuple[LiveServer, str, list[dict[str, Any]]]],
    seconds: float,
    rounds: int,
    concurrency: int,
) -> dict[str, Any]:
    """(b): localize throughput of each server, alternating W1 W2 / W2 W1 phases."""
    rates: dict[int, list[float]] = {workers: [] for workers in servers}
    errors = 0
    for server, room_id, bodies in servers.values():  # warm every process
        warm_s = min(_WARM_S, seconds)
        asyncio.run(_throughput(server.url, _path(room_id), bodies, warm_s, concurrency))
    for round_index in range(rounds):
        order = sorted(servers) if round_index % 2 == 0 else sorted(servers, reverse=True)
        for workers in order:
            server, room_id, bodies = servers[workers]
            rate, failed = asyncio.run(
                _throughput(server.url, _path(room_id), bodies, seconds, concurrency)
            )
            rates[workers].append(rate)
            errors += failed
    medians = {workers: statistics.median(values) for workers, values in rates.items()}
    return {
        "concurrency": concurrency,
        "seconds_per_phase": seconds,
        "rounds": rounds,
        "rps_per_round": {str(w): [round(r, 1) for r in values] for w, values in rates.items()},
        "rps_median": {str(w): round(value, 1) for w, value in medians.items()},
        "workers_2_over_1": round(medians[2] / medians[1], 2),
        "errors": errors,
    }


def _path(room_id: str) -> str:
    return f"/v1/rooms/{room_id}/localize"


def _batch(url: str, room_id: str, bodies: list[dict[str, Any]], rounds: int) -> dict[str, Any]:
    """(c): one batch of the bodies against the same bodies as single requests."""
    singles, batches, batch_over_solves = [], [], []
    batch_body = _encoded({"items": bodies})
    single_bodies = [_encoded(body) for body in bodies]
    with httpx.Client(base_url=url, headers=_HEADERS, timeout=300.0) as client:
        batch_answers: list[dict[str, Any]] = []
        single_answers: list[dict[str, Any]] = []
        for round_index in range(rounds):
            for kind in ("single", "batch") if round_index % 2 == 0 else ("batch", "single"):
                start = time.perf_counter()
                if kind == "batch":
                    response = _post(client, f"/v1/rooms/{room_id}/localize/batch", batch_body)
                    response.raise_for_status()
                    wall = time.perf_counter() - start
                    batches.append(wall)
                    batch_answers = response.json()["items"]
                    solves_s = sum(float(item["elapsed_ms"]) for item in batch_answers) / 1e3
                    batch_over_solves.append(wall / solves_s)
                else:
                    single_answers = []
                    for body in single_bodies:
                        answer = _post(client, _path(room_id), body)
                        answer.raise_for_status()
                        single_answers.append(answer.json())
                    singles.append(time.perf_counter() - start)
    same = all(
        a["estimates"] == b["estimates"] for a, b in zip(batch_answers, single_answers, strict=True)
    )
    single_s, batch_s = statistics.median(singles), statistics.median(batches)
    return {
        "measurements": len(bodies),
        "rounds": rounds,
        "singles_s_median": round(single_s, 3),
        "batch_s_median": round(batch_s, 3),
        "batch_speedup": round(single_s / batch_s, 2),
        # the batch's wall time over the sum of its items' solver times, median of rounds
        "batch_over_item_solves": round(statistics.median(batch_over_solves), 2),
        "same_estimates": same,
    }


@contextlib.contextmanager
def _servers(root: Path) -> Iterator[dict[int, LiveServer]]:
    with (
        live_server(root / "w1", timeout_s=300.0, VLP_WORKERS="1") as one,
        live_server(root / "w2", timeout_s=300.0, VLP_WORKERS="2") as two,
    ):
        yield {1: one, 2: two}


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Start the servers, measure (a), (b), (c) and return the figures."""
    load = " ".join(f"{value:.2f}" for value in os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp, _servers(Path(tmp)) as servers:
        idle_mib = _peak_rss_mib(servers[1].process.pid)
        prepared = {}
        for workers, server in servers.items():
            room_id = ready_demo_room(server.url, timeout_s=300.0)
            count = max(args.batch, args.measurements)
            prepared[workers] = (server, room_id, _measurements(server.url, room_id, count))
        one, room_one, bodies_one = prepared[1]
        sequential = _sequential(one, room_one, bodies_one, args.sequential)
        batch = _batch(one.url, room_one, bodies_one[: args.batch], args.batch_rounds)
        omp_bodies = [{**body, "solver": "omp"} for body in bodies_one[: args.batch]]
        batch_omp = _batch(one.url, room_one, omp_bodies, args.batch_rounds)
        scaling = _scaling(prepared, args.seconds, args.rounds, args.concurrency)
    ratios = {
        "service_overhead_over_healthz": sequential["service_overhead_over_healthz"],
        "batch_over_item_solves": batch["batch_over_item_solves"],
        "workers_2_over_1": scaling["workers_2_over_1"],
        "idle_api_process_peak_mib": round(idle_mib),
    }
    return {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{_cpu_model()}, {os.cpu_count()} cores",
        "commit": _commit(),
        "load_average_at_start": load,
        "ratios": ratios,
        "sequential_one_worker": sequential,
        "batch_vs_singles": batch,
        "batch_vs_singles_omp": batch_omp,
        "throughput_workers": scaling,
    }


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.http``."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--sequential", type=int, default=300, help="requests of each kind")
    parser.add_argument("--measurements", type=int, default=100, help="distinct bodies cycled")
    parser.add_argument("--seconds", type=float, default=5.0, help="per throughput phase")
    parser.add_argument("--rounds", type=int, default=5, help="throughput phases per server")
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--batch", type=int, default=100, help="measurements per batch")
    parser.add_argument("--batch-rounds", type=int, default=5)
    args = parser.parse_args(argv)
    print(json.dumps(run(args), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
