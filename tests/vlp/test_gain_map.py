"""The survey's gain map: its interpolant, its held-out rows, its evidence, and where it lives
in the room's model (layout mapping, fingerprint, off-grid table, calibration)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from app.vlp import gain_map as gm
from app.vlp.calibration import CalibrationResult, calibrate, calibrated_layout, masked_layout
from app.vlp.channel import channel_gains
from app.vlp.errors import GeometryError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.gain_map import GainMap, fit_gain_map
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.presets import paper_layout
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.survey import Survey, simulate_survey


def _field(points: np.ndarray, led: int) -> np.ndarray:
    """A smooth log gain factor over a 4 x 4 m floor, different for each LED."""
    x, y = points[:, 0], points[:, 1]
    return 0.15 * np.sin(1.3 * x + led) * np.cos(0.9 * y - 0.5 * led)


def _rows(step: float, n_leds: int, noise_sd: float, seed: int) -> tuple[np.ndarray, ...]:
    ticks = np.arange(step / 2, 4.0, step)
    points = np.array([(x, y) for x in ticks for y in ticks])
    rng = np.random.default_rng(seed)
    row_points = np.repeat(points, n_leds, axis=0)
    leds = np.tile(np.arange(n_leds), len(points))
    truth = np.array([_field(p[None], j)[0] for p, j in zip(row_points, leds, strict=True)])
    return row_points, leds, truth + noise_sd * rng.standard_normal(truth.size)


def test_a_smooth_field_is_mapped_and_predicted_between_the_points() -> None:
    points, leds, residuals = _rows(0.5, 3, 0.01, seed=1)
    fit = fit_gain_map(points, leds, residuals, 3)
    assert fit.gain_map is not None and fit.evidence > gm.MIN_EVIDENCE
    between = np.random.default_rng(2).uniform(0.5, 3.5, size=(200, 2))
    predicted = fit.gain_map.log_factors(between)
    truth = np.stack([_field(between, j) for j in range(3)])
    # The field's own spread is 0.15; between the points the map is within a few percent.
    assert np.sqrt(np.mean((predicted - truth) ** 2)) < 0.02
    assert np.sqrt(np.mean(truth**2)) > 0.05


def test_independent_residuals_show_no_map() -> None:
    rng = np.random.default_rng(3)
    points, leds, _ = _rows(0.5, 3, 0.0, seed=0)
    fit = fit_gain_map(points, leds, 0.1 * rng.standard_normal(leds.size), 3)
    assert fit.gain_map is None
    assert fit.evidence < gm.MIN_EVIDENCE
    assert np.all(fit.held_out == 0.0)


def test_held_out_rows_are_predicted_as_refits_without_them() -> None:
    points, leds, residuals = _rows(0.8, 2, 0.02, seed=4)
    residuals[5] = np.nan  # an unused row: predicted by the map, never fitted to
    fit = fit_gain_map(points, leds, residuals, 2)
    assert fit.gain_map is not None
    scale = fit.gain_map.length_scale_m
    for row in (0, 1, 7, 12):
        led = leds[row]
        others = np.flatnonzero(
            (leds == led) & np.isfinite(residuals) & (np.arange(leds.size) != row)
        )
        refit = np.linalg.solve(
            _kernel(points[others], points[others], scale) + fit.noise_ratio * np.eye(others.size),
            residuals[others],
        )
        expected = _kernel(points[row][None], points[others], scale) @ refit
        assert fit.held_out[row] == pytest.approx(float(expected[0]), abs=1e-9)
    assert fit.held_out[5] == pytest.approx(
        float(fit.gain_map.log_factors(points[5][None])[leds[5], 0]), abs=1e-12
    )


def test_the_evidence_is_the_gaussian_likelihood_ratio() -> None:
    points, leds, residuals = _rows(0.8, 1, 0.02, seed=5)
    y = residuals
    best = -np.inf
    for scale in gm.LENGTH_SCALES_M:
        kernel = _kernel(points, points, scale)
        for ratio in gm.NOISE_RATIOS:
            shape = kernel + ratio * np.eye(y.size)
            signal = float(y @ np.linalg.solve(shape, y)) / y.size
            best = max(best, stats.multivariate_normal(cov=signal * shape).logpdf(y))
    null = float(np.sum(stats.norm(scale=np.sqrt(np.mean(y**2))).logpdf(y)))
    assert fit_gain_map(points, leds, y, 1).evidence == pytest.approx(best - null, rel=1e-9)


def test_a_layout_carries_its_map_and_drops_masked_leds_from_it() -> None:
    layout = paper_layout()
    weights = np.arange(2 * layout.n_leds, dtype=float).reshape(2, layout.n_leds) / 100
    mapped = replace(layout, gain_map=GainMap(((1.0, 1.0), (3.0, 2.0)), _tuples(weights), 0.7))
    assert layout_from_mapping(mapped.to_mapping()) == mapped
    masked = masked_layout(mapped, [0, 5])
    assert masked.gain_map is not None
    assert np.array_equal(np.asarray(masked.gain_map.weights), np.delete(weights, [0, 5], axis=1))
    with pytest.raises(GeometryError) as error:
        replace(layout, gain_map=GainMap(((1.0, 1.0),), ((0.1, 0.2),), 0.7))
    assert error.value.field == "gain_map.weights"


def test_the_fingerprint_and_the_off_grid_table_follow_the_map() -> None:
    layout = paper_layout()
    rng = np.random.default_rng(6)
    nodes = rng.uniform(0.5, 3.5, size=(6, 2))
    weights = 0.2 * rng.standard_normal((6, layout.n_leds))
    pairs = tuple((float(x), float(y)) for x, y in nodes)
    mapped = replace(layout, gain_map=GainMap(pairs, _tuples(weights), 0.8))
    centres = layout.cell_centres(np.arange(layout.n_cells))
    expected = channel_gains(layout, centres) * np.exp(_direct_map(nodes, weights, 0.8, centres))
    fingerprint = build_fingerprint(mapped)
    assert np.allclose(fingerprint.gains.toarray(), expected, rtol=1e-12, atol=0.0)
    table = fingerprint.reflection_table()
    assert table is not None
    off_grid = rng.uniform(0.3, 3.7, size=(50, 2))
    total = channel_gains(layout, off_grid) + table.evaluate(off_grid[:, 0], off_grid[:, 1])[0]
    truth = channel_gains(layout, off_grid) * np.exp(_direct_map(nodes, weights, 0.8, off_grid))
    # The table interpolates on 0.2 m nodes: within a small part of the map's own change.
    change = np.abs(truth - channel_gains(layout, off_grid))
    assert np.max(np.abs(total - truth)) < 0.02 * np.max(change)
    assert build_fingerprint(layout).reflection_table() is None


def test_calibration_maps_what_its_model_cannot_fit() -> None:
    layout = paper_layout()
    ticks = np.arange(0.25, 4.0, 0.5)
    points = np.array([(x, y) for x in ticks for y in ticks])
    clean = simulate_survey(layout, points, 1e-9, rng=0)
    field = np.array(
        [_field(p[None], int(j))[0] for p, j in zip(clean.points, clean.led_indices, strict=True)]
    )
    survey = Survey(clean.points, clean.led_indices, clean.amplitudes * np.exp(field))
    plain = calibrate(layout, survey)
    mapped = calibrate(layout, survey, fit_gain_map=True)
    assert plain.gain_map is None and mapped.gain_map is not None
    between = np.random.default_rng(7).uniform(0.5, 3.5, size=(100, 2))
    truth = channel_gains(layout, between) * np.exp(
        np.stack([_field(between, j) for j in range(layout.n_leds)])
    )

    true_amplitudes = truth * layout.pilot_amplitudes[:, None]

    def model_error(result: CalibrationResult) -> float:
        """Median |log| of the calibrated model's amplitudes over the true ones."""
        fitted = build_fingerprint(calibrated_layout(layout, result))
        gains = channel_gains(fitted.layout, between)
        table = fitted.reflection_table()
        if table is not None:
            gains = gains + table.evaluate(between[:, 0], between[:, 1])[0]
        amplitudes = gains * fitted.layout.pilot_amplitudes[:, None]
        return float(np.median(np.abs(np.log(amplitudes / true_amplitudes))))

    assert model_error(mapped) < 0.5 * model_error(plain)


