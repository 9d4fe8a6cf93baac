"""The per-process fingerprint/solver cache, on a real registry with ready fingerprints."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp

from app.clock import FakeClock
from app.main import create_app
from app.registry import Registry
from app.registry.errors import FingerprintNotReady, RoomNotFound
from app.schemas import Measurement
from app.services import localization
from app.services.fingerprint_cache import FingerprintCache, held_bytes
from app.services.localization import (
    WAITLESS_TARGETS,
    localize_in_memory,
    localize_measurement,
)
from app.telemetry import Metrics
from app.vlp.errors import ProblemSizeError
from tests.api.conftest import ADMIN, TestClient, make_settings, small_room, wait_for_room


@pytest.fixture
def two_ready_rooms(tmp_path: Path) -> Iterator[tuple[TestClient, Registry, list[str]]]:
    settings = make_settings(tmp_path, demo=True, embedded_workers=1)
    with TestClient(create_app(settings)) as client:
        second = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()["id"]
        first = client.get("/v1/rooms", headers=ADMIN).json()["items"][0]["id"]
        for room_id in (first, second):
            wait_for_room(client, room_id)
        registry: Registry = client.app.state.registry  # type: ignore[attr-defined]
        yield client, registry, [first, second]


def _counts(metrics: Metrics) -> tuple[float, float]:
    samples = {
        sample.labels["result"]: sample.value
        for family in metrics.cache.collect()
        for sample in family.samples
        if sample.name.endswith("_total")
    }
    return samples.get("hit", 0.0), samples.get("miss", 0.0)


def test_version_is_reread_only_after_the_interval(
    two_ready_rooms: tuple[TestClient, Registry, list[str]],
) -> None:
    client, registry, (room_id, _) = two_ready_rooms
    clock = FakeClock()
    cache = FingerprintCache(
        registry=registry, size=4, version_check_seconds=1.0, metrics=Metrics(), clock=clock
    )
    version = cache.current_version(room_id)
    assert version == registry.current_version(room_id=room_id)
    client.delete(f"/v1/rooms/{room_id}", headers=ADMIN)
    clock.advance(0.9)
    assert cache.current_version(room_id) == version  # still cached
    clock.advance(0.1)
    with pytest.raises(RoomNotFound):
        cache.current_version(room_id)


def test_room_without_ready_version_is_not_cached(tmp_path: Path) -> None:
    with TestClient(create_app(make_settings(tmp_path))) as client:
        room_id = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()["id"]
        registry: Registry = client.app.state.registry  # type: ignore[attr-defined]
        cache = FingerprintCache(
            registry=registry, size=2, version_check_seconds=60.0, metrics=Metrics()
        )
        with pytest.raises(FingerprintNotReady):
            cache.current_version(room_id)
        with pytest.raises(FingerprintNotReady):
            cache.current_version(room_id)


def test_lru_keeps_size_entries_and_solvers_with_them(
    two_ready_rooms: tuple[TestClient, Registry, list[str]],
) -> None:
    _, registry, (first, second) = two_ready_rooms
    metrics = Metrics()
    cache = FingerprintCache(registry=registry, size=1, version_check_seconds=1.0, metrics=metrics)
    v_first, v_second = cache.current_version(first), cache.current_version(second)
    fingerprint = cache.fingerprint(first, v_first)
    assert cache.fingerprint(first, v_first) is fingerprint
    assert _counts(metrics) == (1.0, 1.0)
    solver = cache.prepare(first, v_first, "correlation", "nnls")
    assert _counts(metrics) == (2.0, 1.0)  # one lookup, one count
    assert cache.prepare(first, v_first, "correlation", "nnls") is solver
    assert cache.prepare(first, v_first, "power", "nnls") is not solver
    assert solver.solver.fingerprint is fingerprint and solver.fingerprint is fingerprint
    assert solver.masked_leds == ()
    # A second room evicts the first (size 1): it is loaded again, with a new solver.
    assert cache.fingerprint(second, v_second).n_leds == 2
    assert cache.fingerprint(first, v_first) is not fingerprint
    assert cache.prepare(first, v_first, "correlation", "nnls") is not solver
    cache.forget(first)
    hits, misses = _counts(metrics)
    assert cache.fingerprint(first, v_first) is not None
    assert _counts(metrics) == (hits, misses + 1)


def test_held_bytes_counts_each_buffer_once() -> None:
    values = np.arange(1000, dtype=np.float64)  # 8000 bytes
    indices = np.arange(1000, dtype=np.int32)  # 4000
    indptr = np.array([0, 500, 1000], dtype=np.int32)  # 12
    matrix = sp.csr_array((values, indices, indptr), shape=(2, 1000))
    # a second sparse array sharing the index arrays, with values of its own (8000)
    scaled = sp.csr_array((values * 2.0, indices, indptr), shape=(2, 1000))
    held = [matrix, scaled, values[:10], {"again": values}, (indices,)]
    assert held_bytes(held) == 8000 + 4000 + 12 + 8000
    assert held_bytes(values[::2]) == 8000  # a view holds its whole base
    assert held_bytes(object(), "text", 3.0) == 0


def test_entries_beyond_the_byte_budget_are_dropped_least_recent_first(
    two_ready_rooms: tuple[TestClient, Registry, list[str]],
) -> None:
    _, registry, (first, second) = two_ready_rooms
    metrics = Metrics()
    sizes = {}
    for room_id in (first, second):
        alone = FingerprintCache(
            registry=registry, size=4, version_check_seconds=1.0, metrics=Metrics()
        )
        alone.prepare(room_id, alone.current_version(room_id), "correlation", "nnls")
        sizes[room_id] = alone.held_bytes
        assert sizes[room_id] > 0
    # Room to hold both: both stay.
    roomy = FingerprintCache(
        registry=registry,
        size=4,
        version_check_seconds=1.0,
        metrics=metrics,
        max_bytes=sizes[first] + sizes[second],
    )
    v_first, v_second = roomy.current_version(first), roomy.current_version(second)
    kept = roomy.prepare(first, v_first, "correlation", "nnls")
    roomy.prepare(second, v_second, "correlation", "nnls")
    assert roomy.held_bytes == sizes[first] + sizes[second]
    assert roomy.prepare(first, v_first, "correlation", "nnls") is kept
    # One byte less: preparing the second room drops the first, the least recently used.
    tight = FingerprintCache(
        registry=registry,
        size=4,
        version_check_seconds=1.0,
        metrics=metrics,
        max_bytes=sizes[first] + sizes[second] - 1,
    )
    dropped = tight.prepare(first, v_first, "correlation", "nnls")
    tight.prepare(second, v_second, "correlation", "nnls")
    assert tight.held_bytes == sizes[second]
    assert tight.prepare(first, v_first, "correlation", "nnls") is not dropped
    # A room larger than the whole budget is still served, alone.
    tiny = FingerprintCache(
        registry=registry, size=4, version_check_seconds=1.0, metrics=metrics, max_bytes=1
    )
    tiny.prepare(first, v_first, "correlation", "nnls")
    assert tiny.held_bytes == sizes[first]
    tiny.prepare(second, v_second, "correlation", "nnls")
    assert tiny.held_bytes == sizes[second]


def _measurement(client: TestClient, room_id: str) -> Measurement:
    simulated = client.post(
        f"/v1/rooms/{room_id}/simulate",
        json={"targets": 2, "snr_db": 30, "seed": 3},
        headers=ADMIN,
    )
    body = simulated.json()["measurement"]
    body.pop("fingerprint_version", None)
    return Measurement.model_validate(body)


def test_in_memory_lookup_answers_only_what_needs_no_registry_read(
    two_ready_rooms: tuple[TestClient, Registry, list[str]],
) -> None:
    _, registry, (room_id, _) = two_ready_rooms
    clock = FakeClock()
    metrics = Metrics()
    cache = FingerprintCache(
        registry=registry, size=2, version_check_seconds=1.0, metrics=metrics, clock=clock
    )
    assert cache.prepared_in_memory(room_id, None, "correlation", "omp") is None  # no version
    version = cache.current_version(room_id)
    assert cache.prepared_in_memory(room_id, None, "correlation", "omp") is None  # not loaded
    assert _counts(metrics) == (0.0, 0.0)  # nothing was read
    prepared = cache.prepare(room_id, version, "correlation", "omp")
    hits, misses = _counts(metrics)
    assert cache.prepared_in_memory(room_id, None, "correlation", "omp") == (version, prepared)
    assert cache.prepared_in_memory(room_id, version, "correlation", "omp") == (version, prepared)
    assert _counts(metrics) == (hits + 2, misses)
    assert cache.prepared_in_memory(room_id, version, "power", "omp") is None  # not prepared
    clock.advance(1.0)  # the current version is due for a re-read: only a pinned one answers
    assert cache.prepared_in_memory(room_id, None, "correlation", "omp") is None
    assert cache.prepared_in_memory(room_id, version, "correlation", "omp") == (version, prepared)


def test_a_waitless_localize_answers_as_the_thread_pool_one_or_leaves_it(
    two_ready_rooms: tuple[TestClient, Registry, list[str]],
) -> None:
    client, registry, (room_id, _) = two_ready_rooms
    metrics = Metrics()
    cache = FingerprintCache(registry=registry, size=2, version_check_seconds=60.0, metrics=metrics)
    body = _measurement(client, room_id)
    assert localize_in_memory(cache, metrics, room_id=room_id, body=body) is None  # cold
    assert _counts(metrics) == (0.0, 0.0)  # and nothing was read for it
    reference = localize_measurement(cache, metrics, room_id=room_id, body=body)
    answer = localize_in_memory(cache, metrics, room_id=room_id, body=body)
    assert answer is not None
    assert answer.estimates == reference.estimates
    assert answer.fingerprint_version == reference.fingerprint_version
    # a solve larger than the bound goes to the pool
    assert (
        localize_in_memory(cache, metrics, room_id=room_id, body=body, max_waitless_work=1) is None
    )
    # and one of more targets than the bound (each costs its own fits)
    crowd = body.model_copy(update={"targets": WAITLESS_TARGETS + 1})
    assert localize_in_memory(cache, metrics, room_id=room_id, body=crowd) is None
    # so does one whose solver is busy with another request
    prepared = cache.prepare(room_id, reference.fingerprint_version, "correlation", "gridless")
    with prepared.lock:
        assert localize_in_memory(cache, metrics, room_id=room_id, body=body) is None
    # a request over the service's limit is refused as on the pool's path
    with pytest.raises(ProblemSizeError):
        localize_in_memory(cache, metrics, room_id=room_id, body=body, max_work=1)


def test_a_localize_left_to_the_pool_is_read_there_only(
    two_ready_rooms: tuple[TestClient, Registry, list[str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Whether a request may be solved on the loop is decided from its counts: the
    # measurement of one that goes to the pool is made once, there.
    client, registry, (room_id, _) = two_ready_rooms
    metrics = Metrics()
    cache = FingerprintCache(registry=registry, size=2, version_check_seconds=60.0, metrics=metrics)
    body = _measurement(client, room_id)
    localize_measurement(cache, metrics, room_id=room_id, body=body)  # prepares the solver
    made: list[str] = []
    measurement_task = localization._measurement_task

    def counted(*args: Any) -> Any:
        made.append(args[1])
        return measurement_task(*args)

    monkeypatch.setattr(localization, "_measurement_task", counted)
    crowd = body.model_copy(update={"targets": WAITLESS_TARGETS + 1})
    assert localize_in_memory(cache, metrics, room_id=room_id, body=crowd) is None
    assert (
        localize_in_memory(cache, metrics, room_id=room_id, body=body, max_waitless_work=1) is None
    )
    assert made == []
    assert localize_in_memory(cache, metrics, room_id=room_id, body=body) is not None
    assert made == [room_id]


def test_a_room_localizer_looks_each_solver_up_once_and_answers_as_a_single_localize(
    two_ready_rooms: tuple[TestClient, Registry, list[str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    client, registry, (room_id, _) = two_ready_rooms
    metrics = Metrics()
    cache = FingerprintCache(registry=registry, size=2, version_check_seconds=60.0, metrics=metrics)
    body = _measurement(client, room_id)
    omp = body.model_copy(update={"solver": "omp"})
    references = [
        localize_measurement(cache, metrics, room_id=room_id, body=b) for b in (body, omp)
    ]
    lookups: list[tuple[str, str]] = []
    prepare = cache.prepare

    def counted(room: str, version: int, model: Any, name: str) -> Any:
        lookups.append((model, name))
        return prepare(room, version, model, name)

    monkeypatch.setattr(cache, "prepare", counted)
    localizer = localization.RoomLocalizer(cache, metrics, room_id=room_id)
    read = [localizer.read(b) for b in (body, omp, body, omp, body)]
    answers = [localizer.answer(localizer.solve(r)) for r in read]
    assert lookups == [("correlation", "gridless"), ("correlation", "omp")]
    for answer, reference in zip(answers, [*references, *references, references[0]], strict=True):
        assert answer.model_dump(exclude={"elapsed_ms"}) == reference.model_dump(
            exclude={"elapsed_ms"}
        )
