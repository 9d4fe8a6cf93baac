"""The child-side build: matrices written to the store, progress reported, limits."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from app.jobs.build import BuildTask, build_and_store, store_fingerprint
from app.registry import Registry
from app.registry.store import MatrixStore
from app.vlp.errors import ProblemSizeError
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.presets import paper_layout
from tests.build_gate import BuildGate
from tests.db_fixtures import claim_next, hall_layout
from tests.waiting import SAFETY_TIMEOUT_S


def test_store_fingerprint_dense_room(tmp_path: Path, paper_fingerprint: Fingerprint) -> None:
    stored = store_fingerprint(paper_fingerprint, MatrixStore(tmp_path))
    assert sorted(stored) == ["H", "J", "psi"]
    assert {info.format for info, _ in stored.values()} == {"npy"}
    again = store_fingerprint(build_fingerprint(paper_layout()), MatrixStore(tmp_path / "b"))
    assert {k: v[0].sha256 for k, v in stored.items()} == {k: v[0].sha256 for k, v in again.items()}


def test_store_fingerprint_large_hall_keeps_h_sparse_only(tmp_path: Path) -> None:
    fingerprint = build_fingerprint(hall_layout())
    assert not fingerprint.is_dense
    store = MatrixStore(tmp_path)
    stored = store_fingerprint(fingerprint, store)
    assert sorted(stored) == ["H"]
    info, _ = stored["H"]
    assert (info.format, info.shape) == ("npz", (256, 16000))
    loaded = sp.load_npz(store.path_for(info.sha256, info.format))
    assert (loaded != fingerprint.gains).nnz == 0


def test_build_and_store_reports_progress_and_matches(
    registry: Registry, paper_fingerprint: Fingerprint
) -> None:
    room = registry.create_room(name="Paper room", layout=paper_layout().to_mapping())
    claimed = claim_next(registry, lease_seconds=60)
    assert claimed is not None
    task = BuildTask(
        database_url=registry.database_url,
        data_dir=str(registry.data_dir),
        job_id=claimed.job_id,
        worker_id="w",
        layout=claimed.layout,
        progress_interval_s=0.0,
    )
    result = build_and_store(task)
    assert (result.leds, result.grid_points) == (16, 400)
    assert result.build_seconds > 0
    progress = registry.get_job(job_id=room.job_id or "").progress
    assert 0.5 < progress < 1.0  # the last LED's update before completion
    info, _ = result.matrices["H"]
    h = np.load(registry.store.path_for(info.sha256, info.format))
    np.testing.assert_array_equal(h, paper_fingerprint.dense_gains())


def test_the_test_gate_holds_one_build_at_its_progress_until_opened(
    registry: Registry, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    gate = BuildGate(tmp_path / "gate", at=0.5)
    for name, value in gate.env().items():
        monkeypatch.setenv(name, value)
    gate.shut()
    rooms = [registry.create_room(name=n, layout=paper_layout().to_mapping()) for n in "ab"]
    tasks = []
    for room in rooms:
        claimed = claim_next(registry, worker_id=f"w-{room.name}", room_id=room.id)
        assert claimed is not None
        tasks.append(
            BuildTask(
                database_url=registry.database_url,
                data_dir=str(registry.data_dir),
                job_id=claimed.job_id,
                worker_id=claimed.worker_id,
                layout=claimed.layout,
            )
        )
    held = threading.Thread(target=build_and_store, args=(tasks[0],))
    held.start()
    assert gate.wait_held() == tasks[0].job_id
    progress = registry.get_job(job_id=tasks[0].job_id).progress
    assert 0.5 <= progress < 1.0  # recorded before the hold was announced
    # One hold per shutting of the gate: the other build passes while the first waits.
    assert build_and_store(tasks[1]).grid_points == 400
    assert held.is_alive()
    gate.open()
    held.join(SAFETY_TIMEOUT_S)
    assert not held.is_alive()


def test_build_refuses_too_many_cells(tmp_path: Path) -> None:
    task = BuildTask(
        database_url=f"sqlite:///{tmp_path / 'unused.sqlite3'}",
        data_dir=str(tmp_path),
        job_id="0" * 32,
        worker_id="w",
        layout=paper_layout().to_mapping(),
        max_cells=100,
    )
    with pytest.raises(ProblemSizeError, match="400 grid points"):
        build_and_store(task)
    assert not (tmp_path / "matrices").exists()
