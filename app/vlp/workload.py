"""How much work a localize request asks for, so a service can refuse what it cannot afford.

A solve scans the grid for every target it places and fits every target against every
observation, so its work grows with the product ``grid points x observations x targets``:
``observations`` is M for the power model and for terminals' own amplitudes (each terminal
has M), and ``M (M + 1) / 2`` for the correlation model. With K unknown the solver may place
up to :data:`~app.vlp.constants.MAX_TARGETS` targets, so that many count. The product is a
bound, not a prediction (the gridless solver's large-room paths are much cheaper than it for
most rooms): a request above the service's limit is refused before any work is done.
"""

from __future__ import annotations

from dataclasses import dataclass

from .constants import MAX_TARGETS
from .measurements import Model

__all__ = ["LocalizeWork", "localize_work"]


@dataclass(frozen=True)
class LocalizeWork:
    """The work of one localize request: ``grid_points * observations * targets``."""

    grid_points: int
    observations: int
    targets: int

    @property
    def units(self) -> int:
        """The product (an exact integer: no overflow for any admissible room)."""
        return self.grid_points * self.observations * self.targets

    def describe(self) -> str:
        """``"N x obs x K = product"`` for a problem's detail."""
        return (
            f"{self.grid_points} grid points x {self.observations} observations x "
            f"{self.targets} targets = {self.units}"
        )


def localize_work(
    *, n_cells: int, n_leds: int, model: Model, targets: int | None, terminals: int | None = None
) -> LocalizeWork:
    """The work of solving one measurement.

    Parameters
    ----------
    n_cells, n_leds : int
        N and M of the fingerprint.
    model : {"power", "correlation"}
        The model of an aggregated measurement (ignored with ``terminals``).
    targets : int or None
        K when given; None means counted by the solver (up to ``MAX_TARGETS``).
    terminals : int or None
        The number of terminals when each is fitted from its own M amplitudes (one target
        per terminal); None for an aggregated measurement (including terminals' amplitudes
        summed into one because K differs from their number).

    Returns
    -------
    LocalizeWork
    """
    if terminals is not None:
        return LocalizeWork(n_cells, n_leds, max(terminals, 1))
    observations = n_leds if model == "power" else n_leds * (n_leds + 1) // 2
    return LocalizeWork(n_cells, observations, MAX_TARGETS if targets is None else targets)