def _kernel(a: np.ndarray, b: np.ndarray, scale: float) -> np.ndarray:
    distance = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    return np.asarray(np.exp(-0.5 * (distance / scale) ** 2))


def _direct_map(nodes: np.ndarray, weights: np.ndarray, scale: float, at: np.ndarray) -> np.ndarray:
    out = np.zeros((weights.shape[1], at.shape[0]))
    for k in range(nodes.shape[0]):
        bump = np.exp(-np.sum((at - nodes[k]) ** 2, axis=1) / (2 * scale**2))
        out += weights[k][:, None] * bump[None, :]
    return out


def _tuples(array: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in array)


def test_a_dense_survey_maps_each_led_on_a_bounded_share_of_its_rows() -> None:
    points, leds, residuals = _rows(0.125, 2, 0.01, seed=8)  # 1,024 points per LED
    fit = fit_gain_map(points, leds, residuals, 2)
    assert fit.gain_map is not None
    weights = np.asarray(fit.gain_map.weights)
    assert np.all(np.count_nonzero(weights, axis=0) <= gm.MAX_ROWS_PER_LED)
    # The rows left out are predicted by the map, as well as the fitted rows are held out.
    truth = np.array([_field(p[None], j)[0] for p, j in zip(points, leds, strict=True)])
    assert np.sqrt(np.mean((fit.held_out - truth) ** 2)) < 0.02


def test_terminals_are_found_on_the_mapped_model() -> None:
    """Amplitudes of a room whose LEDs are off their model by a mapped factor: the solver on
    the mapped layout finds the terminals where the same layout without its map misses."""
    layout = replace(paper_layout(), grid=replace(paper_layout().grid, receivers_level=True))
    rng = np.random.default_rng(9)
    nodes = rng.uniform(0.5, 3.5, size=(12, 2))
    weights = 0.25 * rng.standard_normal((12, layout.n_leds))
    pairs = tuple((float(x), float(y)) for x, y in nodes)
    mapped = replace(layout, gain_map=GainMap(pairs, _tuples(weights), 0.8))
    truth = rng.uniform(0.4, 3.6, size=(6, 2))
    gains = channel_gains(layout, truth) * np.exp(_direct_map(nodes, weights, 0.8, truth))
    amplitudes = (gains * layout.pilot_amplitudes[:, None]).T
    errors = {}
    for name, lay in (("mapped", mapped), ("unmapped", layout)):
        solver = GridlessSolver(build_fingerprint(lay), "correlation")
        found = solver.solve_terminals(amplitudes).positions
        errors[name] = float(np.max(np.linalg.norm(found - truth, axis=1)))
    assert errors["mapped"] < 0.01 < errors["unmapped"], errors


def test_residuals_of_an_exact_model_map_nothing() -> None:
    points, leds, _ = _rows(0.5, 2, 0.0, seed=0)
    fit = fit_gain_map(points, leds, np.zeros(leds.size), 2)
    assert fit.gain_map is None and np.all(fit.held_out == 0.0)
