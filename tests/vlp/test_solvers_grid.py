"""Grid solvers (omp, nnls, l1): exact noiseless recovery, references, errors, large rooms."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

import app.vlp.fingerprints as fingerprints
from app.vlp.errors import MeasurementError, SolverError, SolverFailed, UnknownSolverError
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Room
from app.vlp.measurements import (
    Measurement,
    Model,
    measurement_from_amplitudes,
    noise_atom,
)
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers import make_solver, solver_names
from app.vlp.solvers._counting import estimate_target_count
from app.vlp.solvers._grid import GridDictionary
from app.vlp.solvers.base import Solver
from app.vlp.solvers.l1 import L1Solver, solve_l1_fresh

MODELS: tuple[Model, ...] = ("power", "correlation")
GRID_SOLVERS = ("omp", "nnls", "l1")
# Well-separated on-grid supports in the paper room (cells of the 20 x 20 grid).
EASY_SUPPORTS = {"K1": [45], "K2": [45, 310], "K3": [42, 357, 57], "K3b": [21, 378, 190]}


@pytest.fixture(scope="module")
def solvers(paper_fingerprint: Fingerprint) -> dict[tuple[str, str], Solver]:
    return {
        (name, model): make_solver(name, paper_fingerprint, model)
        for name in GRID_SOLVERS
        for model in MODELS
    }


def _measure(layout: Layout, cells: list[int], model: Model) -> Measurement:
    amps = true_amplitudes(layout, layout.cell_centres(np.array(cells)))
    return measurement_from_amplitudes(amps, model, layout.n_leds)


def test_registered() -> None:
    assert {"omp", "nnls", "l1"} <= set(solver_names())


def test_unknown_solver(paper_fingerprint: Fingerprint) -> None:
    with pytest.raises(UnknownSolverError) as info:
        make_solver("simplex", paper_fingerprint, "power")
    assert info.value.field == "solver"


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("name", ["nnls", "l1"])
@pytest.mark.parametrize("case", list(EASY_SUPPORTS))
def test_exact_recovery(
    solvers: dict[tuple[str, str], Solver], paper_room: Layout, name: str, model: Model, case: str
) -> None:
    cells = EASY_SUPPORTS[case]
    measurement = _measure(paper_room, cells, model)
    for n_targets in (len(cells), None):  # given K, and K estimated
        solution = solvers[name, model].solve(measurement, n_targets)
        assert sorted(solution.grid_indices.tolist()) == sorted(cells)
        assert_allclose(solution.weights, 1.0, rtol=1e-6)
        assert_allclose(
            np.sort(solution.positions, axis=0),
            np.sort(paper_room.cell_centres(np.array(cells)), axis=0),
        )
        assert solution.noise_power == pytest.approx(0.0, abs=1e-6 * np.max(measurement.values))
        assert solution.residual_norm <= 1e-6 * np.linalg.norm(measurement.values)
        assert solution.converged


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("seed", range(6))
def test_nnls_random_separated_supports(
    solvers: dict[tuple[str, str], Solver], paper_room: Layout, model: Model, seed: int
) -> None:
    gen = np.random.default_rng(seed)
    centres = paper_room.cell_centres()
    for n_targets in (1, 2, 3):
        while True:
            cells = gen.choice(paper_room.n_cells, n_targets, replace=False)
            gaps = np.linalg.norm(centres[cells, None] - centres[None, cells], axis=2)
            if n_targets == 1 or gaps[np.triu_indices(n_targets, 1)].min() >= 1.0:
                break
        solution = solvers["nnls", model].solve(_measure(paper_room, cells.tolist(), model))
        assert sorted(solution.grid_indices.tolist()) == sorted(cells.tolist())


@pytest.mark.parametrize("model", MODELS)
def test_omp_finds_any_single_target(
    solvers: dict[tuple[str, str], Solver], paper_room: Layout, model: Model
) -> None:
    solver = solvers["omp", model]
    for cell in range(paper_room.n_cells):
        solution = solver.solve(_measure(paper_room, [cell], model), 1)
        assert solution.grid_indices.tolist() == [cell]
        assert solution.weights[0] == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize("model", MODELS)
def test_omp_two_far_targets(
    solvers: dict[tuple[str, str], Solver], paper_room: Layout, model: Model
) -> None:
    measurement = _measure(paper_room, [0, 399], model)
    for n_targets in (2, None):
        solution = solvers["omp", model].solve(measurement, n_targets)
        assert sorted(solution.grid_indices.tolist()) == [0, 399]
        assert_allclose(solution.weights, 1.0, rtol=1e-6)


def _reference_omp(
    matrix: np.ndarray, noise: np.ndarray, values: np.ndarray, n_targets: int
) -> tuple[list[int], np.ndarray]:
    """Textbook OMP with the noise atom selected first (slow, from the definition)."""
    unit = noise / np.linalg.norm(noise)
    projector = np.eye(len(values)) - np.outer(unit, unit)
    projected = projector @ matrix
    projected /= np.linalg.norm(projected, axis=0)
    support: list[int] = []
    basis = unit[:, None]
    coef = np.linalg.lstsq(basis, values, rcond=None)[0]
    for _ in range(n_targets):
        residual = values - basis @ coef
        score = np.abs(projected.T @ residual)
        score[support] = -1
        support.append(int(np.argmax(score)))
        basis = np.column_stack((matrix[:, support], noise))
        norms = np.linalg.norm(basis, axis=0)  # column scaling for a well-posed lstsq
        coef = np.linalg.lstsq(basis / norms, values, rcond=None)[0] / norms
    return support, coef


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("seed", range(4))
def test_omp_matches_reference(
    solvers: dict[tuple[str, str], Solver],
    paper_room: Layout,
    paper_fingerprint: Fingerprint,
    model: Model,
    seed: int,
) -> None:
    gen = np.random.default_rng(seed)
    positions = gen.uniform(0.2, 3.8, size=(4, 2))
    amps = true_amplitudes(paper_room, positions)
    amps = amps + 0.02 * np.max(amps) * gen.standard_normal(amps.shape)
    measurement = measurement_from_amplitudes(amps, model, paper_room.n_leds)
    noise = noise_atom(model, paper_room.n_leds)
    floor = 0.05 * np.max(measurement.values)  # a clearly positive noise floor
    values = measurement.values + floor * noise
    matrix = (
        np.asarray(paper_fingerprint.power_matrix())
        if model == "power"
        else paper_fingerprint.correlation_matrix()
    )
    support, coef = _reference_omp(matrix, noise, values, 4)
    solution = solvers["omp", model].solve(Measurement(model, values, paper_room.n_leds), 4)
    assert coef[-1] > 0
    order = np.argsort(support)
    assert_array_equal(np.sort(solution.grid_indices), np.array(support)[order])
    mine = dict(zip(solution.grid_indices.tolist(), solution.weights.tolist(), strict=True))
    assert_allclose([mine[j] for j in np.array(support)[order]], coef[:-1][order], rtol=1e-8)
    assert solution.noise_power == pytest.approx(coef[-1], rel=1e-8)
    assert solution.n_iter == 4
    assert solution.residual_norm == pytest.approx(
        np.linalg.norm(values - np.column_stack((matrix[:, support], noise)) @ coef), rel=1e-8
    )


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("name", GRID_SOLVERS)
def test_noise_floor_is_fitted_not_reported(
    solvers: dict[tuple[str, str], Solver], paper_room: Layout, name: str, model: Model
) -> None:
    measurement = _measure(paper_room, [45, 310], model)
    if name == "omp":
        measurement = _measure(paper_room, [0, 399], model)
    floor = (0.1 if model == "correlation" else 0.01) * float(np.max(measurement.values))
    noisy = Measurement(model, measurement.values + floor * noise_atom(model, 16), 16)
    solution = solvers[name, model].solve(noisy, 2)
    assert solution.n_targets == 2
    assert solution.noise_power == pytest.approx(floor, rel=1e-5)
    assert_allclose(solution.weights, 1.0, rtol=1e-5)


@pytest.mark.parametrize("name", GRID_SOLVERS)
def test_bad_inputs(solvers: dict[tuple[str, str], Solver], paper_room: Layout, name: str) -> None:
    solver = solvers[name, "power"]
    measurement = _measure(paper_room, [45], "power")
    for bad in (0, -1, 65):
        with pytest.raises(SolverError, match="targets") as info:
            solver.solve(measurement, bad)
        assert info.value.field == "targets"
    with pytest.raises(MeasurementError) as wrong_model:
        solver.solve(_measure(paper_room, [45], "correlation"), 1)
    assert wrong_model.value.field == "model"
    short = Measurement("power", measurement.values[:15], 15)
    with pytest.raises(MeasurementError, match="15 LEDs"):
        solver.solve(short, 1)


def test_targets_limited_by_grid_size() -> None:
    tiny = Layout(Room(1.0, 1.0, 3.0), Grid(0.5, 0.85), (Led(0.5, 0.5, 3.0),))
    solver = make_solver("nnls", build_fingerprint(tiny), "power")
    with pytest.raises(SolverError, match="between 1 and 4"):
        solver.solve(measurement_from_amplitudes(np.ones((1, 1)), "power", 1), 5)


def test_estimate_target_count() -> None:
    assert estimate_target_count(np.array([0.98, 1.02, 0.4, 0.5, 0.0])) == 3
    assert estimate_target_count(np.array([0.2, -5.0, np.nan])) == 1
    assert estimate_target_count(np.full(100, 1.0)) == 64
    assert estimate_target_count(np.full(10, 1.0), max_targets=4) == 4


def test_l1_compiled_equals_fresh(
    solvers: dict[tuple[str, str], Solver], paper_room: Layout
) -> None:
    solver = solvers["l1", "correlation"]
    assert isinstance(solver, L1Solver)
    dictionary = solver.dictionary
    assert dictionary.normalised is not None
    values = _measure(paper_room, [45, 310, 122], "correlation").values
    target = values / np.linalg.norm(values)
    compiled, compiled_noise = solver.program.solve(target, 1e-3)
    fresh, fresh_noise = solve_l1_fresh(dictionary.normalised, dictionary.noise_unit, target, 1e-3)
    assert_allclose(compiled, fresh, atol=1e-6)
    assert compiled_noise == pytest.approx(fresh_noise, abs=1e-6)
    residual = dictionary.normalised @ compiled + compiled_noise * dictionary.noise_unit
    assert np.linalg.norm(residual - target) <= 1e-3 * (1 + 1e-6)


def test_l1_reports_infeasible_problems(solvers: dict[tuple[str, str], Solver]) -> None:
    solver = solvers["l1", "power"]
    assert isinstance(solver, L1Solver)
    dictionary = solver.dictionary
    assert dictionary.normalised is not None
    # nonnegative occupancies and noise can never produce a negative measurement
    with pytest.raises(SolverFailed, match="did not converge") as info:
        solve_l1_fresh(dictionary.normalised, dictionary.noise_unit, -dictionary.noise_unit, 0.0)
    assert info.value.field == "solver"


def _as_large(fingerprint: Fingerprint, monkeypatch: pytest.MonkeyPatch) -> Fingerprint:
    """A copy of a fingerprint that takes the large-room (non-dense) code paths."""
    monkeypatch.setattr(fingerprints, "DENSE_GAINS_LIMIT", 0)
    return Fingerprint(layout=fingerprint.layout, gains=fingerprint.gains)


def test_l1_refuses_large_rooms(
    paper_fingerprint: Fingerprint, monkeypatch: pytest.MonkeyPatch
) -> None:
    with pytest.raises(SolverError, match="dense") as info:
        make_solver("l1", _as_large(paper_fingerprint, monkeypatch), "power")
    assert info.value.field == "solver"


@pytest.mark.parametrize("model", MODELS)
def test_large_room_dictionary_matches_dense(
    paper_fingerprint: Fingerprint,
    model: Model,
    monkeypatch: pytest.MonkeyPatch,
    rng: np.random.Generator,
) -> None:
    dense = GridDictionary(paper_fingerprint, model)
    large = GridDictionary(_as_large(paper_fingerprint, monkeypatch), model)
    assert dense.is_materialised and not large.is_materialised
    assert_allclose(large.column_norms, dense.column_norms, rtol=1e-12)
    assert_allclose(large.noise_free_norms, dense.noise_free_norms, rtol=1e-10)
    residual = rng.standard_normal(dense.n_rows)  # full rank: every eigenvalue counts
    assert_allclose(large.correlate(residual), dense.correlate(residual), rtol=1e-9, atol=1e-12)
    cells = np.array([3, 77, 210])
    coefficients = rng.random(4)
    assert_allclose(
        large.predict(cells, coefficients), dense.predict(cells, coefficients), atol=1e-14
    )
    empty = np.array([], dtype=np.intp)
    assert_allclose(large.predict(empty, np.array([2.0])), 2.0 * large.noise_unit)
    block, rows, rest = large.restrict(cells, residual)
    dense_block, _, _ = dense.restrict(cells, residual)
    # the same least-squares problem: equal normal equations and right-hand sides
    assert_allclose(block.T @ block, dense_block.T @ dense_block, atol=1e-12)
    assert_allclose(block.T @ rows, dense_block.T @ residual, atol=1e-12)
    assert rest == pytest.approx(residual @ residual - rows @ rows)


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("name", ["omp", "nnls"])
def test_large_room_paths_give_dense_answers(
    paper_fingerprint: Fingerprint,
    paper_room: Layout,
    name: str,
    model: Model,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    dense_solver = make_solver(name, paper_fingerprint, model)
    large_solver = make_solver(name, _as_large(paper_fingerprint, monkeypatch), model)
    gen = np.random.default_rng(7)
    amps = true_amplitudes(paper_room, paper_room.cell_centres(np.array([45, 310, 122])))
    amps = amps + 0.01 * np.max(amps) * gen.standard_normal(amps.shape)
    measurement = measurement_from_amplitudes(amps, model, 16)
    for n_targets in (3, None):
        want = dense_solver.solve(measurement, n_targets)
        got = large_solver.solve(measurement, n_targets)
        assert_array_equal(got.grid_indices, want.grid_indices)
        assert_allclose(got.weights, want.weights, rtol=1e-8)
        assert got.noise_power == pytest.approx(want.noise_power, rel=1e-6, abs=1e-20)
        assert got.residual_norm == pytest.approx(want.residual_norm, rel=1e-8)


_HALL_SCRIPT = textwrap.dedent("""
    import json, resource, time
    import numpy as np
    from app.vlp.fingerprints import build_fingerprint
    from app.vlp.layout import Grid, Layout, Led, Receiver, Room
    from app.vlp.measurements import measurement_from_amplitudes
    from app.vlp.simulation import true_amplitudes
    from app.vlp.solvers import make_solver
    from app.vlp.metrics import mean_position_error

    start = time.perf_counter()
    spacing = 100 / 32
    leds = tuple(Led(x=spacing * (ix + 0.5), y=spacing * (iy + 0.5), z=6.0)
                 for ix in range(32) for iy in range(32))
    layout = Layout(Room(100.0, 100.0, 6.0), Grid(0.1, 0.85), leds, Receiver(fov_deg=60.0))
    fingerprint = build_fingerprint(layout)
    out = {"n_cells": fingerprint.n_cells, "n_leds": fingerprint.n_leds,
           "dense": fingerprint.is_dense, "build_s": time.perf_counter() - start}
    truth = np.array([[23.43, 61.27], [71.05, 30.38]])
    amps = true_amplitudes(layout, truth)
    for model, name in (("power", "nnls"), ("power", "omp"), ("correlation", "omp")):
        measurement = measurement_from_amplitudes(amps, model, layout.n_leds)
        solution = make_solver(name, fingerprint, model).solve(measurement, 2)
        out[model + "-" + name] = mean_position_error(solution.positions, truth)
    out["total_s"] = time.perf_counter() - start
    out["maxrss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps(out))
""")


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_large_hall_in_a_subprocess() -> None:
    """100 m x 100 m at 0.1 m (N = 10^6), 1024 LEDs: bounded memory, targets found.

    The run's time is reported (``build_s``, ``total_s``) but not asserted: the timeout is a
    safety bound. Build time and memory of this hall: ``python -m bench.hall_build``."""
    root = Path(__file__).resolve().parents[2]
    result = subprocess.run(
        [sys.executable, "-W", "error", "-c", _HALL_SCRIPT],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=380,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["n_cells"] == 1_000_000 and report["n_leds"] == 1024
    assert not report["dense"]
    assert report["maxrss_bytes"] < 2 * 1024**3, report
    for key in ("power-nnls", "power-omp", "correlation-omp"):
        assert report[key] < 0.3, report


def test_l1_is_safe_to_share_between_threads(
    solvers: dict[tuple[str, str], Solver], paper_room: Layout
) -> None:
    supports = [[45, 310], [21, 378], [0, 399], [42, 357]]
    measurements = [_measure(paper_room, cells, "power") for cells in supports]
    solver = solvers["l1", "power"]
    with ThreadPoolExecutor(max_workers=4) as pool:
        found = list(pool.map(lambda m: solver.solve(m, 2), measurements))
    for cells, solution in zip(supports, found, strict=True):
        assert sorted(solution.grid_indices.tolist()) == sorted(cells)
