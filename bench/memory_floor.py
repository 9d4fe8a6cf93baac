"""What an API process must hold: peak resident memory as the serving stack loads, step by step.

Run from the repository root::

    python -m bench.memory_floor

Each step runs in a fresh interpreter (BLAS one thread) and reports that process's peak resident
memory (``VmHWM``), its anonymous and file-backed parts, after importing:

1. ``libraries``: numpy, scipy's modules the service uses, pydantic, FastAPI, SQLAlchemy;
2. ``+ numba``: and numba (which loads LLVM, ``libllvmlite.so``);
3. ``+ one compiled kernel``: and one trivial ``@njit(cache=True)`` function, called once from
   its cache (what the first compiled kernel of any process costs: numba's typing and target
   contexts);
4. ``+ app``: and ``app.main`` (the service's own modules);
5. ``+ warm-up``: and the solver kernels' warm-up the service runs before it serves.

Step 3's anonymous memory is a floor for any process that answers with compiled kernels; the
file-backed part (shared libraries mapped from the page cache) varies with what the cache holds.
Step 5 against `vlp serve`'s own figure (``bench.http``) shows what serving adds.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from ._common import REPO_ROOT

__all__ = ["STEPS", "main", "measure"]

_LIBRARIES = (
    "import numpy, scipy.linalg, scipy.optimize, scipy.sparse, scipy.spatial, scipy.special\n"
    "import pydantic, fastapi, sqlalchemy\n"
)
_KERNEL = "import numba\n@numba.njit(cache=True)\ndef add(a, b):\n    return a + b\n"

STEPS: tuple[tuple[str, str], ...] = (
    ("libraries", _LIBRARIES),
    ("+ numba", _LIBRARIES + "import numba\n"),
    ("+ one compiled kernel", _LIBRARIES + "from floor_kernel import add\nadd(1.0, 2.0)\n"),
    (
        "+ app",
        _LIBRARIES + "from floor_kernel import add\nadd(1.0, 2.0)\nimport app.main\n",
    ),
    (
        "+ warm-up",
        _LIBRARIES
        + "from floor_kernel import add\nadd(1.0, 2.0)\nimport app.main\n"
        + "from app.vlp.solvers import warm_up\nwarm_up()\n",
    ),
)

_REPORT = (
    "\nfields = dict(line.split(':', 1) for line in open('/proc/self/status'))\n"
    "print(*(int(fields[k].split()[0]) for k in ('VmHWM', 'RssAnon', 'RssFile')))\n"
)


def measure(code: str, kernel_dir: Path) -> tuple[float, float, float]:
    """Peak, anonymous and file-backed resident memory (MiB) of a fresh interpreter that ran
    ``code`` (with ``kernel_dir`` on its path), after a first run that fills numba's cache."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(kernel_dir), str(REPO_ROOT)])
    command = [sys.executable, "-c", code + _REPORT]
    for _ in range(2):  # the first run compiles into the cache; the second loads from it
        done = subprocess.run(
            command, env=env, cwd=REPO_ROOT, capture_output=True, text=True, check=True
        )
    peak, anonymous, file_backed = (int(v) / 1024 for v in done.stdout.split()[-3:])
    return peak, anonymous, file_backed


def main(argv: Sequence[str] | None = None) -> int:
    """Print the table (MiB)."""
    del argv
    with tempfile.TemporaryDirectory(prefix="vlp-floor-") as tmp:
        kernel_dir = Path(tmp)
        (kernel_dir / "floor_kernel.py").write_text(_KERNEL, encoding="utf-8")
        print("| step | peak MiB | anonymous MiB | file-backed MiB |")
        print("|---|---|---|---|")
        for name, code in STEPS:
            peak, anonymous, file_backed = measure(code, kernel_dir)
            print(f"| {name} | {peak:.0f} | {anonymous:.0f} | {file_backed:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
