"""Build and store the largest room the service admits by default, as a worker would.

The hall: 100 x 100 m, 0.1 m grid (N = 10^6 = the default ``max_grid_points``), 1024 LEDs
on a 3.125 m pitch. Runs :func:`app.jobs.build.build_and_store` in this process against a
throwaway store and reports build and store time, H's size and the peak resident memory.

    python -m bench.hall_build
    python -m bench.hall_build --reflectance 0.7,0.2,0.8   # walls, floor, ceiling
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import tempfile
import time
from pathlib import Path

from app.jobs.build import store_fingerprint
from app.registry.store import MatrixStore
from app.vlp.errors import ProblemSizeError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Reflectance, Room
from bench._common import machine_record

__all__ = ["main", "million_point_hall"]


def million_point_hall() -> Layout:
    """A 100 x 100 m hall, 0.1 m grid (N = 10^6), 1024 LEDs on a 3.125 m pitch at 3 m."""
    leds = tuple(
        Led(x=1.5625 + 3.125 * (i % 32), y=1.5625 + 3.125 * (i // 32), z=3.0) for i in range(1024)
    )
    return Layout(
        room=Room(length=100.0, width=100.0, height=3.0),
        grid=Grid(step=0.1, receiver_height=0.85),
        leds=leds,
        name="Million-point hall",
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.hall_build``."""
    parser = argparse.ArgumentParser(prog="python -m bench.hall_build")
    parser.add_argument(
        "--reflectance", default=None, help="walls,floor,ceiling (default: line of sight only)"
    )
    args = parser.parse_args(argv)
    layout = million_point_hall()
    if args.reflectance:
        walls, floor, ceiling = (float(v) for v in args.reflectance.split(","))
        room = dataclasses.replace(layout.room, reflectance=Reflectance(walls, floor, ceiling))
        layout = dataclasses.replace(layout, room=room)
    started = time.perf_counter()
    try:
        fingerprint = build_fingerprint(layout)
    except ProblemSizeError as exc:
        peak = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        refusal = {"refused": exc.message, "field": exc.field, "peak_rss_mib": peak}
        print(json.dumps(refusal, indent=2))
        return 1
    built = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        stored = store_fingerprint(fingerprint, MatrixStore(Path(tmp)))
    done = time.perf_counter()
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    report = {
        "grid_points": layout.n_cells,
        "leds": layout.n_leds,
        "nonzeros": int(fingerprint.gains.nnz),
        "stored": {
            name: {"format": info.format, "bytes": size} for name, (info, size) in stored.items()
        },
        "build_s": round(built - started, 1),
        "store_s": round(done - built, 1),
        "peak_rss_mib": round(peak_kib / 1024),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "machine": machine_record(),
    }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
