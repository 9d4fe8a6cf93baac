"""Compile (or load from the disk cache) every kernel before the first request.

The top of the kernels' imports: it imports the kernel table (which imports every kernel's
caller), and nothing in :mod:`app.vlp` imports it but :mod:`app.vlp.solvers` (which exports
:func:`warm_up`). It runs every row of the kernel table (:mod:`._kernel_table`: each kernel
on the examples its parity test compares with its reference). The calls go through the same
code as a solve, so they compile exactly the argument types a solve uses.
"""

from __future__ import annotations

import threading

from .._kernels import kernel_mode
from ._kernel_table import KERNEL_TABLE

__all__ = ["warm_table", "warm_up"]

_lock = threading.Lock()
_warm = False


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel the default solver and the
    tracking filter use.

    Idempotent and thread-safe; a no-op with the reference kernels. Called by the service at
    start-up, so that no terminal's request waits for the compiler.
    """
    global _warm
    if kernel_mode() != "compiled":
        return
    with _lock:
        if _warm:
            return
        warm_table()
        _warm = True


def warm_table() -> None:
    """Every row of the kernel table: its kernel on each of its examples."""
    for row in KERNEL_TABLE:
        for args in row.examples():
            row.kernel(*args)
