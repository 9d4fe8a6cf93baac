"""The bound with nuisance parameters against independent computations.

- no nuisances: equal to :func:`aggregated_crlb` and, per terminal, :func:`single_target_crlb`;
- a Fisher information built here by central differences of an explicit mean (perturbed
  layouts through :func:`los_gains` / :func:`diffuse_gains`, not the bound's derivatives);
- a closed form for one terminal with an unknown gain (Schur complement).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.vlp.channel import los_gains
from app.vlp.crlb import (
    Nuisances,
    aggregated_correlation_covariance,
    aggregated_crlb,
    nuisance_crlb,
    single_target_crlb,
)
from app.vlp.errors import MeasurementError
from app.vlp.layout import Layout, Reflectance
from app.vlp.measurements import vech
from app.vlp.presets import paper_layout
from app.vlp.reflections import diffuse_gains
from app.vlp.typing import FloatArray

SIGMA = 2e-7
POINTS = np.array([[1.0, 1.0], [3.1, 2.5], [2.2, 0.7]])


@pytest.fixture(scope="module")
def room() -> Layout:
    return paper_layout()


@pytest.mark.parametrize("model", ["correlation", "power"])
def test_without_nuisances_equals_the_aggregated_bound(room: Layout, model: str) -> None:
    plain = aggregated_crlb(room, POINTS, SIGMA, model)  # type: ignore[arg-type]
    mine = nuisance_crlb(room, POINTS, SIGMA, model)  # type: ignore[arg-type]
    np.testing.assert_allclose(mine.per_target, plain.per_target, rtol=1e-9)
    np.testing.assert_allclose(mine.covariance, plain.covariance, rtol=1e-7, atol=1e-20)


def test_terminals_without_nuisances_are_single_target_bounds(room: Layout) -> None:
    mine = nuisance_crlb(room, POINTS, SIGMA, "terminals")
    expected = [single_target_crlb(room, p, SIGMA) for p in POINTS]
    np.testing.assert_allclose(mine.per_target, expected, rtol=1e-9)


def test_one_terminal_with_an_unknown_gain_matches_the_closed_form(room: Layout) -> None:
    """a = e^u g(p) + n, prior u ~ N(0, s^2): the position block of the inverse is the
    inverse of ``G^T G / sigma^2 - G^T g g^T G / (sigma^2 (g^T g + sigma^2 / s^2))``."""
    point = np.array([1.3, 2.9])
    gain_sd = 0.1
    xyz = np.array([[*point, room.grid.receiver_height]])
    step = 1e-6
    pilots = room.pilot_amplitudes
    g = los_gains(room, xyz)[:, 0] * pilots
    grad = np.column_stack(
        [
            (
                los_gains(room, xyz + step * np.eye(3)[axis])[:, 0]
                - los_gains(room, xyz - step * np.eye(3)[axis])[:, 0]
            )
            * pilots
            / (2 * step)
            for axis in range(2)
        ]
    )
    info = grad.T @ grad / SIGMA**2
    info -= np.outer(grad.T @ g, g @ grad) / (SIGMA**2 * (g @ g + SIGMA**2 / gain_sd**2))
    expected = float(np.sqrt(np.trace(np.linalg.inv(info))))
    bound = nuisance_crlb(
        room, point[None, :], SIGMA, "terminals", Nuisances(log_gain_sd=gain_sd)
    ).mean
    assert bound == pytest.approx(expected, rel=1e-6)
    # A tight prior gives back the known-gain bound, a loose one costs more.
    tight = nuisance_crlb(room, point[None, :], SIGMA, "terminals", Nuisances(log_gain_sd=1e-6))
    assert tight.mean == pytest.approx(single_target_crlb(room, point, SIGMA), rel=1e-6)
    loose = nuisance_crlb(room, point[None, :], SIGMA, "terminals", Nuisances(log_gain_sd=10.0))
    assert loose.mean > bound > tight.mean


def _mean_and_jacobian(
    room: Layout, nuisances: Nuisances, model: str
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Mean of the measurement at the truth, its Jacobian by central differences of an
    explicit parametrisation, the prior information and the signal matrix S."""
    n_targets, n_leds = POINTS.shape[0], room.n_leds
    z0 = room.grid.receiver_height

    def amplitudes(theta: FloatArray) -> FloatArray:
        k = n_targets
        pos = theta[: 2 * k].reshape(k, 2)
        heights = z0 + theta[2 * k : 3 * k]
        tilts = theta[3 * k : 5 * k].reshape(k, 2)
        log_gains = theta[5 * k : 6 * k]
        log_scale = theta[6 * k]
        led_log_amp = theta[6 * k + 1 : 6 * k + 1 + n_leds]
        led_angles = theta[6 * k + 1 + n_leds :]
        leds = tuple(
            replace(
                led,
                pilot_amplitude=led.pilot_amplitude * float(np.exp(led_log_amp[i])),
                half_power_angle_deg=led.half_power_angle_deg + float(led_angles[i]),
            )
            for i, led in enumerate(room.leds)
        )
        perturbed = replace(room, leds=leds)
        normals = np.column_stack((tilts, np.ones(k)))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        xyz = np.column_stack((pos, heights))
        channel = los_gains(perturbed, xyz, normals)
        if room.room.reflectance is not None:
            # The diffuse part with the nominal LEDs and upward normals (as the bound).
            channel = channel + diffuse_gains(room, xyz)
        amps = channel * perturbed.pilot_amplitudes[:, None]
        return np.asarray(amps * np.exp(log_gains + 0.5 * log_scale)[None, :])

    def mean(theta: FloatArray) -> FloatArray:
        amps = amplitudes(theta)
        if model == "terminals":
            return amps.T.ravel()
        return np.asarray(vech(amps @ amps.T))

    k = n_targets
    n_params = 6 * k + 1 + 2 * n_leds
    truth = np.zeros(n_params)
    truth[: 2 * k] = POINTS.ravel()
    steps = np.full(n_params, 1e-5)
    if room.room.reflectance is not None:
        steps[: 3 * k] = 0.02  # the diffuse quadrature is not smooth below its 1e-4 noise
    jac = np.column_stack(
        [
            (
                mean(truth + steps[j] * np.eye(n_params)[j])
                - mean(truth - steps[j] * np.eye(n_params)[j])
            )
            / (2 * steps[j])
            for j in range(n_params)
        ]
    )
    prior = np.concatenate(
        (
            np.zeros(2 * k),
            np.full(k, nuisances.height_sd_m**-2),
            np.full(2 * k, nuisances.tilt_sd**-2),
            np.full(k, (nuisances.log_gain_sd or 1.0) ** -2),
            [(nuisances.log_scale_sd or 1.0) ** -2],
            np.full(n_leds, nuisances.led_log_amplitude_sd**-2),
            np.full(n_leds, nuisances.led_half_power_sd_deg**-2),
        )
    )
    amps = amplitudes(truth)
    return mean(truth), jac, prior, amps @ amps.T


