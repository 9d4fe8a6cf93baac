"""Which kernels the default solver runs: compiled (numba) or the plain NumPy reference.

The compiled kernels (:mod:`._channel_compiled`, :mod:`._fit_compiled`) compute the same
numbers as the NumPy code they stand in for (``tests/vlp/test_compiled_kernels.py`` compares
them); they exist because a 16-LED problem is bound by the per-call overhead of NumPy, not
by its arithmetic. The environment variable ``VLP_KERNELS`` picks the default
(``compiled``, or ``reference``); :func:`use_kernels` switches within a process (the
benchmarks time both side by side).

Compiled functions are cached on disk (``NUMBA_CACHE_DIR``, else next to the sources, else
the user's cache folder); with no writable place they are compiled in memory at every start
(slower to start, same results). :func:`warm_up` compiles (or loads) every kernel, so that no
request pays for it.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, Literal

import numba

__all__ = [
    "KERNELS",
    "KernelMode",
    "compiled",
    "compiled_reassociating",
    "kernel_mode",
    "use_kernels",
    "warm_up",
]

KernelMode = Literal["compiled", "reference"]
KERNELS: tuple[KernelMode, ...] = ("compiled", "reference")
_ENV = "VLP_KERNELS"


def _mode_from_env() -> KernelMode:
    value = os.environ.get(_ENV, "compiled").strip().lower() or "compiled"
    if value not in KERNELS:
        raise ValueError(f"{_ENV} must be one of {', '.join(KERNELS)}, got {value!r}")
    return "compiled" if value == "compiled" else "reference"


_mode: KernelMode = _mode_from_env()
_lock = threading.Lock()
_warm = False


def kernel_mode() -> KernelMode:
    """The kernels in use in this process."""
    return _mode


@contextmanager
def use_kernels(mode: KernelMode) -> Iterator[None]:
    """Run the block with ``mode``'s kernels (process-wide: for benchmarks and tests)."""
    global _mode
    if mode not in KERNELS:
        raise ValueError(f"kernels must be one of {', '.join(KERNELS)}, got {mode!r}")
    before = _mode
    _mode = mode
    try:
        yield
    finally:
        _mode = before


def compiled(function: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit(cache=True, nogil=True)``, without the disk cache when no folder for it
    is writable (numba refuses to decorate then)."""
    return _jit(function, {})


def compiled_reassociating(function: Callable[..., Any]) -> Callable[..., Any]:
    """:func:`compiled`, free to reorder sums (vectorised reductions: round-off differs from
    a sequential sum, within the 1e-10 the tests allow)."""
    return _jit(function, {"fastmath": {"reassoc", "contract"}})


def _jit(function: Callable[..., Any], options: dict[str, Any]) -> Callable[..., Any]:
    try:
        dispatcher: Callable[..., Any] = numba.njit(cache=True, nogil=True, **options)(function)
    except RuntimeError:
        dispatcher = numba.njit(cache=False, nogil=True, **options)(function)
    return dispatcher


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel the default solver uses.

    Idempotent and thread-safe; a no-op with the reference kernels. Called by the service at
    start-up, so that no terminal's request waits for the compiler.
    """
    global _warm
    if _mode != "compiled":
        return
    with _lock:
        if _warm:
            return
        from ._warm_up import exercise

        exercise()
        _warm = True
