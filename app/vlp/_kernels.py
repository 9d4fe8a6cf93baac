"""The kernel engine: which kernels run (compiled with numba, or their plain NumPy
references), the ``@compiled`` decorators, and the disk cache of compiled code.

This module is the bottom of the science package's kernels: it imports nothing from
:mod:`app.vlp`, so every kernel module and every caller can import it without a circle.
:func:`app.vlp.solvers.warm_up`, at the top, compiles every kernel before the first request.

The compiled kernels (the ``_compiled`` modules of :mod:`app.vlp.solvers.gridless` and
:mod:`app.vlp._radii_compiled`) compute the same numbers as the NumPy code they stand in for
(``tests/vlp/gridless/test_kernel_table.py`` compares them); they exist because a 16-LED problem
is bound by the per-call overhead of NumPy, not by its arithmetic. The environment variable
``VLP_KERNELS`` picks the default (``compiled``, or ``reference``); :func:`use_kernels`
switches within a process (the benchmarks time both side by side). Callers choose between a
kernel and its reference only through :func:`dispatch` (the function to call; every kernel
and its reference are listed in ``app/vlp/solvers/_kernel_table.py``).

Compiled functions are cached on disk, in a folder named after a digest of every source file
of :mod:`app.vlp` (:func:`kernel_cache_dir`) inside ``NUMBA_CACHE_DIR``, else next to the
sources, else the user's cache folder; with no writable place they are compiled in memory at
every start (slower to start, same results). The digest is there because numba keys a cached
function by its own file only: a kernel that calls one in another file would keep the old
callee's machine code after that file changed (an upgrade in place, a checkout).
"""

from __future__ import annotations

import hashlib
import importlib
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal, ParamSpec, TypeVar

import numba

__all__ = [
    "KERNELS",
    "KernelMode",
    "compiled",
    "compiled_inline",
    "compiled_reassociating",
    "dispatch",
    "kernel_cache_dir",
    "kernel_mode",
    "use_kernels",
]

KernelMode = Literal["compiled", "reference"]
KERNELS: tuple[KernelMode, ...] = ("compiled", "reference")
_ENV = "VLP_KERNELS"
_P = ParamSpec("_P")
_R = TypeVar("_R")


def _mode_from_env() -> KernelMode:
    value = os.environ.get(_ENV, "compiled").strip().lower() or "compiled"
    if value not in KERNELS:
        raise ValueError(f"{_ENV} must be one of {', '.join(KERNELS)}, got {value!r}")
    return "compiled" if value == "compiled" else "reference"


_mode: KernelMode = _mode_from_env()
# The science package, whose sources key the compiled kernels' disk cache.
_SCIENCE_ROOT = Path(__file__).resolve().parent
# numba's settings (``CACHE_DIR`` is read when a kernel is decorated) and its cache-folder
# function; untyped modules.
_NUMBA_CONFIG: Any = importlib.import_module("numba.core.config")
_APPDIRS: Any = importlib.import_module("numba.misc.appdirs")


def kernel_cache_dir(base: Path, sources: Path) -> Path:
    """The folder under ``base`` for kernels compiled from the ``*.py`` files below
    ``sources``: ``base / "vlp-<digest>"``, the digest of their relative paths and contents."""
    digest = hashlib.sha256()
    for path in sorted(sources.rglob("*.py")):
        digest.update(path.relative_to(sources).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
        digest.update(b"\0")
    return base / f"vlp-{digest.hexdigest()[:16]}"


def _use_keyed_cache() -> None:
    """Point numba's cache at :func:`kernel_cache_dir` of the first writable base: the
    operator's ``NUMBA_CACHE_DIR`` (only that one, when set), else the package's
    ``__pycache__``, else the user's cache folder. Runs before any kernel is decorated
    (numba picks a function's cache folder then)."""
    if _NUMBA_CONFIG.CACHE_DIR:
        bases = [Path(_NUMBA_CONFIG.CACHE_DIR)]
    else:
        user_cache = Path(_APPDIRS.AppDirs(appname="numba", appauthor=False).user_cache_dir)
        bases = [Path(__file__).resolve().parent / "__pycache__", user_cache]
    for base in bases:
        folder = kernel_cache_dir(base, _SCIENCE_ROOT)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(folder, os.W_OK):
            _NUMBA_CONFIG.CACHE_DIR = str(folder)
            return
    # Nowhere writable: numba's own locators find none either, and _jit compiles in memory.
    _NUMBA_CONFIG.CACHE_DIR = str(kernel_cache_dir(bases[0], _SCIENCE_ROOT))


_use_keyed_cache()


def kernel_mode() -> KernelMode:
    """The kernels in use in this process."""
    return _mode


def dispatch(kernel: Callable[_P, _R], reference: Callable[_P, _R]) -> Callable[_P, _R]:
    """The function to call: ``kernel`` (a function of the reference's arguments that runs the
    compiled code) while the compiled kernels are in use, else its NumPy ``reference``.

    The one place where the science package chooses between a compiled kernel and its
    reference (the kernel engine's mode is read nowhere else, but as part of a cache key)."""
    return kernel if _mode == "compiled" else reference


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


def compiled_inline(function: Callable[..., Any]) -> Callable[..., Any]:
    """:func:`compiled`, inlined into its compiled callers by numba (in their typed code, not
    as a call): for the small functions of a model that a loop calls every iteration, whose
    arguments are large tuples of arrays (measured: a call per iteration costs more than the
    work it saves to write it once). The same arithmetic, so the same numbers."""
    return _jit(function, {"inline": "always"})


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
