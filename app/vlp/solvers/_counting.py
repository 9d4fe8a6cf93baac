"""How many targets: the one counting rule every grid solver uses when K is not given."""

from __future__ import annotations

import numpy as np

from ..typing import FloatArray
from .base import MAX_TARGETS

__all__ = ["estimate_target_count"]


def estimate_target_count(weights: FloatArray, *, max_targets: int = MAX_TARGETS) -> int:
    """Estimate K from fitted grid occupancies.

    Parameters
    ----------
    weights : ndarray of shape (n,)
        Fitted occupancies in the units of the *unnormalised* dictionary (``J`` or Psi), so
        that one terminal standing on grid point ``j`` gives weight 1 at ``j``. Negative
        entries (possible with least squares) are ignored.
    max_targets : int, default=MAX_TARGETS
        Upper clip.

    Returns
    -------
    n_targets : int
        ``round(sum(max(weights, 0)))`` clipped to ``[1, max_targets]``.

    Notes
    -----
    Each terminal contributes one unit of pilot energy: its column of ``J`` (or Psi) enters
    the aggregated measurement with coefficient 1 (paper eqs. 12 and 16). A terminal between
    grid points is spread over neighbouring columns whose weights still add up to about 1,
    so the total weight counts the terminals. The noise atom's coefficient is not a weight
    and must not be included.

    Examples
    --------
    >>> estimate_target_count(np.array([0.98, 0.0, 0.55, 0.47, 1.1]))
    3
    >>> estimate_target_count(np.array([0.0, 0.1]))
    1
    """
    values = np.asarray(weights, dtype=np.float64)
    total = float(np.sum(values[np.isfinite(values) & (values > 0)]))
    return int(min(max(round(total), 1), max_targets))
