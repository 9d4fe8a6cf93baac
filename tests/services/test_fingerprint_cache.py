"""The per-process fingerprint/solver cache, on a real registry with ready fingerprints."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from app.clock import FakeClock
from app.main import create_app
from app.registry import Registry
from app.registry.errors import FingerprintNotReady, RoomNotFound
from app.services.fingerprint_cache import FingerprintCache
from app.telemetry import Metrics
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
