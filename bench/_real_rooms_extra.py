"""Two more modes of ``bench.real_rooms``: bounds with nuisances, and survey calibration.

- :func:`run_bounds`: for the placements of the main benchmark, the hybrid Cramer-Rao bound
  (:func:`app.vlp.crlb.nuisance_crlb`) of each condition's nuisances, aggregated correlation
  and per terminal, K = 1 / 4 / 8.
- :func:`run_calibrated`: the realistic mix with the reflectance in the layout, K = 8, located
  with the layout as given (uncalibrated) and after a survey calibration of the TRUE room
  (its perturbed LEDs and reflections, surveyed on a 0.5 m grid at the terminals' noise).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from app.vlp.calibration import calibrate, calibrated_layout, simulate_survey
from app.vlp.crlb import Nuisances, nuisance_crlb
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Layout, Reflectance
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.metrics import mean_position_error
from app.vlp.simulation import (
    TRUE_ELEMENT_SIZE_M,
    Impairments,
    SimulatedTerminals,
    random_positions,
    simulate_terminals,
)
from app.vlp.solvers import make_solver
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver
from app.vlp.typing import FloatArray

__all__ = [
    "BOUND_CASES",
    "CALIBRATIONS",
    "BoundCase",
    "draw_terminals",
    "run_bounds",
    "run_calibrated",
]

_BOUND_MODES: tuple[Literal["correlation", "terminals"], ...] = ("correlation", "terminals")
# The solver's priors (GridlessOptions defaults): what a service that does not know the
# terminals' gains or the measurement's scale has to assume.
_OPTIONS = GridlessOptions()
SOLVER_PRIORS = Nuisances(log_gain_sd=_OPTIONS.log_gain_sd, log_scale_sd=_OPTIONS.log_scale_sd)


def tilt_sd(max_deg: float) -> float:
    """sd of each tangent component of a normal whose polar angle is uniform in
    [0, max_deg] and azimuth uniform: ``sqrt(E[tan^2 theta] / 2)``."""
    theta = np.linspace(0.0, math.radians(max_deg), 2001)
    return float(math.sqrt(np.mean(np.tan(theta) ** 2) / 2.0))


@dataclass(frozen=True)
class BoundCase:
    """One row of the bound table: the room's channel (reflectance in the layout) and the
    nuisances, and the achieved row of the main table it is compared with."""

    name: str
    achieved: str
    reflectance: Reflectance | None
    nuisances: Nuisances


WALLS = Reflectance(walls=0.7, floor=0.0, ceiling=0.0)
MIX = Impairments.realistic_mix()
# Only what the condition really draws is a nuisance (the Bayesian bound averages over the
# prior, so it holds for draws from it, not for a truth that sits at the prior's mean).
_MIX_NUISANCES = Nuisances(
    height_sd_m=MIX.height_sd_m,
    tilt_sd=tilt_sd(MIX.tilt_max_deg),
    led_log_amplitude_sd=MIX.led_amplitude_sd,
    led_half_power_sd_deg=MIX.led_half_power_sd_deg,
)

BOUND_CASES: tuple[BoundCase, ...] = (
    BoundCase("ideal (model known)", "ideal", None, Nuisances()),
    BoundCase(
        "reflections 0.7 in layout (model known)", "reflections 0.7, in layout", WALLS, Nuisances()
    ),
    BoundCase(
        "gain sd 10 %: gains (prior sd 0.1) and scale (prior sd 0.5)",
        "gain sd 10 %",
        None,
        SOLVER_PRIORS,
    ),
    BoundCase(
        "heights sd 15 cm (in layout): heights",
        "heights sd 15 cm, sd in layout",
        None,
        Nuisances(height_sd_m=0.15),
    ),
    BoundCase(
        "mix, reflectance in layout: heights, tilts, LED amplitudes and beams",
        "realistic mix, reflectance in layout",
        MIX.reflectance,
        _MIX_NUISANCES,
    ),
    BoundCase(
        "mix with the LEDs known (a perfect calibration): heights, tilts",
        "realistic mix, reflectance in layout",
        MIX.reflectance,
        dataclasses.replace(_MIX_NUISANCES, led_log_amplitude_sd=0.0, led_half_power_sd_deg=0.0),
    ),
)


def _with_reflectance(layout: Layout, reflectance: Reflectance | None) -> Layout:
    room = dataclasses.replace(layout.room, reflectance=reflectance)
    return dataclasses.replace(layout, room=room)


def run_bounds(
    rooms: Sequence[str],
    trials: int,
    ks: Sequence[int],
    placements: Callable[[str, int, int], FloatArray],
    noise_std: Callable[[str], float],
) -> list[tuple[str, str, int, int, str, float]]:
    """Every (room, case, K, trial, mode) bound in metres (RMS, ``sqrt(var_x + var_y)``
    averaged over the K targets). ``placements(room, K, trial)`` gives the positions of the
    main benchmark, ``noise_std(room)`` its noise."""
    from .rooms import make_room

    rows: list[tuple[str, str, int, int, str, float]] = []
    for room in rooms:
        base = make_room(room)
        sigma = noise_std(room)
        for case in BOUND_CASES:
            layout = _with_reflectance(base, case.reflectance)
            for count in ks:
                for trial in range(trials):
                    pts = placements(room, count, trial)
                    for mode in _BOUND_MODES:
                        bound = nuisance_crlb(layout, pts, sigma, mode, case.nuisances)
                        rows.append((room, case.name, count, trial, mode, bound.mean))
    return rows


@dataclass(frozen=True)
class Calibration:
    """How the service's model is calibrated before it locates the terminals."""

    name: str
    survey: bool
    fit_reflectance: bool = False
    led_position_bound_m: float = 0.3
    # The calibrated layout also says how much the receivers' heights spread (the
    # condition's own sd, as an admin who knows how the phones are held would set it).
    height_sd_in_layout: bool = False
    # ... and how much their photodiodes tilt (grid.receiver_tilt_sd, the condition's own).
    tilt_sd_in_layout: bool = False


