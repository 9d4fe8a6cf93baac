"""The model of the joint fit under the room's tolerances (docs/explanation/solver.md, "Room
tolerances"): each LED's amplitude and beam width, optionally each photodiode's tilt, with
their data-sheet priors; its residual and Jacobian, compiled (:mod:`._compiled.tolerance`) or
in NumPy (the references). :mod:`.tolerances` fits it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..._kernels import dispatch
from ...typing import FloatArray
from ._compiled import tolerance as compiled_tolerance
from ._compiled.channel import channel_constants
from ._compiled.tolerance import (
    GAINS,
    ORDER,
    SLOPE_X,
    SLOPE_Y,
    TILT_X,
    TILT_Y,
)
from .channel import ChannelKernel
from .lm import (
    EIG_FLOOR,
    SIGMA2_FLOOR,
    SIGMA2_REL_FLOOR,
)
from .state import (
    MAX_LOG_GAIN,
    MAX_LOG_SCALE,
    FitState,
)
from .whitening import (
    Whitening,
    _vech_indices,
    entry_variances,
)

_LN2 = math.log(2.0)


@dataclass(frozen=True)
class RoomTolerances:
    """Prior standard deviations of the room's tolerances.

    Attributes
    ----------
    led_log_amplitude_sd : float
        Each LED's log pilot amplitude (0.05: 5 %).
    led_half_power_sd_deg : float
        Each LED's half-power angle, degrees.
    tilt_sd : float
        Each tangent component of each photodiode's normal (about radians of tilt); 0: the
        photodiodes are taken as level (no tilt parameters).
    """

    led_log_amplitude_sd: float
    led_half_power_sd_deg: float
    tilt_sd: float


class JointModel:
    """Residual and Jacobian of the joint fit. ``theta = [x (K), y (K), u (K), v, a (M),
    delta (M), t_x (K), t_y (K), s]``."""

    def __init__(
        self,
        kernel: ChannelKernel,
        heights: FloatArray,
        priors: tuple[float, float],
        tolerances: RoomTolerances,
    ) -> None:
        self.kernel = kernel
        self.heights = heights
        self._settings = (priors, tolerances)
        self.n_targets = heights.shape[0]
        self.n_leds = kernel.n_leds
        orders = kernel.orders
        # Half-power angle phi: order m = -ln 2 / ln cos(phi), so dm/dphi = ln 2 tan(phi) /
        # ln^2 cos(phi) (in magnitude): the order's prior sd for the angle's.
        cos_half = np.exp(-_LN2 / orders)
        half = np.arccos(np.clip(cos_half, -1.0, 1.0))
        spread = math.radians(tolerances.led_half_power_sd_deg)
        # |dm / dphi| per radian: a wider beam has a smaller order.
        self.order_per_radian = _LN2 * np.tan(half) / np.log(cos_half) ** 2
        order_sd = self.order_per_radian * spread
        gain_sd, scale_sd = priors
        k, m = self.n_targets, self.n_leds
        self.n_tilts = 2 * k if tolerances.tilt_sd > 0 else 0
        self.prior_inverse_sd = np.concatenate(
            (
                np.full(k, 1.0 / gain_sd),
                [1.0 / scale_sd],
                np.full(m, 1.0 / tolerances.led_log_amplitude_sd),
                1.0 / np.maximum(order_sd, 1e-12),
                np.full(self.n_tilts, 1.0 / max(tolerances.tilt_sd, 1e-300)),
            )
        )
        self.upper, self.lower, self.is_diag = _vech_indices("correlation", m)
        # The compiled kernels' constants (None: the kernel's diffuse table has no compiled
        # form, and the NumPy reference runs).
        self._constants = channel_constants(kernel)
        # Writable contiguous copies: the kernels' argument types (read-only arrays would
        # compile another signature, at a request's expense).
        self._heights = np.array(heights, dtype=np.float64, order="C", copy=True)
        self._prior_inverse_sd = np.array(self.prior_inverse_sd, dtype=np.float64, copy=True)

    def with_heights(self, heights: FloatArray) -> JointModel:
        """This model with the targets at ``heights`` (K,), metres."""
        return JointModel(self.kernel, heights, *self._settings)

    def size(self) -> int:
        return int(3 * self.n_targets + 2 * self.n_leds + self.n_tilts + 2)

    def pack(self, state: FitState) -> FloatArray:
        m = self.n_leds
        return np.concatenate(
            (
                state.positions[:, 0],
                state.positions[:, 1],
                state.log_gains,
                [state.log_scale],
                np.zeros(2 * m + self.n_tilts),
                [state.noise],
            )
        )

    def split(
        self, theta: FloatArray
    ) -> tuple[FloatArray, FloatArray, float, FloatArray, FloatArray, FloatArray, float]:
        k, m = self.n_targets, self.n_leds
        positions = np.column_stack((theta[:k], theta[k : 2 * k]))
        at = 3 * k + 1
        return (
            positions,
            theta[2 * k : 3 * k],
            float(theta[3 * k]),
            theta[at : at + m],
            theta[at + m : at + 2 * m],
            (
                theta[at + 2 * m : at + 2 * m + 2 * k].reshape(2, k)
                if self.n_tilts
                else np.zeros((2, k))
            ),
            float(theta[-1]),
        )

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        k = self.n_targets
        lower = np.full(self.size(), -np.inf)
        upper = np.full(self.size(), np.inf)
        length, width = self.kernel.bounds
        lower[: 2 * k] = 0.0
        upper[:k], upper[k : 2 * k] = length, width
        lower[2 * k : 3 * k], upper[2 * k : 3 * k] = -MAX_LOG_GAIN, MAX_LOG_GAIN
        lower[3 * k], upper[3 * k] = -MAX_LOG_SCALE, MAX_LOG_SCALE
        lower[-1] = 0.0
        return lower, upper

    def gains(self, theta: FloatArray) -> tuple[FloatArray, FloatArray, dict[str, FloatArray]]:
        """``g`` of every target, shape (M, K), the multipliers ``e^(v + 2 u)`` and the
        pieces the Jacobian needs."""
        return dispatch(joint_gains_kernel, joint_gains_reference)(self, theta)

    def whitening(self, theta: FloatArray, noise: float) -> Whitening:
        """The plug-in whitening of this model's gains at ``theta`` with the noise
        coefficient ``noise`` (as ``Whitening.from_state``)."""
        gains, multipliers, _ = self.gains(theta)
        k, m = self.n_targets, self.n_leds
        power = float(np.sum(gains**2 * multipliers)) / (m * k)
        sigma2 = max(noise / k, SIGMA2_REL_FLOOR * power, SIGMA2_FLOOR)
        signal = (gains * multipliers) @ gains.T
        signal.flat[:: m + 1] += 0.5 * k * sigma2
        lam, rotation = np.linalg.eigh(signal)
        lam = np.maximum(lam, EIG_FLOOR * max(float(lam[-1]), SIGMA2_FLOOR))
        var = entry_variances(sigma2, lam, self.upper, self.lower, self.is_diag)
        return Whitening("correlation", m, rotation, 1.0 / np.sqrt(var))

    def residual_and_jacobian(
        self, theta: FloatArray, white: Whitening, data: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Residual ``[data - c mu; -theta_nuisance / sd]`` and ``J = d(c mu)/d theta``
        (with the priors' rows), shapes (L + n_prior,) and (L + n_prior, P)."""
        return dispatch(joint_residual_kernel, joint_residual_reference)(self, theta, white, data)

    def compiled_model(self, white: Whitening, data: FloatArray) -> tuple[Any, ...] | None:
        """The fields of the compiled joint fit (:class:`._compiled.tolerance.JointFitModel`)
        for ``white`` and ``data`` (whitened), or None when the channel has no compiled
        form."""
        constants = self._constants
        if constants is None:
            return None
        return (
            *constants,
            white.compiled(),
            np.ascontiguousarray(data, dtype=np.float64),
            self._heights,
            self.n_tilts > 0,
            self._prior_inverse_sd,
        )


