"""How fast the paths are that the test suite checks by counting work, not by timing it.

The tests assert what bounds the work (the 10^6-point room map is evaluated on at most
200 x 200 samples; a 1.6e11-point grid is refused before the layout is built; ``stop()``
does not wait for a running build). This measures what that buys, as medians:

- ``room map``: ``room_map_png`` of a 100 x 100 m room with a 0.1 m grid (10^6 points),
  600 px wide, coverage and CRLB heat maps (in this process, one BLAS thread);
- ``tiny grid refused``: ``POST /v1/rooms`` with a 1e-5 m grid over 4 x 4 m, answered 422
  (the app in-process through Starlette's test client, SQLite registry);
- ``worker stop``: ``EmbeddedWorkers.stop()`` while a build that never ends is running in
  the worker's process pool (the job goes back to the queue).

    python -m bench.bounded_work [--repeat 5] [--update-doc docs/results/bounded-work.md]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

from threadpoolctl import threadpool_limits

from app.jobs import EmbeddedWorkers
from app.jobs.build import BuildTask
from app.main import create_app
from app.pictures import room_map_png
from app.registry import Registry
from app.registry.queue import StoredBuild
from app.settings import Settings
from app.vlp.layout import Grid, Layout, Led, Room
from bench._common import machine_markdown, machine_record, replace_section

__all__ = ["main"]

_ADMIN_KEY = "bench-admin-key-0123456789"
_TINY_GRID_ROOM = {
    "name": "Tiny grid",
    "room": {"length": 4.0, "width": 4.0, "height": 3.0},
    "grid": {"step": 1e-5, "receiver_height": 0.8},
    "leds": [{"x": 1.0, "y": 1.0}],
}


def _median_s(run: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        run()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def _big_room() -> Layout:
    leds = tuple(Led(x, y, 4.0) for x in (20.0, 50.0, 80.0) for y in (25.0, 75.0))
    return Layout(Room(100.0, 100.0, 4.0), Grid(0.1, 0.85), leds, name="Big")


def room_map_seconds(repeat: int) -> dict[str, float]:
    """Median render time of the 10^6-point room map, per heat map."""
    big = _big_room()
    with threadpool_limits(limits=1):
        return {
            "coverage": _median_s(
                partial(room_map_png, big, heatmap="coverage", width_px=600), repeat
            ),
            "crlb": _median_s(partial(room_map_png, big, heatmap="crlb", width_px=600), repeat),
        }


def tiny_grid_seconds(repeat: int, data_dir: Path) -> float:
    """Median time to refuse a 1.6e11-point grid over HTTP (in-process app)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Using `httpx` with `starlette.testclient`")
        from fastapi.testclient import TestClient

    settings = Settings(data_dir=data_dir, admin_keys=_ADMIN_KEY, embedded_workers=0, demo=False)
    headers = {"X-API-Key": _ADMIN_KEY}
    with TestClient(create_app(settings)) as client:

        def refuse() -> None:
            response = client.post("/v1/rooms", json=_TINY_GRID_ROOM, headers=headers)
            if response.status_code != 422:
                raise RuntimeError(f"expected 422, got {response.status_code}: {response.text}")

        refuse()  # warm up
        return _median_s(refuse, repeat)


def endless_build(task: BuildTask) -> StoredBuild:
    """A build that never ends (run in the worker's child process)."""
    del task
    threading.Event().wait()
    raise AssertionError("unreachable")


def worker_stop_seconds(repeat: int, data_dir: Path) -> float:
    """Median time of ``EmbeddedWorkers.stop()`` with a build running."""
    registry = Registry(
        database_url=f"sqlite:///{data_dir / 'registry.sqlite3'}", data_dir=data_dir
    )
    registry.migrate()
    settings = Settings(
        data_dir=data_dir,
        database_url=registry.database_url,
        embedded_workers=1,
        job_poll_seconds=0.05,
        job_heartbeat_seconds=0.1,
    )
    layout = {
        "room": {"length": 2.0, "width": 2.0, "height": 3.0},
        "grid": {"step": 0.5, "receiver_height": 0.85},
        "leds": [{"x": 1.0, "y": 1.0}],
    }
    times = []
    try:
        for index in range(repeat):
            room = registry.create_room(name=f"stop {index}", layout=layout)
            workers = EmbeddedWorkers(registry=registry, settings=settings, build=endless_build)
            workers.start()
            while registry.get_job(job_id=room.job_id or "").status != "running":
                time.sleep(0.02)
            time.sleep(0.5)  # let the build process start
            started = time.perf_counter()
            workers.stop(timeout=5)
            times.append(time.perf_counter() - started)
            registry.delete_room(room_id=room.id)
    finally:
        registry.dispose()
    return statistics.median(times)


@dataclass(frozen=True)
class Figures:
    """One run's medians."""

    repeat: int
    room_map_s: dict[str, float]
    tiny_grid_ms: float
    worker_stop_s: float


def markdown(figures: Figures, argv: Sequence[str]) -> str:
    """The docs section for one run."""
    rows = [
        ("room map, 10^6 points, coverage", f"{figures.room_map_s['coverage']:.2f} s"),
        ("room map, 10^6 points, CRLB", f"{figures.room_map_s['crlb']:.2f} s"),
        ("tiny grid (1.6e11 points) refused over HTTP", f"{figures.tiny_grid_ms:.1f} ms"),
        ("worker stop with a build running", f"{figures.worker_stop_s:.2f} s"),
    ]
    table = "\n".join(f"| {name} | {value} |" for name, value in rows)
    command = " ".join(["python -m bench.bounded_work", *argv])
    return (
        "## Bounded work (what the test suite checks by counting)\n\n"
        "The suite asserts what bounds these paths (samples evaluated, allocations, a stop "
        "that does not wait for the build), never their time; the times are here. Medians "
        f"of {figures.repeat} runs each ({10 * figures.repeat} for the refusal).\n\n"
        f"Command (repository root): `{command}`\n\n"
        f"{machine_markdown(machine_record())}\n\n"
        "| path | median |\n|---|---|\n"
        f"{table}\n"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m bench.bounded_work``; prints the figures as JSON."""
    parser = argparse.ArgumentParser(prog="python -m bench.bounded_work", description=__doc__)
    parser.add_argument("--repeat", type=int, default=5, help="runs per figure (median)")
    parser.add_argument("--update-doc", type=Path, default=None, help="rewrite its section")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        figures = Figures(
            repeat=args.repeat,
            room_map_s=room_map_seconds(args.repeat),
            tiny_grid_ms=1000.0 * tiny_grid_seconds(10 * args.repeat, Path(tmp) / "http"),
            worker_stop_s=worker_stop_seconds(args.repeat, Path(tmp) / "workers"),
        )
    if args.update_doc is not None:
        shown = list(argv) if argv is not None else sys.argv[1:]
        replace_section(
            args.update_doc,
            "bounded-work",
            markdown(figures, shown),
            preamble="# Results: bounded work\n",
        )
    print(json.dumps(asdict(figures), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
