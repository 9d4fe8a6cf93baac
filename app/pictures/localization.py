"""Estimates against the truth, like the paper's Fig. 3."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from app.vlp.errors import MeasurementError
from app.vlp.layout import Layout
from app.vlp.typing import FloatArray, IntArray

from ._render import draw_grid, draw_leds, draw_room, new_figure, png_bytes

__all__ = ["localization_png", "match_estimates"]


def match_estimates(estimates: FloatArray, truth: FloatArray) -> tuple[IntArray, IntArray]:
    """Hungarian matching of estimates to true positions by Euclidean distance.

    Parameters
    ----------
    estimates : ndarray of shape (K_est, 2), metres
    truth : ndarray of shape (K_true, 2), metres

    Returns
    -------
    estimate_rows, truth_rows : ndarray of shape (min(K_est, K_true),)
        Matched pairs ``(estimates[estimate_rows[n]], truth[truth_rows[n]])`` minimising the
        summed distance.
    """
    cost = np.linalg.norm(estimates[:, None, :] - truth[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(cost)
    return rows.astype(np.intp), cols.astype(np.intp)


def localization_png(
    layout: Layout,
    estimates: FloatArray,
    truth: FloatArray | None = None,
    *,
    labels: Sequence[str | None] | None = None,
    width_px: int = 800,
    title: str | None = None,
) -> bytes:
    """Estimated positions (and the true ones) on the room plan, as PNG bytes.

    Parameters
    ----------
    layout : Layout
    estimates : ndarray of shape (K, 2), metres
        Estimated target positions.
    truth : ndarray of shape (K_true, 2), metres, default=None
        True positions (red dots); each is joined to its Hungarian-matched estimate.
    labels : sequence of str or None, length K, default=None
        A label per estimate (e.g. the terminal id), drawn next to it.
    width_px : int, default=800
    title : str, default=None
        Defaults to the number of targets and, with ``truth``, the mean matched error.

    Returns
    -------
    png : bytes

    Raises
    ------
    MeasurementError
        On a wrong shape or a non-finite value (``field`` is ``"estimates"``, ``"truth"`` or
        ``"labels"``).

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> png = localization_png(paper_layout(), np.array([[1.0, 1.1]]), np.array([[1.0, 1.0]]),
    ...                        labels=["t1"], width_px=300)
    >>> png.startswith(b"\\x89PNG")
    True
    """
    est = _positions(estimates, "estimates")
    true = None if truth is None else _positions(truth, "truth")
    if labels is not None and len(labels) != est.shape[0]:
        raise MeasurementError(
            f"labels must have one entry per estimate ({est.shape[0]}), got {len(labels)}",
            field="labels",
        )
    figure = new_figure(layout, width_px)
    axes = figure.add_subplot()
    draw_grid(axes, layout, color="0.8")
    draw_leds(axes, layout, footprints=False, labels=False)
    errors_m = np.empty(0)
    if true is not None and est.size and true.size:
        rows, cols = match_estimates(est, true)
        for r, c in zip(rows, cols, strict=True):
            axes.plot(
                [est[r, 0], true[c, 0]],
                [est[r, 1], true[c, 1]],
                color="0.3",
                linewidth=0.9,
                zorder=6,
            )
        axes.plot([], [], color="0.3", linewidth=0.9, label="matched pair")
        errors_m = np.linalg.norm(est[rows] - true[cols], axis=1)
    if true is not None:
        axes.scatter(true[:, 0], true[:, 1], s=30, c="red", zorder=7, label="true position")
    axes.scatter(
        est[:, 0],
        est[:, 1],
        s=70,
        marker="x",
        c="tab:blue",
        linewidths=1.8,
        zorder=8,
        label="estimate",
    )
    if labels is not None:
        offset = 0.015 * max(layout.room.length, layout.room.width)
        for (x, y), label in zip(est, labels, strict=True):
            if label:
                axes.annotate(
                    str(label),
                    (x + offset, y - offset),
                    fontsize="x-small",
                    color="tab:blue",
                    zorder=9,
                    va="top",
                )
    draw_room(axes, layout, title or _default_title(layout, est, true, errors_m))
    figure.legend(loc="outside lower center", ncols=4, fontsize="small", frameon=False)
    return png_bytes(figure)


def _default_title(
    layout: Layout, estimates: FloatArray, truth: FloatArray | None, errors_m: FloatArray
) -> str:
    text = f"{layout.name or 'Room'}: {estimates.shape[0]} estimates"
    if truth is not None:
        text += f", {truth.shape[0]} targets"
    if errors_m.size:
        text += f"; mean error {100.0 * float(errors_m.mean()):.1f} cm"
    return text


def _positions(values: FloatArray, name: str) -> FloatArray:
    array = np.asarray(values, dtype=np.float64)
    if array.size == 0:
        return np.empty((0, 2))
    if array.ndim != 2 or array.shape[1] != 2:
        raise MeasurementError(f"{name} must have shape (K, 2), got {array.shape}", field=name)
    if not np.all(np.isfinite(array)):
        raise MeasurementError(f"{name} must be finite", field=name)
    return array
