"""Locality in large rooms: each terminal sees only the LEDs of its own footprint.

In a large hall (10^6 grid points, 1024 LEDs) a receiver at the grid's height sees an LED only
within a horizontal radius ``R = (z_led - z) tan(FOV)`` of it, so a terminal's own amplitudes
pin it to the neighbourhood of its strongest LED: the terminal lies within ``R`` of that LED
(it sees it), and so do the grid points whose fingerprint resembles its amplitudes. Scoring
only those points (a coarse lattice over the disc's bounding box, then every grid point
around the best lattice points) finds the same starting points as scoring the whole grid,
at a cost independent of the room's size. Private: callers validate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..._kernels import dispatch
from ...channel import channel_gains
from ...fingerprints import Fingerprint
from ...layout import Layout
from ...typing import FloatArray, IntArray
from ._compiled import scan as compiled_scan
from .channel import ChannelKernel
from .terminals import starting_cells

__all__ = ["PowerScan", "TerminalWindows"]

# Lattice points per footprint radius in the coarse pass (the fine pass then scores every
# grid point within one lattice spacing of the best few).
_LATTICE_PER_RADIUS = 12
# Best lattice points whose neighbourhoods are scored at full resolution.
_COARSE_BEST = 4
# Power scans: tiles per footprint radius, and the most tiles scored before scoring all.
_TILES_PER_RADIUS = 8
_FIRST_TILES = 8
_SORTED_TILES = 512
_MAX_TILES = 4096


@dataclass(frozen=True)
class TerminalWindows:
    """Candidate grid points and nearby LEDs of a terminal, around its strongest LED.

    Made by :meth:`build` (``lowest_height``: the lowest receiver height the solver admits,
    where a footprint is widest).

    Attributes
    ----------
    fingerprint : Fingerprint
    radius_cells : int
        The footprint radius (largest over the LEDs) in grid steps, rounded up, plus one.
    stride : int
        Grid steps between coarse lattice points.
    gains_by_cell : scipy.sparse.csr_array of shape (N, M)
        ``G^T``.
    led_xy : ndarray of shape (M, 2)
        LED positions, metres.
    """

    fingerprint: Fingerprint
    radius_cells: int
    stride: int
    gains_by_cell: sp.csr_array
    led_xy: FloatArray
    _kernels: dict[tuple[int, float], tuple[ChannelKernel, IntArray]] = field(
        default_factory=dict, compare=False, repr=False
    )

    @classmethod
    def build(cls, fingerprint: Fingerprint, lowest_height: float) -> TerminalWindows | None:
        """The windows of a room, or None when a receiver sees the whole room (FOV 90
        degrees) or the room has diffuse reflections (every LED reaches every point)."""
        layout = fingerprint.layout
        fov = layout.receiver.fov_deg
        if fov >= 90.0 or layout.room.reflectance is not None:
            return None
        drop = float(layout.led_positions[:, 2].max()) - lowest_height
        radius = drop * math.tan(math.radians(fov))
        step = layout.grid.step
        radius_cells = math.ceil(radius / step) + 1
        stride = max(1, radius_cells // _LATTICE_PER_RADIUS)
        # Rows are grid points (G^T, shared with the correlation operator): one row gathers
        # a point's few nonzero scaled gains.
        by_cell = fingerprint.correlation_operator().gains_by_cell
        return cls(fingerprint, radius_cells, stride, by_cell, layout.led_positions[:, :2])

    def is_useful(self) -> bool:
        """True when a window is much smaller than the room (else scoring everything is as
        cheap)."""
        layout = self.fingerprint.layout
        side = 2 * self.radius_cells + 1
        return side * side * 4 < layout.n_cells

    def candidates(self, amplitudes: FloatArray) -> tuple[IntArray, FloatArray]:
        """Grid points near the terminal's strongest LED and their scores.

        Parameters
        ----------
        amplitudes : ndarray of shape (M,)
            The terminal's amplitudes (any positive scale).

        Returns
        -------
        cells : ndarray of shape (n,)
            Column indices j.
        scores : ndarray of shape (n,)
            ``(g_j . a)^2 / ||g_j||^2`` where ``g_j . a > 0``, else 0 (the whole-grid
            score, restricted to these points; ``g_j = diag(x) h_j``).
        """
        layout = self.fingerprint.layout
        n_x, n_y = layout.n_x, layout.n_y
        values = np.asarray(amplitudes, dtype=np.float64)
        brightest = int(np.argmax(values))
        led = layout.leds[brightest]
        step = layout.grid.step
        centre_x, centre_y = int(led.x / step), int(led.y / step)
        low_x, high_x = (
            max(0, centre_x - self.radius_cells),
            min(n_x, centre_x + self.radius_cells + 1),
        )
        low_y, high_y = (
            max(0, centre_y - self.radius_cells),
            min(n_y, centre_y + self.radius_cells + 1),
        )
        half = self.stride // 2
        coarse_x = np.arange(low_x + half, high_x, self.stride)
        coarse_y = np.arange(low_y + half, high_y, self.stride)
        coarse = (coarse_x[:, None] * n_y + coarse_y[None, :]).ravel()
        coarse_scores = self._scores(coarse, values)
        if self.stride == 1:
            return coarse, coarse_scores
        best = coarse[np.argsort(coarse_scores)[::-1][:_COARSE_BEST]]
        offsets = np.arange(-self.stride, self.stride + 1)
        fine: list[IntArray] = []
        for cell in best:
            ix, iy = divmod(int(cell), n_y)
            xs = offsets[(ix + offsets >= 0) & (ix + offsets < n_x)] + ix
            ys = offsets[(iy + offsets >= 0) & (iy + offsets < n_y)] + iy
            fine.append((xs[:, None] * n_y + ys[None, :]).ravel())
        cells = np.unique(np.concatenate([coarse, *fine]))
        return cells, self._scores(cells, values)

    def near_kernel(self, amplitudes: FloatArray, scale: float) -> tuple[ChannelKernel, IntArray]:
        """A channel kernel of the LEDs near the terminal's strongest LED, and their indices.

        They are the LEDs within twice the footprint radius of it (plus one step): all that
        an upright receiver anywhere within the footprint can see. Kept per strongest LED.
        """
        brightest = int(np.argmax(amplitudes))
        key = (brightest, scale)
        known = self._kernels.get(key)
        if known is not None:
            return known
        layout = self.fingerprint.layout
        xy = self.led_xy
        reach = (2 * self.radius_cells + 1) * layout.grid.step
        inside = np.flatnonzero(np.hypot(*(xy - xy[brightest]).T) <= reach)
        near = Layout(
            room=layout.room,
            grid=layout.grid,
            leds=tuple(layout.leds[int(i)] for i in inside),
            receiver=layout.receiver,
        )
        made = (ChannelKernel(near, scale), inside)
        self._kernels[key] = made
        return made

    def _scores(self, cells: IntArray, amplitudes: FloatArray) -> FloatArray:
        rows = self.gains_by_cell[cells]
        correlation = np.asarray(rows @ amplitudes)
        energy = np.asarray(rows.multiply(rows).sum(axis=1)).ravel()
        positive = (correlation > 0.0) & (energy > 0.0)
        return np.where(positive, correlation**2 / np.where(positive, energy, 1.0), 0.0)

    def starting_cells(
        self, amplitudes: FloatArray, centres: FloatArray, min_distance_m: float
    ) -> list[int]:
        """:func:`.gridless.terminals.starting_cells` over :meth:`candidates` (grid indices)."""
        cells, scores = self.candidates(amplitudes)
        chosen = starting_cells(scores, centres[cells], min_distance_m)
        return [int(cells[index]) for index in chosen]


@dataclass(frozen=True)
class PowerScan:
    """The exact best grid point of a power-model insertion scan, without scoring all N.

    The scan's score of grid point j is ``2 w <g_j^2, r> - w^2 c ||g_j^2||^2`` (plain metric,
    ``c`` the squared weight). Grid points are grouped into square tiles; for each tile and
    LED, ``B[t, i]`` bounds ``g_ij^2`` over the tile (the gain at the tile's point nearest to
    the LED: a line-of-sight gain only falls with the horizontal distance), so
    ``2 w B r^+ - w^2 c min_t ||g_j^2||^2`` bounds every score in tile t. Tiles are scored
    exactly, best bound first, until the next bound is below the best score found: the
    answer is the whole-grid ``argmax`` (ties to the lowest index, as ``numpy.argmax``), with
    the same floating-point operations for the points scored. Private: callers validate.
    """

    n_y: int
    n_x: int
    tile: int
    inverse_scale: float
    bounds: sp.csr_array
    min_fourth: FloatArray
    fourth_sums: FloatArray
    gains_by_cell: sp.csr_array

    @classmethod
    def build(
        cls, fingerprint: Fingerprint, scale: float, fourth_sums: FloatArray
    ) -> PowerScan | None:
        """The scan of a room whose H is line of sight only (None otherwise, or when tiles
        would not be much smaller than the room). A survey's gain map scales H beyond the
        line-of-sight bounds the tiles are scored by: no scan then either."""
        layout = fingerprint.layout
        fov = layout.receiver.fov_deg
        if fov >= 90.0 or layout.room.reflectance is not None or layout.gain_map is not None:
            return None
        step, n_x, n_y = layout.grid.step, layout.n_x, layout.n_y
        drop = float(layout.led_positions[:, 2].max()) - layout.grid.receiver_height
        reach = drop * math.tan(math.radians(fov)) + step
        tile = max(2, math.ceil(reach / step) // _TILES_PER_RADIUS)
        n_tx, n_ty = -(-n_x // tile), -(-n_y // tile)
        if n_tx * n_ty < 64:
            return None
        inverse_scale = 1.0 / scale
        rows: list[IntArray] = []
        cols: list[IntArray] = []
        vals: list[FloatArray] = []
        span = tile * step
        for index, led in enumerate(layout.leds):
            tx = np.arange(
                max(0, math.floor((led.x - reach) / span) - 1),
                min(n_tx, math.floor((led.x + reach) / span) + 2),
            )
            ty = np.arange(
                max(0, math.floor((led.y - reach) / span) - 1),
                min(n_ty, math.floor((led.y + reach) / span) + 2),
            )
            # Nearest cell centre of each tile to the LED (centres span the tile's cells).
            low_x = (tx * tile + 0.5) * step
            high_x = (np.minimum((tx + 1) * tile, n_x) - 0.5) * step
            low_y = (ty * tile + 0.5) * step
            high_y = (np.minimum((ty + 1) * tile, n_y) - 0.5) * step
            near_x = np.clip(led.x, low_x, high_x)
            near_y = np.clip(led.y, low_y, high_y)
            points = np.column_stack((np.repeat(near_x, ty.shape[0]), np.tile(near_y, tx.shape[0])))
            single = Layout(
                room=layout.room, grid=layout.grid, leds=(led,), receiver=layout.receiver
            )
            gains = channel_gains(single, points)[0] * led.pilot_amplitude * inverse_scale
            keep = gains > 0
            # A margin over the rounding of the grid's own (identically computed) gains.
            vals.append((gains[keep] ** 2) * (1.0 + 1e-9))
            cols.append(np.full(int(keep.sum()), index, dtype=np.intp))
            rows.append((np.repeat(tx, ty.shape[0]) * n_ty + np.tile(ty, tx.shape[0]))[keep])
        bounds = sp.csr_array(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(n_tx * n_ty, layout.n_leds),
        )
        padded = np.full((n_tx * tile, n_ty * tile), np.inf)
        padded[:n_x, :n_y] = fourth_sums.reshape(n_x, n_y)
        min_fourth = padded.reshape(n_tx, tile, n_ty, tile).min(axis=(1, 3)).ravel()
        by_cell = fingerprint.correlation_operator().gains_by_cell
        return cls(n_y, n_x, tile, inverse_scale, bounds, min_fourth, fourth_sums, by_cell)

    def best(
        self, residual: FloatArray, weight: float, norm_scale: float
    ) -> tuple[int, float, float] | None:
        """``(j, score_j, norm_j)`` of the best grid point, or None when more than
        :data:`_MAX_TILES` tiles would have to be scored (the caller then scores all).

        ``norm_j = norm_scale * ||g_j^2||^2`` and ``score_j = 2 w num_j - w^2 norm_j`` with
        ``num_j = <g_j^2, residual>``.
        """
        positive = np.maximum(residual, 0.0)
        upper = (2.0 * weight * (self.bounds @ positive)) * (1.0 + 1e-9) - (
            weight**2 * norm_scale * self.min_fourth
        ) * (1.0 - 1e-9)
        # The best few tiles in order (a partial sort); all of them only when those are
        # not enough (rare).
        head = min(_SORTED_TILES, upper.shape[0])
        order = np.argpartition(-upper, head - 1)[:head]
        order = order[np.argsort(-upper[order], kind="stable")]
        best_cell, best_score, best_norm = -1, -math.inf, 0.0
        done, batch = 0, _FIRST_TILES
        while done < upper.shape[0]:
            if done == order.shape[0]:
                rest = np.argsort(-upper, kind="stable")
                order = np.concatenate((order, rest[~np.isin(rest, order)]))
            if upper[order[done]] < best_score:
                break
            if done >= _MAX_TILES:
                return None
            tiles = order[done : done + batch]
            done += tiles.shape[0]
            batch *= 2
            cell, score, norm = dispatch(best_of_tiles_kernel, best_of_tiles_reference)(
                self, tiles, residual, weight, norm_scale
            )
            if score > best_score or (score == best_score and cell < best_cell):
                best_cell, best_score, best_norm = cell, score, norm
        return best_cell, best_score, best_norm

    def _cells(self, tiles: IntArray) -> IntArray:
        """Grid indices of the cells of ``tiles`` (tile ``t = tx * n_ty + ty``)."""
        n_ty = -(-self.n_y // self.tile)
        tx, ty = np.divmod(tiles, n_ty)
        offsets = np.arange(self.tile)
        xs = tx[:, None, None] * self.tile + offsets[None, :, None]
        ys = ty[:, None, None] * self.tile + offsets[None, None, :]
        inside = (xs < self.n_x) & (ys < self.n_y)
        xs, ys = np.broadcast_arrays(xs, ys)
        return np.asarray((xs * self.n_y + ys)[inside])


def best_of_tiles_kernel(
    scan: PowerScan, tiles: IntArray, residual: FloatArray, weight: float, norm_scale: float
) -> tuple[int, float, float]:
    """:func:`best_of_tiles_reference` in one compiled call."""
    by_cell = scan.gains_by_cell
    cell, score, norm = compiled_scan.best_of_tiles_kernel(
        np.ascontiguousarray(tiles, dtype=np.int64),
        (scan.n_x, scan.n_y, scan.tile),
        (by_cell.indptr, by_cell.indices, by_cell.data),
        scan.inverse_scale,
        np.ascontiguousarray(residual, dtype=np.float64),
        scan.fourth_sums,
        (2.0 * weight, weight**2, norm_scale),
    )
    return int(cell), float(score), float(norm)


def best_of_tiles_reference(
    scan: PowerScan, tiles: IntArray, residual: FloatArray, weight: float, norm_scale: float
) -> tuple[int, float, float]:
    """``(j, score_j, norm_j)`` of the best grid point of ``tiles`` of ``scan`` (ties to the
    lowest j), in NumPy."""
    cells = scan._cells(tiles)
    rows = scan.gains_by_cell[cells]
    # The same operations as H^2 = (G / scale)^2 in the solver, row by row.
    squared = sp.csr_array(
        ((rows.data * scan.inverse_scale) ** 2, rows.indices, rows.indptr),
        shape=rows.shape,
    )
    num = np.asarray(squared @ residual)
    norms = norm_scale * scan.fourth_sums[cells]
    scores = 2.0 * weight * num - weight**2 * norms
    score = float(np.max(scores))
    tied = scores == score
    cell = int(np.min(cells[tied]))
    return cell, score, float(norms[cells == cell][0])


def squared_gains_dot(
    gains_by_cell: sp.csr_array, inverse_scale: float, vector: FloatArray, fourth: bool
) -> FloatArray:
    """``sum_i (g_ij / scale)^2 v_i`` (``fourth``: ``(g_ij / scale)^4 v_i``) for every grid
    point j, shape (N,), from ``G^T`` (``gains_by_cell``, N x M): the power model's scans of a
    large room, without a squared copy of G of their own (the same numbers as
    ``((G / scale)^2)^T @ v``: each point's LEDs summed in increasing order)."""
    return np.asarray(
        dispatch(squared_gains_dot_kernel, squared_gains_dot_reference)(
            gains_by_cell, inverse_scale, vector, fourth
        )
    )


def squared_gains_dot_kernel(
    gains_by_cell: sp.csr_array, inverse_scale: float, vector: FloatArray, fourth: bool
) -> FloatArray:
    """:func:`squared_gains_dot_reference` in one compiled call."""
    return np.asarray(
        compiled_scan.squared_gains_dot_kernel(
            (gains_by_cell.indptr, gains_by_cell.indices, gains_by_cell.data),
            inverse_scale,
            np.ascontiguousarray(vector, dtype=np.float64),
            fourth,
        )
    )


def squared_gains_dot_reference(
    gains_by_cell: sp.csr_array, inverse_scale: float, vector: FloatArray, fourth: bool
) -> FloatArray:
    """:func:`squared_gains_dot` in NumPy (a transient squared copy of ``G^T``)."""
    squared = (gains_by_cell.data * inverse_scale) ** 2
    if fourth:
        squared = squared**2
    rows = sp.csr_array(
        (squared, gains_by_cell.indices, gains_by_cell.indptr), shape=gains_by_cell.shape
    )
    return np.asarray(rows @ np.asarray(vector, dtype=np.float64))
