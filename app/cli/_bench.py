"""``vlp bench NAME ARGS...``: run a benchmark module of the repository's ``bench/`` folder."""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Sequence

__all__ = ["BENCHMARKS", "run_benchmark"]

# The benchmarks `vlp bench` offers, each the module `bench.<name>` with `main(argv) -> int`.
BENCHMARKS = ("accuracy", "http", "load", "tracking")


def run_benchmark(module_name: str, argv: Sequence[str]) -> int:
    """Import ``module_name`` and call its ``main(argv)``.

    ``bench/`` is not part of the installed package: it is found from the current directory
    (the repository root).

    Parameters
    ----------
    module_name : str
        e.g. ``"bench.accuracy"``.
    argv : sequence of str
        Passed through unchanged.

    Returns
    -------
    int
        The benchmark's exit code; 2 (with a message on stderr) when it is not there.
    """
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is None or not module_name.startswith(exc.name):
            raise
        print(
            f"vlp bench: no module {module_name} here ({os.getcwd()}); run it from the "
            "repository root, where bench/ is (this checkout may not have that benchmark yet)",
            file=sys.stderr,
        )
        return 2
    entry = getattr(module, "main", None)
    if not callable(entry):
        print(f"vlp bench: {module_name} has no main(argv) to call", file=sys.stderr)
        return 2
    return int(entry(list(argv)) or 0)
