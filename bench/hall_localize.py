"""Localize K terminals in the million-point hall through the API of a real ``vlp serve``.

Starts ``vlp serve`` (SQLite, one embedded build worker, BLAS one thread) on a free loopback
port, creates the hall of :func:`bench.hall_build.million_point_hall`, waits for its build
(the job's build time and the server's peak memory while it ran are reported), then for each
measurement form (``power``, ``terminals``): simulates ``--repeat`` measurements of K random
terminals at ``--snr`` dB with the server's ``/simulate`` (seeded), sends each to localize
and reports the median wall time of the request as the client sees it, the server's solve
time (``elapsed_ms``), the mean position error against the simulation's truth and the server's
extra peak resident memory during the form's requests (``VmHWM`` reset through
``/proc/<pid>/clear_refs`` after the first, cold request, which loads H and prepares the
solver and is reported on its own); and how much larger all the requests left the server.

Before the hall, the server solves one small room (the paper's) in each form, as any serving
process does with its first requests: that loads the solvers' compiled kernels (about 0.2 GiB,
code the process holds whatever room it serves), which a process started with
``VLP_WARM_KERNELS_AT_START=1`` holds from its start. So two growths are reported:
``server_growth_from_requests_mib``, the hall's requests' own (resident size after them
against before the first, the kernels already loaded), and ``server_growth_from_idle_mib``,
against the idle process before anything (kernels, small room and hall together).
The server runs with the environment's ``VLP_*`` settings (e.g. ``VLP_WARM_KERNELS_AT_START``).

    python -m bench.hall_localize [--targets 50] [--repeat 5] [--snr 30]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.vlp.metrics import matched_errors
from app.vlp.presets import paper_layout
from bench._common import machine_record
from bench._server import ADMIN_KEY, TERMINAL_KEY, live_server
from bench.hall_build import million_point_hall

__all__ = ["main", "run"]

_FORMS = {"power": {"model": "power"}, "terminals": {"form": "terminals"}}


def _memory_kib(pid: int) -> dict[str, int]:
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text(encoding="utf-8").splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0])
    return values


def _reset_peak(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5", encoding="utf-8")


def _wait_ready(client: httpx.Client, room_id: str, timeout_s: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        room: dict[str, Any] = client.get(f"/v1/rooms/{room_id}").json()
        status = room["fingerprint"]["status"]
        if status == "ready":
            return room
        if status == "failed" or time.monotonic() > deadline:
            raise RuntimeError(f"the hall's build ended {status!r}: {room['fingerprint']}")
        time.sleep(0.2)


def _first_solves(client: httpx.Client) -> None:
    """Create the paper's room and localize one measurement of it in each form."""
    created = client.post("/v1/rooms", json={"name": "Paper room", **paper_layout().to_mapping()})
    created.raise_for_status()
    room_id = created.json()["id"]
    _wait_ready(client, room_id, 600.0)
    for options in ({"model": "power"}, {"model": "correlation"}, {"form": "terminals"}):
        simulation = client.post(
            f"/v1/rooms/{room_id}/simulate",
            json={"targets": 4, "snr_db": 30.0, "seed": 0, **options},
        )
        simulation.raise_for_status()
        _localize(client, room_id, simulation.json()["measurement"])


def _localize(client: httpx.Client, room_id: str, body: dict[str, Any]) -> tuple[float, Any]:
    started = time.perf_counter()
    response = client.post(
        f"/v1/rooms/{room_id}/localize", json=body, headers={"X-API-Key": TERMINAL_KEY}
    )
    wall = time.perf_counter() - started
    response.raise_for_status()
    return wall, response.json()


def _error_m(answer: dict[str, Any], truth: list[dict[str, Any]]) -> float:
    estimates = np.array([[e["x"], e["y"]] for e in answer["estimates"]])
    true = np.array([[t["x"], t["y"]] for t in truth])
    return float(np.mean(matched_errors(estimates, true)))


