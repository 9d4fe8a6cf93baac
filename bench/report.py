"""Markdown of the accuracy benchmark: the generated part of ``docs/results/accuracy.md``."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ._common import machine_markdown, replace_section
from .plots import method_label
from .rooms import make_room

if TYPE_CHECKING:
    from .accuracy import Case
    from .results import Summary

__all__ = ["GRID_FLOOR_FACTOR", "TARGETS_CM", "target_rows", "write_accuracy_md"]

# Mean distance from a uniform point of the unit square to its centre, (sqrt2 + ln(1+sqrt2))/6.
GRID_FLOOR_FACTOR = (math.sqrt(2.0) + math.log(1.0 + math.sqrt(2.0))) / 6.0
# Accuracy targets (docs/explanation/accuracy.md): paper room, 30 dB, correlation model, default
# solver: mean error ceilings (cm).
TARGETS_CM = {1: 3.0, 4: 6.0, 8: 10.0}
PREAMBLE = """# Results: accuracy on the paper's model (Fig. 3 and Fig. 4)

Written by `python -m bench.accuracy`: the command, machine and date of the run are at the
top of the generated block. What the numbers mean:
[the accuracy explanation](../explanation/accuracy.md).
"""


def _cm(value: float) -> str:
    if math.isinf(value):
        return "∞"
    return "–" if math.isnan(value) else f"{100 * value:.2f}"


def _bound(value: float, n_values: int, n_targets: int) -> str:
    """A CRLB cell: "∞" when 2K positions + the noise power outnumber the measured values."""
    if 2 * n_targets + 1 > n_values:
        return "∞ (2K+1 > values)"
    return _cm(value)


def target_rows(
    summary: Sequence[Summary], default: str, floor_m: float
) -> list[tuple[int, str, float, float, bool]]:
    """(K, ceiling text, mean m, median m, met) for the default solver, CoCSM, paper, 30 dB."""
    out = []
    for s in sorted(summary, key=lambda s: s.n_targets):
        if (s.room, s.snr_db, s.method, s.model) != ("paper", 30.0, default, "correlation"):
            continue
        limits = []
        if s.n_targets in TARGETS_CM:
            limits.append(TARGETS_CM[s.n_targets] / 100)
        if s.n_targets <= 4:
            limits.append(floor_m)
        if not limits:
            continue
        ceiling = min(limits)
        text = " and ".join(
            ([f"≤ {TARGETS_CM[s.n_targets]:g} cm"] if s.n_targets in TARGETS_CM else [])
            + ([f"< floor {100 * floor_m:.2f} cm"] if s.n_targets <= 4 else [])
        )
        met = s.failures == 0 and s.mean_error_m <= ceiling
        out.append((s.n_targets, text, s.mean_error_m, s.median_error_m, met))
    return out


def _table(summary: Sequence[Summary], room: str, snr: float) -> str:
    cell = [s for s in summary if s.room == room and s.snr_db == snr]
    methods = sorted(
        {(s.method, s.model) for s in cell}, key=lambda m: (m[0] != "rss", m[0], m[1] != "power")
    )
    head = [
        "K",
        *(method_label(*m) for m in methods),
        "grid floor",
        "CRLB CSM",
        "CRLB CoCSM",
        "CRLB 1 target",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    trials = {}
    for k in sorted({s.n_targets for s in cell}):
        by = {(s.method, s.model): s for s in cell if s.n_targets == k}
        cols = [str(k)]
        for m in methods:
            s = by.get(m)
            if s is None:
                cols.append("")
                continue
            trials[m] = s.trials
            fail = f" ({s.failures} failed)" if s.failures else ""
            cols.append(f"{_cm(s.mean_error_m)} ({_cm(s.median_error_m)}){fail}")
        any_row = next(iter(by.values()))
        bound = {s.model: s.crlb_m for s in by.values()}
        n_leds = make_room(room).n_leds
        cols += [
            _cm(any_row.grid_floor_m),
            _bound(bound.get("power", math.nan), n_leds, k),
            _bound(bound.get("correlation", math.nan), n_leds * (n_leds + 1) // 2, k),
            _cm(any_row.crlb_single_m),
        ]
        lines.append("| " + " | ".join(cols) + " |")
    counts = ", ".join(f"{method_label(*m)}: {n}" for m, n in trials.items())
    return "\n".join(lines) + f"\n\nTrials per K (last K shown): {counts}.\n"


def write_accuracy_md(
    path: Path,
    summary: Sequence[Summary],
    cases: Sequence[Case],
    solvers: Sequence[str],
    machine: Mapping[str, str],
    *,
    argv: Sequence[str],
    elapsed_s: float,
    figures: Sequence[Path],
) -> None:
    """Replace the generated section of ``path`` (created with a preamble if missing)."""
    default = solvers[0]
    step = 0.2
    floor = GRID_FLOOR_FACTOR * step
    parts = [
        "## Results (generated)",
        "",
        f"Command (repository root): `{' '.join(['python -m bench.accuracy', *argv])}`",
        f"Wall time {elapsed_s:.0f} s. Solvers: {', '.join(solvers)} (default `{default}`).",
        "",
        machine_markdown(machine),
        "",
        "Cells are the MEAN over trials of the per-trial mean error, with the MEDIAN over",
        "trials in brackets, in centimetres. Grid floor: mean distance from the targets to",
        "their nearest grid centre. CRLB CSM / CoCSM: median over trials of the aggregated",
        "bound (RMS per target) of that measurement model; CRLB 1 target: median of the",
        "single-target bound averaged over the targets (RSS-like, one terminal alone).",
        "The bounds are on the RMS error of an unbiased estimator, so a biased estimator's",
        "MEAN error can sit slightly below them. CSM has M values for 2K + 1 unknowns",
        "(positions and noise power): from K = M/2 on its bound is infinite.",
        "",
        f"### Targets (paper room, 30 dB, CoCSM-VLP, `{default}`)",
        "",
        "| K | target | mean (cm) | median (cm) | met (on the mean) |",
        "|---|---|---|---|---|",
    ]
    for k, text, mean, median, met in target_rows(summary, default, floor):
        parts.append(
            f"| {k} | {text} | {_cm(mean)} | {_cm(median)} | {'yes' if met else '**no**'} |"
        )
    parts += ["", f"Analytic floor of the 0.2 m grid: {100 * floor:.2f} cm.", ""]
    for room, snr in sorted(
        {(c.room, c.snr_db) for c in cases}, key=lambda rs: (rs[0] != "paper", rs[1] != 30.0, rs[1])
    ):
        parts += [f"### Room `{room}`, {snr:g} dB", "", _table(summary, room, snr)]
    if figures:
        parts += ["### Figures", ""]
        parts += [f"![{fig.stem}](../figures/{fig.name})" for fig in figures]
    replace_section(path, "accuracy-results", "\n".join(parts), preamble=PREAMBLE)
