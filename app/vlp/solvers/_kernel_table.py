"""The table of compiled kernels: each row a kernel, its NumPy reference and example arguments.

One rule names them: a kernel ``foo`` is the module-level pair ``foo_reference`` (NumPy) and
``foo_kernel`` (the same arguments; it packs them into the compiled code's tuples and calls
``foo_kernel`` of a ``_compiled`` module, falling back to ``foo_reference`` where that code
does not apply), next to each other in the module that uses them, whose callers reach them
only through ``dispatch(foo_kernel, foo_reference)`` (:func:`app.vlp._kernels.dispatch`).
``misfit_design_reference`` lives in :mod:`app.vlp.uncertainty`, which must not import the
solver: its kernel is :mod:`.gridless.uncertainty`'s. The tracking filter's step
(:mod:`app.vlp.tracking.step`) is a row too. One table drives both
:func:`app.vlp.solvers.warm_up` (every row's kernel on its examples, so neither a request nor
a tracker's step waits for the compiler) and the parametrized parity test
(``tests/vlp/gridless/test_kernel_table.py``: the kernel gives its reference's numbers on
every example): a new kernel is one row here, its examples in :mod:`._kernel_examples` (the
filter's in :mod:`._kernel_tracks`).

Like :mod:`._warm_up`, this module is at the top of the kernels' imports: it imports the
kernels' callers, and nothing in :mod:`app.vlp` imports it but :mod:`._warm_up`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

from ..radii import covariance_radii_kernel, covariance_radii_reference
from ..tracking.step import predict_update_kernel, predict_update_reference
from ..uncertainty import misfit_design_reference
from ._kernel_examples import (
    Arguments,
    best_of_tiles_examples,
    channel_rows_examples,
    channel_rows_parts,
    correlation_profiles_examples,
    correlation_scores_examples,
    covariance_radii_examples,
    escape_test_examples,
    fit_examples,
    grow_examples,
    joint_examples,
    joint_fit_examples,
    joint_gains_examples,
    joint_gains_parts,
    misfit_design_examples,
    objective_examples,
    profile_cells_examples,
    refine_examples,
    sandwich_examples,
    sandwich_parts,
    search_parts,
    squared_gains_dot_examples,
    terminal_fit_examples,
    whitened_data_examples,
    whitening_examples,
    whitening_metric,
)
from ._kernel_tracks import predict_update_examples, predict_update_parts
from .gridless.channel_rows import channel_rows_kernel, channel_rows_reference
from .gridless.fitting import correlation_scores_kernel, correlation_scores_reference
from .gridless.joint_model import (
    joint_gains_kernel,
    joint_gains_reference,
    joint_residual_kernel,
    joint_residual_reference,
)
from .gridless.local import (
    best_of_tiles_kernel,
    best_of_tiles_reference,
    squared_gains_dot_kernel,
    squared_gains_dot_reference,
)
from .gridless.model import (
    fit_kernel,
    fit_reference,
    gram_kernel,
    gram_reference,
    residual_kernel,
    residual_reference,
)
from .gridless.report import correlation_profiles_kernel, correlation_profiles_reference
from .gridless.search import (
    escape_test_kernel,
    escape_test_reference,
    grow_kernel,
    grow_reference,
    refine_kernel,
    refine_reference,
)
from .gridless.terminal_solve import profile_cells_kernel, profile_cells_reference
from .gridless.terminals import (
    terminal_fit_kernel,
    terminal_fit_reference,
)
from .gridless.tolerances import joint_fit_kernel, joint_fit_reference
from .gridless.uncertainty import (
    misfit_design_kernel,
    sandwich_covariances_kernel,
    sandwich_covariances_reference,
)
from .gridless.whitening import (
    whitened_data_kernel,
    whitened_data_reference,
    whitening_kernel,
    whitening_reference,
)

__all__ = ["KERNEL_TABLE", "KernelRow"]


class KernelRow(NamedTuple):
    """One compiled kernel: ``kernel(*args)`` equals ``reference(*args)`` (to ``rtol``
    relative to the reference's largest magnitude; 0: bit for bit) for every ``args`` of
    ``examples()``, which also gives the argument types a solve compiles. ``compared``
    gives the parts of an answer that must agree (default: all of it), where an answer
    holds more than its meaning fixes (an eigenbasis's signs)."""

    name: str
    reference: Callable[..., Any]
    kernel: Callable[..., Any]
    examples: Callable[[], list[Arguments]]
    rtol: float = 1e-10
    compared: Callable[[Any], Any] | None = None


KERNEL_TABLE: tuple[KernelRow, ...] = (
    KernelRow(
        "whitened_data", whitened_data_reference, whitened_data_kernel, whitened_data_examples
    ),
    KernelRow(
        "correlation_scores",
        correlation_scores_reference,
        correlation_scores_kernel,
        correlation_scores_examples,
    ),
    KernelRow(
        "correlation_profiles",
        correlation_profiles_reference,
        correlation_profiles_kernel,
        correlation_profiles_examples,
    ),
    KernelRow("residual", residual_reference, residual_kernel, objective_examples),
    KernelRow("gram", gram_reference, gram_kernel, objective_examples),
    KernelRow(
        "channel_rows",
        channel_rows_reference,
        channel_rows_kernel,
        channel_rows_examples,
        compared=channel_rows_parts,
    ),
    KernelRow("fit", fit_reference, fit_kernel, fit_examples, rtol=1e-8),
    KernelRow(
        "whitening",
        whitening_reference,
        whitening_kernel,
        whitening_examples,
        compared=whitening_metric,
    ),
    KernelRow(
        "misfit_design", misfit_design_reference, misfit_design_kernel, misfit_design_examples
    ),
    KernelRow(
        "squared_gains_dot",
        squared_gains_dot_reference,
        squared_gains_dot_kernel,
        squared_gains_dot_examples,
    ),
    KernelRow(
        "best_of_tiles",
        best_of_tiles_reference,
        best_of_tiles_kernel,
        best_of_tiles_examples,
        rtol=0.0,
    ),
    KernelRow(
        "joint_gains",
        joint_gains_reference,
        joint_gains_kernel,
        joint_gains_examples,
        compared=joint_gains_parts,
    ),
    KernelRow("joint_residual", joint_residual_reference, joint_residual_kernel, joint_examples),
    KernelRow("joint_fit", joint_fit_reference, joint_fit_kernel, joint_fit_examples),
    KernelRow(
        "sandwich_covariances",
        sandwich_covariances_reference,
        sandwich_covariances_kernel,
        sandwich_examples,
        rtol=1e-8,  # a chain of kernels: round-off amplified (nearly collinear leverages)
        compared=sandwich_parts,
    ),
    KernelRow("grow", grow_reference, grow_kernel, grow_examples, compared=search_parts),
    KernelRow("refine", refine_reference, refine_kernel, refine_examples, compared=search_parts),
    KernelRow("escape_test", escape_test_reference, escape_test_kernel, escape_test_examples),
    KernelRow("terminal_fit", terminal_fit_reference, terminal_fit_kernel, terminal_fit_examples),
    KernelRow(
        "profile_cells",
        profile_cells_reference,
        profile_cells_kernel,
        profile_cells_examples,
        rtol=0.0,  # cells: the same ones
    ),
    KernelRow(
        "covariance_radii",
        covariance_radii_reference,
        covariance_radii_kernel,
        covariance_radii_examples,
    ),
    KernelRow(
        "predict_update",
        predict_update_reference,
        predict_update_kernel,
        predict_update_examples,
        compared=predict_update_parts,
    ),
)
