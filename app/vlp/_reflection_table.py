"""The diffuse gains precomputed on nodes and interpolated, with gradients, anywhere.

The gridless solver evaluates the channel at arbitrary points hundreds of times per solve;
:func:`~app.vlp.reflections.diffuse_gains` is far too slow for that, but the reflected part is
smooth, so it is tabulated once per layout (upward receivers) and interpolated with a
tensor-product cubic Hermite interpolant whose node slopes are finite differences of the node
values (C1, with exact gradients of the interpolant).

Nodes: along x and y, the room's walls and interior nodes at most :data:`NODE_SPACING_M` apart,
plus nodes :data:`WALL_NODE_OFFSETS_M` from each wall, where the gains change fastest (their
scale there is the distance to the wall). With ``grid.receiver_height_sd > 0`` the heights
``receiver_height +- 3 sd`` are covered by at least four levels at most
:data:`HEIGHT_SPACING_M` apart. ``docs/results/reflections.md`` has the measured interpolation
error.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from ._diffuse import diffuse_gains
from .channel import los_gains
from .errors import GeometryError, ProblemSizeError
from .layout import Layout
from .typing import FloatArray, IntArray

__all__ = [
    "HEIGHT_SPACING_M",
    "MAX_TABLE_ENTRIES",
    "NODE_SPACING_M",
    "WALL_NODE_OFFSETS_M",
    "ReflectionTable",
]

NODE_SPACING_M = 0.2
WALL_NODE_OFFSETS_M = (0.02, 0.05, 0.1)
HEIGHT_SPACING_M = 0.1
# Receivers on a wall's line are evaluated this far inside (the limit from inside the room).
_WALL_INSET_M = 1e-4
# Coefficients (nodes x LEDs x 4 or 8 Hermite terms) above which a table is refused: 8e6
# float64 = 64 MB, and a build of minutes, not hours (its cost grows like nodes x LEDs x
# wall length). Hall-scale rooms exceed it (docs/explanation/reflections.md, "The reflection
# table").
MAX_TABLE_ENTRIES = 8_000_000
# Points evaluated per call of diffuse_gains while building (progress granularity).
_BUILD_CHUNK = 64

ProgressCallback = Callable[[float], None]


@dataclass(frozen=True, eq=False)
class ReflectionTable:
    """Diffuse gains of every LED on a node grid, with Hermite coefficients.

    Attributes
    ----------
    x_nodes, y_nodes : ndarray of shape (n_x,), (n_y,)
        Node coordinates, metres, from 0 to the room's length / width.
    z_nodes : ndarray of shape (n_z,)
        Receiver heights, metres; one level when the layout has no height spread.
    coefficients : ndarray of shape (n_x * n_y * n_z, n_terms, M)
        Per node the value and its finite-difference derivatives in Hermite order
        (``f, f_y, f_x, f_xy`` in 2-D; ``f, f_z, f_y, f_yz, f_x, f_xz, f_xy, f_xyz`` in 3-D).
    receiver_height : float
        The layout's ``grid.receiver_height``, metres: the height evaluated when none is given.
    """

    x_nodes: FloatArray
    y_nodes: FloatArray
    z_nodes: FloatArray
    coefficients: FloatArray
    receiver_height: float
    _plan: _EvaluationPlan = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_plan", _EvaluationPlan.of(self))

    @property
    def n_leds(self) -> int:
        """M."""
        return int(self.coefficients.shape[2])

    @property
    def has_heights(self) -> bool:
        """True when the table spans several receiver heights (3-D interpolation)."""
        return self.z_nodes.size > 1

    @classmethod
    def build(cls, layout: Layout, *, progress: ProgressCallback | None = None) -> ReflectionTable:
        """Tabulate :func:`diffuse_gains` (upward receivers) for ``layout``, and with its
        ``gain_map`` what that map adds (:meth:`with_gain_map`).

        Parameters
        ----------
        layout : Layout
            Its ``room.reflectance`` is used (all diffuse gains 0 when None).
        progress : callable, default=None
            Called with the fraction done (0..1) as nodes are evaluated.

        Returns
        -------
        ReflectionTable

        Raises
        ------
        ProblemSizeError
            When the table would hold more than :data:`MAX_TABLE_ENTRIES` coefficients.
        """
        x_nodes, y_nodes, z_nodes = cls.check_size(layout)
        points = _node_points(layout, x_nodes, y_nodes, z_nodes)
        values = np.zeros((layout.n_leds, points.shape[0]))
        if layout.room.reflectance is not None:
            for start in range(0, points.shape[0], _BUILD_CHUNK):
                chunk = slice(start, start + _BUILD_CHUNK)
                values[:, chunk] = diffuse_gains(layout, points[chunk])
                if progress is not None:
                    progress(min(1.0, (start + _BUILD_CHUNK) / points.shape[0]))
        shaped = values.T.reshape(x_nodes.size, y_nodes.size, z_nodes.size, layout.n_leds)
        table = cls(
            x_nodes,
            y_nodes,
            z_nodes,
            _hermite_coefficients(shaped, x_nodes, y_nodes, z_nodes),
            layout.grid.receiver_height,
        )
        return table if layout.gain_map is None else table.with_gain_map(layout)

    def with_gain_map(self, layout: Layout) -> ReflectionTable:
        """This table of diffuse gains ``d`` with what ``layout.gain_map`` adds to the model:
        ``(l + d) exp(g) - l`` at every node, ``l`` the line-of-sight gain, so that the
        line-of-sight gain plus the table is the whole mapped gain."""
        if layout.gain_map is None:
            return self
        x_nodes, y_nodes, z_nodes = self.x_nodes, self.y_nodes, self.z_nodes
        points = _node_points(layout, x_nodes, y_nodes, z_nodes)
        diffuse = self.coefficients[:, 0, :].T  # the node values, (M, nodes)
        los = los_gains(layout, points)
        values = (los + diffuse) * np.exp(layout.gain_map.log_factors(points[:, :2])) - los
        shaped = values.T.reshape(x_nodes.size, y_nodes.size, z_nodes.size, layout.n_leds)
        return ReflectionTable(
            x_nodes,
            y_nodes,
            z_nodes,
            _hermite_coefficients(shaped, x_nodes, y_nodes, z_nodes),
            self.receiver_height,
        )

    @staticmethod
    def check_size(layout: Layout) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The nodes a table for ``layout`` would have, after checking it fits the limit.

        Raises
        ------
        ProblemSizeError
            When the table would hold more than :data:`MAX_TABLE_ENTRIES` coefficients.
        """
        x_nodes = _axis_nodes(layout.room.length)
        y_nodes = _axis_nodes(layout.room.width)
        z_nodes = _height_nodes(layout)
        n_terms = 8 if z_nodes.size > 1 else 4
        entries = x_nodes.size * y_nodes.size * z_nodes.size * n_terms * layout.n_leds
        if entries > MAX_TABLE_ENTRIES:
            raise ProblemSizeError(
                f"a reflection table for this room needs {entries} coefficients, more than the "
                f"limit {MAX_TABLE_ENTRIES}; reflections are supported up to rooms of a few "
                "hundred square metres",
                field="room.reflectance",
            )
        return x_nodes, y_nodes, z_nodes

    def evaluate(
        self, xs: FloatArray, ys: FloatArray, zs: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Interpolated diffuse gains and their gradients at receiver points.

        Parameters
        ----------
        xs, ys : ndarray of shape (P,)
            Receiver coordinates, metres; clipped into the room (no extrapolation).
        zs : ndarray of shape (P,), default=None
            Receiver heights, metres, clipped into the table's height range; None means the
            table's receiver height. Ignored by a single-height table (its ``d/dz`` is 0).

        Returns
        -------
        gains, d_dx, d_dy, d_dz : ndarrays of shape (M, P)
            Gains and their derivatives (per metre) of the interpolant.
        """
        x = np.asarray(xs, dtype=np.float64).ravel()
        y = np.asarray(ys, dtype=np.float64).ravel()
        if x.shape != y.shape:
            raise GeometryError(
                f"xs and ys must have the same length, got {x.shape} and {y.shape}", field="ys"
            )
        plan = self._plan
        if self.has_heights:
            z = np.full_like(x, self.receiver_height) if zs is None else np.asarray(zs, np.float64)
            coords = np.concatenate((x, y, z.ravel())).reshape(3, x.size)
        else:
            coords = np.concatenate((x, y)).reshape(2, x.size)
        # All axes at once: each axis's nodes are shifted apart on one line (plan.shifts), so
        # one searchsorted and one batched matmul give every axis's cell and Hermite weights.
        coords = np.minimum(np.maximum(coords, plan.lows), plan.highs) + plan.shifts
        flat_coords = coords.ravel()
        cells = np.searchsorted(plan.nodes, flat_coords, side="right") - 1
        low = plan.nodes[cells]
        t = (flat_coords - low) / (plan.nodes[cells + 1] - low)
        t2 = t * t
        powers = np.concatenate((np.ones_like(t), t, t2, t2 * t)).reshape(4, t.size)
        basis = (powers.T @ _UNIT_BASIS) * plan.scales[cells]
        basis = basis.reshape(coords.shape[0], x.size, 2, 4)  # axis, P, value/deriv, 4
        index = (plan.strides @ cells.reshape(coords.shape))[:, None] + plan.offsets
        gathered = self.coefficients.reshape(-1, self.n_leds)[index]  # (P, terms, M)
        # every combination of value / derivative per axis, (P, 2^axes, terms), indexed by
        # the bits (x, y[, z]) "is a derivative", x the highest: value 0, d/dx 2^(axes-1), ...
        if self.has_heights:
            weights = (
                basis[0][:, :, None, None, :, None, None]
                * basis[1][:, None, :, None, None, :, None]
                * basis[2][:, None, None, :, None, None, :]
            ).reshape(x.size, 8, 64)
        else:
            weights = (basis[0][:, :, None, :, None] * basis[1][:, None, :, None, :]).reshape(
                x.size, 4, 16
            )
        result = np.matmul(weights, gathered).transpose(1, 2, 0)  # (combinations, M, P)
        if self.has_heights:
            return result[0], result[4], result[2], result[1]
        return result[0], result[2], result[1], np.zeros((self.n_leds, x.size))

    def to_arrays(self) -> dict[str, FloatArray]:
        """The table as plain arrays (for ``numpy.savez`` and :meth:`from_arrays`)."""
        return {
            "x_nodes": self.x_nodes,
            "y_nodes": self.y_nodes,
            "z_nodes": self.z_nodes,
            "coefficients": self.coefficients,
            "receiver_height": np.array(self.receiver_height),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, FloatArray]) -> ReflectionTable:
        """The table stored by :meth:`to_arrays`."""
        table = cls(
            np.asarray(arrays["x_nodes"], dtype=np.float64),
            np.asarray(arrays["y_nodes"], dtype=np.float64),
            np.asarray(arrays["z_nodes"], dtype=np.float64),
            np.asarray(arrays["coefficients"], dtype=np.float64),
            float(np.asarray(arrays["receiver_height"])),
        )
        nodes = table.x_nodes.size * table.y_nodes.size * table.z_nodes.size
        terms = 8 if table.has_heights else 4
        if table.coefficients.ndim != 3 or table.coefficients.shape[:2] != (nodes, terms):
            raise GeometryError(
                f"coefficients of shape {table.coefficients.shape} do not fit {nodes} nodes "
                f"with {terms} Hermite terms",
                field="coefficients",
            )
        return table


_OFFSETS = np.array([0, 1], dtype=np.intp)
# Basis per output: value, d/dx, d/dy (, d/dz); 0 = the value basis, 1 = its derivative.
_X3, _Y3 = np.array([0, 1, 0]), np.array([0, 0, 1])
# The cubic Hermite basis on a unit cell as polynomials in t (rows: 1, t, t^2, t^3); columns
# (value, d/dt) x (corner 0, 1) x (node value, node slope). On a cell of width w, the slope
# columns of the value basis scale by w and the value columns of the derivative by 1 / w.
_UNIT_BASIS = np.array(
    [
        [1, 0, 0, 0, 0, 1, 0, 0],
        [0, 1, 0, 0, -6, -4, 6, -2],
        [-3, -2, 3, -1, 6, 3, -6, 3],
        [2, 1, -2, 1, 0, 0, 0, 0],
    ],
    dtype=np.float64,
)
_X4, _Y4, _Z4 = np.array([0, 1, 0, 0]), np.array([0, 0, 1, 0]), np.array([0, 0, 0, 1])


def _axis_nodes(extent: float) -> FloatArray:
    count = max(1, math.ceil(extent / NODE_SPACING_M - 1e-9))
    base = np.linspace(0.0, extent, count + 1)
    extra = [
        offset
        for offset in WALL_NODE_OFFSETS_M
        if offset < base[1] and np.min(np.abs(base - offset)) > 0.25 * offset
    ]
    nodes = np.concatenate((base, extra, [extent - offset for offset in extra]))
    return np.unique(nodes)


def _height_nodes(layout: Layout) -> FloatArray:
    grid = layout.grid
    if grid.receiver_height_sd == 0:
        return np.array([grid.receiver_height])
    low = max(0.0, grid.receiver_height - 3.0 * grid.receiver_height_sd)
    high = min(
        layout.room.height - _WALL_INSET_M, grid.receiver_height + 3.0 * grid.receiver_height_sd
    )
    count = max(4, math.ceil((high - low) / HEIGHT_SPACING_M - 1e-9) + 1)
    return np.linspace(low, high, count)


def _slopes(values: FloatArray, nodes: FloatArray, axis: int) -> FloatArray:
    if nodes.size < 2:
        return np.zeros_like(values)
    if nodes.size == 2:
        return np.asarray(np.gradient(values, nodes, axis=axis, edge_order=1))
    return np.asarray(np.gradient(values, nodes, axis=axis, edge_order=2))


def _node_points(
    layout: Layout, x_nodes: FloatArray, y_nodes: FloatArray, z_nodes: FloatArray
) -> FloatArray:
    """(nodes, 3) receiver points of the table's nodes, x major; wall lines just inside."""
    inset_x = np.clip(x_nodes, _WALL_INSET_M, layout.room.length - _WALL_INSET_M)
    inset_y = np.clip(y_nodes, _WALL_INSET_M, layout.room.width - _WALL_INSET_M)
    grid_x, grid_y, grid_z = np.meshgrid(inset_x, inset_y, z_nodes, indexing="ij")
    return np.column_stack((grid_x.ravel(), grid_y.ravel(), grid_z.ravel()))


def _hermite_coefficients(
    values: FloatArray, x_nodes: FloatArray, y_nodes: FloatArray, z_nodes: FloatArray
) -> FloatArray:
    """(n_x, n_y, n_z, M) node values -> (nodes, terms, M) in Hermite order (x major)."""
    f_x = _slopes(values, x_nodes, 0)
    terms_x = [values, f_x]
    terms_xy = [t for base in terms_x for t in (base, _slopes(base, y_nodes, 1))]
    if z_nodes.size > 1:
        terms = [t for base in terms_xy for t in (base, _slopes(base, z_nodes, 2))]
    else:
        terms = terms_xy
    stacked = np.stack(terms, axis=3)  # (n_x, n_y, n_z, terms, M)
    return np.ascontiguousarray(stacked.reshape(-1, len(terms), values.shape[3]))


def _cell_scales(nodes: FloatArray) -> FloatArray:
    """Per cell, the factors of :data:`_UNIT_BASIS`'s columns: (n_cells, 8).

    A single node (one receiver height) has one pseudo-cell whose weights select that node's
    value and give every derivative 0.
    """
    if nodes.size == 1:
        return np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]])
    widths = np.diff(nodes)[:, None]
    ones = np.ones_like(widths)
    return np.hstack((ones, widths, ones, widths, 1 / widths, ones, 1 / widths, ones))


