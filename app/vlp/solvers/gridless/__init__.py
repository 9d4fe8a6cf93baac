"""The default solver, a pipeline of stages (docs/explanation/solver.md).

- :mod:`.solver`: :class:`GridlessSolver`, which prepares the room once and runs the stages;
- :mod:`.options`: its options and the policy they resolve to;
- :mod:`.channel`: the continuous channel model (line of sight, interpolated reflections);
- :mod:`.model`: the fit state, priors, whitening and objective of the aggregated fit;
- :mod:`.lm`: the Levenberg-Marquardt constants every fit uses, and the projected loop;
- :mod:`.local`: the large rooms' scans and the terminals' windows;
- :mod:`.tolerances`: the joint fit under the room's tolerances;
- :mod:`.terminals`: each terminal's own fit;
- :mod:`.whitening_memo`: whitenings already computed;
- :mod:`._compiled`: the numba kernels, each standing in for NumPy code in the modules above.
"""

from .options import GridlessOptions
from .solver import GridlessSolver

__all__ = ["GridlessOptions", "GridlessSolver"]
