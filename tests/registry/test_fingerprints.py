"""Fingerprint versions: readiness, the version switch, matrix verification, loading."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from app.registry import Registry
from app.registry.errors import (
    CorruptMatrix,
    FingerprintNotFound,
    FingerprintNotReady,
    MatrixNotFound,
    RoomNotFound,
)
from app.services.matrices import rebuilding_if_corrupt
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.presets import paper_layout
from tests.db_fixtures import (
    build_now,
    claim_next,
    hall_layout,
    overwrite,
    record_build,
    small_layout,
    stored_build,
)


def test_not_ready_before_the_first_build(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    assert registry.current_version(room_id=room.id) is None
    with pytest.raises(FingerprintNotReady):
        registry.get_fingerprint(room_id=room.id, version=None)
    with pytest.raises(FingerprintNotFound):
        registry.get_fingerprint(room_id=room.id, version=1)
    with pytest.raises(RoomNotFound):
        registry.get_fingerprint(room_id="0" * 32, version=1)
    with pytest.raises(RoomNotFound):
        registry.current_version(room_id="0" * 32)
    assert registry.list_fingerprints(room_id=room.id) == []


def test_paper_room_fingerprint_metadata_and_files(
    registry: Registry, paper_fingerprint: Fingerprint
) -> None:
    room = registry.create_room(name="Paper", layout=paper_layout().to_mapping())
    assert build_now(registry, room_id=room.id) == 1
    ready = registry.get_room(room_id=room.id)
    assert (ready.fingerprint_status, ready.fingerprint_version) == ("ready", 1)
    record = registry.get_fingerprint(room_id=room.id, version=None)
    assert (record.version, record.layout_version, record.leds, record.grid_points) == (
        1,
        1,
        16,
        400,
    )
    assert record.job_id == room.job_id
    assert {name: info.shape for name, info in record.matrices.items()} == {
        "H": (16, 400),
        "J": (16, 400),
        "psi": (136, 400),
    }
    expected = {
        "H": paper_fingerprint.dense_gains(),
        "J": paper_fingerprint.power_matrix(),
        "psi": paper_fingerprint.correlation_matrix(),
    }
    for name, info in record.matrices.items():
        path = registry.matrix_path(room_id=room.id, version=1, name=name)
        assert info.format == "npy"
        assert hashlib.sha256(path.read_bytes()).hexdigest() == info.sha256
        np.testing.assert_allclose(np.load(path), expected[name], rtol=1e-12, atol=0)
    with pytest.raises(MatrixNotFound):
        registry.matrix_path(room_id=room.id, version=1, name="G")
    with pytest.raises(FingerprintNotFound):
        registry.matrix_path(room_id=room.id, version=2, name="H")


def test_load_fingerprint_equals_direct_build(
    registry: Registry, paper_fingerprint: Fingerprint
) -> None:
    room = registry.create_room(name="Paper room", layout=paper_layout().to_mapping())
    build_now(registry, room_id=room.id)
    loaded = registry.load_fingerprint(room_id=room.id, version=1)
    assert loaded.layout == paper_fingerprint.layout
    assert loaded.gains.shape == paper_fingerprint.gains.shape
    np.testing.assert_array_equal(loaded.gains.toarray(), paper_fingerprint.gains.toarray())
    np.testing.assert_array_equal(loaded.gains.indices, paper_fingerprint.gains.indices)


def test_rebuild_is_a_new_version_with_the_same_bytes(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    build_now(registry, room_id=room.id)
    job = registry.request_build(room_id=room.id)
    assert job.id != room.job_id
    assert build_now(registry, room_id=room.id) == 2
    versions = registry.list_fingerprints(room_id=room.id)
    assert [fp.version for fp in versions] == [2, 1]
    assert versions[0].matrices == versions[1].matrices
    assert registry.get_job(job_id=job.id).fingerprint_version == 2


def test_version_switches_only_when_the_build_finishes(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    build_now(registry, room_id=room.id)
    registry.request_build(room_id=room.id)
    claimed = claim_next(registry, lease_seconds=30)
    assert claimed is not None
    during = registry.get_room(room_id=room.id)
    assert (during.fingerprint_status, during.fingerprint_version) == ("building", 1)
    assert registry.get_fingerprint(room_id=room.id, version=None).version == 1
    assert record_build(registry, claimed, stored_build(registry, claimed))
    after = registry.get_room(room_id=room.id)
    assert (after.fingerprint_status, after.fingerprint_version) == ("ready", 2)


def test_build_of_an_old_layout_does_not_become_current(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout(2))
    old = claim_next(registry, lease_seconds=30)
    assert old is not None
    registry.replace_room(
        room_id=room.id, name="a", layout=small_layout(3), expected_layout_version=1
    )
    assert record_build(registry, old, stored_build(registry, old)) == 1
    stale = registry.get_room(room_id=room.id)
    assert (stale.fingerprint_version, stale.fingerprint_status) == (None, "pending")
    assert registry.get_fingerprint(room_id=room.id, version=1).layout_version == 1
    assert build_now(registry, room_id=room.id) == 2
    fresh = registry.get_fingerprint(room_id=room.id, version=None)
    assert (fresh.version, fresh.layout_version, fresh.leds) == (2, 2, 3)


def test_completion_after_delete_records_nothing(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    claimed = claim_next(registry, lease_seconds=30)
    assert claimed is not None
    build = stored_build(registry, claimed)
    registry.delete_room(room_id=room.id)
    assert record_build(registry, claimed, build) is None


@pytest.mark.parametrize("damage", ["flip", "truncate", "remove"])
def test_corrupt_matrix_is_refused_and_the_rebuild_repairs_it(
    registry: Registry, damage: str
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    build_now(registry, room_id=room.id)
    path = registry.matrix_path(room_id=room.id, version=1, name="H")
    good = path.read_bytes()
    if damage == "flip":
        overwrite(path, good[:-1] + bytes([good[-1] ^ 0xFF]))
    elif damage == "truncate":
        overwrite(path, good[:100])
    else:
        path.unlink()
    with pytest.raises(CorruptMatrix, match="sha256"):
        registry.matrix_path(room_id=room.id, version=1, name="H")
    assert registry.get_room(room_id=room.id).fingerprint_status == "ready"  # reads never write
    # The service's reads queue the repair explicitly.
    with (
        pytest.raises(CorruptMatrix, match="rebuild"),
        rebuilding_if_corrupt(registry, room_id=room.id),
    ):
        registry.matrix_path(room_id=room.id, version=1, name="H")
    rebuild = registry.get_room(room_id=room.id)
    assert rebuild.fingerprint_status == "pending"
    assert rebuild.fingerprint_version == 1
    with pytest.raises(CorruptMatrix), rebuilding_if_corrupt(registry, room_id=room.id):
        registry.load_fingerprint(room_id=room.id, version=1)  # coalesces onto the same job
    assert registry.get_room(room_id=room.id).job_id == rebuild.job_id
    assert build_now(registry, room_id=room.id) == 2
    assert path.read_bytes() == good
    assert registry.matrix_path(room_id=room.id, version=1, name="H") == path


def test_layout_snapshot_is_kept_per_version(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout(2))
    build_now(registry, room_id=room.id)
    registry.replace_room(
        room_id=room.id, name="a", layout=small_layout(3), expected_layout_version=1
    )
    build_now(registry, room_id=room.id)
    first = registry.load_fingerprint(room_id=room.id, version=1)
    second = registry.load_fingerprint(room_id=room.id, version=2)
    assert (first.n_leds, second.n_leds) == (2, 3)
    direct = build_fingerprint(layout_from_mapping(small_layout(2)))
    np.testing.assert_array_equal(first.gains.toarray(), direct.gains.toarray())


def test_large_hall_stores_sparse_h_and_no_psi(registry: Registry) -> None:
    hall = hall_layout()
    room = registry.create_room(name="Hall", layout=hall.to_mapping())
    build_now(registry, room_id=room.id)
    record = registry.get_fingerprint(room_id=room.id, version=None)
    assert sorted(record.matrices) == ["H"]
    assert record.matrices["H"].format == "npz"
    with pytest.raises(MatrixNotFound, match="psi"):
        registry.matrix_path(room_id=room.id, version=1, name="psi")
    loaded = registry.load_fingerprint(room_id=room.id, version=1)
    direct = build_fingerprint(hall)
    assert not loaded.is_dense
    assert (loaded.gains != direct.gains).nnz == 0


def test_files_of_a_lost_build_can_be_dropped(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    claimed = claim_next(registry, lease_seconds=30)
    assert claimed is not None
    build = stored_build(registry, claimed)
    files = [(info.sha256, info.format) for info, _ in build.matrices.values()]
    paths = [registry.store.path_for(sha, fmt) for sha, fmt in files]
    registry.delete_room(room_id=room.id)
    assert all(path.exists() for path in paths)  # written, but not yet recorded
    registry.drop_unreferenced_files(files)
    assert not any(path.exists() for path in paths)
