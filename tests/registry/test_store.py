"""The content-addressed matrix store: deterministic bytes, atomic writes, verification."""

from __future__ import annotations

import hashlib
import io
import os
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from app.registry.store import STALE_TEMPORARY_SECONDS, MatrixStore, matrix_bytes
from tests.db_fixtures import overwrite


def _sparse(rng: np.random.Generator) -> sp.csr_array:
    dense = rng.random((7, 30))
    dense[dense < 0.7] = 0.0
    return sp.csr_array(dense)


def test_npy_bytes_match_numpy_save(rng: np.random.Generator) -> None:
    array = rng.random((5, 11))
    payload, fmt = matrix_bytes(array)
    reference = io.BytesIO()
    np.save(reference, array)
    assert fmt == "npy"
    assert payload == reference.getvalue()


def test_npz_is_deterministic_and_scipy_readable(
    rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    matrix = _sparse(rng)
    first, fmt = matrix_bytes(matrix)
    # A later wall clock must not change the bytes (np.savez would stamp the zip entries).
    monkeypatch.setattr("time.time", lambda: 4_000_000_000.0)
    second, _ = matrix_bytes(sp.csr_array(matrix.toarray()))
    assert fmt == "npz"
    assert first == second
    with zipfile.ZipFile(io.BytesIO(first)) as archive:
        assert {info.date_time for info in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    path = tmp_path / "m.npz"
    path.write_bytes(first)
    loaded = sp.load_npz(path)
    assert isinstance(loaded, sp.csr_array)
    np.testing.assert_array_equal(loaded.toarray(), matrix.toarray())


def test_put_names_file_by_sha256_and_is_idempotent(
    rng: np.random.Generator, tmp_path: Path
) -> None:
    store = MatrixStore(tmp_path / "store")
    array = rng.random((3, 4))
    info, size = store.put(array)
    path = store.path_for(info.sha256, info.format)
    assert path.read_bytes() == matrix_bytes(array)[0]
    assert hashlib.sha256(path.read_bytes()).hexdigest() == info.sha256
    assert path.name == f"{info.sha256}.npy"
    assert size == path.stat().st_size
    assert info.shape == (3, 4)
    mtime = path.stat().st_mtime_ns
    assert store.put(array.copy())[0] == info
    assert path.stat().st_mtime_ns == mtime  # a verified file is not rewritten
    leftovers = [p for p in path.parent.iterdir() if p.name.startswith(".tmp-")]
    assert leftovers == []


def test_verify_detects_corruption_and_put_repairs_it(
    rng: np.random.Generator, tmp_path: Path
) -> None:
    store = MatrixStore(tmp_path)
    array = rng.random((4, 4))
    info, _ = store.put(array)
    path = store.path_for(info.sha256, info.format)
    assert store.verify(path, info.sha256)
    good = path.read_bytes()
    overwrite(path, good[:-8] + b"\0" * 8)
    assert not store.verify(path, info.sha256)
    store.put(array)
    assert path.read_bytes() == good
    assert store.verify(path, info.sha256)
    path.unlink()
    assert not store.verify(path, info.sha256)


def test_failed_write_leaves_no_partial_file(
    rng: np.random.Generator, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = MatrixStore(tmp_path)
    array = rng.random((2, 2))

    def broken_fsync(fd: int) -> None:
        del fd
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        store.put(array)
    assert [p for p in tmp_path.rglob("*") if p.is_file()] == []


def test_path_for_rejects_bad_names(tmp_path: Path) -> None:
    store = MatrixStore(tmp_path)
    with pytest.raises(ValueError, match="sha256"):
        store.path_for("../../etc", "npy")
    with pytest.raises(ValueError, match="sha256"):
        store.path_for("a" * 64, "pkl")


def _rot(path: Path) -> None:
    """Flip the last byte keeping size and mtime, as bit rot would."""
    stat = path.stat()
    payload = bytearray(path.read_bytes())
    payload[-1] ^= 0xFF
    os.chmod(path, 0o644)
    path.write_bytes(bytes(payload))
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))


def test_corruption_that_keeps_mtime_and_size_is_found_on_reverification(
    rng: np.random.Generator, tmp_path: Path
) -> None:
    trusting = MatrixStore(tmp_path, reverify_after_s=3600.0)
    checking = MatrixStore(tmp_path, reverify_after_s=0.0)
    info, _ = trusting.put(rng.random((3, 3)))
    path = trusting.path_for(info.sha256, info.format)
    assert trusting.verify(path, info.sha256) and checking.verify(path, info.sha256)
    _rot(path)
    assert trusting.verify(path, info.sha256)  # within its trust window: not re-hashed
    assert not checking.verify(path, info.sha256)
    assert not MatrixStore(tmp_path).verify(path, info.sha256)  # a fresh process re-hashes


def test_stale_temporaries_are_removed_and_fresh_ones_kept(
    rng: np.random.Generator, tmp_path: Path
) -> None:
    store = MatrixStore(tmp_path)
    assert MatrixStore(tmp_path / "absent").remove_stale_temporaries() == 0
    info, _ = store.put(rng.random((2, 3)))
    path = store.path_for(info.sha256, info.format)
    stale = path.parent / ".tmp-killed-writer.npy"
    fresh = path.parent / ".tmp-live-writer.npy"
    stale.write_bytes(b"half a matrix")
    fresh.write_bytes(b"being written")
    old = time.time() - STALE_TEMPORARY_SECONDS - 60
    os.utime(stale, (old, old))
    assert store.remove_stale_temporaries() == 1
    assert not stale.exists() and fresh.exists()
    assert store.verify(path, info.sha256)


def test_a_large_matrix_is_streamed_to_disk_not_held_as_bytes(tmp_path: Path) -> None:
    """Storing a sparse matrix of 4 * 10^6 nonzeros allocates far less than its file (written
    and hashed in chunks), and the file holds exactly :func:`matrix_bytes` of it."""
    import tracemalloc

    n_rows, per_row = 64, 62_500  # 4 * 10^6 nonzeros: 32 MB of gains, 16 MB of indices
    indices = np.tile(np.arange(0, 2 * per_row, 2, dtype=np.int32), n_rows)
    indptr = np.arange(0, n_rows * per_row + 1, per_row, dtype=np.int32)
    data = np.random.default_rng(5).random(indices.shape[0])
    matrix = sp.csr_array((data, indices, indptr), shape=(n_rows, 2 * per_row))
    store = MatrixStore(tmp_path)
    tracemalloc.start()
    try:
        info, size = store.put(matrix)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    path = store.path_for(info.sha256, info.format)
    assert size == path.stat().st_size > 32_000_000  # at least the gains
    assert peak < size / 2, (peak, size)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == info.sha256
    assert path.read_bytes() == matrix_bytes(matrix)[0]
    loaded = sp.load_npz(path)
    assert (loaded != matrix).nnz == 0
