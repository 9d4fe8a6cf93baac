"""The table of compiled kernels: each row a kernel, its NumPy reference and example arguments.

A row's ``kernel`` and ``reference`` take the same arguments (the ``kernel`` is the function
:func:`app.vlp._kernels.dispatch` hands a caller while the compiled kernels are in use, so it
converts those arguments into the compiled code's tuples). One table drives both
:func:`app.vlp.solvers.warm_up` (every row's kernel on its examples, so a request never waits
for the compiler) and the parametrized parity test (``tests/vlp/gridless/test_kernel_table.py``:
the kernel gives its reference's numbers on every example): a new kernel is one row here.

Like :mod:`._warm_up`, this module is at the top of the kernels' imports: it imports the
kernels' callers, and nothing in :mod:`app.vlp` imports it but :mod:`._warm_up`.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np
import scipy.sparse as sp

from ..presets import paper_layout
from ..uncertainty import misfit_design
from .gridless.channel import ChannelKernel
from .gridless.fitting import _correlation_scores, _dense_scores_kernel
from .gridless.local import PowerScan, _squared_gains_dot_kernel, _squared_gains_dot_reference
from .gridless.model import Objective, gram, gram_reference
from .gridless.report import _correlation_products, _correlation_products_kernel
from .gridless.state import FitState, Priors
from .gridless.uncertainty import _misfit_design_kernel
from .gridless.whitening import Whitening

__all__ = ["KERNEL_TABLE", "KernelRow"]

Arguments = tuple[Any, ...]


class KernelRow(NamedTuple):
    """One compiled kernel: ``kernel(*args)`` equals ``reference(*args)`` (to ``rtol``
    relative to the reference's largest magnitude; 0: bit for bit) for every ``args`` of
    ``examples()``, which also gives the argument types a solve compiles."""

    name: str
    reference: Callable[..., Any]
    kernel: Callable[..., Any]
    examples: Callable[[], list[Arguments]]
    rtol: float = 1e-10


def _kernel() -> ChannelKernel:
    return ChannelKernel(paper_layout(), 1.0)


def _state(kernel: ChannelKernel, rng: np.random.Generator, k: int) -> FitState:
    """A random state of ``k`` targets on the receiver plane."""
    length, width = kernel.bounds
    positions = np.column_stack(
        (rng.uniform(0.2, length - 0.2, k), rng.uniform(0.2, width - 0.2, k))
    )
    return FitState(
        positions,
        rng.uniform(0.5, 1.5, k),
        float(rng.uniform(1e-4, 1e-2)),
        np.full(k, kernel.receiver_height),
        rng.uniform(-0.2, 0.2, k),
    )


def _whitenings(kernel: ChannelKernel, rng: np.random.Generator) -> list[Whitening]:
    """Both models' metrics at a random two-target state, and the correlation model's
    plain metric (the search's)."""
    state = _state(kernel, rng, 2)
    return [
        Whitening._from_state_reference("correlation", kernel, state, 2.0),
        Whitening._from_state_reference("power", kernel, state, 2.0),
        Whitening.identity("correlation", kernel.n_leds),
    ]


def _whitened_data() -> list[Arguments]:
    kernel = _kernel()
    rng = np.random.default_rng(8)
    return [
        (white, rng.standard_normal(white.weights.shape[0])) for white in _whitenings(kernel, rng)
    ]


def _gains(kernel: ChannelKernel, rng: np.random.Generator, n_points: int) -> np.ndarray:
    """Line-of-sight gains (M, n_points) of random points of the room."""
    length, width = kernel.bounds
    xs = rng.uniform(0.0, length, n_points)
    ys = rng.uniform(0.0, width, n_points)
    return np.ascontiguousarray(kernel.gains_xy(xs, ys))


def _dense_room(gains: np.ndarray) -> Any:
    """The fields of a dense room that the correlation scores read."""
    return SimpleNamespace(
        fingerprint=SimpleNamespace(n_leds=gains.shape[0]), dense=True, gains=gains
    )


def _correlation_scores_examples() -> list[Arguments]:
    kernel = _kernel()
    rng = np.random.default_rng(11)
    room = _dense_room(_gains(kernel, rng, 30))
    return [
        (room, white, rng.standard_normal(white.weights.shape[0]))
        for white in _whitenings(kernel, rng)
        if white.model == "correlation"
    ]


def _correlation_products_examples() -> list[Arguments]:
    kernel = _kernel()
    rng = np.random.default_rng(12)
    gains = _gains(kernel, rng, 30)
    examples = []
    for white in _whitenings(kernel, rng):
        if white.model != "correlation":
            continue
        for k in (1, 3):
            examples.append(
                (
                    white,
                    rng.standard_normal(white.weights.shape[0]),
                    gains,
                    _gains(kernel, rng, k),
                    rng.uniform(0.5, 1.5, k),
                )
            )
    return examples


def _gram_examples() -> list[Arguments]:
    kernel = _kernel()
    rng = np.random.default_rng(13)
    priors = Priors(0.1, 0.5, 0.05, kernel.receiver_height, (0.6, 1.1))
    examples = []
    for model in ("correlation", "power"):
        for k in (1, 3):
            state = _state(kernel, rng, k)
            white = Whitening._from_state_reference(model, kernel, state, 2.0)
            values = rng.standard_normal((white.weights.shape[0],))
            objective = Objective(kernel, white, values, False, priors)
            examples.append((objective, objective.pack(state), state))
    return examples


def _misfit_design_examples() -> list[Arguments]:
    rng = np.random.default_rng(31)
    examples = []
    for n_data, n_params, widths in ((40, 6, (5, 50, 1)), (12, 4, (3,))):
        jacobian = rng.standard_normal((n_data, n_params))
        normal = jacobian.T @ jacobian + np.diag(rng.uniform(0.0, 1.0, n_params))
        examples.append(
            (jacobian, normal, [rng.standard_normal((n_data, width)) for width in widths])
        )
    return examples


def _by_cell(rng: np.random.Generator, n_cells: int, n_leds: int) -> sp.csr_array:
    """A sparse ``G^T`` (cells x LEDs), about half of it zero."""
    dense = rng.uniform(0.0, 2.0, (n_cells, n_leds)) * (rng.uniform(size=(n_cells, n_leds)) < 0.5)
    return sp.csr_array(dense)


def _squared_gains_dot_examples() -> list[Arguments]:
    rng = np.random.default_rng(21)
    by_cell = _by_cell(rng, 12, 16)
    return [(by_cell, 0.5, rng.standard_normal(16), fourth) for fourth in (False, True)]


def _best_of_tiles_examples() -> list[Arguments]:
    """Tiles of a 5 x 4 grid in 2 x 2 tiles (the last row and column partial)."""
    rng = np.random.default_rng(22)
    n_x, n_y, n_leds = 5, 4, 16
    by_cell = _by_cell(rng, n_x * n_y, n_leds)
    squared = by_cell.power(2)
    fourth_sums = np.asarray(squared.power(2).sum(axis=1), dtype=np.float64)
    scan = PowerScan(n_y, n_x, 2, 1.0, sp.csr_array((6, n_leds)), np.zeros(6), fourth_sums, by_cell)
    return [
        (scan, np.array(tiles, dtype=np.int64), rng.standard_normal(n_leds), weight, 1.5)
        for tiles, weight in (([0], 1.0), ([5, 2, 3], 0.7), ([0, 1, 2, 3, 4, 5], 2.0))
    ]


KERNEL_TABLE: tuple[KernelRow, ...] = (
    KernelRow("whitened_data", Whitening._data_reference, Whitening._data_kernel, _whitened_data),
    KernelRow(
        "correlation_scores",
        _correlation_scores,
        _dense_scores_kernel,
        _correlation_scores_examples,
    ),
    KernelRow(
        "correlation_products",
        _correlation_products,
        _correlation_products_kernel,
        _correlation_products_examples,
    ),
    KernelRow("gram", gram_reference, gram, _gram_examples),
    KernelRow("misfit_design", misfit_design, _misfit_design_kernel, _misfit_design_examples),
    KernelRow(
        "squared_gains_dot",
        _squared_gains_dot_reference,
        _squared_gains_dot_kernel,
        _squared_gains_dot_examples,
    ),
    KernelRow(
        "best_of_tiles",
        PowerScan._best_of_tiles_reference,
        PowerScan._best_of_tiles_kernel,
        _best_of_tiles_examples,
        rtol=0.0,
    ),
)
