"""Accuracy benchmark: the paper's Fig. 3 and Fig. 4, every solver x model, RSS and the CRLB.

Run from the repository root::

    python -m bench.accuracy            # full run (~20 min on 2 cores), writes under docs/
    python -m bench.accuracy --quick    # ~1 min smoke run, writes under bench/out/quick/

Every trial draws K targets uniformly in the room (no two in one grid cell, off the grid) and
one noisy amplitude per terminal and LED from a seed fixed by (room, SNR, K, trial), so every
method sees exactly the same placements and noise. Per trial and method the error is the mean
distance between the estimates and the truth after optimal (Hungarian) matching; the summary
reports the MEDIAN and the MEAN over trials of that per-trial mean error, the grid's
quantisation floor (mean distance from the targets to their nearest grid centres), the
aggregated CRLB of each measurement model and the single-target CRLB.
"""

from __future__ import annotations

import argparse
import sys
import time
import zlib
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from app.vlp.baseline import rss_localize
from app.vlp.crlb import aggregated_crlb, single_target_crlb
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout
from app.vlp.measurements import MODELS, Model, measurement_from_amplitudes
from app.vlp.metrics import mean_position_error
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from app.vlp.solvers import Solver, make_solver
from app.vlp.typing import FloatArray

from ._common import REPO_ROOT, load_solvers, machine_record, write_csv
from .results import (
    CRLB,
    CRLB_SINGLE,
    GRID_FLOOR,
    NO_MODEL,
    RSS,
    SUMMARY_HEADER,
    TRIAL_HEADER,
    Row,
    summarise,
    summary_tuple,
)
from .rooms import make_room

__all__ = ["SEED", "Case", "Row", "default_cases", "main", "quick_cases", "run_cases", "summarise"]

SEED = 20261122
SLOW_SOLVERS = frozenset({"l1"})


@dataclass(frozen=True)
class Case:
    """One (room, SNR, K) cell of the benchmark and how many trials it gets."""

    room: str
    snr_db: float
    n_targets: int
    trials: int
    slow_trials: int


def default_cases() -> list[Case]:
    """The full run: Fig. 4 at 30 dB (K = 1..16), 20 and 40 dB, and the hall at 30 dB."""
    cases = [Case("paper", 30.0, k, 150, 30) for k in range(1, 17)]
    for snr in (20.0, 40.0):
        cases += [Case("paper", snr, k, 60, 15) for k in (1, 2, 4, 8, 12, 16)]
    cases += [Case("hall", 30.0, k, 60, 15) for k in (1, 4, 8)]
    return cases


def quick_cases() -> list[Case]:
    """A ~1 minute run with the same shape of output (few K, few trials)."""
    cases = [Case("paper", 30.0, k, 10, 3) for k in (1, 4, 8)]
    cases += [Case("paper", snr, k, 4, 2) for snr in (20.0, 40.0) for k in (1, 8)]
    cases += [Case("hall", 30.0, k, 4, 2) for k in (1, 8)]
    return cases


@dataclass
class _Context:
    layout: Layout
    fingerprint: Fingerprint
    solvers: dict[tuple[str, Model], Solver]


@cache
def _context(room: str, solver_names: tuple[str, ...]) -> _Context:
    layout = make_room(room)
    fingerprint = build_fingerprint(layout)
    solvers = {
        (name, model): make_solver(name, fingerprint, model)
        for name in solver_names
        for model in MODELS
    }
    return _Context(layout, fingerprint, solvers)


def trial_generator(case: Case, trial: int) -> np.random.Generator:
    """The generator of one trial: placements, then noise (same for every method)."""
    key = (zlib.crc32(case.room.encode()), round(case.snr_db * 10), case.n_targets, trial)
    return np.random.default_rng(np.random.SeedSequence(SEED, spawn_key=key))


