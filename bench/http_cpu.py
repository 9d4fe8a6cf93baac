"""Server CPU per request of two source trees' ``vlp serve``, side by side in one run.

Starts one API process (``--workers 1``, SQLite, BLAS one thread) from each tree; K = 8
correlation measurements of the demo (paper) room at 30 dB. In each round, for each server
in turn (the order alternating between rounds), three blocks of requests over one
keep-alive connection: ``/healthz``, localize with the ``omp`` solver (the path with a
nearly free solve) and localize with the default solver; the server's CPU time
(``/proc/<pid>/stat``) per request of each block. Medians over the rounds. CPU time is what a
shared, loaded machine stretches least, where latency ratios swing from run to run. The
kernel counts CPU time in clock ticks (10 ms), so a short block can show 0 and a ratio over it
is reported as null: use blocks of 100 or more for figures.

    python -m bench.http_cpu BEFORE_TREE [AFTER_TREE] [--block 100] [--rounds 6]

AFTER_TREE defaults to this repository; a tree is a source checkout (e.g. ``git worktree
add /tmp/before main``) run with this environment's packages.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import tempfile
from pathlib import Path
from typing import Any

import httpx

from bench._common import REPO_ROOT
from bench._server import TERMINAL_KEY, LiveServer, live_server, ready_demo_room
from bench.http import _cpu_seconds, _measurements, _ratio

__all__ = ["main", "run"]

_KINDS = ("healthz", "localize_omp", "localize_default")


def _block(
    client: httpx.Client, server: LiveServer, room_id: str, bodies: list[dict[str, Any]], kind: str
) -> tuple[float, float]:
    """Server CPU milliseconds per request over one block, and the answers' mean solver
    time (0 for ``/healthz``)."""
    pid = server.process.pid
    path = f"/v1/rooms/{room_id}/localize"
    solver_ms = 0.0
    before = _cpu_seconds(pid)
    for body in bodies:
        if kind == "healthz":
            client.get("/healthz").raise_for_status()
            continue
        sent = {**body, "solver": "omp"} if kind == "localize_omp" else body
        answer = client.post(path, json=sent)
        answer.raise_for_status()
        solver_ms += float(answer.json()["elapsed_ms"])
    return (_cpu_seconds(pid) - before) / len(bodies) * 1e3, solver_ms / len(bodies)


def run(trees: dict[str, Path], block: int, rounds: int) -> dict[str, Any]:
    """Start a server per tree and measure; the figures per tree."""
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        servers = {
            name: stack.enter_context(
                live_server(Path(tmp) / name, timeout_s=600.0, source=tree, VLP_WORKERS="1")
            )
            for name, tree in trees.items()
        }
        rooms = {name: ready_demo_room(s.url, timeout_s=300.0) for name, s in servers.items()}
        first = next(iter(trees))
        bodies = _measurements(servers[first].url, rooms[first], block)
        clients = {
            name: stack.enter_context(
                httpx.Client(base_url=s.url, headers={"X-API-Key": TERMINAL_KEY}, timeout=120.0)
            )
            for name, s in servers.items()
        }
        for name in trees:  # warm the caches of both solvers
            for kind in _KINDS[1:]:
                _block(clients[name], servers[name], rooms[name], bodies, kind)
        cpu: dict[str, dict[str, list[float]]] = {n: {k: [] for k in _KINDS} for n in trees}
        solver: dict[str, list[float]] = {name: [] for name in trees}
        for round_index in range(rounds):
            order = list(trees) if round_index % 2 == 0 else list(reversed(trees))
            for name in order:
                for kind in _KINDS:
                    ms, solve_ms = _block(clients[name], servers[name], rooms[name], bodies, kind)
                    cpu[name][kind].append(ms)
                    if kind == "localize_default":
                        solver[name].append(solve_ms)
    report: dict[str, Any] = {"block": block, "rounds": rounds}
    report["load_average_at_end"] = " ".join(f"{value:.2f}" for value in os.getloadavg())
    for name, tree in trees.items():
        medians = {kind: statistics.median(values) for kind, values in cpu[name].items()}
        report[name] = {
            "tree": str(tree),
            **{f"cpu_ms_{kind}": round(value, 3) for kind, value in medians.items()},
            "solver_mean_ms_default": round(statistics.median(solver[name]), 3),
            # None when a block of /healthz took less than one clock tick of CPU time
            "localize_omp_over_healthz": _ratio(medians["localize_omp"], medians["healthz"]),
        }
    return report


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.http_cpu``."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("before", type=Path, help="source tree of the first server")
    parser.add_argument("after", type=Path, nargs="?", default=REPO_ROOT)
    parser.add_argument("--block", type=int, default=100, help="requests per block")
    parser.add_argument("--rounds", type=int, default=6)
    args = parser.parse_args(argv)
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    print(json.dumps(run(trees, args.block, args.rounds), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
