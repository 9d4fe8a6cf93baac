"""The default solver's time, this checkout against another source tree, interleaved.

Run from the repository root, with the other tree unpacked somewhere (any commit)::

    git archive b325b9d | (mkdir -p /tmp/base && tar -x -C /tmp/base)
    python -m bench.solver_ab /tmp/base                # 10 rounds
    python -m bench.solver_ab /tmp/base --rounds 4
    python -m bench.solver_ab /tmp/base --forms power:1,power:4,power:8

Two worker processes, one importing ``app`` (and ``bench``) from the other tree and one from
this checkout, each with the default ``gridless`` solver built and warmed up once per model
(the other tree's numba kernels compile into its own cache on its first run). They take
turns: in every round each solves the same 50 seeded measurements of the paper room at
30 dB (:func:`bench.solver_timing._kernel_pool`) per form (``terminals``: each terminal's own
amplitudes, ``solve_terminals``), the order of the two alternating
between rounds, so that both see the same load. Medians of the CPU time per solve (BLAS one
thread). Prints a table; writes nothing (the figures go into ``docs/explanation/performance.md``
by hand, with the command).
"""

from __future__ import annotations

import argparse
import ast
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._common import REPO_ROOT

__all__ = ["FORMS", "main"]

FORMS = (
    ("correlation", 1),
    ("correlation", 4),
    ("correlation", 8),
    ("power", 1),
    ("power", 8),
    ("terminals", 1),
    ("terminals", 8),
)
SOLVES_PER_TURN = 50

# The worker: only what both trees have (solver_timing's pool, make_solver, warm_up).
_WORKER = """
import sys, time
from threadpoolctl import threadpool_limits
from app.vlp.fingerprints import build_fingerprint
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.solvers import make_solver, warm_up
from bench.rooms import make_room
from bench.solver_timing import CASE, _kernel_pool

warm_up()
layout = make_room(CASE.room)
fingerprint = build_fingerprint(layout)
solvers = {m: make_solver("gridless", fingerprint, m) for m in ("correlation", "power")}
pools = {}
threadpool_limits(1)
print("ready", flush=True)
for line in sys.stdin:
    model, k, n = line.split()
    k, n = int(k), int(n)
    if model == "terminals":
        # each terminal's own amplitudes (K, M), the correlation solver's solve_terminals
        solve = lambda a, k: solvers["correlation"].solve_terminals(a)
    else:
        solve = solvers[model].solve
    if (model, k) not in pools:
        pools[(model, k)] = [
            a if model == "terminals" else measurement_from_amplitudes(a, model, layout.n_leds)
            for a in _kernel_pool(k, 50)
        ]
        for m in pools[(model, k)][:2]:
            solve(m, k)
    times = []
    for i in range(n):
        m = pools[(model, k)][i % 50]
        start = time.process_time()
        solve(m, k)
        times.append(time.process_time() - start)
    print(repr(times), flush=True)
"""


def _start(tree: Path) -> subprocess.Popen[str]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(tree))
    worker = subprocess.Popen(
        [sys.executable, "-c", _WORKER],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=tree,
    )
    assert worker.stdout is not None
    if worker.stdout.readline().strip() != "ready":
        raise RuntimeError(f"the worker on {tree} did not start")
    return worker


def _turn(worker: subprocess.Popen[str], model: str, k: int) -> list[float]:
    assert worker.stdin is not None and worker.stdout is not None
    worker.stdin.write(f"{model} {k} {SOLVES_PER_TURN}\n")
    worker.stdin.flush()
    times: list[float] = ast.literal_eval(worker.stdout.readline())
    return times


def _forms(text: str) -> tuple[tuple[str, int], ...]:
    """``power:1,power:8`` as ``(("power", 1), ("power", 8))``."""
    forms = []
    for item in text.split(","):
        model, _, k = item.strip().partition(":")
        if model not in {form for form, _ in FORMS} or not k.isdigit() or int(k) < 1:
            raise argparse.ArgumentTypeError(f"not a FORM:K pair: {item!r}")
        forms.append((model, int(k)))
    return tuple(forms)


def main(argv: Sequence[str] | None = None) -> int:
    """Time both trees, interleaved, and print the medians and their ratio."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.solver_ab",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("base", type=Path, help="the other source tree (its root folder)")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument(
        "--forms",
        type=_forms,
        default=FORMS,
        help="comma-separated FORM:K pairs, e.g. power:1,power:4,power:8 (default: all of FORMS)",
    )
    args = parser.parse_args(argv)
    forms: tuple[tuple[str, int], ...] = args.forms
    load = os.getloadavg()
    workers = {"base": _start(args.base.resolve()), "this": _start(REPO_ROOT)}
    times: dict[tuple[str, int], dict[str, list[float]]] = {
        form: {"base": [], "this": []} for form in forms
    }
    try:
        for round_index in range(args.rounds):
            order = ("base", "this") if round_index % 2 == 0 else ("this", "base")
            for model, k in forms:
                for name in order:
                    times[(model, k)][name] += _turn(workers[name], model, k)
    finally:
        for worker in workers.values():
            worker.kill()
            worker.wait()
    print(f"load average at start: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print("| form | base (ms) | this (ms) | this / base |")
    print("|---|---|---|---|")
    for (model, k), pair in times.items():
        base, this = (1e3 * float(np.median(pair[name])) for name in ("base", "this"))
        print(f"| {model}, K = {k} | {base:.3g} | {this:.3g} | {this / base:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