CALIBRATIONS: tuple[Calibration, ...] = (
    Calibration("uncalibrated (layout as given)", survey=False),
    Calibration("survey, LED x/y fixed", survey=True, led_position_bound_m=0.0),
    Calibration("survey (default: LED x/y within 0.3 m)", survey=True),
    Calibration("survey, reflectance fitted too", survey=True, fit_reflectance=True),
    Calibration("survey (default), receivers' height sd in layout", True, height_sd_in_layout=True),
    Calibration(
        "survey (default), receivers' height and tilt sd in layout",
        True,
        height_sd_in_layout=True,
        tilt_sd_in_layout=True,
    ),
)
SURVEY_STEP_M = 0.5


def _survey_points(layout: Layout) -> FloatArray:
    xs = np.arange(SURVEY_STEP_M / 2, layout.room.length, SURVEY_STEP_M)
    ys = np.arange(SURVEY_STEP_M / 2, layout.room.width, SURVEY_STEP_M)
    return np.array([(x, y) for x in xs for y in ys])


def draw_terminals(
    layout: Layout,
    count: int,
    impairments: Impairments,
    *,
    snr_db: float,
    placement_rng: np.random.Generator,
    noise_rng: np.random.Generator,
) -> tuple[FloatArray, SimulatedTerminals]:
    """``count`` terminals placed uniformly in ``layout``'s room (no two in one grid cell)
    with ``placement_rng``, and what they measure under ``impairments`` at ``snr_db`` with
    ``noise_rng``: positions (K, 2) m and the simulation. Placements depend on the room's
    geometry only, so benchmarks key them apart from the condition to pair their rows."""
    positions = random_positions(layout, count, rng=placement_rng)
    simulated = simulate_terminals(layout, positions, impairments, snr_db=snr_db, rng=noise_rng)
    return positions, simulated


def run_calibrated(
    rooms: Sequence[str],
    trials: int,
    impairments: Impairments,
    condition_name: str,
    generator: Callable[..., np.random.Generator],
    count: int = 8,
    first_trial: int = 0,
) -> list[tuple[str, str, int, int, str, float]]:
    """Every (room, calibration, K, trial, mode) error in metres. The terminals, their
    amplitudes and the true room are those of the main benchmark's ``condition_name`` row
    (same generators), so "uncalibrated" reproduces that row."""
    from .rooms import make_room

    rows: list[tuple[str, str, int, int, str, float]] = []
    for room in rooms:
        nominal = make_room(room)
        layout = _with_reflectance(nominal, impairments.reflectance)
        plain = build_fingerprint(layout)
        points = _survey_points(layout)
        for trial in range(first_trial, first_trial + trials):
            positions, simulated = draw_terminals(
                layout,
                count,
                impairments,
                snr_db=30.0,
                placement_rng=generator(room, count, trial),
                noise_rng=generator(room, condition_name, count, trial),
            )
            survey = simulate_survey(
                simulated.true_layout,
                points,
                simulated.noise_std,
                rng=generator(room, "survey", trial),
                element_size_m=TRUE_ELEMENT_SIZE_M,
            )
            calibrated: dict[tuple[float, bool], Layout] = {}
            for calibration in CALIBRATIONS:
                if calibration.survey:
                    key = (calibration.led_position_bound_m, calibration.fit_reflectance)
                    if key not in calibrated:  # one calibration per survey and settings
                        result = calibrate(
                            layout,
                            survey,
                            led_position_bound_m=key[0],
                            fit_reflectance=key[1],
                        )
                        calibrated[key] = calibrated_layout(layout, result)
                    fitted = calibrated[key]
                    grid = fitted.grid
                    if calibration.height_sd_in_layout:
                        grid = dataclasses.replace(grid, receiver_height_sd=impairments.height_sd_m)
                    if calibration.tilt_sd_in_layout:
                        tilt_sd = impairments.tilt_component_sd_deg
                        grid = dataclasses.replace(grid, receiver_tilt_sd=tilt_sd)
                    fitted = dataclasses.replace(fitted, grid=grid)
                    fingerprint = build_fingerprint(fitted)
                else:
                    fingerprint = plain
                solver = make_solver("gridless", fingerprint, "correlation")
                assert isinstance(solver, GridlessSolver)
                measurement = measurement_from_amplitudes(
                    simulated.amplitudes, "correlation", layout.n_leds
                )
                for mode in ("correlation", "terminals"):
                    try:
                        if mode == "correlation":
                            found = solver.solve(measurement, count).positions
                        else:
                            found = solver.solve_terminals(simulated.amplitudes).positions
                        error = mean_position_error(found, positions)
                    except Exception:  # a failing solve is counted, not fatal
                        error = float("nan")
                    rows.append((room, calibration.name, count, trial, mode, error))
    return rows