def joint_gains_kernel(
    model: JointModel, theta: FloatArray
) -> tuple[FloatArray, FloatArray, dict[str, FloatArray]]:
    """:func:`joint_gains_reference` in one compiled call (in NumPy for a channel without a
    compiled form)."""
    constants = model._constants
    if constants is None:
        return joint_gains_reference(model, theta)
    pieces, multipliers = compiled_tolerance.joint_gains_kernel(
        *constants,
        np.ascontiguousarray(theta, dtype=np.float64),
        model._heights,
        model.n_tilts > 0,
    )
    return (
        pieces[GAINS],
        multipliers,
        {
            "slopes": np.stack((pieces[SLOPE_X], pieces[SLOPE_Y]), axis=2),
            "amplitude_part": pieces[GAINS],
            "order_part": pieces[ORDER],
            "tilt_x": pieces[TILT_X],
            "tilt_y": pieces[TILT_Y],
        },
    )


def joint_gains_reference(
    model: JointModel, theta: FloatArray
) -> tuple[FloatArray, FloatArray, dict[str, FloatArray]]:
    """:meth:`JointModel.gains` in plain NumPy."""
    positions, log_gains, log_scale, amps, order_changes, tilts, _ = model.split(theta)
    kernel = model.kernel
    k = model.n_targets
    blocks = kernel.gradients_xyz(positions[:, 0], positions[:, 1], model.heights)
    total = blocks[:, 3 * k : 4 * k]
    offsets = kernel.led_xyz[:, np.newaxis, :] - np.column_stack((positions, model.heights))
    drop = np.maximum(offsets[:, :, 2], 1e-9)
    dist2 = np.einsum("mkc,mkc->mk", offsets, offsets)
    orders = kernel.orders[:, np.newaxis]
    in_view = drop * drop >= kernel.cos_fov2 * dist2
    los = (
        kernel.free_height_factor[:, np.newaxis]
        * drop ** (orders + 1.0)
        * dist2 ** (-(orders + 3.0) / 2.0)
        * in_view
    )
    log_cos = 0.5 * np.log(drop * drop / dist2)
    beam = (
        (orders + 1.0 + order_changes[:, np.newaxis])
        / (orders + 1.0)
        * np.exp(order_changes[:, np.newaxis] * log_cos)
    )
    per_tilt = los / drop
    tilt_gain = per_tilt * (offsets[:, :, 0] * tilts[0] + offsets[:, :, 1] * tilts[1])
    amplitude = np.exp(amps)[:, np.newaxis]
    gains = amplitude * (los * beam + tilt_gain + (total - los))
    multipliers = np.exp(log_scale + 2.0 * log_gains)
    # d g / d x: the line of sight's own slope changes with the beam (cos^delta) and the
    # tilt term; both are small corrections of the nominal slope, kept exactly here.
    dx_nominal = blocks[:, :k]
    dy_nominal = blocks[:, k : 2 * k]
    # d log cos(phi) / dx = (x_led - x) / d^2 (cos phi = D / d, d^2 grows with dx^2).
    along = offsets[:, :, :2] / dist2[:, :, np.newaxis]
    beam_slope = order_changes[:, np.newaxis, np.newaxis] * along  # d log beam / d(x, y)
    # d los / dx = los (m + 3) (x_led - x) / d^2 (the kernel's formula; the nominal slope
    # below already holds it once, and the diffuse part's).
    los_slope = los[:, :, np.newaxis] * (orders + 3.0)[:, :, np.newaxis] * along
    # tilt term t . v_xy * los / D: d/dx = -t_x los / D + (t . v_xy) dlos/dx / D.
    tilt_dot = offsets[:, :, 0] * tilts[0] + offsets[:, :, 1] * tilts[1]
    extra = np.empty((model.n_leds, k, 2))
    for axis in range(2):
        extra[:, :, axis] = (
            los_slope[:, :, axis] * (beam - 1.0)
            + los * beam * beam_slope[:, :, axis]
            - tilts[axis] / drop * los
            + tilt_dot / drop * los_slope[:, :, axis]
        )
    slopes = amplitude[:, :, np.newaxis] * (np.stack((dx_nominal, dy_nominal), axis=2) + extra)
    pieces = {
        "slopes": slopes,
        "amplitude_part": gains,
        "order_part": amplitude
        * los
        * beam
        * (1.0 / (orders + 1.0 + order_changes[:, np.newaxis]) + log_cos),
        "tilt_x": amplitude * per_tilt * offsets[:, :, 0],
        "tilt_y": amplitude * per_tilt * offsets[:, :, 1],
    }
    return gains, multipliers, pieces


