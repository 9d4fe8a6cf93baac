"""The fit's state and the nuisance priors of the ``gridless`` solver (normalised units, see
:mod:`.model`): the targets' positions, weights, heights and gains, the common scale and the
noise coefficient, with the bounds on the log gains and scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ...typing import FloatArray


@dataclass(frozen=True)
class Priors:
    """Gaussian priors of the nuisance parameters; a None standard deviation = not fitted.

    Attributes
    ----------
    log_gain_sd : float or None
        Standard deviation of each target's log amplitude gain ``u_k`` (mean 0).
    log_scale_sd : float or None
        Standard deviation of the common log power scale ``v`` (mean 0).
    height_sd : float
        Standard deviation of each target's height around ``height_mean``, metres; 0 keeps
        every target on the receivers' plane.
    height_mean : float
        The receivers' nominal height, metres.
    height_bounds : tuple of float
        Heights are kept within these, metres.
    """

    log_gain_sd: float | None = None
    log_scale_sd: float | None = None
    height_sd: float = 0.0
    height_mean: float = 0.0
    height_bounds: tuple[float, float] = (0.0, 0.0)

    @property
    def fits_gains(self) -> bool:
        """True when each target's gain is a parameter."""
        return self.log_gain_sd is not None

    @property
    def fits_scale(self) -> bool:
        """True when the common scale is a parameter."""
        return self.log_scale_sd is not None

    @property
    def fits_heights(self) -> bool:
        """True when each target's height is a parameter."""
        return self.height_sd > 0.0


# Log amplitude gains are kept within +-ln 2 (a terminal between half and twice the modelled
# gain) and the log power scale within +-ln 10^4 (beyond, the measurement is refused).
MAX_LOG_GAIN = math.log(2.0)


MAX_LOG_SCALE = math.log(1e4)

# A state's facts when every target is on the receivers' plane with a unit multiplier.
PLAIN_FACTS = (True, True)


@dataclass
class FitState:
    """Current estimate.

    Attributes
    ----------
    positions : ndarray of shape (K, 2), metres
    weights : ndarray of shape (K,)
        Fixed (or, with free weights, fitted) multipliers of each target's atom.
    noise : float
        Noise coefficient s (normalised units).
    heights : ndarray of shape (K,), metres
    log_gains : ndarray of shape (K,)
        Each target's log amplitude gain ``u_k``.
    log_scale : float
        The common log power scale ``v``.
    converged : bool
        Whether the Levenberg-Marquardt run that produced this state stopped by its
        tolerance (or at a local minimum) rather than by running out of iterations.
    """

    positions: FloatArray
    weights: FloatArray
    noise: float
    heights: FloatArray
    log_gains: FloatArray
    log_scale: float = 0.0
    # (all on the receivers' plane, unit multipliers), filled by the objective on first use.
    facts: tuple[bool, bool] | None = field(default=None, compare=False, repr=False)
    converged: bool = field(default=True, compare=False, repr=False)

    @classmethod
    def empty(cls, log_scale: float = 0.0) -> FitState:
        """No targets yet."""
        return cls(np.zeros((0, 2)), np.zeros(0), 0.0, np.zeros(0), np.zeros(0), log_scale)

    @property
    def n_targets(self) -> int:
        """K."""
        return int(self.positions.shape[0])

    def effective_weights(self) -> FloatArray:
        """``w_k exp(v + 2 u_k)``: each atom's multiplier in the model."""
        return np.asarray(self.weights * np.exp(self.log_scale + 2.0 * self.log_gains))

    def subset(self, keep: npt.NDArray[np.bool_] | npt.NDArray[np.integer[Any]]) -> FitState:
        """The targets selected by the boolean or index array ``keep``."""
        return FitState(
            self.positions[keep],
            self.weights[keep],
            self.noise,
            self.heights[keep],
            self.log_gains[keep],
            self.log_scale,
            # Some of the targets of a state on the plane with unit multipliers are too.
            facts=PLAIN_FACTS if self.facts == PLAIN_FACTS else None,
        )

    def with_target(self, position: FloatArray, height: float) -> FitState:
        """This state plus one unit-gain target at ``position`` and ``height``."""
        k = self.positions.shape[0]
        plain = self.facts == PLAIN_FACTS and k > 0 and height == self.heights[0]
        # Filled in place: the search adds targets tens of times a solve, and a
        # concatenation with a Python tuple costs several times the copy.
        positions = np.empty((k + 1, 2))
        positions[:k] = self.positions
        positions[k] = position
        return FitState(
            positions,
            _appended(self.weights, 1.0),
            self.noise,
            _appended(self.heights, height),
            _appended(self.log_gains, 0.0),
            self.log_scale,
            # A unit-gain target at the plane's height keeps a plain state plain.
            facts=PLAIN_FACTS if plain else None,
        )

    def facts_on(self, receiver_height: float) -> tuple[bool, bool]:
        """Whether every target is on the receivers' plane at ``receiver_height``, and whether
        every multiplier is 1 (remembered: a fit evaluates many thetas against one state)."""
        facts = self.facts
        if facts is None:
            on_plane = bool((self.heights == receiver_height).all())
            unit = (
                self.log_scale == 0.0
                and not self.log_gains.any()
                and bool((self.weights == 1.0).all())
            )
            facts = self.facts = (on_plane, bool(unit))
        return facts

    def reordered(self, order: npt.NDArray[np.integer[Any]]) -> FitState:
        """The targets in the order ``order``."""
        return self.subset(order)


def _appended(values: FloatArray, last: float) -> FloatArray:
    """``values`` (shape (K,)) with ``last`` after them, a new array of shape (K + 1,)."""
    n_values = values.shape[0]
    out = np.empty(n_values + 1)
    out[:n_values] = values
    out[n_values] = last
    return out
