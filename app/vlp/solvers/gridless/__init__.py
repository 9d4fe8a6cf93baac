"""The default solver, a pipeline of stages (docs/explanation/solver.md).

- :mod:`.solver`: :class:`GridlessSolver`, a thin estimator: it prepares the room once and
  its ``_solve`` runs the stages below in order;
- :mod:`.options`: its options and the policy they resolve to;
- :mod:`.room`: the frozen per-room precomputation;
- :mod:`.fitting`: what every stage calls (the run's objectives, whitenings and fits);
- :mod:`.search`: the nominal search (insertions, refinements, escapes, counting, prescale);
- :mod:`.stages`: the nuisance stages, each gated (scale and heights, gains, tolerances);
- :mod:`.uncertainty`: the covariances of the positions;
- :mod:`.report`: far optima, mirror twins, bounded radii, the sentences of ``fit.detail``;
- :mod:`.terminal_solve`: terminals that send their own amplitudes, one fit each;
- :mod:`.channel`: the continuous channel model (line of sight, interpolated reflections);
- :mod:`.channel_rows`: its gains and gradients at points, compiled or in NumPy;
- :mod:`.state`, :mod:`.whitening`, :mod:`.model`: the fit state and priors, the plug-in
  whitening, and the objective of the aggregated fit;
- :mod:`.lm`: the Levenberg-Marquardt constants every fit uses, and the projected loop;
- :mod:`.local`: the large rooms' scans and the terminals' windows;
- :mod:`.joint_model`, :mod:`.tolerances`: the joint model under the room's tolerances, and
  its fit;
- :mod:`.terminals`: each terminal's own fit;
- :mod:`.whitening_memo`: whitenings already computed;
- :mod:`._compiled`: the numba kernels, each ``foo_kernel`` standing in for the
  ``foo_reference`` of a module above (the kernel table, ``app/vlp/solvers/_kernel_table.py``,
  lists them).
"""

from .options import GridlessOptions
from .solver import GridlessSolver

__all__ = ["GridlessOptions", "GridlessSolver"]
