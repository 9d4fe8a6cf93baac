"""A content-addressed store of immutable matrix files.

A matrix is saved as ``.npy`` (a dense float64 array) or ``.npz`` (a sparse CSR array in the
layout of ``scipy.sparse.save_npz``) and named after the sha256 of its bytes:
``<root>/<sha[:2]>/<sha>.<format>``. Files are written to a temporary file in the same
directory, fsynced and renamed over the final name, so a reader sees either nothing or the
whole file, and a rewrite repairs a corrupt file in place. The same array always gives the
same bytes (the zip entries of an ``.npz`` carry a fixed timestamp), hence the same name.
A writer killed mid-write leaves a ``.tmp-*`` file that nothing refers to and nothing serves;
:meth:`MatrixStore.remove_stale_temporaries` deletes such files once they are old enough
that no live writer can still own them.
"""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, BinaryIO, cast

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from ._typing import StoredMatrix
from .records import MatrixInfo

__all__ = [
    "FORMATS",
    "REVERIFY_SECONDS",
    "STALE_TEMPORARY_SECONDS",
    "MatrixStore",
    "matrix_bytes",
]

FORMATS = ("npy", "npz")
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)
_CHUNK = 1 << 20
_DEFLATE_LEVEL = 1
# Sub-folder of the root where files are written before their hash (their name) is known.
_STAGING = "staging"
_HEX = frozenset("0123456789abcdef")
_TEMP_PREFIX = ".tmp-"
# A temporary file lives for one write (seconds even for a 10^6-point hall); one untouched
# for an hour belongs to a writer that died. Several hosts may share the store, so the
# writer's liveness cannot be checked directly.
STALE_TEMPORARY_SECONDS = 3600.0
REVERIFY_SECONDS = 60.0


def _write_npy(handle: BinaryIO, array: NDArray[Any]) -> None:
    """``numpy.save``'s bytes of ``array``, written from its own memory in 1 MiB slices (no
    copy of the array, whatever ``handle`` is: a zip entry would get 16 MiB copies)."""
    array = np.ascontiguousarray(array)
    if array.dtype.hasobject:
        raise ValueError("object arrays are not stored")
    np.lib.format.write_array_header_1_0(handle, np.lib.format.header_data_from_array_1_0(array))
    raw = array.reshape(-1).view(np.uint8).data
    for start in range(0, raw.nbytes, _CHUNK):
        handle.write(raw[start : start + _CHUNK])


def _zip_entry(name: str, compress: bool) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
    info.compress_type = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    if compress:
        # ZipInfo's level attribute is public from Python 3.13 (compress_level).
        level_attribute = "compress_level" if hasattr(info, "compress_level") else "_compresslevel"
        setattr(info, level_attribute, _DEFLATE_LEVEL)
    return info


def _write_npz(handle: BinaryIO, matrix: sp.csr_array) -> None:
    entries: dict[str, NDArray[Any]] = {
        "indices": matrix.indices,
        "indptr": matrix.indptr,
        "format": np.array(b"csr"),
        "shape": np.array(matrix.shape),
        "data": matrix.data,
        "_is_array": np.array(True),
    }
    with zipfile.ZipFile(handle, "w") as archive:
        for key, value in entries.items():
            # Gains are float noise to deflate (a quarter smaller at 4x the write time of
            # everything else); the sorted column indices shrink five-fold at level 1.
            with archive.open(_zip_entry(key, compress=key != "data"), "w") as entry:
                _write_npy(cast(BinaryIO, entry), value)


def _write_matrix(handle: BinaryIO, matrix: StoredMatrix) -> str:
    """Write the deterministic file of ``matrix`` to ``handle`` (seekable); its format."""
    if sp.issparse(matrix):
        csr = sp.csr_array(matrix)
        csr.sort_indices()
        _write_npz(handle, csr)
        return "npz"
    _write_npy(handle, np.asarray(matrix, dtype=np.float64))
    return "npy"


def matrix_bytes(matrix: StoredMatrix) -> tuple[bytes, str]:
    """The deterministic file bytes of ``matrix`` and their format (``"npy"`` or ``"npz"``)."""
    buffer = io.BytesIO()
    fmt = _write_matrix(buffer, matrix)
    return buffer.getvalue(), fmt


def _sha256_of_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        while chunk := handle.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


