"""What an API process must hold: peak resident memory as the serving stack loads, step by step.

Run from the repository root::

    python -m bench.memory_floor

Each step runs in a fresh interpreter (BLAS one thread) and reports that process's peak resident
memory (``VmHWM``), its anonymous and file-backed parts, after importing:

1. ``libraries``: numpy, scipy's modules the service uses, pydantic, FastAPI, SQLAlchemy;
2. ``+ app (no numba)``: and ``app.main``, which imports neither the solvers nor numba (a
   process loads them with its first solver);
3. ``+ numba``: the libraries and numba (which loads LLVM, ``libllvmlite.so``);
4. ``+ one compiled kernel``: and one trivial ``@njit(cache=True)`` function, called once from
   its cache (what the first compiled kernel of any process costs: numba's typing and target
   contexts);
5. ``+ app``: and ``app.main`` (the service's own modules);
6. ``+ warm-up``: and the solver kernels' warm-up (what a process holds once it solves).

Step 4's anonymous memory is a floor for any process that answers with compiled kernels; the
file-backed part (shared libraries mapped from the page cache) varies with what the cache holds.

Then two real ``vlp serve`` processes (one API process, an empty data directory, so the demo
room is seeded and built by the worker's child process), each measured once ready and after its
first ``/healthz``: one as configured by default (the kernels load with the first solver), one
with ``VLP_WARM_KERNELS_AT_START=1`` (loaded before serving). The same server's peak after its
first localize of the demo room (K = 8 correlation) shows what solving adds.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import httpx

from ._common import REPO_ROOT
from ._server import TERMINAL_KEY, live_server, ready_demo_room

__all__ = ["STEPS", "main", "measure"]

_LIBRARIES = (
    "import numpy, scipy.linalg, scipy.optimize, scipy.sparse, scipy.spatial, scipy.special\n"
    "import pydantic, fastapi, sqlalchemy\n"
)
_KERNEL = "import numba\n@numba.njit(cache=True)\ndef add(a, b):\n    return a + b\n"

STEPS: tuple[tuple[str, str], ...] = (
    ("libraries", _LIBRARIES),
    ("+ app (no numba)", _LIBRARIES + "import app.main\n"),
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


def _peak_mib(pid: int) -> float:
    """A process's peak resident memory so far (``VmHWM``), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text(encoding="utf-8").splitlines():
        key, _, rest = line.partition(":")
        if key == "VmHWM":
            return int(rest.split()[0]) / 1024
    raise RuntimeError(f"no VmHWM in /proc/{pid}/status")


def measure_serve(warm_at_start: bool) -> tuple[float, float, float]:
    """Peak resident memory (MiB) of one ``vlp serve`` on an empty data directory after its
    first ``/healthz``, then after its first localize; and that localize's wall time (ms)."""
    with (
        tempfile.TemporaryDirectory(prefix="vlp-floor-serve-") as tmp,
        live_server(
            Path(tmp),
            timeout_s=600.0,
            VLP_WORKERS="1",
            VLP_WARM_KERNELS_AT_START="1" if warm_at_start else "0",
        ) as server,
    ):
        pid = server.process.pid
        with httpx.Client(
            base_url=server.url, headers={"X-API-Key": TERMINAL_KEY}, timeout=300.0
        ) as client:
            client.get("/healthz").raise_for_status()
            idle = _peak_mib(pid)
            room_id = ready_demo_room(server.url, timeout_s=600.0)
            simulated = client.post(
                f"/v1/rooms/{room_id}/simulate", json={"targets": 8, "snr_db": 30, "seed": 0}
            )
            simulated.raise_for_status()
            started = time.perf_counter()
            client.post(
                f"/v1/rooms/{room_id}/localize", json=simulated.json()["measurement"]
            ).raise_for_status()
            first_ms = (time.perf_counter() - started) * 1e3
        return idle, _peak_mib(pid), first_ms


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
    print()
    print(
        "| `vlp serve` | peak MiB after the first /healthz | after the first localize | "
        "first localize ms |"
    )
    print("|---|---|---|---|")
    for name, warm_at_start in (("default", False), ("VLP_WARM_KERNELS_AT_START=1", True)):
        idle, solved, first_ms = measure_serve(warm_at_start)
        print(f"| {name} | {idle:.0f} | {solved:.0f} | {first_ms:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