def joint_residual_kernel(
    model: JointModel, theta: FloatArray, white: Whitening, data: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """:func:`joint_residual_reference` in one compiled call (in NumPy for a channel without
    a compiled form)."""
    constants = model._constants
    if constants is None:
        return joint_residual_reference(model, theta, white, data)
    residual, jacobian = compiled_tolerance.joint_residual_kernel(
        *constants,
        white.compiled(),
        np.ascontiguousarray(data, dtype=np.float64),
        np.ascontiguousarray(theta, dtype=np.float64),
        model._heights,
        model.n_tilts > 0,
        model._prior_inverse_sd,
    )
    return residual, jacobian


def joint_residual_reference(
    model: JointModel, theta: FloatArray, white: Whitening, data: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """:meth:`JointModel.residual_and_jacobian` in plain NumPy."""
    k = model.n_targets
    gains, multipliers, pieces = joint_gains_reference(model, theta)
    rotation = white.rotation
    assert rotation is not None
    upper, lower, weights = white.upper, white.lower, white.weights
    rotated = rotation.T @ gains  # (M', K)
    atoms = rotated[upper] * rotated[lower]  # (L, K)
    modelled = atoms @ multipliers + float(theta[-1]) * model.is_diag
    residual = data - weights * modelled

    def per_target(directions: FloatArray) -> FloatArray:
        moved = rotation.T @ directions
        block = moved[upper] * rotated[lower] + rotated[upper] * moved[lower]
        return np.asarray(weights[:, np.newaxis] * block * multipliers[np.newaxis, :])

    def per_led(directions: FloatArray) -> FloatArray:
        # LED i's parameter moves row i of g: moved[a, k] = U[i, a] directions[i, k].
        # Column i: w (U[i, up] Q[i, lo] + U[i, lo] Q[i, up]), Q = (D c) @ rotated^T.
        q = (directions * multipliers) @ rotated.T  # (M, M')
        block = rotation[:, upper] * q[:, lower] + rotation[:, lower] * q[:, upper]
        return np.asarray((weights[np.newaxis, :] * block).T)

    slopes = pieces["slopes"]
    columns = [
        per_target(slopes[:, :, 0]),
        per_target(slopes[:, :, 1]),
        2.0 * weights[:, np.newaxis] * atoms * multipliers[np.newaxis, :],
        (weights * (atoms @ multipliers))[:, np.newaxis],
        per_led(pieces["amplitude_part"]),
        per_led(pieces["order_part"]),
        *((per_target(pieces["tilt_x"]), per_target(pieces["tilt_y"])) if model.n_tilts else ()),
        (weights * model.is_diag)[:, np.newaxis],
    ]
    jacobian = np.concatenate(columns, axis=1)
    nuisance = theta[2 * k : 2 * k + model.prior_inverse_sd.shape[0]]
    prior_residual = -nuisance * model.prior_inverse_sd
    prior_rows = np.zeros((prior_residual.shape[0], theta.shape[0]))
    prior_rows[:, 2 * k : 2 * k + prior_residual.shape[0]] = np.diag(model.prior_inverse_sd)
    return np.concatenate((residual, prior_residual)), np.vstack((jacobian, prior_rows))
