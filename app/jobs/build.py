"""The build itself, run in a worker's child process.

The child builds the fingerprint with :func:`app.vlp.fingerprints.build_fingerprint`, writes
the matrix files into the content-addressed store itself and returns only their metadata, so
no large array crosses the process boundary. It reports progress straight into the job's row
(at most every ``progress_interval_s`` seconds, and only while the parent still holds the
lease). BLAS is limited to one thread per child: the pool already runs builds in parallel.
A child whose parent dies (``kill -9`` of ``vlp serve`` or ``vlp worker``) ends itself within
a second instead of finishing a build nobody will record, which would hold the memory of a
second build while the job is rebuilt elsewhere.

Test-only hook (inert unless ``VLP_TEST_BUILD_GATE`` is set; see :class:`_BuildGate`): the
fault tests hold a real build at a chosen progress so that their ``kill -9`` always lands
mid-build, whatever the machine's speed.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import Engine
from threadpoolctl import threadpool_limits

from app.registry.blob_store import MatrixStorage, MatrixStoreKind, open_matrix_store
from app.registry.db import create_registry_engine
from app.registry.errors import RegistryError
from app.registry.queue import JobQueue, StoredBuild
from app.registry.records import MatrixInfo
from app.vlp.fingerprints import PSI_DENSE_LIMIT, Fingerprint, build_fingerprint
from app.vlp.layout_mapping import layout_from_mapping

from .calibrate import apply_calibration

__all__ = [
    "BuildTask",
    "build_and_store",
    "init_build_process",
    "store_fingerprint",
    "watch_parent",
]

_BLAS_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_ORPHAN_CHECK_SECONDS = 0.5
_ORPHAN_EXIT_CODE = 70
_GATE_ENV = "VLP_TEST_BUILD_GATE"
_GATE_AT_ENV = "VLP_TEST_BUILD_GATE_AT"
_GATE_POLL_SECONDS = 0.05


@dataclass(frozen=True)
class BuildTask:
    """Everything a child needs to build one claimed job (picklable).

    ``calibration`` is the payload of a calibration job: the child fits it first and builds
    the calibrated, masked layout (:func:`app.jobs.calibrate.apply_calibration`).
    """

    database_url: str
    data_dir: str
    job_id: str
    worker_id: str
    layout: dict[str, Any]
    matrix_store: MatrixStoreKind = "files"
    max_cells: int | None = None
    progress_interval_s: float = 0.5
    calibration: dict[str, Any] | None = None


def init_build_process() -> None:
    """Pool initializer: one BLAS/OpenMP thread per build process; exit when orphaned."""
    for name in _BLAS_ENV:
        os.environ[name] = "1"
    threadpool_limits(limits=1)
    watch_parent(os.getppid())


def watch_parent(parent_pid: int, interval_s: float = _ORPHAN_CHECK_SECONDS) -> threading.Thread:
    """Start a daemon thread that ends this process once ``parent_pid`` is no longer its parent.

    A re-parented process (the parent died, even by SIGKILL) sees another ``getppid()``.
    Polling works for every way the parent can die, unlike ``PR_SET_PDEATHSIG``, which fires
    when the *thread* that started the child ends.
    """

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(interval_s)
        os._exit(_ORPHAN_EXIT_CODE)

    thread = threading.Thread(target=watch, name="vlp-orphan-watch", daemon=True)
    thread.start()
    return thread


class _BuildGate:
    """Test-only: hold one build at a given progress until the test lets it go on.

    Read from the environment of the build process (inherited from ``vlp serve`` or
    ``vlp worker``); without ``VLP_TEST_BUILD_GATE`` nothing here ever runs.

    - ``VLP_TEST_BUILD_GATE``: path of a gate file that the test creates and deletes.
    - ``VLP_TEST_BUILD_GATE_AT``: the progress fraction to hold at (default 0).

    The first build whose progress reaches the fraction while the gate file exists takes the
    hold: it creates ``<gate>.held`` (exclusively, so only one build per gate is held)
    holding its job id, after its progress is in the job row. It then waits, polling, until
    the gate file is deleted. Other builds pass by.
    """

    def __init__(self, path: str, at: float) -> None:
        self._gate = Path(path)
        self._held = Path(f"{path}.held")
        self._at = at
        self._passed = False

    @classmethod
    def from_environment(cls) -> _BuildGate | None:
        path = os.environ.get(_GATE_ENV)
        if not path:
            return None
        return cls(path, float(os.environ.get(_GATE_AT_ENV, "0")))

    def should_hold(self, fraction: float) -> bool:
        """True once, when ``fraction`` first reaches the hold point while the gate is shut."""
        if self._passed or fraction < self._at:
            return False
        self._passed = True
        return self._gate.exists()

    def hold(self, job_id: str) -> None:
        """Announce the hold (unless another build has it) and wait for the gate to open."""
        # link() publishes the whole marker at once and fails if another build has one.
        draft = self._held.with_name(f"{self._held.name}.{os.getpid()}.{threading.get_ident()}")
        draft.write_text(job_id, encoding="utf-8")
        try:
            os.link(draft, self._held)
        except FileExistsError:
            return
        finally:
            draft.unlink()
        while self._gate.exists():
            time.sleep(_GATE_POLL_SECONDS)


class _ProgressReporter:
    """Writes the fraction done into the job row, throttled; never fails the build."""

    def __init__(self, task: BuildTask) -> None:
        self._task = task
        self._engine: Engine | None = None
        self._last = time.monotonic()
        self._gate = _BuildGate.from_environment()

    def __call__(self, fraction: float) -> None:
        now = time.monotonic()
        held = self._gate is not None and self._gate.should_hold(fraction)
        if not held and (now - self._last < self._task.progress_interval_s or fraction >= 1.0):
            return
        self._last = now
        self._report(fraction)
        if held and self._gate is not None:
            self._gate.hold(self._task.job_id)

    def _report(self, fraction: float) -> None:
        if self._engine is None:
            self._engine = create_registry_engine(self._task.database_url)
        try:
            JobQueue(self._engine).report_progress(
                job_id=self._task.job_id,
                worker_id=self._task.worker_id,
                progress=fraction,
            )
        except RegistryError:
            return

    def close(self) -> None:
        if self._engine is not None:
            self._engine.dispose()


def store_fingerprint(
    fingerprint: Fingerprint, store: MatrixStorage
) -> dict[str, tuple[MatrixInfo, int]]:
    """Write H (always), J (when dense) and psi (when within the limit) into ``store``.

    Returns
    -------
    dict
        ``name -> (MatrixInfo, size_bytes)`` for every stored matrix.
    """
    stored = {
        "H": store.put(fingerprint.dense_gains() if fingerprint.is_dense else fingerprint.gains)
    }
    if fingerprint.is_dense:
        stored["J"] = store.put(fingerprint.power_matrix())
    n_rows = fingerprint.n_leds * (fingerprint.n_leds + 1) // 2
    if n_rows * fingerprint.n_cells <= PSI_DENSE_LIMIT:
        stored["psi"] = store.put(fingerprint.correlation_matrix())
    return stored


def build_and_store(task: BuildTask) -> StoredBuild:
    """Build the fingerprint of ``task.layout`` and store its matrices (runs in the child).

    Raises
    ------
    app.vlp.errors.VLPError
        When the layout is invalid or larger than ``task.max_cells``, or the calibration
        cannot be applied.
    """
    started = time.perf_counter()
    layout = layout_from_mapping(task.layout)
    outcome = None
    if task.calibration is not None:
        outcome = apply_calibration(layout, task.calibration)
        layout = layout_from_mapping(outcome["layout"])
    reporter = _ProgressReporter(task)
    try:
        fingerprint = build_fingerprint(layout, progress=reporter, max_cells=task.max_cells)
        engine = create_registry_engine(task.database_url)
        try:
            store = open_matrix_store(
                task.matrix_store, data_dir=Path(task.data_dir), engine=engine
            )
            stored = store_fingerprint(fingerprint, store)
        finally:
            engine.dispose()
    finally:
        reporter.close()
    return StoredBuild(
        leds=fingerprint.n_leds,
        grid_points=fingerprint.n_cells,
        build_seconds=time.perf_counter() - started,
        matrices=stored,
        calibration=outcome,
    )
