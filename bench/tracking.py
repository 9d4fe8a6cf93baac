"""Tracking benchmark: simulated walkers, raw fixes from the service's solver, tracks.

Run from the repository root::

    python -m bench.tracking                       # every room and mode, 120 s, docs/
    python -m bench.tracking --quick               # paper room, 20 s, bench/out/quick/
    python -m bench.tracking --stream-url postgresql+psycopg://postgres@127.0.0.1:5432/test
    python -m bench.tracking --rooms paper --duration 60 --seed 7 --out /tmp/tracking

Walkers follow random waypoints at 1.4 m/s with pauses of 2-8 s (and, in a second set, two
people cross in the room's length), speeding up and slowing down at 2 m/s^2, at 5 Hz, in the
paper room, the paper room as a realistic mix (reflections, tilts, heights, LED tolerances;
the layout knows the reflectance) and the hall, with and without shadowing (5 % of fixes
have their strongest LED blocked). Fixes come as each terminal's own labelled amplitudes
(K = 4) or as one correlation of K = 4 or 8 anonymous terminals. Reported: the tracked and
raw RMSE while walking and standing, the lag after a start, the coverage of the tracked 95 %
radius, GOSPA (cut-off 1 m) with its parts, identity switches per 100 m walked, and the time
of one tracking step for 10, 100 and 1,000 tracks. With ``--stream-url`` (a PostgreSQL URL)
two ``vlp serve`` processes share it and the delay from a tracked POST on one to its event on
the other's stream is measured.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from app.vlp.tracking import (
    TrackerSettings,
    Tracks,
    associate,
    predict,
    start_tracks,
    step_labelled,
)

from ._common import REPO_ROOT, machine_markdown, machine_record, write_csv
from ._tracking_runs import CLOSE_PASS_M, ROOMS, Outcome, Scenario, run_scenario
from ._tracking_stream import stream_latencies_ms

__all__ = ["main"]

SEED = 20261127
# The walking model alone: no track ever stands (``--walking-only``).
WALKING_ONLY = TrackerSettings(standing_prior=1e-12, mean_dwell_s=1e12)
FILTERS = {False: "the standing / walking mixture", True: "the walking model alone"}
COLUMNS = [
    "room",
    "mode",
    "walkers",
    "shadowing",
    "paths",
    "raw_rmse_walking_m",
    "tracked_rmse_walking_m",
    "ratio_walking",
    "raw_rmse_standing_m",
    "tracked_rmse_standing_m",
    "ratio_standing",
    "lag_median_s",
    "lag_starts",
    "coverage_95",
    "gospa_raw_m",
    "gospa_tracked_m",
    "gospa_tracked_localisation",
    "gospa_tracked_missed",
    "gospa_tracked_false",
    "switches",
    "walked_m",
    "switches_per_100m",
    "averaged_rmse_standing_m",
    "close_passes",
    "unshadowed_averaged_rmse_standing_m",
]


def _scenarios(rooms: Sequence[str]) -> list[Scenario]:
    cells = []
    for room in rooms:
        for shadowing in (False, True):
            cells.append(Scenario(room, "terminals", 4, shadowing))
            cells.append(Scenario(room, "correlation", 4, shadowing))
            cells.append(Scenario(room, "correlation", 8, shadowing))
        cells.append(Scenario(room, "terminals", 2, False, "crossing"))
        cells.append(Scenario(room, "correlation", 2, False, "crossing"))
    return cells


def _rms(values: Sequence[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values)) if values else math.nan


def _mean(rows: Sequence[tuple[float, ...]], column: int) -> float:
    return statistics.fmean(row[column] for row in rows) if rows else math.nan


def _row(outcome: Outcome) -> list[object]:
    s = outcome.scenario
    walk = (_rms(outcome.raw_walking), _rms(outcome.tracked_walking))
    stand = (_rms(outcome.raw_standing), _rms(outcome.tracked_standing))
    per_100m = 100.0 * outcome.switches / outcome.walked_m if outcome.walked_m else math.nan
    return [
        ROOMS[s.room].name,
        s.mode,
        s.walkers,
        s.shadowing,
        s.paths,
        walk[0],
        walk[1],
        walk[1] / walk[0] if walk[0] else math.nan,
        stand[0],
        stand[1],
        stand[1] / stand[0] if stand[0] else math.nan,
        statistics.median(outcome.lags_s) if outcome.lags_s else math.nan,
        len(outcome.lags_s),
        statistics.fmean(outcome.covered) if outcome.covered else math.nan,
        _mean(outcome.gospa_raw, 0),
        _mean(outcome.gospa_tracked, 0),
        _mean(outcome.gospa_tracked, 1),
        _mean(outcome.gospa_tracked, 2),
        _mean(outcome.gospa_tracked, 3),
        outcome.switches if s.mode == "correlation" else math.nan,
        outcome.walked_m,
        per_100m if s.mode == "correlation" else math.nan,
        _rms(outcome.averaged_standing),
        outcome.close_passes if s.mode == "correlation" else math.nan,
        _rms(outcome.unshadowed_standing),
    ]


def step_times_ms(sizes: Sequence[int], repeats: int) -> list[tuple[int, float, float]]:
    """Median time of one labelled step (predict + update of every track) and of one
    anonymous association (gated assignment) for ``n`` tracks of one room, milliseconds."""
    settings = TrackerSettings()
    gen = np.random.default_rng(SEED)
    out = []
    for n in sizes:
        positions = gen.uniform(0, 20, (n, 2))
        noise = np.tile(0.03**2 * np.eye(2), (n, 1, 1))
        tracks = step_labelled(
            Tracks.empty(), np.full(n, -1), positions, noise, 0.0, settings
        ).tracks
        rows = np.arange(n)
        labelled, anonymous = [], []
        for k in range(repeats):
            moved = positions + 0.05 * gen.standard_normal((n, 2))
            started = time.perf_counter()
            step_labelled(tracks, rows, moved, noise, 0.2 * (k + 1), settings)
            labelled.append(time.perf_counter() - started)
            bank = start_tracks(positions, noise, np.zeros(n), settings)
            started = time.perf_counter()
            associate(predict(bank, np.full(n, 0.2), settings), moved, noise, settings)
            anonymous.append(time.perf_counter() - started)
        out.append((n, 1e3 * statistics.median(labelled), 1e3 * statistics.median(anonymous)))
    return out


def _format(value: object) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.3g}"
    return str(value)


def _table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_format(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _pooled(outcomes: Sequence[Outcome], mode: str, shadowing: bool | None) -> Outcome:
    pooled = Outcome(Scenario("pooled", mode, 0, bool(shadowing)))
    for o in outcomes:
        s = o.scenario
        if s.mode != mode or (shadowing is not None and s.shadowing != shadowing):
            continue
        if mode == "correlation" and s.walkers != 4:
            continue
        for name in (
            "raw_walking",
            "tracked_walking",
            "raw_standing",
            "tracked_standing",
            "covered",
            "lags_s",
            "averaged_standing",
            "unshadowed_standing",
            "gospa_raw",
            "gospa_tracked",
        ):
            getattr(pooled, name).extend(getattr(o, name))
        pooled.switches += o.switches
        pooled.close_passes += o.close_passes
        pooled.walked_m += o.walked_m
    return pooled


def _targets(
    outcomes: Sequence[Outcome], steps: list[tuple[int, float, float]], stream: list[float]
) -> str:
    shadowed = _pooled(outcomes, "terminals", True)
    clean = _pooled(outcomes, "terminals", False)
    labelled = _pooled(outcomes, "terminals", None)
    anonymous = _pooled(outcomes, "correlation", None)

    def ratio(pool: Outcome, walking: bool) -> float:
        raw, tracked = (
            (pool.raw_walking, pool.tracked_walking)
            if walking
            else (pool.raw_standing, pool.tracked_standing)
        )
        return _rms(tracked) / _rms(raw)

    def averaged(pool: Outcome) -> float:
        return _rms(pool.averaged_standing) / _rms(pool.raw_standing)

    def unshadowed(pool: Outcome) -> float:
        return _rms(pool.unshadowed_standing) / _rms(pool.raw_standing)

    gospa_drop = 1.0 - _mean(anonymous.gospa_tracked, 0) / _mean(anonymous.gospa_raw, 0)
    hundred = next((t for n, t, _ in steps if n == 100), math.nan)
    per_100m = 100.0 / anonymous.walked_m if anonymous.walked_m else math.nan
    rows: list[list[object]] = [
        [
            "tracked / raw RMSE, labelled, shadowing, walking",
            "<= 0.7",
            ratio(shadowed, True),
            "-",
        ],
        [
            "the same, standing",
            "<= 0.3",
            ratio(shadowed, False),
            f"{averaged(shadowed):.3g}; unshadowed only {unshadowed(shadowed):.3g}",
        ],
        ["without shadowing, walking", "<= 1.0", ratio(clean, True), "-"],
        ["without shadowing, standing", "<= 0.6", ratio(clean, False), averaged(clean)],
        [
            "lag after a start (median), s",
            "<= 0.5",
            statistics.median(labelled.lags_s) if labelled.lags_s else math.nan,
            "-",
        ],
        [
            "coverage of the tracked 95 % radius",
            "0.90-0.98",
            statistics.fmean(labelled.covered),
            "-",
        ],
        [
            "identity switches per 100 m, anonymous K = 4",
            "<= 1",
            anonymous.switches * per_100m,
            anonymous.close_passes * per_100m,
        ],
        [
            "GOSPA, tracked vs raw, anonymous K = 4 (reduction)",
            ">= 25 %",
            f"{100 * gospa_drop:.0f} %",
            "-",
        ],
        ["tracking step, 100 tracks, ms", "<= 1", hundred, "-"],
        [
            "POST -> event on another process's stream, p95, ms",
            "<= 100",
            float(np.percentile(stream, 95)) if stream else "not run (no --stream-url)",
            "-",
        ],
    ]
    return _table(["measure", "target", "measured", "floor"], rows)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and write its results page and CSVs."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--duration", type=float, default=None, help="seconds of walking (120; --quick: 20)"
    )
    parser.add_argument("--rooms", default="paper,mix,hall", help=f"subset of {','.join(ROOMS)}")
    parser.add_argument(
        "--quick", action="store_true", help="paper room, 20 s, under bench/out/quick/"
    )
    parser.add_argument("--out", type=Path, default=None, help="where docs/ files go")
    parser.add_argument("--repeats", type=int, default=200, help="timed repeats per step size")
    parser.add_argument("--sizes", default="10,100,1000", help="track counts timed")
    parser.add_argument("--stream-url", default=None, help="PostgreSQL URL for the stream delay")
    parser.add_argument("--stream-posts", type=int, default=200)
    parser.add_argument(
        "--seed",
        type=int,
        default=SEED,
        help=f"seed of the walkers' paths and of their measurements' noise ({SEED})",
    )
    parser.add_argument(
        "--walking-only",
        action="store_true",
        help="the walking (constant-velocity) model alone, no standing model: what the "
        "mixture adds",
    )
    args = parser.parse_args(argv)
    duration = args.duration or (20.0 if args.quick else 120.0)
    rooms = ["paper"] if args.quick else args.rooms.split(",")
    out = args.out or (REPO_ROOT / ("bench/out/quick" if args.quick else "docs"))
    command = "python -m bench.tracking " + " ".join(argv if argv is not None else sys.argv[1:])
    started = time.perf_counter()
    settings = WALKING_ONLY if args.walking_only else TrackerSettings()
    with threadpool_limits(limits=1):
        outcomes = []
        for scenario in _scenarios(rooms):
            outcomes.append(
                run_scenario(scenario, duration_s=duration, seed=args.seed, settings=settings)
            )
            print(f"{scenario}: done after {time.perf_counter() - started:.0f} s", flush=True)
        steps = step_times_ms([int(n) for n in args.sizes.split(",")], args.repeats)
    stream = stream_latencies_ms(args.stream_url, args.stream_posts) if args.stream_url else []
    rows = [_row(o) for o in outcomes]
    write_csv(out / "data" / "tracking.csv", COLUMNS, rows)
    write_csv(
        out / "data" / "tracking_step_time.csv",
        ["tracks", "labelled_step_ms", "association_ms"],
        steps,
    )
    page = "\n".join(
        [
            "# Tracking results",
            "",
            "Generated by `bench/tracking.py`; do not edit by hand. Command:",
            "",
            f"    {command.strip()}",
            "",
            f"{duration:g} s of walking per cell at 5 Hz, seed {args.seed}; run time "
            f"{time.perf_counter() - started:.0f} s. CSV: `docs/data/tracking.csv`, "
            "`docs/data/tracking_step_time.csv`. What the columns mean: "
            "[tracking moving terminals](../how-to/track-moving-terminals.md).",
            "",
            f"Filter: {FILTERS[args.walking_only]}.",
            "",
            "## Targets",
            "",
            _targets(outcomes, steps, stream),
            "",
            "Floor: for standing, the RMSE of the weighted mean (by the inverse of each fix's "
            "covariance) of all the raw fixes of each pause over the raw RMSE (the part of the "
            "error successive fixes at one place share, which no averaging removes); with "
            "shadowing, also the same mean of only the fixes that were not shadowed (what an "
            "estimator that knew which fixes were shadowed would leave); for "
            "identity switches, how often two walkers come within "
            f"{CLOSE_PASS_M:g} m of each other per 100 m walked (closer than a person's width, "
            "where positions alone cannot tell them apart). Switches are counted as the CLEAR "
            "MOT metrics count them: a walker keeps its track while it stays within 1 m.",
            "",
            "## Every cell",
            "",
            _table(
                [
                    "room",
                    "mode",
                    "K",
                    "shadowing",
                    "paths",
                    "raw walk m",
                    "tracked walk m",
                    "ratio walk",
                    "raw stand m",
                    "tracked stand m",
                    "ratio stand",
                    "lag s",
                    "starts",
                    "coverage",
                    "GOSPA raw",
                    "GOSPA tracked",
                    "loc",
                    "missed",
                    "false",
                    "switches",
                    "walked m",
                    "switches / 100 m",
                    "averaged stand m",
                    "close passes",
                    "unshadowed averaged stand m",
                ],
                rows,
            ),
            "",
            "## Tracking step time",
            "",
            _table(["tracks", "labelled step (ms)", "association (ms)"], steps),
            "",
            "Machine:",
            "",
            machine_markdown(machine_record()),
            "",
        ]
    )
    (out / "results" / "tracking.md").parent.mkdir(parents=True, exist_ok=True)
    (out / "results" / "tracking.md").write_text(page, encoding="utf-8")
    print(f"wrote {out / 'results' / 'tracking.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
