"""In-process solve time per solver x model (paper room, 30 dB, K = 8), warm caches.

Run from the repository root::

    python -m bench.solver_timing            # writes docs/data/solver_timing.csv and the
                                             # "Solver timings" section of
                                             # docs/results/solver-timing.md
    python -m bench.solver_timing --quick    # a few repetitions, into bench/out/quick/
    python -m bench.solver_timing --kernels  # only the default solver, compiled vs reference
                                             # kernels (the "Compiled kernels" section)

Each solver object is built once (as the service caches it) and warmed up; only ``.solve``
is timed, cycling over a pool of seeded K = 8 measurements. BLAS is limited to one thread
(threadpoolctl). ``OPENBLAS_CORETYPE`` is left as the machine sets it and recorded. The l1
solver is also timed with its compiled cvxpy problem swapped for one rebuilt on every call
(``app.vlp.solvers.l1.solve_l1_fresh``), which gives the speed-up of compiling once.

The default solver is also timed with its compiled (numba) kernels and with their NumPy
references side by side, K = 1, 4 and 8, for the correlation and power models and for
terminals sending their own amplitudes: each measurement is solved with both, one after the
other, so that both see the same load (:func:`run_kernels`).
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from app.vlp._kernels import KernelMode, use_kernels
from app.vlp.fingerprints import build_fingerprint
from app.vlp.measurements import MODELS, Measurement, Model, measurement_from_amplitudes
from app.vlp.simulation import noise_std_for_snr
from app.vlp.solvers import Solver, make_solver, warm_up
from app.vlp.typing import FloatArray

from ._common import (
    REPO_ROOT,
    load_solvers,
    machine_markdown,
    machine_record,
    replace_section,
    write_csv,
)
from .accuracy import Case, draw_trial
from .rooms import make_room

__all__ = [
    "FreshL1Program",
    "KernelTiming",
    "Timing",
    "main",
    "measurement_pool",
    "run_kernels",
    "time_solver",
]

CASE = Case("paper", 30.0, 8, 0, 0)
POOL_SIZE = 50
FAST_REPETITIONS = 300
# A combination gets at least this many timed solves, more while within the time budget.
MIN_REPETITIONS = 30
BUDGET_S = 20.0
# In-process targets at K = 8 (median, milliseconds); l1 compiled vs rebuilt.
TARGET_MEDIAN_MS = {"gridless": 5.0, "omp": 1.0}
TARGET_L1_SPEEDUP = 3.0
HEADER = ("solver", "model", "variant", "repetitions", "median_ms", "p90_ms", "mean_ms", "min_ms")
PREAMBLE = "# Results: solver timings\n"
# In-process targets for the default solver's compiled kernels (median, milliseconds), by (form, K).
KERNEL_TARGETS_MS = {("correlation", 8): 2.0, ("power", 8): 5.0, ("correlation", 1): 0.3}
KERNEL_KS = (1, 4, 8)
KERNEL_FORMS = ("correlation", "power", "terminals")
KERNEL_HEADER = (
    "form",
    "k",
    "repetitions",
    "reference_cpu_ms",
    "compiled_cpu_ms",
    "ratio",
    "reference_wall_ms",
    "compiled_wall_ms",
)


@dataclass(frozen=True)
class KernelTiming:
    """Median solve times of the default solver with both kernels, milliseconds: CPU time
    of the process (what an idle core would take) and wall time (also the waits for a core
    on a shared machine)."""

    form: str
    n_targets: int
    repetitions: int
    reference_ms: float
    compiled_ms: float
    reference_wall_ms: float
    compiled_wall_ms: float

    @property
    def ratio(self) -> float:
        """Compiled over reference CPU time (below 1: the compiled kernels are faster)."""
        return self.compiled_ms / self.reference_ms

    def as_tuple(self) -> tuple[object, ...]:
        """The CSV row in :data:`KERNEL_HEADER` order."""
        return (
            self.form,
            self.n_targets,
            self.repetitions,
            f"{self.reference_ms:.4g}",
            f"{self.compiled_ms:.4g}",
            f"{self.ratio:.3f}",
            f"{self.reference_wall_ms:.4g}",
            f"{self.compiled_wall_ms:.4g}",
        )


def _kernel_pool(n_targets: int, size: int) -> list[FloatArray]:
    """Seeded noisy amplitudes (K, M) of the paper room at 30 dB."""
    layout = make_room(CASE.room)
    std = noise_std_for_snr(build_fingerprint(layout), CASE.snr_db)
    case = Case(CASE.room, CASE.snr_db, n_targets, 0, 0)
    return [draw_trial(case, trial, layout, std)[1] for trial in range(size)]


def run_kernels(*, repetitions: int, budget_s: float) -> list[KernelTiming]:
    """Time the default solver with the compiled and the reference kernels, interleaved."""
    warm_up()
    layout = make_room(CASE.room)
    fingerprint = build_fingerprint(layout)
    results = []
    for form in KERNEL_FORMS:
        model: Model = "power" if form == "power" else "correlation"
        solver = make_solver("gridless", fingerprint, model)
        for n_targets in KERNEL_KS:
            amplitudes = _kernel_pool(n_targets, POOL_SIZE)
            calls: list[Callable[[], object]]
            if form == "terminals":
                solve_terminals = solver.solve_terminals  # type: ignore[attr-defined]
                calls = [functools.partial(solve_terminals, a) for a in amplitudes]
            else:
                calls = [
                    functools.partial(
                        solver.solve,
                        measurement_from_amplitudes(a, model, layout.n_leds),
                        n_targets,
                    )
                    for a in amplitudes
                ]
            cpu: dict[KernelMode, list[float]] = {"reference": [], "compiled": []}
            wall: dict[KernelMode, list[float]] = {"reference": [], "compiled": []}
            started = time.perf_counter()
            for index in range(repetitions + 2):
                call = calls[index % len(calls)]
                for mode in ("reference", "compiled"):
                    with use_kernels(mode):
                        start, start_cpu = time.perf_counter(), time.process_time()
                        call()
                        elapsed_cpu = time.process_time() - start_cpu
                        elapsed = time.perf_counter() - start
                    if index >= 2:  # the first two rounds warm the caches
                        cpu[mode].append(elapsed_cpu)
                        wall[mode].append(elapsed)
                done = index - 1
                if done >= MIN_REPETITIONS and time.perf_counter() - started > budget_s:
                    break
            results.append(
                KernelTiming(
                    form,
                    n_targets,
                    len(cpu["compiled"]),
                    1e3 * float(np.median(cpu["reference"])),
                    1e3 * float(np.median(cpu["compiled"])),
                    1e3 * float(np.median(wall["reference"])),
                    1e3 * float(np.median(wall["compiled"])),
                )
            )
    return results


def kernels_markdown(
    results: Sequence[KernelTiming],
    machine: dict[str, str],
    argv: Sequence[str],
    load: tuple[float, float, float],
) -> str:
    """The self-contained "Compiled kernels" section of ``docs/results/solver-timing.md``."""
    parts = [
        "## Default solver: compiled vs reference kernels",
        "",
        "In-process `gridless` solve time (paper room, 30 dB, BLAS limited to one thread) with",
        "the compiled (numba) kernels and with their plain NumPy references (`VLP_KERNELS`),",
        "each measurement solved with both one after the other, so that both see the same",
        f"load; cycling over {POOL_SIZE} seeded measurements per K, after two warm-up rounds.",
        "`terminals`: each terminal's own amplitudes (`solve_terminals`). Medians of the",
        "process's CPU time per solve (what an idle core takes; on a shared machine the wall",
        "time also holds the waits for a core, shown too).",
        "",
        f"Command (repository root): `{' '.join(['python -m bench.solver_timing', *argv])}`",
        "",
        machine_markdown(machine),
        f"- load average at start (1/5/15 min): `{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}`",
        "",
        "| form | K | repetitions | reference CPU (ms) | compiled CPU (ms) | compiled / reference "
        "| reference wall (ms) | compiled wall (ms) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    parts += [
        f"| {t.form} | {t.n_targets} | {t.repetitions} | {t.reference_ms:.3g} | "
        f"{t.compiled_ms:.3g} | {t.ratio:.2f} | {t.reference_wall_ms:.3g} | "
        f"{t.compiled_wall_ms:.3g} |"
        for t in results
    ]
    by = {(t.form, t.n_targets): t for t in results}
    parts += [
        "",
        "### Targets (compiled kernels)",
        "",
        "| check | target | measured | met |",
        "|---|---|---|---|",
    ]
    for (form, n_targets), limit in KERNEL_TARGETS_MS.items():
        found = by.get((form, n_targets))
        if found is not None:
            met = "yes" if found.compiled_ms <= limit else "**no**"
            parts.append(
                f"| `gridless` {form}, K = {n_targets}, median CPU time | ≤ {limit:g} ms | "
                f"{found.compiled_ms:.3g} ms | {met} |"
            )
    parts += ["", "Raw numbers: `docs/data/kernel_timing.csv`."]
    return "\n".join(parts)


@dataclass(frozen=True)
class Timing:
    """Solve times of one solver x model (x variant), milliseconds."""

    solver: str
    model: str
    variant: str
    repetitions: int
    median_ms: float
    p90_ms: float
    mean_ms: float
    min_ms: float

    def as_tuple(self) -> tuple[object, ...]:
        """The CSV row in :data:`HEADER` order."""
        return (
            self.solver,
            self.model,
            self.variant,
            self.repetitions,
            *(f"{v:.4g}" for v in (self.median_ms, self.p90_ms, self.mean_ms, self.min_ms)),
        )


def measurement_pool(model: Model, size: int = POOL_SIZE) -> list[Measurement]:
    """``size`` seeded K = 8 measurements of the paper room at 30 dB (accuracy's trials)."""
    layout = make_room(CASE.room)
    std = noise_std_for_snr(build_fingerprint(layout), CASE.snr_db)
    return [
        measurement_from_amplitudes(draw_trial(CASE, trial, layout, std)[1], model, layout.n_leds)
        for trial in range(size)
    ]


def time_solver(
    solve: Callable[[Measurement], object],
    pool: Sequence[Measurement],
    *,
    repetitions: int,
    budget_s: float,
) -> FloatArray:
    """Seconds per call of ``solve``, cycling over ``pool`` after 3 warm-up calls.

    Runs ``repetitions`` calls, or fewer (but at least :data:`MIN_REPETITIONS`) when that
    would exceed ``budget_s``.
    """
    for measurement in pool[:3]:
        solve(measurement)
    times: list[float] = []
    started = time.perf_counter()
    for index in range(repetitions):
        measurement = pool[index % len(pool)]
        start = time.perf_counter()
        solve(measurement)
        times.append(time.perf_counter() - start)
        if index + 1 >= MIN_REPETITIONS and time.perf_counter() - started > budget_s:
            break
    return np.asarray(times)


class FreshL1Program:
    """Stands in for the l1 solver's compiled problem and rebuilds the problem every call."""

    def __init__(self, solver: Solver) -> None:
        from app.vlp.solvers.l1 import solve_l1_fresh

        self._solve_fresh = solve_l1_fresh
        dictionary = solver.dictionary  # type: ignore[attr-defined]
        self._matrix = dictionary.normalised
        self._noise_unit = dictionary.noise_unit

    def solve(self, target: FloatArray, eps: float) -> tuple[FloatArray, float]:
        """``solve_l1_fresh`` on the solver's dictionary."""
        return self._solve_fresh(self._matrix, self._noise_unit, target, eps)


def _timing(solver: str, model: str, variant: str, seconds: FloatArray) -> Timing:
    ms = 1e3 * seconds
    return Timing(
        solver,
        model,
        variant,
        int(ms.size),
        float(np.median(ms)),
        float(np.percentile(ms, 90)),
        float(np.mean(ms)),
        float(np.min(ms)),
    )


def _clarabel_share(solver: Solver, model: str, pool: Sequence[Measurement]) -> Timing:
    """Clarabel's own solve time inside the compiled l1 solver (cvxpy's ``solver_stats``)."""
    problem = solver.program.problem  # type: ignore[attr-defined]
    seconds = []
    for measurement in pool[:MIN_REPETITIONS]:
        solver.solve(measurement, CASE.n_targets)
        seconds.append(float(problem.solver_stats.solve_time))
    return _timing("l1", model, "Clarabel alone (in compiled once)", np.asarray(seconds))


def run(names: Sequence[str], *, repetitions: int, budget_s: float) -> list[Timing]:
    """Time every solver x model; l1 also with its problem rebuilt on every call."""
    fingerprint = build_fingerprint(make_room(CASE.room))
    results = []
    for model in MODELS:
        pool = measurement_pool(model)
        for name in names:
            solver = make_solver(name, fingerprint, model)

            def solve(m: Measurement, solver: Solver = solver) -> object:
                return solver.solve(m, CASE.n_targets)

            seconds = time_solver(solve, pool, repetitions=repetitions, budget_s=budget_s)
            results.append(
                _timing(name, model, "compiled once" if name == "l1" else "warm", seconds)
            )
            if name == "l1":
                results.append(_clarabel_share(solver, model, pool))
                fresh = make_solver(name, fingerprint, model)
                fresh.program = FreshL1Program(fresh)  # type: ignore[attr-defined]

                def solve_fresh(m: Measurement, solver: Solver = fresh) -> object:
                    return solver.solve(m, CASE.n_targets)

                seconds = time_solver(solve_fresh, pool, repetitions=repetitions, budget_s=budget_s)
                results.append(_timing(name, model, "rebuilt every call", seconds))
    return results


def _targets(results: Sequence[Timing]) -> list[str]:
    lines = ["| check | model | target | measured | met |", "|---|---|---|---|---|"]
    by = {(t.solver, t.model, t.variant): t for t in results}
    for name, limit in TARGET_MEDIAN_MS.items():
        for model in MODELS:
            t = by.get((name, model, "warm"))
            if t is not None:
                lines.append(
                    f"| `{name}` median solve, K = 8 | {model} | ≤ {limit:g} ms | "
                    f"{t.median_ms:.3g} ms | {'yes' if t.median_ms <= limit else '**no**'} |"
                )
    for model in MODELS:
        once = by.get(("l1", model, "compiled once"))
        fresh = by.get(("l1", model, "rebuilt every call"))
        if once is not None and fresh is not None:
            speedup = fresh.median_ms / once.median_ms
            lines.append(
                f"| `l1` compiled once vs rebuilt every call (medians) | {model} | "
                f"≥ {TARGET_L1_SPEEDUP:g}x | {speedup:.1f}x | "
                f"{'yes' if speedup >= TARGET_L1_SPEEDUP else '**no**'} |"
            )
    return lines


def _notes(results: Sequence[Timing]) -> list[str]:
    """Plain-language reading of the l1 and default-solver numbers."""
    by = {(t.solver, t.model, t.variant): t for t in results}
    lines = []
    for model in MODELS:
        once = by.get(("l1", model, "compiled once"))
        fresh = by.get(("l1", model, "rebuilt every call"))
        core = by.get(("l1", model, "Clarabel alone (in compiled once)"))
        if once and fresh and core:
            lines.append(
                f"- `l1`, {model}: Clarabel's own solve is {core.median_ms:.3g} ms of the "
                f"{once.median_ms:.3g} ms median, so rebuilding the cvxpy problem adds only "
                f"{fresh.median_ms - once.median_ms:.3g} ms "
                f"({fresh.median_ms / once.median_ms:.1f}x); no caching of the problem can "
                f"reach {TARGET_L1_SPEEDUP:g}x while the interior-point solve dominates."
            )
    for model in MODELS:
        t = by.get(("gridless", model, "warm"))
        if t:
            limit = TARGET_MEDIAN_MS["gridless"]
            verdict = "within" if t.median_ms <= limit else "above"
            lines.append(
                f"- `gridless`, {model}: median {t.median_ms:.3g} ms, {verdict} the "
                f"{limit:g} ms target ({t.median_ms / limit:.2f}x)."
            )
    return lines


def markdown(
    results: Sequence[Timing],
    machine: dict[str, str],
    argv: Sequence[str],
    load: tuple[float, float, float],
) -> str:
    """The self-contained "Solver timings" section of ``docs/results/solver-timing.md``."""
    parts = [
        "## Solver timings",
        "",
        "In-process `Solver.solve` time for the paper's room (16 LEDs, N = 400) at 30 dB with",
        "K = 8 targets given, both measurement models. Each solver object is built once and",
        "warmed up (as the service caches it per room, fingerprint and model); only `.solve` is",
        f"timed, cycling over {POOL_SIZE} seeded measurements. BLAS limited to one thread",
        "(threadpoolctl). `OPENBLAS_CORETYPE` is left as the machine sets it (recorded below).",
        "",
        f"Command (repository root): `{' '.join(['python -m bench.solver_timing', *argv])}`",
        "",
        machine_markdown(machine),
        f"- BLAS while timing: `{_blas_under_limit()}`",
        f"- load average at start (1/5/15 min): `{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}` "
        "(the 2 cores may be shared; medians are robust to that, p90 less so)",
        "",
        "| solver | model | variant | repetitions | median (ms) | p90 (ms) | mean (ms) "
        "| min (ms) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    parts += [
        f"| `{t.solver}` | {t.model} | {t.variant} | {t.repetitions} | {t.median_ms:.3g} | "
        f"{t.p90_ms:.3g} | {t.mean_ms:.3g} | {t.min_ms:.3g} |"
        for t in results
    ]
    parts += [
        "",
        "### Timing targets",
        "",
        *_targets(results),
        "",
        *_notes(results),
        "",
        "Raw numbers: `docs/data/solver_timing.csv`.",
    ]
    return "\n".join(parts)


def _blas_under_limit() -> str:
    with threadpool_limits(limits=1):
        return "; ".join(
            f"{i.get('internal_api')} {i.get('architecture')}, {i.get('num_threads')} thread(s)"
            for i in threadpool_info()
            if i.get("user_api") == "blas"
        )


def main(argv: Sequence[str] | None = None) -> int:
    """Time every registered solver and write the CSV and the markdown section."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.solver_timing",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quick", action="store_true", help="few repetitions (~1 min)")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default docs/, or bench/out/quick with --quick)",
    )
    parser.add_argument("--solvers", default=None, help="comma-separated (default: all)")
    parser.add_argument(
        "--kernels",
        action="store_true",
        help="only the default solver's compiled vs reference kernels",
    )
    args = parser.parse_args(argv)
    out = args.out or (REPO_ROOT / ("bench/out/quick" if args.quick else "docs"))
    shown = list(argv) if argv is not None else sys.argv[1:]
    if args.kernels:
        return _main_kernels(out, shown, quick=args.quick)
    names = args.solvers.split(",") if args.solvers else load_solvers()
    if args.solvers:
        load_solvers()
    load = os.getloadavg()
    with threadpool_limits(limits=1):
        results = run(
            names,
            repetitions=MIN_REPETITIONS if args.quick else FAST_REPETITIONS,
            budget_s=2.0 if args.quick else BUDGET_S,
        )
    write_csv(out / "data" / "solver_timing.csv", HEADER, (t.as_tuple() for t in results))
    replace_section(
        out / "results" / "solver-timing.md",
        "solver-timings",
        markdown(results, machine_record(), shown, load),
        preamble=PREAMBLE,
    )
    for t in results:
        print(
            f"{t.solver:10s} {t.model:12s} {t.variant:20s} median {t.median_ms:8.3f} ms "
            f"p90 {t.p90_ms:8.3f} ms  ({t.repetitions} reps)"
        )
    return 0


def _main_kernels(out: Path, shown: Sequence[str], *, quick: bool) -> int:
    load = os.getloadavg()
    with threadpool_limits(limits=1):
        results = run_kernels(
            repetitions=MIN_REPETITIONS if quick else FAST_REPETITIONS,
            budget_s=2.0 if quick else BUDGET_S,
        )
    write_csv(out / "data" / "kernel_timing.csv", KERNEL_HEADER, (t.as_tuple() for t in results))
    replace_section(
        out / "results" / "solver-timing.md",
        "kernel-timings",
        kernels_markdown(results, machine_record(), shown, load),
        preamble=PREAMBLE,
    )
    for t in results:
        print(
            f"gridless {t.form:12s} K={t.n_targets} CPU reference {t.reference_ms:8.3f} ms "
            f"compiled {t.compiled_ms:8.3f} ms  ratio {t.ratio:.2f}  (wall "
            f"{t.reference_wall_ms:.3f} / {t.compiled_wall_ms:.3f} ms, {t.repetitions} reps)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
