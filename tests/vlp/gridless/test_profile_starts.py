"""A terminal's weighted passes also start from the best grid cells of their own cost
(:func:`app.vlp.solvers.gridless.terminal_solve.profile_starts`)."""

from __future__ import annotations

import numpy as np
import pytest

from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Room
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers.gridless.options import GridlessOptions
from app.vlp.solvers.gridless.room import PreparedRoom
from app.vlp.solvers.gridless.terminal_solve import (
    _PROFILE_START_SPACING_M,
    _PROFILE_STARTS,
    profile_starts,
)
from app.vlp.solvers.gridless.terminals import fit_terminal


@pytest.fixture(scope="module")
def five_led_room() -> PreparedRoom:
    spots = [(1.5, 1.5), (4.5, 1.5), (1.5, 5.0), (4.5, 5.0), (3.0, 3.3)]
    layout = Layout(
        room=Room(6.0, 6.6, 2.8),
        grid=Grid(0.1, 0.8),
        leds=tuple(Led(x=x, y=y, z=2.8, half_power_angle_deg=45.0) for x, y in spots),
        name="five LEDs",
    )
    return PreparedRoom(build_fingerprint(layout), "correlation", GridlessOptions())


def test_the_starts_are_the_cells_of_lowest_weighted_profile_cost(
    five_led_room: PreparedRoom,
) -> None:
    # The cost recomputed cell by cell with the simulator's channel (not the room's gains)
    # and each cell's gain by least squares: the starts are its best cells, far enough
    # apart and from the previous optimum, and better than any cell around that optimum.
    room = five_led_room
    layout = room.fingerprint.layout
    rng = np.random.default_rng(3)
    truth = np.array([[4.1, 2.2]])
    values = true_amplitudes(layout, truth)[0] / room.scale * rng.uniform(0.8, 1.2, 5)
    variances = rng.uniform(0.5, 2.0, 5) * 1e-3 * float(values @ values)
    previous = np.array([1.0, 6.0])
    starts = profile_starts(room, values[None, :], [variances], previous[None, :])[0]

    gains = true_amplitudes(layout, room.centres) / room.scale  # (N, M)
    root_weights = 1.0 / np.sqrt(variances)
    cost = np.empty(len(gains))
    for n, column in enumerate(gains):
        gain = np.linalg.lstsq((root_weights * column)[:, None], root_weights * values)[0][0]
        gain = float(np.clip(gain, 1e-3, 1e3)) if column.any() else 1.0
        cost[n] = float(np.sum((root_weights * (values - gain * column)) ** 2))
        assert room.priors.log_gain_sd is not None
        cost[n] += (np.log(gain) / room.priors.log_gain_sd) ** 2
    # Only cells that fit better than any within the spacing of the previous optimum.
    around = np.hypot(*(room.centres - previous).T) < _PROFILE_START_SPACING_M
    better = cost < cost[around].min()
    assert better.any()
    expected: list[np.ndarray] = []
    for n in np.argsort(cost, kind="stable"):
        if not better[n]:
            break
        point = room.centres[n]
        if all(
            np.hypot(*(point - other)) >= _PROFILE_START_SPACING_M
            for other in [previous, *expected]
        ):
            expected.append(point)
        if len(expected) == _PROFILE_STARTS:
            break
    np.testing.assert_allclose(starts, np.array(expected), atol=1e-12)


def test_a_pass_started_in_the_wrong_basin_finds_the_truth(five_led_room: PreparedRoom) -> None:
    # Started from the point mirrored through the room's centre, a terminal's own fit stays
    # in that basin now and then; with the starts of its own cost it lands on the truth.
    room = five_led_room
    layout = room.fingerprint.layout
    stuck = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        truth = np.array([rng.uniform(0.3, 5.7), rng.uniform(0.3, 6.3)])
        values = true_amplitudes(layout, truth[None, :])[0] / room.scale
        wrong = np.array([layout.room.length, layout.room.width]) - truth
        sigma2 = 1e-4 * float(values @ values) / values.size

        def fitted(
            starts: np.ndarray, values: np.ndarray = values, sigma2: float = sigma2
        ) -> np.ndarray:
            return fit_terminal(
                room.kernel,
                values,
                starts,
                priors=room.priors,
                sigma2=sigma2,
                height=None,
                normal=None,
            ).position

        alone = fitted(wrong[None, :])
        extra = profile_starts(room, values[None, :], [sigma2], wrong[None, :])[0]
        searched = fitted(np.vstack((wrong, extra)))
        np.testing.assert_allclose(searched, truth, atol=1e-3)
        stuck += int(np.linalg.norm(alone - truth) > 0.2)
    assert stuck >= 1  # not a formality: from the wrong start alone some stay there


def test_the_option_switches_the_starts_off(
    five_led_room: PreparedRoom, monkeypatch: pytest.MonkeyPatch
) -> None:
    # With ``weighted_pass_starts`` off the weighted passes start from the previous optimum
    # only: the grid's cost is never searched; on, it is.
    from app.vlp.solvers.gridless import terminal_solve

    calls: list[int] = []

    def counted(*args: object, **kwargs: object) -> list[np.ndarray]:
        calls.append(1)
        return profile_starts(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(terminal_solve, "profile_starts", counted)
    layout = five_led_room.fingerprint.layout
    amplitudes = true_amplitudes(layout, np.array([[2.0, 3.0]]))
    for switched_on in (False, True):
        room = PreparedRoom(
            five_led_room.fingerprint,
            "correlation",
            GridlessOptions(weighted_pass_starts=switched_on),
        )
        calls.clear()
        solution = terminal_solve.solve_terminals(room, amplitudes)
        np.testing.assert_allclose(solution.positions[0], [2.0, 3.0], atol=1e-2)
        assert bool(calls) is switched_on
