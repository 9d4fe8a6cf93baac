"""The examples of the filter step's row in the kernel table reach every branch of the step.

The row (``predict_update``, ``app/vlp/solvers/_kernel_table.py``) has the compiled step give
its NumPy reference's numbers on these examples (``tests/vlp/gridless/test_kernel_table.py``):
a branch no example takes would go unchecked.
"""

from __future__ import annotations

import numpy as np

from app.vlp._kernels import use_kernels
from app.vlp.solvers._kernel_tracks import predict_update_examples
from app.vlp.tracking.starts import consistent_runs
from app.vlp.tracking.step import fix_offsets, predict_update_reference


def test_the_filter_rows_examples_reach_every_branch() -> None:
    reached: set[str] = set()
    examples = predict_update_examples()
    for bank, positions, covariances, time_s, settings, learn, inflate_chi2 in examples:
        with use_kernels("reference"):
            updated, wild = predict_update_reference(
                bank, positions, covariances, time_s, settings, learn, inflate_chi2
            )
            at_gate, _ = predict_update_reference(
                bank, positions, covariances, time_s, settings, learn, None
            )
        reached.add(f"learn={learn}")
        restarted = updated.wild >= settings.reset_after_wild
        if np.any(wild & ~restarted):
            reached.add("wild")
        if np.any(restarted):
            reached.add("restarted")
        if np.any(bank.times_s > time_s) and np.any(bank.times_s < time_s):
            reached.add("tracks newer and older than the fix")
        if np.any(np.isnan(bank.noise_var)) and np.any(np.isnan(bank.stated_var)):
            reached.add("levels not learned yet")
        if inflate_chi2 is not None and not np.array_equal(updated.means, at_gate.means):
            # some fix lay between its own bound and the gate: inflated, not wild
            reached.add("inflated below the gate")
        offsets = fix_offsets(bank, positions, covariances, time_s, settings)
        standing = bank.model_probabilities[:, 0] >= 0.5
        runs = consistent_runs(bank.offset, offsets, settings) & standing & ~restarted
        if learn and np.any(runs):
            reached.add("a run sets a standing track off")
    assert reached == {
        "learn=True",
        "learn=False",
        "wild",
        "restarted",
        "tracks newer and older than the fix",
        "levels not learned yet",
        "inflated below the gate",
        "a run sets a standing track off",
    }