def draw_trial(
    case: Case, trial: int, layout: Layout, noise_std: float
) -> tuple[FloatArray, FloatArray]:
    """Positions (K, 2) and noisy amplitudes (K, M) of one trial."""
    gen = trial_generator(case, trial)
    positions = random_positions(layout, case.n_targets, distinct_cells=True, rng=gen)
    return positions, noisy_amplitudes(layout, positions, noise_std, rng=gen)


def _run_trial(case: Case, trial: int, ctx: _Context) -> Iterator[Row]:
    layout = ctx.layout
    std = noise_std_for_snr(ctx.fingerprint, case.snr_db)
    truth, amps = draw_trial(case, trial, layout, std)
    base = (case.room, case.snr_db, case.n_targets, trial)
    centres = layout.cell_centres(layout.nearest_cell(truth))
    floor = float(np.mean(np.linalg.norm(truth - centres, axis=1)))
    yield Row(*base, GRID_FLOOR, NO_MODEL, floor, 0.0)
    single = np.mean([single_target_crlb(layout, point, std) for point in truth])
    yield Row(*base, CRLB_SINGLE, NO_MODEL, float(single), 0.0)
    for model in MODELS:
        yield Row(*base, CRLB, model, aggregated_crlb(layout, truth, std, model=model).mean, 0.0)
    yield _attempt(base, RSS, NO_MODEL, truth, lambda: rss_localize(layout, amps))
    for (name, model), solver in ctx.solvers.items():
        if name in SLOW_SOLVERS and trial >= case.slow_trials:
            continue

        def solve(solver: Solver = solver, model: Model = model) -> FloatArray:
            measurement = measurement_from_amplitudes(amps, model, layout.n_leds)
            return solver.solve(measurement, case.n_targets).positions

        yield _attempt(base, name, model, truth, solve)


def _attempt(
    base: tuple[str, float, int, int],
    method: str,
    model: str,
    truth: FloatArray,
    locate: Callable[[], FloatArray],
) -> Row:
    start = time.perf_counter()
    try:
        estimate = locate()
    except Exception as exc:  # a failing method is counted, not fatal
        return Row(*base, method, model, float("nan"), 0.0, type(exc).__name__)
    elapsed = 1e3 * (time.perf_counter() - start)
    return Row(*base, method, model, float(mean_position_error(estimate, truth)), elapsed)


def _run_chunk(case: Case, trials: range, solver_names: tuple[str, ...]) -> list[Row]:
    with threadpool_limits(limits=1):
        ctx = _context(case.room, solver_names)
        return [row for trial in trials for row in _run_trial(case, trial, ctx)]


def _chunks(cases: Sequence[Case], size: int) -> list[tuple[Case, range]]:
    work = [
        (case, range(start, min(start + size, case.trials)))
        for case in cases
        for start in range(0, case.trials, size)
    ]
    # Largest K first so the slowest chunks do not end the run alone.
    return sorted(work, key=lambda item: -item[0].n_targets)


def _progress(done: int, total: int, started: float) -> None:
    if done == total or done % max(1, total // 10) == 0:
        print(
            f"  {done}/{total} chunks, {time.perf_counter() - started:.0f} s",
            file=sys.stderr,
            flush=True,
        )


def run_cases(cases: Sequence[Case], solver_names: Sequence[str], *, jobs: int = 1) -> list[Row]:
    """Run every trial of every case; rows sorted by (room, SNR, K, trial, method, model)."""
    names = tuple(solver_names)
    work = _chunks(cases, 10)
    rows: list[Row] = []
    started = time.perf_counter()
    if jobs <= 1:
        for done, (case, trials) in enumerate(work, 1):
            rows += _run_chunk(case, trials, names)
            _progress(done, len(work), started)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(_run_chunk, case, trials, names) for case, trials in work]
            for done, future in enumerate(as_completed(futures), 1):
                rows += future.result()
                _progress(done, len(work), started)
    return sorted(rows, key=lambda r: (r.room, r.snr_db, r.n_targets, r.trial, r.method, r.model))


