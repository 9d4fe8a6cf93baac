"""Fingerprints: the channel matrix H and the dictionaries J and Psi built from it.

``H[i, j] = h_ij`` (M x N), ``J[i, j] = (h_ij x_i)^2`` (paper eq. 13) and Psi's row
``(i, l)``, ``i <= l`` in ``numpy.triu_indices(M)`` order, is ``(h_ij x_i)(h_lj x_l)``
(paper eq. 17, rows reordered). ``H`` is kept sparse: an LED outside a point's field of view
contributes exactly zero, which in a large hall is most pairs. Psi is only materialised
below :data:`PSI_DENSE_LIMIT` entries; above it solvers use :class:`CorrelationOperator`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TypeVar, cast

import numpy as np
import scipy.sparse as sp

from .channel import channel_gains
from .errors import ProblemSizeError
from .layout import Layout
from .operators import CorrelationOperator
from .reflections import ReflectionTable
from .typing import FloatArray, IntArray

__all__ = [
    "DENSE_GAINS_LIMIT",
    "NLOS_RELATIVE_FLOOR",
    "PSI_DENSE_LIMIT",
    "Fingerprint",
    "ProgressCallback",
    "build_fingerprint",
]

# Entries (M * N) up to which H, J and G are also kept dense for fast small solves.
DENSE_GAINS_LIMIT = 4_000_000
# Entries (M(M+1)/2 * N) up to which Psi may be materialised (1.6e8 bytes of float64).
PSI_DENSE_LIMIT = 20_000_000

# Diffuse gains below this fraction of the LED's largest line-of-sight gain are left out of H
# (keeps H sparse in large rooms; far below the noise at any usable SNR).
NLOS_RELATIVE_FLOOR = 1e-4
# Share of the progress reported for the line-of-sight part when reflections follow.
_LOS_SHARE = 0.05
# Grid points interpolated at once from the reflection table (bounds the gather's memory).
_TABLE_CHUNK = 4096

ProgressCallback = Callable[[float], None]
_T = TypeVar("_T")


@dataclass(eq=False)
class Fingerprint:
    """The channel matrix of a layout and the dictionaries derived from it.

    Parameters
    ----------
    layout : Layout
    gains : scipy.sparse.csr_array of shape (M, N)
        ``H``, dimensionless DC gains.

    Notes
    -----
    ``scaled_gains`` is ``G = diag(x) H``: its column ``g_j`` is what one terminal at grid
    point ``j`` receives, so ``J = G ∘ G`` and ``Psi[:, j] = vech(g_j g_j^T)``.
    """

    layout: Layout
    gains: sp.csr_array
    _cache: dict[str, object] = field(default_factory=dict, repr=False)

    @property
    def n_leds(self) -> int:
        """M."""
        return int(self.gains.shape[0])

    @property
    def n_cells(self) -> int:
        """N."""
        return int(self.gains.shape[1])

    @property
    def is_dense(self) -> bool:
        """True when the problem is small enough to keep dense copies of H, G and J."""
        return self.n_leds * self.n_cells <= DENSE_GAINS_LIMIT

    @property
    def pilot_amplitudes(self) -> FloatArray:
        """x, ndarray of shape (M,)."""
        return self.layout.pilot_amplitudes

    def cell_centres(self) -> FloatArray:
        """Every grid point's centre, shape (N, 2) (:meth:`Layout.cell_centres`), made once:
        the solvers of both models read the same array (16 MB in the million-point hall).
        Callers must not write into it."""
        return self._cached("centres", self.layout.cell_centres)

    def scaled_gains(self) -> sp.csr_array:
        """``G = diag(x) H``, sparse of shape (M, N); read-only.

        ``G`` has H's sparsity, so it shares H's index arrays (in the million-point hall they
        are 40 MiB), and with every pilot amplitude 1 it is H's values too.
        """
        return self._cached("G_sparse", self._scale_rows)

    def _scale_rows(self) -> sp.csr_array:
        gains = self.gains
        amplitudes = self.pilot_amplitudes
        if np.all(amplitudes == 1.0):
            values = gains.data
        else:  # each stored h_ij times its row's x_i: the product diag(x) @ H computes
            values = gains.data * np.repeat(amplitudes, np.diff(gains.indptr))
        scaled = sp.csr_array((values, gains.indices, gains.indptr), shape=gains.shape)
        scaled.has_sorted_indices = gains.has_sorted_indices
        return scaled

    def dense_scaled_gains(self) -> FloatArray:
        """``G`` as a dense ndarray of shape (M, N); refused above :data:`DENSE_GAINS_LIMIT`."""
        self._require_dense("G")
        return self._cached("G_dense", lambda: np.asarray(self.scaled_gains().toarray()))

    def dense_gains(self) -> FloatArray:
        """``H`` as a dense ndarray of shape (M, N); refused above :data:`DENSE_GAINS_LIMIT`."""
        self._require_dense("H")
        return self._cached("H_dense", lambda: np.asarray(self.gains.toarray()))

    def power_matrix(self) -> FloatArray | sp.csr_array:
        """``J`` of shape (M, N): dense when small, else sparse (same sparsity as H)."""
        if self.is_dense:
            return self._cached("J_dense", lambda: self.dense_scaled_gains() ** 2)
        return self._cached("J_sparse", lambda: sp.csr_array(self.scaled_gains().power(2)))

    def received_power(self) -> tuple[FloatArray, float]:
        """What the grid points receive: ``sum_i J[i, j]`` for each point j (N,), and the sum
        of all of J.

        The simulation's SNR convention and the scale check read only these sums, so they
        are kept instead of J: a sparse J is as large as H (120 MiB in the million-point
        hall), and only the grid solvers keep it (:meth:`power_matrix`).
        """

        def make() -> tuple[FloatArray, float]:
            power = self.power_matrix() if self.is_dense else self.scaled_gains().power(2)
            return np.asarray(power.sum(axis=0)).ravel(), float(power.sum())

        return self._cached("received_power", make)

    def correlation_operator(self) -> CorrelationOperator:
        """Psi as a matrix-free operator of shape (M(M+1)/2, N)."""
        return self._cached("psi_op", lambda: CorrelationOperator(self.scaled_gains()))

    def correlation_matrix(self) -> FloatArray:
        """Psi materialised, ndarray of shape (M(M+1)/2, N).

        Raises
        ------
        ProblemSizeError
            When it has more than :data:`PSI_DENSE_LIMIT` entries.
        """
        rows = self.n_leds * (self.n_leds + 1) // 2
        if rows * self.n_cells > PSI_DENSE_LIMIT:
            raise ProblemSizeError(
                f"psi would have {rows} x {self.n_cells} = {rows * self.n_cells} entries, more "
                f"than the limit {PSI_DENSE_LIMIT}; use H and the pilot amplitudes instead",
                field="psi",
            )

        def build() -> FloatArray:
            g = self.dense_scaled_gains() if self.is_dense else self.scaled_gains().toarray()
            upper, lower = np.triu_indices(self.n_leds)
            return np.asarray(g[upper] * g[lower])

        return self._cached("psi_dense", build)

    def reflection_table(self) -> ReflectionTable | None:
        """What the model adds to the line-of-sight gains off the grid: the diffuse gains
        and the calibrated ``gain_map``'s part (:class:`ReflectionTable`), or None without
        ``room.reflectance`` or ``gain_map``. Built on first use unless
        :func:`build_fingerprint` made it or :meth:`attach_reflection_table` supplied a
        stored one."""
        if self.layout.room.reflectance is None and self.layout.gain_map is None:
            return None
        return self._cached("reflection_table", lambda: ReflectionTable.build(self.layout))

    def attach_reflection_table(self, table: ReflectionTable) -> None:
        """Use ``table`` (e.g. loaded with :meth:`ReflectionTable.from_arrays`) from now on."""
        self._cache["reflection_table"] = table

    def _require_dense(self, name: str) -> None:
        if not self.is_dense:
            raise ProblemSizeError(
                f"{name} is {self.n_leds} x {self.n_cells}, above the dense limit "
                f"{DENSE_GAINS_LIMIT} entries; use the sparse form",
                field=name,
            )

    def _cached(self, key: str, make: Callable[[], _T]) -> _T:
        if key not in self._cache:
            self._cache[key] = make()
        return cast(_T, self._cache[key])


def build_fingerprint(
    layout: Layout,
    *,
    progress: ProgressCallback | None = None,
    max_cells: int | None = None,
) -> Fingerprint:
    """Compute H for every LED and grid point, one LED (a chunk of rows) at a time.

    Only the grid points inside an LED's field-of-view disc are evaluated, so the cost and
    memory are proportional to the number of nonzero gains, not to M * N. With
    ``room.reflectance`` H is the total gain: the first-bounce diffuse gains, interpolated
    from a :class:`~app.vlp.reflections.ReflectionTable` (kept with the fingerprint for
    off-grid use), are added, except those below :data:`NLOS_RELATIVE_FLOOR` times the LED's
    largest line-of-sight gain.

    Parameters
    ----------
    layout : Layout
    progress : callable, default=None
        Called with the fraction done (0..1) after each LED.
    max_cells : int, default=None
        Refuse layouts with more grid points than this.

    Returns
    -------
    Fingerprint

    Raises
    ------
    ProblemSizeError
        When ``layout.n_cells > max_cells``, or the room is too large for a reflection table.
    """
    if max_cells is not None and layout.n_cells > max_cells:
        raise ProblemSizeError(
            f"layout has {layout.n_cells} grid points, more than the limit {max_cells}",
            field="grid.step",
        )
    step, n_x, n_y = layout.grid.step, layout.n_x, layout.n_y
    tan_fov = (
        math.tan(math.radians(layout.receiver.fov_deg))
        if layout.receiver.fov_deg < 90
        else math.inf
    )
    reflecting = layout.room.reflectance is not None
    if reflecting:
        ReflectionTable.check_size(layout)  # refuse before the line-of-sight work
    los_progress = progress
    if progress is not None and reflecting:
        outer = progress

        def los_progress(fraction: float) -> None:
            outer(_LOS_SHARE * fraction)

    # One LED is one row of H, and its cells come in increasing order (ix outer, iy inner):
    # the CSR arrays are assembled directly, with no COO triplets to convert and sort (the
    # hall's H has 10^7 nonzeros: each extra copy is 10^8 bytes of peak memory).
    index_type = np.int32 if layout.n_cells < np.iinfo(np.int32).max else np.int64
    cols: list[IntArray] = []
    vals: list[FloatArray] = []
    counts = np.zeros(layout.n_leds + 1, dtype=np.int64)
    for i, led in enumerate(layout.leds):
        radius = (led.z - layout.grid.receiver_height) * tan_fov + step
        ix = _cell_range(led.x, radius, step, n_x)
        iy = _cell_range(led.y, radius, step, n_y)
        cells = (ix[:, None] * n_y + iy[None, :]).ravel()
        single = Layout(room=layout.room, grid=layout.grid, leds=(led,), receiver=layout.receiver)
        gains = channel_gains(single, layout.cell_centres(cells))[0]
        keep = gains > 0
        cols.append(cells[keep].astype(index_type))
        vals.append(gains[keep])
        counts[i + 1] = cols[-1].shape[0]
        if los_progress is not None:
            los_progress((i + 1) / layout.n_leds)
    indptr = np.cumsum(counts)
    if indptr[-1] < np.iinfo(index_type).max:
        indptr = indptr.astype(index_type)
    indices = np.concatenate(cols)
    del cols
    data = np.concatenate(vals)
    del vals
    matrix = sp.csr_array((data, indices, indptr), shape=(layout.n_leds, layout.n_cells))
    matrix.has_sorted_indices = True
    if not reflecting:
        return Fingerprint(layout=layout, gains=_with_gain_map(layout, matrix))
    table_progress = None
    if progress is not None:
        outer_progress = progress

        def table_progress(fraction: float) -> None:
            outer_progress(_LOS_SHARE + (1.0 - _LOS_SHARE) * fraction)

    table = ReflectionTable.build(replace(layout, gain_map=None), progress=table_progress)
    gains = _with_gain_map(layout, _with_reflections(layout, matrix, table))
    fingerprint = Fingerprint(layout=layout, gains=gains)
    fingerprint.attach_reflection_table(table.with_gain_map(layout))
    return fingerprint


def _with_gain_map(layout: Layout, gains: sp.csr_array) -> sp.csr_array:
    """``gains`` with every LED's row times its ``gain_map`` factor at the grid centres."""
    if layout.gain_map is None:
        return gains
    out = gains.copy()
    for i in range(layout.n_leds):
        start, stop = int(out.indptr[i]), int(out.indptr[i + 1])
        for first in range(start, stop, _TABLE_CHUNK):
            last = min(first + _TABLE_CHUNK, stop)
            centres = layout.cell_centres(np.asarray(out.indices[first:last], dtype=np.intp))
            factors = layout.gain_map.log_factors(centres, led=i)[0]
            out.data[first:last] *= np.exp(factors)
    return out


