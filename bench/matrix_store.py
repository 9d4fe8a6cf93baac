"""Store the million-point hall's H in PostgreSQL and fetch it on a second "host".

Builds H of :func:`bench.hall_build.million_point_hall`, writes it into the local cache of one
:class:`app.registry.blob_store.DatabaseMatrixStore`, uploads it (4 MiB chunks, one
transaction), then fetches it into the empty cache of a second store on the same database,
as an API process on another machine would. Reports the file size, the upload and fetch
times and the Python heap peak (tracemalloc) of each step: a whole file held in memory would
show as a peak of the file's size.

    python -m bench.matrix_store [--database-url postgresql+psycopg://...]

The database gets a throwaway schema, dropped at the end.
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
import tracemalloc
import uuid
from collections.abc import Sequence
from pathlib import Path

import psycopg
from sqlalchemy import make_url

from app.registry import Registry
from app.registry.blob_store import CHUNK_BYTES, DatabaseMatrixStore
from app.vlp.fingerprints import build_fingerprint
from bench._common import machine_record
from bench.hall_build import million_point_hall

__all__ = ["main"]

DEFAULT_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


def _admin(url: str) -> psycopg.Connection[tuple[object, ...]]:
    parsed = make_url(url)
    return psycopg.connect(
        host=parsed.host or "127.0.0.1",
        port=parsed.port or 5432,
        dbname=parsed.database or "test",
        user=parsed.username or "postgres",
        password=parsed.password,
        autocommit=True,
    )


def _measure(database_url: str, work: Path) -> dict[str, object]:
    # Two hosts sharing one database: each registry's store caches under its own data_dir.
    registry = Registry(
        database_url=database_url, data_dir=work / "host-a", matrix_store="database"
    )
    other = Registry(database_url=database_url, data_dir=work / "host-b", matrix_store="database")
    registry.migrate()
    try:
        writer, reader = registry.store, other.store
        assert isinstance(writer, DatabaseMatrixStore) and isinstance(reader, DatabaseMatrixStore)
        fingerprint = build_fingerprint(million_point_hall())
        started = time.perf_counter()
        info, size_bytes = writer.cache.put(fingerprint.gains)
        cached = time.perf_counter()
        del fingerprint

        tracemalloc.start()
        upload_started = time.perf_counter()
        writer.upload_cached(info.sha256, info.format, size_bytes)
        uploaded = time.perf_counter()
        upload_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        fetched_path = reader.verified_path(info.sha256, info.format)
        fetched = time.perf_counter()
        fetch_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert fetched_path is not None, "the fetched file failed its sha256 check"
        return {
            "file": f"H.{info.format}",
            "file_mib": round(size_bytes / 2**20, 1),
            "chunk_mib": CHUNK_BYTES / 2**20,
            "compress_and_cache_s": round(cached - started, 1),
            "upload_s": round(uploaded - upload_started, 1),
            "fetch_and_verify_s": round(fetched - uploaded, 1),
            "upload_heap_peak_mib": round(upload_peak / 2**20, 1),
            "fetch_heap_peak_mib": round(fetch_peak / 2**20, 1),
            "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        }
    finally:
        registry.dispose()
        other.dispose()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m bench.matrix_store``."""
    parser = argparse.ArgumentParser(prog="python -m bench.matrix_store")
    parser.add_argument("--database-url", default=DEFAULT_URL)
    args = parser.parse_args(argv)
    schema = f"bench_{uuid.uuid4().hex[:12]}"
    with _admin(args.database_url) as admin:
        admin.execute(f'CREATE SCHEMA "{schema}"')
    url = make_url(args.database_url).update_query_dict({"options": f"-csearch_path={schema}"})
    try:
        with tempfile.TemporaryDirectory() as tmp:
            report = _measure(url.render_as_string(hide_password=False), Path(tmp))
    finally:
        with _admin(args.database_url) as admin:
            admin.execute(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE')
    with Path("/proc/loadavg").open() as loadavg:
        report["load_average_1min"] = loadavg.read().split()[0]
    report["machine"] = machine_record()
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
