"""Calibrations in the registry and the queue: the job fits and builds the calibrated, masked
layout; later builds of that layout keep it; a PUT of the layout drops it."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from sqlalchemy import func, select

from app.registry import Registry
from app.registry._schema import calibrations
from app.registry.errors import PreconditionFailed, RecordNotFound
from app.vlp.calibration import simulate_survey
from app.vlp.layout_mapping import layout_from_mapping
from tests.db_fixtures import build_now, claim_next, raw_engine, small_layout


def _room(registry: Registry) -> str:
    """A 2 x 2 m room with 4 LEDs, its first (nominal) version built."""
    room = registry.create_room(name="Cal", layout=small_layout(4))
    assert build_now(registry, room_id=room.id) == 1
    return room.id


def _survey_request(
    registry: Registry, room_id: str, *, masked: list[int] | None = None
) -> dict[str, Any]:
    """A noiseless survey of the room with LED 1 dead and LED 2 at 40 %."""
    nominal = layout_from_mapping(registry.get_room(room_id=room_id).layout)
    scale = {1: 1e-9, 2: 0.4}
    true = replace(
        nominal,
        leds=tuple(
            replace(led, pilot_amplitude=scale.get(i, 1.0)) for i, led in enumerate(nominal.leds)
        ),
    )
    ticks = np.arange(0.25, 2.0, 0.5)
    survey = simulate_survey(true, np.array([(x, y) for x in ticks for y in ticks]))
    rows = np.column_stack((survey.points, survey.led_indices, survey.amplitudes))
    return {
        "survey": rows.tolist(),
        "masked_leds": masked or [],
        "mask_dead_leds": True,
        "dimmed_below": 0.75,
        "dead_below": 0.1,
    }


def _calibrate(registry: Registry, room_id: str, request: dict[str, Any]) -> tuple[str, int]:
    room = registry.get_room(room_id=room_id)
    record = registry.create_calibration(
        room_id=room_id, layout_version=room.layout_version, request=request
    )
    assert record.status == "queued" and record.report is None and not record.active
    version = build_now(registry, room_id=room_id)
    return record.id, version


def test_calibration_job_records_report_and_masked_fingerprint(registry: Registry) -> None:
    room_id = _room(registry)
    calibration_id, version = _calibrate(registry, room_id, _survey_request(registry, room_id))
    record = registry.get_calibration(room_id=room_id, calibration_id=calibration_id)
    assert record.status == "succeeded" and record.active
    assert record.fingerprint_version == version == 2
    assert record.masked_leds == (1,)
    assert record.report is not None
    flags = [led["flag"] for led in record.report["leds"]]
    assert flags == ["ok", "dead", "dimmed", "ok"]
    assert record.report["leds"][2]["relative_amplitude"] == pytest.approx(0.4, rel=1e-3)
    fingerprint = registry.get_fingerprint(room_id=room_id, version=None)
    assert fingerprint.version == 2 and fingerprint.leds == 3
    assert fingerprint.calibration_id == calibration_id and fingerprint.masked_leds == (1,)
    loaded = registry.load_fingerprint(room_id=room_id, version=2)
    assert loaded.n_leds == 3
    assert loaded.layout.leds[1].pilot_amplitude == pytest.approx(0.4, rel=1e-3)
    job = registry.get_job(job_id=record.job_id)
    assert job.kind == "calibration" and job.calibration_id == calibration_id
    assert registry.list_calibrations(room_id=room_id)[0].id == calibration_id


def test_rebuild_keeps_calibration_and_put_drops_it(registry: Registry) -> None:
    room_id = _room(registry)
    calibration_id, _ = _calibrate(registry, room_id, _survey_request(registry, room_id))
    registry.request_build(room_id=room_id)
    rebuilt = registry.get_fingerprint(
        room_id=room_id, version=build_now(registry, room_id=room_id)
    )
    assert rebuilt.calibration_id == calibration_id and rebuilt.leds == 3
    room = registry.get_room(room_id=room_id)
    registry.replace_room(
        room_id=room_id, name="Cal", layout=room.layout, expected_layout_version=1
    )
    version = build_now(registry, room_id=room_id)
    fresh = registry.get_fingerprint(room_id=room_id, version=version)
    assert fresh.calibration_id is None and fresh.leds == 4 and fresh.masked_leds == ()
    assert not registry.get_calibration(room_id=room_id, calibration_id=calibration_id).active


def test_mask_only_request_reuses_the_active_calibration(registry: Registry) -> None:
    room_id = _room(registry)
    first, _ = _calibrate(registry, room_id, _survey_request(registry, room_id))
    second, version = _calibrate(
        registry,
        room_id,
        {"survey": [], "masked_leds": [3], "mask_dead_leds": True},
    )
    record = registry.get_calibration(room_id=room_id, calibration_id=second)
    assert record.based_on == first and record.active
    assert record.masked_leds == (1, 3)
    assert record.report is not None and record.report["survey_rows"] == 0
    assert record.report["leds"][2]["flag"] == "dimmed"  # the re-used fit
    assert registry.get_fingerprint(room_id=room_id, version=version).leds == 2
    assert not registry.get_calibration(room_id=room_id, calibration_id=first).active


def test_mask_without_any_calibration_masks_the_nominal_model(registry: Registry) -> None:
    room_id = _room(registry)
    calibration_id, version = _calibrate(
        registry, room_id, {"survey": [], "masked_leds": [0], "mask_dead_leds": True}
    )
    record = registry.get_calibration(room_id=room_id, calibration_id=calibration_id)
    assert record.based_on is None and record.masked_leds == (0,)
    assert record.report is not None
    assert {led["flag"] for led in record.report["leds"]} == {"unsurveyed"}
    fingerprint = registry.load_fingerprint(room_id=room_id, version=version)
    nominal = layout_from_mapping(small_layout(4))
    assert fingerprint.layout.leds == nominal.leds[1:]


def test_calibration_queued_before_a_put_fails_as_superseded(registry: Registry) -> None:
    room_id = _room(registry)
    record = registry.create_calibration(
        room_id=room_id, layout_version=1, request=_survey_request(registry, room_id)
    )
    room = registry.get_room(room_id=room_id)
    registry.replace_room(
        room_id=room_id, name="Cal", layout=room.layout, expected_layout_version=1
    )
    claimed = claim_next(registry, lease_seconds=30)
    assert claimed is not None and claimed.kind == "build_fingerprint"  # the PUT's build
    failed = registry.get_calibration(room_id=room_id, calibration_id=record.id)
    assert failed.status == "failed" and failed.error is not None
    assert "superseded" in failed.error


def test_rebuild_request_does_not_join_a_queued_calibration(registry: Registry) -> None:
    room_id = _room(registry)
    record = registry.create_calibration(
        room_id=room_id, layout_version=1, request={"survey": [], "masked_leds": [0]}
    )
    job = registry.request_build(room_id=room_id)
    assert job.id != record.job_id and job.kind == "build_fingerprint"


def test_stale_layout_version_and_unknown_ids_are_refused(registry: Registry) -> None:
    room_id = _room(registry)
    with pytest.raises(PreconditionFailed):
        registry.create_calibration(room_id=room_id, layout_version=7, request={"survey": []})
    with pytest.raises(RecordNotFound):
        registry.get_calibration(room_id=room_id, calibration_id="nope")
    with pytest.raises(RecordNotFound):
        registry.list_calibrations(room_id="nope")


def test_delete_room_deletes_its_calibrations(registry: Registry) -> None:
    room_id = _room(registry)
    _calibrate(registry, room_id, _survey_request(registry, room_id))
    registry.delete_room(room_id=room_id)
    with pytest.raises(RecordNotFound):
        registry.list_calibrations(room_id=room_id)
    with raw_engine(registry).connect() as conn:
        assert conn.execute(select(func.count()).select_from(calibrations)).scalar_one() == 0
