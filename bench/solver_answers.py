"""Dump the default solver's answers on a fixed set of solves, and compare two dumps.

A refactor of the default (``gridless``) solver must not change what it answers. This solves
a fixed, seeded set of measurements -- rooms (the paper's, an office, a hall), conditions
(ideal; the realistic mix with the reflectance in the layout; and with the height and tilt
spreads in the layout too), the three forms (``power``, ``correlation``, ``terminals``), K
given and counted, 15 to 40 dB -- and writes every number of every answer (positions,
weights, covariances, gains, heights, the fit block, counts, iterations; an error's type and
message when a solve refuses) to one ``.npz``::

    python -m bench.solver_answers --out /tmp/answers-a.npz
    python -m bench.solver_answers --out /tmp/answers-b.npz
    python -m bench.solver_answers --compare /tmp/answers-a.npz /tmp/answers-b.npz

``--compare`` prints the largest relative difference of each field over all solves (and any
answer whose shape, text or count differs) and exits 1 when one exceeds ``--rtol``
(default 0: identical). ``--quick`` solves a small subset (a smoke test of the script).
BLAS is limited to one thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
import time
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from app.vlp.errors import VLPError
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout
from app.vlp.measurements import Model, measurement_from_amplitudes
from app.vlp.simulation import Impairments
from app.vlp.solvers import Solution, Solver, make_solver, warm_up
from app.vlp.solvers.gridless import GridlessSolver

from ._real_rooms_extra import draw_terminals
from .rooms import make_room

__all__ = ["SolveCase", "compare", "main", "plan", "run"]

SEED = 20261127
MIX = Impairments.realistic_mix()
FORMS = ("power", "correlation", "terminals")
# (room, condition) pairs: condition -> (impairments, reflectance in layout, height sd and
# tilt sd declared in the layout).
CONDITIONS: dict[str, tuple[Impairments, bool, float, float]] = {
    "ideal": (Impairments.ideal(), False, 0.0, 0.0),
    "mix": (MIX, True, 0.0, 0.0),
    "mix-spreads": (MIX, True, MIX.height_sd_m, MIX.tilt_component_sd_deg),
}
ROOM_CONDITIONS = (
    ("paper", "ideal"),
    ("paper", "mix"),
    ("paper", "mix-spreads"),
    ("office", "ideal"),
    ("office", "mix"),
    ("hall", "ideal"),
    ("hall", "mix"),
)
KS = (1, 3, 6)
SNRS_DB = (15.0, 25.0, 40.0)
TRIALS = 5


@dataclass(frozen=True)
class SolveCase:
    """One solve: where, under what, which form, how many targets, K given or counted."""

    room: str
    condition: str
    form: str
    n_targets: int
    given: bool
    snr_db: float
    trial: int

    @property
    def key(self) -> str:
        count = "given" if self.given else "counted"
        return (
            f"{self.room}/{self.condition}/{self.form}/k{self.n_targets}/{count}/"
            f"{self.snr_db:g}dB/t{self.trial}"
        )


def plan(*, trials: int = TRIALS, quick: bool = False) -> list[SolveCase]:
    """Every solve of a dump, in a fixed order (terminals: K is the terminals sent)."""
    pairs = ROOM_CONDITIONS[:2] if quick else ROOM_CONDITIONS
    ks = KS[:2] if quick else KS
    cases = []
    for (room, condition), form, k, snr, trial in itertools.product(
        pairs, FORMS, ks, SNRS_DB, range(1 if quick else trials)
    ):
        for given in (True,) if form == "terminals" else (True, False):
            cases.append(SolveCase(room, condition, form, k, given, snr, trial))
    return cases


@cache
def _layout(room: str, condition: str) -> Layout:
    _, reflectance_in_layout, height_sd, tilt_sd = CONDITIONS[condition]
    layout = make_room(room)
    reflectance = MIX.reflectance if reflectance_in_layout else None
    return dataclasses.replace(
        layout,
        room=dataclasses.replace(layout.room, reflectance=reflectance),
        grid=dataclasses.replace(
            layout.grid, receiver_height_sd=height_sd, receiver_tilt_sd=tilt_sd
        ),
    )


@cache
def _fingerprint(room: str, condition: str) -> Fingerprint:
    return build_fingerprint(_layout(room, condition))


@cache
def _solver(room: str, condition: str, model: Model) -> Solver:
    return make_solver("gridless", _fingerprint(room, condition), model)


def _generator(*parts: object) -> np.random.Generator:
    key = tuple(zlib.crc32(str(part).encode()) for part in parts)
    return np.random.default_rng(np.random.SeedSequence(SEED, spawn_key=key))


def _solve(case: SolveCase) -> Solution:
    layout = _layout(case.room, case.condition)
    impairments = CONDITIONS[case.condition][0]
    _, simulated = draw_terminals(
        layout,
        case.n_targets,
        impairments,
        snr_db=case.snr_db,
        placement_rng=_generator("place", case.room, case.n_targets, case.trial),
        noise_rng=_generator("noise", case.key),
    )
    if case.form == "terminals":
        solver = _solver(case.room, case.condition, "correlation")
        assert isinstance(solver, GridlessSolver)
        # Every other trial sends the true heights; every third the true normals too.
        heights = simulated.heights if case.trial % 2 == 1 else None
        normals = simulated.normals if case.trial % 3 == 2 else None
        return solver.solve_terminals(simulated.amplitudes, heights, normals)
    model: Model = "power" if case.form == "power" else "correlation"
    measurement = measurement_from_amplitudes(simulated.amplitudes, model, layout.n_leds)
    return _solver(case.room, case.condition, model).solve(
        measurement, case.n_targets if case.given else None
    )


def _flatten(prefix: str, value: object) -> Iterator[tuple[str, np.ndarray]]:
    """Every field of an answer (dataclasses recursed) as arrays, keyed by their path."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for field in dataclasses.fields(value):
            yield from _flatten(f"{prefix}.{field.name}", getattr(value, field.name))
    elif value is None:
        yield f"{prefix}:none", np.zeros(0)
    elif isinstance(value, str):
        yield prefix, np.array(value)
    else:
        yield prefix, np.asarray(value)