def fig3_estimates(solver_names: Sequence[str]) -> list[tuple[str, str, FloatArray, FloatArray]]:
    """Fig. 3's scene: trial 0 of (paper room, 30 dB, K = 8), each scheme's estimates.

    Returns
    -------
    list of (method, model, truth (8, 2), estimates (8, 2)), metres; the RSS baseline first.
    """
    case = Case("paper", 30.0, 8, 1, 1)
    ctx = _context(case.room, tuple(solver_names))
    truth, amps = draw_trial(case, 0, ctx.layout, noise_std_for_snr(ctx.fingerprint, 30.0))
    scenes = [(RSS, NO_MODEL, truth, np.asarray(rss_localize(ctx.layout, amps)))]
    for name in solver_names:
        for model in MODELS:
            measurement = measurement_from_amplitudes(amps, model, ctx.layout.n_leds)
            estimate = ctx.solvers[name, model].solve(measurement, case.n_targets).positions
            scenes.append((name, model, truth, np.asarray(estimate)))
    return scenes


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m bench.accuracy",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quick", action="store_true", help="~1 minute run (few K and trials)")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default docs/, or bench/out/quick with --quick)",
    )
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--solvers", default=None, help="comma-separated (default: all)")
    parser.add_argument("--rooms", default=None, help="comma-separated subset of paper,hall")
    parser.add_argument("--ks", default=None, help="comma-separated K (overrides the plan)")
    parser.add_argument("--snrs", default=None, help="comma-separated SNR in dB (overrides)")
    parser.add_argument("--trials", type=int, default=None, help="trials per case (overrides)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    return parser.parse_args(argv)


def plan_from_args(args: argparse.Namespace) -> list[Case]:
    """The cases selected by the command line."""
    cases = quick_cases() if args.quick else default_cases()
    if args.rooms:
        cases = [c for c in cases if c.room in args.rooms.split(",")]
    if args.snrs:
        cases = [c for c in cases if c.snr_db in {float(s) for s in args.snrs.split(",")}]
    if args.ks:
        keep = {(c.room, c.snr_db) for c in cases}
        template = {(c.room, c.snr_db): c for c in cases}
        cases = [
            replace(template[key], n_targets=int(k))
            for key in sorted(keep)
            for k in args.ks.split(",")
        ]
    if args.trials is not None:
        cases = [
            replace(c, trials=args.trials, slow_trials=min(c.slow_trials, args.trials))
            for c in cases
        ]
    return cases


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and write CSV, figures and ``results/accuracy.md`` into ``--out``."""
    from . import plots, report

    args = _parse_args(argv)
    out = args.out or (REPO_ROOT / ("bench/out/quick" if args.quick else "docs"))
    registered = load_solvers()
    names = [n for n in (args.solvers.split(",") if args.solvers else registered)]
    cases = plan_from_args(args)
    started = time.perf_counter()
    rows = run_cases(cases, names, jobs=args.jobs)
    summary = summarise(rows)
    elapsed = time.perf_counter() - started
    write_csv(out / "data" / "accuracy_trials.csv", TRIAL_HEADER, (r.as_tuple() for r in rows))
    write_csv(
        out / "data" / "accuracy_summary.csv", SUMMARY_HEADER, (summary_tuple(s) for s in summary)
    )
    figures: list[Path] = []
    if not args.no_plots:
        scenes = fig3_estimates([n for n in names if n in ("gridless", "omp")] or names[:1])
        layout = _context("paper", tuple(names)).layout
        figures.append(plots.fig3(scenes, layout, out / "figures" / "fig3_estimates_k8.png"))
        figures += plots.fig4_all(summary, out / "figures")
    report.write_accuracy_md(
        out / "results" / "accuracy.md",
        summary,
        cases,
        names,
        machine_record(),
        argv=list(argv) if argv is not None else sys.argv[1:],
        elapsed_s=elapsed,
        figures=figures,
    )
    failures = sum(r.status != "ok" for r in rows)
    print(f"{len(rows)} rows, {failures} failures, {elapsed:.0f} s; wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
