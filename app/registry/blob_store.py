"""Matrix files kept in the registry database, with a verified copy on the local disk.

Several hosts that share only the database (no filesystem) serve the same rooms: a build
writes each matrix file into the local content-addressed :class:`~.store.MatrixStore` (the
cache) and then uploads it to ``matrix_blobs`` / ``matrix_blob_chunks`` in ordered chunks
of :data:`CHUNK_BYTES`; a host that lacks the file, or whose copy fails its sha256 check,
streams it back chunk by chunk into its cache, hashing as it writes. Neither direction holds
a whole file in memory, so hall-sized matrices (hundreds of MB) move in bounded memory.

A blob whose bytes do not hash to its name is deleted when found: the caller reports the
matrix corrupt (503) and queues a rebuild, which uploads the file again.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Literal, Protocol

from sqlalchemy import Engine, delete, insert, select
from sqlalchemy.exc import IntegrityError

from app.clock import SystemClock

from ._schema import matrix_blob_chunks, matrix_blobs
from ._typing import StoredMatrix
from .db import translate_errors, write_transaction
from .records import MatrixInfo
from .store import STALE_TEMPORARY_SECONDS, MatrixStore

__all__ = [
    "CHUNK_BYTES",
    "MATRIX_STORES",
    "DatabaseMatrixStore",
    "MatrixStorage",
    "MatrixStoreKind",
    "open_matrix_store",
]

# Rows stamped here (key use, blob upload) are records, not timing logic: real time.
_SYSTEM_CLOCK = SystemClock()

# Large enough that a 500 MB file is ~125 round trips, small enough that a chunk (and the
# driver's encoded copy of it) is a negligible amount of memory next to a build.
CHUNK_BYTES = 4 * 1024 * 1024

MatrixStoreKind = Literal["files", "database"]
MATRIX_STORES: tuple[MatrixStoreKind, ...] = ("files", "database")


class _BlobVanished(Exception):
    """A chunk disappeared while it was read (its room was deleted meanwhile)."""


class MatrixStorage(Protocol):
    """What the registry and the builds need from a matrix store."""

    @property
    def root(self) -> Path:
        """The folder of the (local) matrix files."""
        ...

    def put(self, matrix: StoredMatrix) -> tuple[MatrixInfo, int]:
        """Store ``matrix`` (idempotent); its metadata and size in bytes."""
        ...

    def path_for(self, sha256: str, fmt: str) -> Path:
        """Where the local file with this hash and format lives."""
        ...

    def verified_path(self, sha256: str, fmt: str) -> Path | None:
        """A local file with exactly these bytes, or None when missing or corrupt."""
        ...

    def delete(self, sha256: str, fmt: str) -> None:
        """Forget a file (missing is fine)."""
        ...

    def remove_stale_temporaries(self, older_than_s: float = ...) -> int:
        """Delete leftovers of interrupted writes; how many were removed."""
        ...


class DatabaseMatrixStore:
    """Matrix files in the database, cached (and verified) under ``cache_root``.

    Parameters
    ----------
    engine : Engine
        The registry database (SQLite or PostgreSQL), migrated to ``0005`` or later.
    cache_root : Path
        Directory of the local cache (a :class:`~.store.MatrixStore`).
    """

    def __init__(self, engine: Engine, cache_root: Path) -> None:
        self.engine = engine
        self.cache = MatrixStore(cache_root)

    @property
    def root(self) -> Path:
        """The folder of the verified local cache."""
        return self.cache.root

    def put(self, matrix: StoredMatrix) -> tuple[MatrixInfo, int]:
        """Write ``matrix`` into the cache, then upload it unless the database has it."""
        info, size_bytes = self.cache.put(matrix)
        self.upload_cached(info.sha256, info.format, size_bytes)
        return info, size_bytes

    def path_for(self, sha256: str, fmt: str) -> Path:
        """Where the cached file lives (it may be absent or stale; see verified_path)."""
        return self.cache.path_for(sha256, fmt)

    def verified_path(self, sha256: str, fmt: str) -> Path | None:
        """The cached file, fetched from the database first when missing or corrupt.

        None when the database has no such file or its bytes fail the sha256 check (the
        corrupt blob is then deleted, so that a rebuild stores it again).
        """
        cached = self.cache.verified_path(sha256, fmt)
        if cached is not None:
            return cached
        with translate_errors(), self.engine.connect() as conn:
            head = conn.execute(
                select(matrix_blobs.c.upload_id, matrix_blobs.c.n_chunks).where(
                    matrix_blobs.c.sha256 == sha256, matrix_blobs.c.format == fmt
                )
            ).one_or_none()
        if head is None:
            return None
        try:
            fetched = self.cache.write_verified(
                sha256, fmt, self._chunks(str(head.upload_id), int(head.n_chunks))
            )
        except _BlobVanished:
            return None
        if fetched is None:
            with write_transaction(self.engine) as conn:
                conn.execute(delete(matrix_blobs).where(matrix_blobs.c.upload_id == head.upload_id))
        return fetched

    def delete(self, sha256: str, fmt: str) -> None:
        """Delete the file from the database (its chunks go with it) and from the cache."""
        with write_transaction(self.engine) as conn:
            conn.execute(
                delete(matrix_blobs).where(
                    matrix_blobs.c.sha256 == sha256, matrix_blobs.c.format == fmt
                )
            )
        self.cache.delete(sha256, fmt)

    def remove_stale_temporaries(self, older_than_s: float = STALE_TEMPORARY_SECONDS) -> int:
        """Temporaries of interrupted cache writes (an upload is one transaction: none)."""
        return self.cache.remove_stale_temporaries(older_than_s)

    def upload_cached(self, sha256: str, fmt: str, size_bytes: int) -> None:
        """Upload the cached file of ``size_bytes`` unless the database has that file.

        The head row and then the file's chunks, read one at a time, go in one transaction.
        A file the database already has is trusted as it is: a corrupt one is found (and
        deleted) by the next host that fetches it.
        """
        with translate_errors(), self.engine.connect() as conn:
            known = conn.execute(
                select(matrix_blobs.c.upload_id).where(
                    matrix_blobs.c.sha256 == sha256, matrix_blobs.c.format == fmt
                )
            ).one_or_none()
        if known is not None:
            return
        path = self.cache.path_for(sha256, fmt)
        upload_id = uuid.uuid4().hex
        n_chunks = max(1, -(-size_bytes // CHUNK_BYTES))
        try:
            with write_transaction(self.engine) as conn, path.open("rb") as source:
                conn.execute(
                    insert(matrix_blobs).values(
                        sha256=sha256,
                        format=fmt,
                        upload_id=upload_id,
                        size_bytes=size_bytes,
                        n_chunks=n_chunks,
                        created_at=_SYSTEM_CLOCK.now(),
                    )
                )
                for index in range(n_chunks):
                    conn.execute(
                        insert(matrix_blob_chunks).values(
                            upload_id=upload_id,
                            chunk_index=index,
                            data=source.read(CHUNK_BYTES),
                        )
                    )
        except IntegrityError:
            # Another host uploaded the same content first; its bytes are these bytes.
            return

    def _chunks(self, upload_id: str, n_chunks: int) -> Iterator[bytes]:
        """The blob's chunks in order, one query each (one chunk in memory at a time)."""
        with translate_errors(), self.engine.connect() as conn:
            for index in range(n_chunks):
                data = conn.execute(
                    select(matrix_blob_chunks.c.data).where(
                        matrix_blob_chunks.c.upload_id == upload_id,
                        matrix_blob_chunks.c.chunk_index == index,
                    )
                ).scalar_one_or_none()
                if data is None:
                    raise _BlobVanished(upload_id)
                yield bytes(data)


def open_matrix_store(kind: MatrixStoreKind, *, data_dir: Path, engine: Engine) -> MatrixStorage:
    """The store of that kind: files under ``data_dir / "matrices"``, or the database with
    that directory as its cache."""
    root = data_dir / "matrices"
    if kind == "database":
        return DatabaseMatrixStore(engine, root)
    return MatrixStore(root)