@pytest.mark.parametrize(
    ("model", "walls"),
    [("correlation", None), ("terminals", None), ("correlation", 0.7)],
    ids=["correlation", "terminals", "correlation-reflections"],
)
def test_matches_a_finite_difference_fisher_information(
    room: Layout, model: str, walls: float | None
) -> None:
    nuisances = Nuisances(
        log_gain_sd=0.1,
        log_scale_sd=0.5,
        height_sd_m=0.05,
        tilt_sd=0.07,
        led_log_amplitude_sd=0.05,
        led_half_power_sd_deg=3.0,
    )
    if walls is not None:
        room = replace(room, room=replace(room.room, reflectance=Reflectance(walls, 0.0, 0.0)))
    _, jac, prior, signal = _mean_and_jacobian(room, nuisances, model)
    k = POINTS.shape[0]
    if model == "terminals":
        fisher = jac.T @ jac / SIGMA**2
    else:
        row, col = np.triu_indices(room.n_leds)
        atom = (row == col).astype(np.float64)
        jac = np.column_stack((jac, atom))
        prior = np.append(prior, 0.0)
        cov = aggregated_correlation_covariance(signal, SIGMA**2, k)
        fisher = jac.T @ np.linalg.solve(cov, jac)
    inverse = np.linalg.inv(fisher + np.diag(prior))
    expected = np.sqrt(np.diag(inverse)[: 2 * k].reshape(k, 2).sum(axis=1))
    bound = nuisance_crlb(room, POINTS, SIGMA, model, nuisances)  # type: ignore[arg-type]
    # Central differences of smooth closed forms agree to ~1e-6; with reflections the
    # quadrature's own noise (1e-4 relative) over a 2 cm step limits the agreement.
    np.testing.assert_allclose(bound.per_target, expected, rtol=1e-4 if walls is None else 2e-2)


def test_each_nuisance_costs_something_and_priors_bound_the_cost(room: Layout) -> None:
    base = nuisance_crlb(room, POINTS, SIGMA).per_target
    for nuisances in (
        Nuisances(log_gain_sd=0.1),
        Nuisances(log_scale_sd=0.5),
        Nuisances(height_sd_m=0.15),
        Nuisances(tilt_sd=0.07),
        Nuisances(led_log_amplitude_sd=0.05, led_half_power_sd_deg=3.0),
    ):
        assert np.all(nuisance_crlb(room, POINTS, SIGMA, nuisances=nuisances).per_target >= base)
    flat = nuisance_crlb(room, POINTS, SIGMA, nuisances=Nuisances(log_scale_sd=float("inf")))
    weak = nuisance_crlb(room, POINTS, SIGMA, nuisances=Nuisances(log_scale_sd=0.5))
    assert np.all(flat.per_target >= weak.per_target - 1e-15)


def test_rejects_bad_input(room: Layout) -> None:
    with pytest.raises(MeasurementError) as info:
        nuisance_crlb(room, POINTS, SIGMA, "epochs")  # type: ignore[arg-type]
    assert info.value.field == "model"
    with pytest.raises(MeasurementError) as info:
        Nuisances(log_gain_sd=0.0)
    assert info.value.field == "log_gain_sd"
    with pytest.raises(MeasurementError) as info:
        Nuisances(height_sd_m=-1.0)
    assert info.value.field == "height_sd_m"
