"""A survey's heavy-tailed scatter: measured as a Student-t by the calibration, and the
likelihood terminals in that room are then fitted with."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from app.vlp import uncertainty
from app.vlp._calibration_scatter import survey_scatter
from app.vlp.errors import GeometryError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import AmplitudeError, Layout
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers.gridless import GridlessSolver, terminal_solve
from app.vlp.solvers.gridless.terminal_weights import weighted_square_variance
from app.vlp.survey import Survey
from app.vlp.uncertainty import Misfit


def _survey(amplitudes: np.ndarray) -> Survey:
    count = amplitudes.size
    points = np.column_stack((np.linspace(0.5, 3.5, count), np.full(count, 2.0)))
    return Survey(points, np.zeros(count, dtype=np.int64), amplitudes)


def _level_room(room: Layout, tail_dof: float | None) -> Layout:
    """``room`` surveyed with level receivers: a 1 % relative scatter on many degrees of
    freedom, Gaussian (None) or Student-t."""
    scatter = AmplitudeError(noise_sd=0.0, relative_sd=0.01, dof=500.0, tail_dof=tail_dof)
    return replace(room, grid=replace(room.grid, receivers_level=True), amplitude_error=scatter)


def test_heavy_tailed_errors_are_measured_as_the_student_t_scipy_fits() -> None:
    # One model value everywhere: the scale sqrt(s^2 + (b f)^2) is one number, and the fit is
    # then the maximum-likelihood t of scipy's own fitter (location held at 0).
    rng = np.random.default_rng(4)
    model = np.full(3000, 200.0)
    errors = 6.0 * stats.t.rvs(3.0, size=model.size, random_state=rng)
    scatter = survey_scatter(_survey(model + errors), model, n_params=0)
    assert scatter is not None and scatter.tail_dof is not None
    df, _, scale = stats.t.fit(errors, floc=0.0)
    assert scatter.tail_dof == pytest.approx(df, rel=0.02)
    fitted_scale = math.hypot(scatter.noise_sd, scatter.relative_sd * 200.0)
    assert fitted_scale == pytest.approx(scale, rel=0.01)


def test_gaussian_errors_stay_a_gaussian_scatter() -> None:
    # Noise of sd 3 plus 5 % of the signal: no tails to fit, both sds found.
    rng = np.random.default_rng(9)
    model = rng.uniform(20.0, 400.0, 4000)
    sd = np.hypot(3.0, 0.05 * model)
    scatter = survey_scatter(_survey(model + sd * rng.standard_normal(model.size)), model, 0)
    assert scatter is not None
    assert scatter.tail_dof is None
    assert scatter.noise_sd == pytest.approx(3.0, rel=0.15)
    assert scatter.relative_sd == pytest.approx(0.05, rel=0.1)


@pytest.mark.parametrize("nu", [2.5, 4.0, 10.0])
def test_a_t_weighted_square_has_mean_one_and_the_stated_variance(nu: float) -> None:
    # Integrated over scipy's t density, not the closed form.
    weighted = stats.t(nu)
    mean = weighted.expect(lambda u: (nu + 1.0) * u * u / (nu + u * u))
    second = weighted.expect(lambda u: ((nu + 1.0) * u * u / (nu + u * u)) ** 2)
    assert mean == pytest.approx(1.0, rel=1e-6)
    assert second - mean**2 == pytest.approx(weighted_square_variance(nu), rel=1e-6)
    assert weighted_square_variance(None) == 2.0


def test_a_heavy_tailed_scatter_weighs_an_outlying_amplitude_down(paper_room: Layout) -> None:
    # A level terminal whose amplitudes carry the room's small scatter, and one LED 40 % off
    # (an edge of its beam the model misses): fitted with the survey's t-distribution, that
    # amplitude's weight falls and the position is nearer the truth than with a Gaussian of
    # the same scale, which spreads the outlier over the position.
    truth = np.array([[1.6, 2.3]])
    clean = true_amplitudes(paper_room, truth)
    amplitudes = clean * (1.0 + 0.01 * np.random.default_rng(2).standard_normal(clean.shape))
    strongest = int(np.argmax(clean[0]))
    amplitudes[0, strongest] *= 1.4
    height = np.array([paper_room.grid.receiver_height])
    errors = {}
    for tail_dof in (None, 2.5):
        layout = _level_room(paper_room, tail_dof)
        solver = GridlessSolver(build_fingerprint(layout), "correlation")
        found = solver.solve_terminals(amplitudes, heights=height).positions
        errors[tail_dof] = float(np.linalg.norm(found - truth))
    assert errors[2.5] < 0.5 * errors[None]


def test_the_tails_travel_with_the_layout_and_are_checked(paper_room: Layout) -> None:
    scatter = AmplitudeError(noise_sd=1.0, relative_sd=0.1, dof=40.0, tail_dof=3.0)
    layout = replace(paper_room, amplitude_error=scatter)
    assert layout_from_mapping(layout.to_mapping()).amplitude_error == scatter
    mapping = layout.to_mapping()
    mapping["amplitude_error"]["tail_dof"] = -1.0
    with pytest.raises(GeometryError) as caught:
        layout_from_mapping(mapping)
    assert caught.value.field == "amplitude_error.tail_dof"


def test_with_a_t_scatter_the_requests_own_model_errors_are_not_widened_for_their_dof(
    paper_room: Layout, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A terminal that does not send its height: that height's error is estimated from its
    # residuals. With a Gaussian scatter its few degrees of freedom widen the radius (F);
    # with a t the squares are not Gaussian and it enters at its estimate.
    used: list[Misfit] = []
    covariances_of = uncertainty.predictive_covariances

    def covariances(design, misfit, blocks, level=0.95):  # type: ignore[no-untyped-def]
        used.append(misfit)
        return covariances_of(design, misfit, blocks, level)

    monkeypatch.setattr(terminal_solve, "predictive_covariances", covariances)
    clean = true_amplitudes(paper_room, np.array([[1.6, 2.3]]))
    amplitudes = clean * (1.0 + 0.01 * np.random.default_rng(6).standard_normal(clean.shape))
    dofs = {}
    for tail_dof in (None, 3.0):
        layout = _level_room(paper_room, tail_dof)
        used.clear()
        GridlessSolver(build_fingerprint(layout), "correlation").solve_terminals(amplitudes)
        dofs[tail_dof] = used[-1].dofs
    assert dofs[None].size > 1 and np.all(np.isfinite(dofs[None][1:]))
    assert np.all(np.isinf(dofs[3.0][1:]))
    assert dofs[3.0][0] == dofs[None][0] == 500.0