def run(cases: Sequence[SolveCase], *, progress: bool = False) -> dict[str, np.ndarray]:
    """Solve every case; the answers' arrays keyed ``<case key>/<field path>``."""
    warm_up()
    out: dict[str, np.ndarray] = {}
    started = time.perf_counter()
    for index, case in enumerate(cases):
        try:
            solution = _solve(case)
        except VLPError as exc:
            out[f"{case.key}/error"] = np.array(f"{type(exc).__name__}: {exc}")
        else:
            out[f"{case.key}/n_targets"] = np.array(solution.n_targets)
            out.update(_flatten(case.key + "/", solution))
        if progress and (index + 1) % 100 == 0:
            elapsed = time.perf_counter() - started
            print(f"{index + 1}/{len(cases)} solves, {elapsed:.0f} s", file=sys.stderr)
    return out


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    if a.dtype.kind in "US" or b.dtype.kind in "US" or a.dtype == bool:
        return 0.0 if np.array_equal(a, b) else float("inf")
    x = a.astype(np.float64)
    y = b.astype(np.float64)
    same = (x == y) | (np.isnan(x) & np.isnan(y))
    scale = np.maximum(np.abs(x), np.abs(y))
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(same, 0.0, np.abs(x - y) / np.where(scale > 0, scale, 1.0))
    rel = np.where(np.isnan(rel), np.inf, rel)
    return float(np.max(rel)) if rel.size else 0.0


def compare(
    a: dict[str, np.ndarray], b: dict[str, np.ndarray]
) -> tuple[dict[str, float], list[str]]:
    """The largest relative difference of each field (over all solves), and the keys
    present in only one dump or of different shapes (structural differences)."""
    structural = sorted(set(a) ^ set(b))
    largest: dict[str, float] = {}
    for key in sorted(set(a) & set(b)):
        field = key.split("/", 7)[-1]
        if a[key].shape != b[key].shape:
            structural.append(key)
            continue
        largest[field] = max(largest.get(field, 0.0), _relative(a[key], b[key]))
    return largest, structural


def _load(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m bench.solver_answers``."""
    parser = argparse.ArgumentParser(prog="python -m bench.solver_answers", description=__doc__)
    parser.add_argument("--out", type=Path, help="write the dump here (.npz)")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    parser.add_argument("--rtol", type=float, default=0.0, help="largest allowed difference")
    parser.add_argument("--trials", type=int, default=TRIALS, help="placements per cell")
    parser.add_argument("--quick", action="store_true", help="a small subset")
    args = parser.parse_args(argv)
    if args.compare:
        a, b = (_load(path) for path in args.compare)
        largest, structural = compare(a, b)
        solves = sum(1 for key in a if key.endswith(("/n_targets", "/error")))
        print(f"{solves} solves compared")
        for field, value in sorted(largest.items()):
            print(f"{field:40s} max relative difference {value:.3g}")
        for key in structural[:20]:
            print(f"differs in structure: {key}")
        worst = max(largest.values(), default=0.0)
        print(
            f"largest relative difference: {worst:.3g}; structural differences: {len(structural)}"
        )
        return 0 if worst <= args.rtol and not structural else 1
    if args.out is None:
        parser.error("give --out PATH or --compare A B")
    cases = plan(trials=args.trials, quick=args.quick)
    started = time.perf_counter()
    with threadpool_limits(limits=1):
        answers = run(cases, progress=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **answers)  # type: ignore[arg-type]
    errors = sum(1 for key in answers if key.endswith("/error"))
    print(
        f"{len(cases)} solves ({errors} refused) in {time.perf_counter() - started:.0f} s "
        f"-> {args.out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
