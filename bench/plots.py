"""Figures of the accuracy benchmark (matplotlib, Agg backend; never imported by app/)."""

from __future__ import annotations

import argparse
import csv
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from scipy.optimize import linear_sum_assignment

from app.vlp.layout import Layout
from app.vlp.typing import FloatArray

from .rooms import make_room

if TYPE_CHECKING:
    from .results import Summary

__all__ = ["MODEL_LABELS", "fig3", "fig4", "fig4_all", "main", "method_label", "read_summary"]

MODEL_LABELS = {"power": "CSM-VLP", "correlation": "CoCSM-VLP", "-": ""}
_STYLE = {"power": "-.", "correlation": "-", "-": "-"}
_MARKER = {"power": "s", "correlation": "o", "-": "x"}


def method_label(method: str, model: str) -> str:
    """``"CoCSM-VLP / gridless"``, ``"RSS baseline"``."""
    if method == "rss":
        return "RSS baseline"
    return f"{MODEL_LABELS.get(model, model)} / {method}"


def _matched(truth: FloatArray, estimate: FloatArray) -> tuple[FloatArray, FloatArray]:
    cost = np.linalg.norm(truth[:, None, :] - estimate[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(cost)
    return truth[rows], estimate[cols]


def fig3(
    scenes: Sequence[tuple[str, str, FloatArray, FloatArray]], layout: Layout, path: Path
) -> Path:
    """Estimates against truth for one K = 8 scene, one panel per scheme.

    Parameters
    ----------
    scenes : sequence of (method, model, truth (K, 2), estimates (K, 2)), metres
    layout : Layout
        For the room outline, the grid and the LEDs.
    path : Path
        PNG to write.
    """
    ordered = sorted(scenes, key=lambda s: (s[0] == "rss", s[1] != "power", s[0]))
    ncols = 3
    nrows = math.ceil(len(ordered) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 4.2 * nrows), squeeze=False)
    leds = layout.led_positions
    for ax, (method, model, truth, estimate) in zip(axes.ravel(), ordered, strict=False):
        true_m, est_m = _matched(truth, estimate)
        error_cm = 100 * float(np.mean(np.linalg.norm(true_m - est_m, axis=1)))
        for (x0, y0), (x1, y1) in zip(true_m, est_m, strict=True):
            ax.plot([x0, x1], [y0, y1], color="0.4", lw=1)
        ax.scatter(
            leds[:, 0],
            leds[:, 1],
            marker="*",
            s=70,
            c="gold",
            edgecolors="k",
            linewidths=0.5,
            label="LED",
            zorder=3,
        )
        ax.scatter(true_m[:, 0], true_m[:, 1], s=28, c="red", label="truth", zorder=4)
        ax.scatter(
            est_m[:, 0],
            est_m[:, 1],
            s=36,
            facecolors="none",
            edgecolors="tab:blue",
            label="estimate",
            zorder=5,
        )
        ax.set_xlim(0, layout.room.length)
        ax.set_ylim(0, layout.room.width)
        ax.set_xticks(np.arange(0, layout.room.length + 1e-9, 1.0))
        ax.set_yticks(np.arange(0, layout.room.width + 1e-9, 1.0))
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_title(f"{method_label(method, model)}\nmean error {error_cm:.1f} cm", fontsize=10)
    for ax in axes.ravel()[len(ordered) :]:
        ax.axis("off")
    axes.ravel()[0].legend(loc="upper right", fontsize=7, framealpha=0.9)
    fig.suptitle(f"{layout.name}: K = 8 targets, 30 dB, x / y in metres (trial 0, fixed seed)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def fig4(summary: Sequence[Summary], room: str, path: Path) -> Path:
    """Mean error against K for one room, one panel per SNR (log y, centimetres)."""
    rows = [s for s in summary if s.room == room]
    snrs = sorted({s.snr_db for s in rows})
    methods = sorted({(s.method, s.model) for s in rows}, key=lambda m: (m[0] == "rss", m[0], m[1]))
    solvers = sorted({m for m, _ in methods if m != "rss"})
    colours = {name: plt.get_cmap("tab10")(i) for i, name in enumerate(solvers)}
    n_leds = make_room(room).n_leds
    # Measured values per model; the CRLB is drawn only where 2K + 1 unknowns fit in them.
    n_values = {"power": n_leds, "correlation": n_leds * (n_leds + 1) // 2}
    fig, axes = plt.subplots(
        1, len(snrs), figsize=(5.6 * len(snrs), 4.6), squeeze=False, layout="constrained"
    )
    for ax, snr in zip(axes[0], snrs, strict=True):
        cell = sorted((s for s in rows if s.snr_db == snr), key=lambda s: s.n_targets)
        for method, model in methods:
            line = [s for s in cell if (s.method, s.model) == (method, model)]
            ks = [s.n_targets for s in line]
            ax.plot(
                ks,
                [100 * s.mean_error_m for s in line],
                _STYLE[model],
                marker=_MARKER[model],
                ms=4,
                color=colours.get(method, "k"),
                label=method_label(method, model),
            )
        for model, shade in (("correlation", "0.15"), ("power", "0.55")):
            line = [s for s in cell if s.method == "rss" or s.model == model]

            def crlb_of(s: Summary, model: str = model) -> float:
                identifiable = 2 * s.n_targets + 1 <= n_values[model]
                return s.crlb_m if s.model == model and identifiable else float("nan")

            bound = _per_k(line, crlb_of)
            if bound:
                ax.plot(
                    *zip(*bound, strict=True),
                    "--",
                    color=shade,
                    label=f"CRLB, {MODEL_LABELS[model]} (median)",
                )
        single = _per_k(cell, lambda s: s.crlb_single_m)
        ax.plot(
            *zip(*single, strict=True),
            linestyle=(0, (1, 3)),
            color="k",
            lw=1.2,
            label="CRLB, one terminal alone (median)",
        )
        floor = _per_k(cell, lambda s: s.grid_floor_m)
        ax.plot(
            *zip(*floor, strict=True), ":", color="tab:gray", lw=2, label="grid quantisation floor"
        )
        ax.set_yscale("log")
        ax.set_xlabel("number of targets K")
        ax.set_ylabel("mean position error (cm)")
        ax.set_title(f"{snr:g} dB")
        ax.grid(alpha=0.3, which="both")
    handles, labels = axes[0][0].get_legend_handles_labels()
    # Columns the figure's width holds (about 2.6 inches per label at this font size): a
    # one-panel figure gets 2, so the legend is never wider than the figure.
    columns = max(1, min(len(labels), int(5.6 * len(snrs) / 2.6)))
    fig.legend(handles, labels, loc="outside lower center", ncol=columns, fontsize=8)
    fig.suptitle(f"Mean over trials of the per-trial mean error, room '{room}'")
    path.parent.mkdir(parents=True, exist_ok=True)
    # bbox_inches="tight" grows the canvas to whatever the legend needs, on every side.
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _per_k(rows: Sequence[Summary], value: Callable[[Summary], float]) -> list[tuple[int, float]]:
    """(K, 100 * value) for the first finite value per K, in K order."""
    pick: dict[int, float] = {}
    for s in rows:
        v = value(s)
        if s.n_targets not in pick and np.isfinite(v):
            pick[s.n_targets] = 100 * float(v)
    return sorted(pick.items())


def fig4_all(summary: Sequence[Summary], folder: Path) -> list[Path]:
    """One Fig. 4 per room in the summary: ``folder/fig4_error_vs_k_<room>.png``."""
    rooms = sorted({s.room for s in summary})
    return [fig4(summary, room, folder / f"fig4_error_vs_k_{room}.png") for room in rooms]


def read_summary(path: Path) -> list[Summary]:
    """The summaries of an ``accuracy_summary.csv`` written by ``bench.accuracy``."""
    from .results import Summary

    with path.open(newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    return [
        Summary(
            room=row["room"],
            snr_db=float(row["snr_db"]),
            n_targets=int(row["n_targets"]),
            method=row["method"],
            model=row["model"],
            trials=int(row["trials"]),
            failures=int(row["failures"]),
            median_error_m=float(row["median_error_m"]),
            mean_error_m=float(row["mean_error_m"]),
            p90_error_m=float(row["p90_error_m"]),
            median_time_ms=float(row["median_time_ms"]),
            grid_floor_m=float(row["grid_floor_m"]),
            crlb_m=float(row["crlb_m"]),
            crlb_single_m=float(row["crlb_single_m"]),
        )
        for row in rows
    ]


def main(argv: Sequence[str] | None = None) -> int:
    """Re-draw the Fig. 4 PNGs from a stored summary (no benchmark run)."""
    parser = argparse.ArgumentParser(prog="python -m bench.plots", description=main.__doc__)
    parser.add_argument("--summary", type=Path, default=Path("docs/data/accuracy_summary.csv"))
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    args = parser.parse_args(argv)
    for path in fig4_all(read_summary(args.summary), args.out):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