class MatrixStore:
    """Immutable matrix files under ``root``, named by the sha256 of their content.

    Parameters
    ----------
    root : Path
        Directory of the store (created on first write).
    reverify_after_s : float, default=60.0
        How long a successful hash check is trusted for an unchanged (mtime, size) file.
        Corruption that keeps both (bit rot, a byte patched with its mtime restored) is
        found at most this long after the last check.
    """

    def __init__(self, root: Path, *, reverify_after_s: float = REVERIFY_SECONDS) -> None:
        self.root = root
        self.reverify_after_s = reverify_after_s
        self._verified: dict[Path, tuple[int, int, str, float]] = {}
        self._lock = threading.Lock()

    def path_for(self, sha256: str, fmt: str) -> Path:
        """Where the file with this hash and format lives."""
        if fmt not in FORMATS or len(sha256) != 64 or not set(sha256) <= _HEX:
            raise ValueError(f"expected a sha256 hex digest and one of {FORMATS}, got {fmt!r}")
        return self.root / sha256[:2] / f"{sha256}.{fmt}"

    def put(self, matrix: StoredMatrix) -> tuple[MatrixInfo, int]:
        """Store ``matrix`` (idempotent) and return its metadata and its size in bytes.

        An existing file of that name is kept when its bytes verify and replaced otherwise.
        """
        staging = self.root / _STAGING
        staging.mkdir(parents=True, exist_ok=True)
        handle, tmp_name = tempfile.mkstemp(dir=staging, prefix=_TEMP_PREFIX)
        tmp = Path(tmp_name)
        try:
            # Streamed to disk, then hashed from it: a hall-sized H is never held as bytes.
            with os.fdopen(handle, "w+b") as out:
                fmt = _write_matrix(out, matrix)
                out.flush()
                size = out.tell()
                out.seek(0)
                digest = hashlib.sha256()
                while chunk := out.read(_CHUNK):
                    digest.update(chunk)
                sha256 = digest.hexdigest()
                path = self.path_for(sha256, fmt)
                if not self.verify(path, sha256):
                    os.fsync(out.fileno())
                    self._publish(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        info = MatrixInfo(shape=tuple(int(n) for n in matrix.shape), sha256=sha256, format=fmt)
        return info, size

    def verify(self, path: Path, sha256: str) -> bool:
        """True when ``path`` exists and hashes to ``sha256``.

        A success is remembered per (path, mtime, size) for ``reverify_after_s``, so a file
        is hashed again after it changed on disk, and in any case once that time has passed.
        """
        try:
            stat = path.stat()
        except FileNotFoundError:
            return False
        key = (stat.st_mtime_ns, stat.st_size, sha256)
        now = time.monotonic()
        with self._lock:
            known = self._verified.get(path)
        if known is not None and known[:3] == key and now - known[3] < self.reverify_after_s:
            return True
        if _sha256_of_file(path) != sha256:
            with self._lock:
                self._verified.pop(path, None)
            return False
        with self._lock:
            self._verified[path] = (*key, now)
        return True

    def verified_path(self, sha256: str, fmt: str) -> Path | None:
        """The file with this hash and format when it exists and verifies, else None."""
        path = self.path_for(sha256, fmt)
        return path if self.verify(path, sha256) else None

    def write_verified(self, sha256: str, fmt: str, chunks: Iterable[bytes]) -> Path | None:
        """Write the file streamed as ``chunks`` under its name if they hash to ``sha256``.

        The bytes are hashed as they are written, so a large file is never held in memory;
        when the hash differs nothing is written and None is returned.
        """
        path = self.path_for(sha256, fmt)
        digest = hashlib.sha256()

        def hashed() -> Iterator[bytes]:
            for chunk in chunks:
                digest.update(chunk)
                yield chunk

        if not self._write_atomic(path, hashed(), accept=lambda: digest.hexdigest() == sha256):
            return None
        stat = path.stat()
        with self._lock:
            self._verified[path] = (stat.st_mtime_ns, stat.st_size, sha256, time.monotonic())
        return path

    def delete(self, sha256: str, fmt: str) -> None:
        """Remove a file (missing files are fine)."""
        path = self.path_for(sha256, fmt)
        with self._lock:
            self._verified.pop(path, None)
        path.unlink(missing_ok=True)

    def remove_stale_temporaries(self, older_than_s: float = STALE_TEMPORARY_SECONDS) -> int:
        """Delete temporary files of interrupted writes last modified ``older_than_s`` ago.

        Returns
        -------
        int
            How many files were removed.
        """
        if not self.root.is_dir():
            return 0
        cutoff = time.time() - older_than_s
        removed = 0
        for path in self.root.glob(f"*/{_TEMP_PREFIX}*"):
            try:
                if path.stat().st_mtime < cutoff:
                    path.unlink()
                    removed += 1
            except FileNotFoundError:  # another process removed it first
                continue
        return removed

    def _publish(self, tmp: Path, path: Path) -> None:
        """Rename the fsynced ``tmp`` over ``path`` (read-only) and sync the folder."""
        path.parent.mkdir(parents=True, exist_ok=True)
        os.chmod(tmp, 0o444)
        os.replace(tmp, path)
        directory = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)

    def _write_atomic(
        self, path: Path, chunks: Iterable[bytes], accept: Callable[[], bool] = lambda: True
    ) -> bool:
        """Write ``chunks`` to a temporary file and rename it over ``path`` if ``accept()``."""
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, tmp_name = tempfile.mkstemp(
            dir=path.parent, prefix=_TEMP_PREFIX, suffix=path.suffix
        )
        try:
            with os.fdopen(handle, "wb") as tmp:
                for chunk in chunks:
                    tmp.write(chunk)
                tmp.flush()
                os.fsync(tmp.fileno())
            if not accept():
                Path(tmp_name).unlink(missing_ok=True)
                return False
            os.chmod(tmp_name, 0o444)
            os.replace(tmp_name, path)
        except BaseException:
            Path(tmp_name).unlink(missing_ok=True)
            raise
        directory = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)
        return True