def _with_reflections(layout: Layout, los: sp.csr_array, table: ReflectionTable) -> sp.csr_array:
    """``los`` plus the table's diffuse gains at the grid centres, small ones left out."""
    floor = NLOS_RELATIVE_FLOOR * np.asarray(los.max(axis=1).toarray()).ravel()
    rows: list[IntArray] = []
    cols: list[IntArray] = []
    vals: list[FloatArray] = []
    for start in range(0, layout.n_cells, _TABLE_CHUNK):
        cells = np.arange(start, min(start + _TABLE_CHUNK, layout.n_cells), dtype=np.intp)
        centres = layout.cell_centres(cells)
        diffuse = table.evaluate(centres[:, 0], centres[:, 1])[0]  # (M, chunk)
        led, column = np.nonzero(diffuse >= floor[:, None])
        rows.append(led)
        cols.append(cells[column])
        vals.append(diffuse[led, column])
    nlos = sp.csr_array(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=los.shape
    )
    total = sp.csr_array(los + nlos)
    total.sort_indices()
    return total


def _cell_range(centre: float, radius: float, step: float, count: int) -> IntArray:
    if not math.isfinite(radius):  # a 90-degree field of view sees the whole floor
        return np.arange(count, dtype=np.int64)
    low = max(0, math.floor((centre - radius) / step))
    high = min(count, math.ceil((centre + radius) / step) + 1)
    return np.arange(low, high, dtype=np.int64)
