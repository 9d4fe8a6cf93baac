"""Accuracy and cost of the diffuse-reflection model (the figures in docs/results/reflections.md).

    python -m bench.reflections

Paper room, walls 0.7 (and 0.7 / 0.2 / 0.8 for the table): convergence of
:func:`~app.vlp.reflections.diffuse_gains` with the element size at three receivers, the
NLoS/LoS ratio over the grid, the reflection table's interpolation error at random points,
and medians of the time of ``diffuse_gains``, of a table build and of ``evaluate``. Prints
markdown.
"""

from __future__ import annotations

import dataclasses
import functools
import statistics
import time
from collections.abc import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from app.vlp.channel import los_gains
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Reflectance
from app.vlp.presets import paper_layout
from app.vlp.reflections import ReflectionTable, diffuse_gains

from ._common import machine_markdown, machine_record

__all__ = ["main"]

WALLS = Reflectance(walls=0.7, floor=0.0, ceiling=0.0)
SURFACES = Reflectance(walls=0.7, floor=0.2, ceiling=0.8)
SIZES_M = (0.5, 0.25, 0.1, 0.05, 0.03)
PROBES = {
    "10 cm from a corner": (0.1, 0.1),
    "10 cm from a wall": (0.1, 2.1),
    "centre": (2.1, 1.9),
}


def _with(layout: Layout, reflectance: Reflectance, height_sd: float = 0.0) -> Layout:
    return dataclasses.replace(
        layout,
        room=dataclasses.replace(layout.room, reflectance=reflectance),
        grid=Grid(layout.grid.step, layout.grid.receiver_height, height_sd),
    )


def _median_us(call: Callable[[], object], number: int) -> float:
    """Median over ``number`` timed calls (after a few warm-up calls), microseconds."""
    for _ in range(3):
        call()
    samples = []
    for _ in range(number):
        started = time.perf_counter_ns()
        call()
        samples.append(time.perf_counter_ns() - started)
    return statistics.median(samples) / 1e3


def _convergence(layout: Layout) -> list[str]:
    lines = ["| receiver | " + " | ".join(f"{s:g} m" for s in SIZES_M) + " |"]
    lines.append("|---" * (len(SIZES_M) + 1) + "|")
    for name, (x, y) in PROBES.items():
        xyz = np.array([[x, y, layout.grid.receiver_height]])
        los = float(los_gains(layout, xyz).sum())
        ratios = [
            float(diffuse_gains(layout, xyz, reflectance=WALLS, element_size_m=s).sum()) / los
            for s in SIZES_M
        ]
        lines.append(f"| {name} | " + " | ".join(f"{r:.5f}" for r in ratios) + " |")
    return lines


def _grid_ratio(layout: Layout) -> str:
    centres = layout.cell_centres()
    xyz = np.column_stack((centres, np.full(len(centres), layout.grid.receiver_height)))
    ratio = diffuse_gains(layout, xyz, reflectance=WALLS).sum(0) / los_gains(layout, xyz).sum(0)
    edge = np.min(np.column_stack((centres, 4.0 - centres)), axis=1) < 0.15
    return (
        f"NLoS/LoS (sums over LEDs), walls 0.7: grid mean {ratio.mean():.3f}, grid points next "
        f"to a wall {ratio[edge].mean():.3f}, corners {ratio[[0, 19, 380, 399]].mean():.3f}, "
        f"max {ratio.max():.3f}."
    )


def _table_error(table: ReflectionTable, layout: Layout) -> str:
    gen = np.random.default_rng(11)
    xs, ys = gen.uniform(0, 4, 300), gen.uniform(0, 4, 300)
    near = gen.uniform(0, 0.2, 100)  # and 100 points within 20 cm of a wall
    xs = np.concatenate((xs, near))
    ys = np.concatenate((ys, gen.uniform(0, 4, 100)))
    gains = table.evaluate(xs, ys)[0]
    exact = diffuse_gains(layout, np.column_stack((xs, ys, np.full(xs.size, 0.85))))
    relative = np.abs(gains - exact) / exact.max(axis=1, keepdims=True)
    total = np.abs(gains - exact).sum(0) / (
        exact + los_gains(layout, np.column_stack((xs, ys, np.full(xs.size, 0.85))))
    ).sum(0)
    return (
        f"Table vs diffuse_gains at 400 random points (100 within 20 cm of a wall): error / "
        f"the LED's largest NLoS: max {relative.max():.2e}, 99th percentile "
        f"{np.quantile(relative, 0.99):.2e}, median {np.median(relative):.2e}; summed over "
        f"LEDs relative to the total (LoS + NLoS) signal: max {total.max():.2e}."
    )


def main() -> int:
    """Entry point of ``python -m bench.reflections``."""
    with threadpool_limits(limits=1):  # as the solvers run in the service and benchmarks
        return _run()


def _run() -> int:
    layout = paper_layout()
    lines = ["Machine:", "", machine_markdown(machine_record()), ""]
    lines += ["## Convergence with the element size (NLoS/LoS, paper room, walls 0.7)", ""]
    lines += _convergence(layout)
    lines += ["", _grid_ratio(layout), ""]
    flat = _with(layout, SURFACES)
    started = time.perf_counter()
    table = ReflectionTable.build(flat)
    build_s = time.perf_counter() - started
    lines += [_table_error(table, flat), ""]
    xyz = np.array([[0.3, 2.1, 0.85]])
    timings = {
        "diffuse_gains, one receiver, default cells (ms)": _median_us(
            lambda: diffuse_gains(flat, xyz), 15
        )
        / 1e3,
        "diffuse_gains, one receiver, 0.1 m cells (simulator) (ms)": _median_us(
            lambda: diffuse_gains(flat, xyz, element_size_m=0.1), 15
        )
        / 1e3,
    }
    tall = ReflectionTable.build(_with(layout, SURFACES, 0.05))
    gen = np.random.default_rng(5)
    for count in (1, 8, 50):
        xs, ys, zs = gen.uniform(0, 4, count), gen.uniform(0, 4, count), gen.uniform(0.7, 1, count)
        timings[f"evaluate, P = {count}, M = 16, one height (us)"] = _median_us(
            functools.partial(table.evaluate, xs, ys), 3000
        )
        timings[f"evaluate, P = {count}, M = 16, heights sd 5 cm (us)"] = _median_us(
            functools.partial(tall.evaluate, xs, ys, zs), 3000
        )
    started = time.perf_counter()
    fingerprint = build_fingerprint(flat)
    fingerprint_s = time.perf_counter() - started
    lines += ["| quantity | median |", "|---|---|"]
    lines += [f"| {name} | {value:.1f} |" for name, value in timings.items()]
    lines += [
        f"| table build, paper room, {table.x_nodes.size} x {table.y_nodes.size} nodes (s, "
        f"one run) | {build_s:.1f} |",
        f"| table build, heights sd 5 cm, {tall.z_nodes.size} levels (coefficients) | "
        f"{tall.coefficients.size} |",
        f"| fingerprint with reflections, paper room (s, one run; nnz {fingerprint.gains.nnz} "
        f"of {16 * 400}) | {fingerprint_s:.1f} |",
    ]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