def run(targets: int, repeat: int, snr_db: float) -> dict[str, Any]:
    """Start a server, build the hall, measure both forms; the figures."""
    report: dict[str, Any] = {"targets": targets, "repeat": repeat, "snr_db": snr_db}
    with tempfile.TemporaryDirectory() as tmp, live_server(Path(tmp), VLP_DEMO="0") as server:
        pid = server.process.pid
        with httpx.Client(
            base_url=server.url, headers={"X-API-Key": ADMIN_KEY}, timeout=600.0
        ) as client:
            idle = _memory_kib(pid)["VmRSS"]
            report["server_rss_idle_mib"] = round(idle / 1024)
            _first_solves(client)
            report["server_rss_after_first_solves_mib"] = round(_memory_kib(pid)["VmRSS"] / 1024)
            _reset_peak(pid)
            before = _memory_kib(pid)["VmRSS"]
            created = client.post("/v1/rooms", json=million_point_hall().to_mapping())
            created.raise_for_status()
            room_id = created.json()["id"]
            started = time.perf_counter()
            room = _wait_ready(client, room_id, 600.0)
            version = room["fingerprint"]["version"]
            record = client.get(f"/v1/rooms/{room_id}/fingerprints/{version}").json()
            report["build"] = {
                "created_to_ready_s": round(time.perf_counter() - started, 2),
                "job_build_and_store_s": round(float(record["build_seconds"]), 2),
                "server_peak_extra_mib": round((_memory_kib(pid)["VmHWM"] - before) / 1024),
            }
            # What the requests below leave the process holding: its resident size after
            # them against before the first (the build ran in the worker's child process).
            rss_before_requests = _memory_kib(pid)["VmRSS"]
            report["server_rss_before_requests_mib"] = round(rss_before_requests / 1024)
            for form, options in _FORMS.items():
                walls: list[float] = []
                solves: list[float] = []
                errors: list[float] = []
                rss_before = 0
                for index in range(repeat + 1):
                    simulation = client.post(
                        f"/v1/rooms/{room_id}/simulate",
                        json={"targets": targets, "snr_db": snr_db, "seed": index, **options},
                    ).json()
                    # Seed 0 is the cold request (H loaded, solver prepared); the others
                    # are measured from the resident size after it.
                    if index <= 1:
                        _reset_peak(pid)
                        rss_before = _memory_kib(pid)["VmRSS"]
                    wall, answer = _localize(client, room_id, simulation["measurement"])
                    if index == 0:
                        report[f"{form}_cold"] = {
                            "request_s": round(wall, 2),
                            "peak_extra_mib": round(
                                (_memory_kib(pid)["VmHWM"] - rss_before) / 1024
                            ),
                        }
                        continue
                    walls.append(wall)
                    solves.append(float(answer["elapsed_ms"]) / 1e3)
                    errors.append(_error_m(answer, simulation["truth"]))
                peak = _memory_kib(pid)["VmHWM"]
                report[form] = {
                    "median_request_s": round(statistics.median(walls), 3),
                    "median_solve_s": round(statistics.median(solves), 3),
                    "median_mean_error_cm": round(100 * statistics.median(errors), 2),
                    "worst_mean_error_cm": round(100 * max(errors), 2),
                    "peak_extra_mib": round((peak - rss_before) / 1024),
                }
            rss_after = _memory_kib(pid)["VmRSS"]
            report["server_rss_mib"] = round(rss_after / 1024)
            report["server_growth_from_requests_mib"] = round(
                (rss_after - rss_before_requests) / 1024
            )
            report["server_growth_from_idle_mib"] = round((rss_after - idle) / 1024)
    report["machine"] = machine_record()
    return report


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.hall_localize``."""
    parser = argparse.ArgumentParser(prog="python -m bench.hall_localize")
    parser.add_argument("--targets", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--snr", type=float, default=30.0)
    args = parser.parse_args(argv)
    print(json.dumps(run(args.targets, args.repeat, args.snr), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