@dataclass(frozen=True)
class _EvaluationPlan:
    """Constants of :meth:`ReflectionTable.evaluate`, computed once per table.

    The axes' nodes are laid end to end on one line, each shifted past the previous one's
    end, with the per-cell Hermite bases in the same order; a point's coordinate on axis
    ``a`` is clamped to ``[lows[a], highs[a]]`` (just inside the last node, so its cell is a
    real one) and shifted by ``shifts[a]``. ``strides @ cells + offsets`` are the flat
    coefficient rows of a point's corners and terms, ordered (cx, kx, cy, ky[, cz, kz]) to
    match the outer product of the axes' weights.
    """

    nodes: FloatArray
    scales: FloatArray
    lows: FloatArray
    highs: FloatArray
    shifts: FloatArray
    strides: IntArray
    offsets: IntArray

    @classmethod
    def of(cls, table: ReflectionTable) -> _EvaluationPlan:
        axes = [table.x_nodes, table.y_nodes] + ([table.z_nodes] if table.has_heights else [])
        nodes, scales, shifts, firsts = [], [], [], []
        start, first = 0.0, 0
        for axis in axes:
            shift = start - axis[0]
            nodes.append(axis + shift)
            # a dummy cell bridging to the next axis (never used: coordinates are clamped)
            scales.append(np.vstack((_cell_scales(axis), np.zeros((1, 8)))))
            shifts.append(shift)
            firsts.append(first)
            start = float(axis[-1] + shift) + 1.0
            first += axis.size
        n_y, n_z = table.y_nodes.size, table.z_nodes.size
        node_strides = [n_y * n_z, n_z] + ([1] if table.has_heights else [])
        n_terms = 2 ** len(axes)
        # row of (node, term) in the flat coefficients = node * n_terms + term; the cell
        # index on the joint line minus the axis's first index is the node index on the axis
        strides = np.array(node_strides) * n_terms
        base = -int(np.dot(strides, firsts))
        term_strides = [2 ** (len(axes) - 1 - a) for a in range(len(axes))]
        offsets = []
        for combo in np.ndindex(*(2, 2) * len(axes)):  # (c0, k0, c1, k1, ...)
            corner = combo[0::2]
            term = combo[1::2]
            offsets.append(
                base + int(np.dot(node_strides, corner)) * n_terms + int(np.dot(term_strides, term))
            )
        lows = np.array([axis[0] for axis in axes])[:, None]
        highs = np.array([axis[-1] - 1e-9 * max(1.0, abs(axis[-1])) for axis in axes])[:, None]
        return cls(
            nodes=np.concatenate(nodes),
            scales=np.concatenate(scales),
            lows=lows,
            highs=highs,
            shifts=np.array(shifts)[:, None],
            strides=strides.astype(np.intp),
            offsets=np.array(offsets, dtype=np.intp),
        )
