"""The services' own refusals: each names the body fields (as the body names them, without the
``body.`` prefix the HTTP layer adds) and nothing is stored or queued for a refused request."""

from __future__ import annotations

from typing import Any

import pytest

from app.errors import InvalidFields
from app.registry import Registry
from app.schemas import CalibrationCreate, EpochCreate, SimulationRequest
from app.services.calibrations import MAX_SURVEY_ERRORS, request_calibration
from app.services.epochs import open_requested_epoch
from app.services.simulation import check_simulation_request
from tests.db_fixtures import small_layout


def _fields(error: pytest.ExceptionInfo[InvalidFields]) -> list[str]:
    return [field for field, _ in error.value.errors]


@pytest.mark.parametrize(
    ("body", "fields"),
    [
        ({}, ["targets", "positions"]),
        ({"targets": 2, "positions": [[1.0, 1.0]]}, ["targets", "positions"]),
        ({"targets": 2, "snr_db": 20.0, "noise_std": 1e-6}, ["snr_db", "noise_std"]),
        ({"targets": 2, "impairments": {"gain_sd": 0.1}, "noise_std": 1e-6}, ["noise_std"]),
    ],
    ids=["neither", "both", "snr-and-noise", "impairments-and-noise"],
)
def test_contradicting_simulation_fields_are_named(body: dict[str, Any], fields: list[str]) -> None:
    with pytest.raises(InvalidFields) as refused:
        check_simulation_request(SimulationRequest.model_validate(body))
    assert _fields(refused) == fields


def test_a_consistent_simulation_request_passes() -> None:
    check_simulation_request(SimulationRequest.model_validate({"targets": 2, "snr_db": 20.0}))


@pytest.fixture
def room_id(registry: Registry) -> str:
    return registry.create_room(name="two LEDs", layout=small_layout(2)).id


def test_a_calibration_off_the_room_is_refused_field_by_field(
    registry: Registry, room_id: str
) -> None:
    body = CalibrationCreate.model_validate(
        {
            "survey": [
                {"x": 1.0, "y": 1.0, "led": 2, "amplitude": 1e-6},
                {"x": 2.5, "y": 1.0, "led": 0, "amplitude": 1e-6},
            ],
            "masked_leds": [0, 1, 5],
            "dimmed_below": 0.5,
            "dead_below": 0.6,
        }
    )
    with pytest.raises(InvalidFields) as refused:
        request_calibration(registry, room_id=room_id, body=body)
    assert _fields(refused) == [
        "survey[0].led",
        "survey[1]",
        "masked_leds[2]",
        "masked_leds",
        "dead_below",
    ]
    assert registry.list_calibrations(room_id=room_id) == []


def test_a_long_survey_off_the_room_names_its_first_rows_only(
    registry: Registry, room_id: str
) -> None:
    rows = [{"x": 1.0, "y": 1.0, "led": 7, "amplitude": 1e-6}] * (3 * MAX_SURVEY_ERRORS)
    body = CalibrationCreate.model_validate({"survey": rows})
    with pytest.raises(InvalidFields) as refused:
        request_calibration(registry, room_id=room_id, body=body)
    assert _fields(refused) == [f"survey[{k}].led" for k in range(MAX_SURVEY_ERRORS)]


def test_a_calibration_request_is_queued_as_its_job(registry: Registry, room_id: str) -> None:
    job = request_calibration(
        registry, room_id=room_id, body=CalibrationCreate.model_validate({"masked_leds": [1, 1]})
    )
    [calibration] = registry.list_calibrations(room_id=room_id)
    assert job.kind == "calibration" and calibration.job_id == job.id
    assert calibration.request["masked_leds"] == [1]


def test_an_epoch_that_could_never_fill_is_refused(registry: Registry, room_id: str) -> None:
    with pytest.raises(InvalidFields) as refused:
        open_requested_epoch(
            registry, room_id=room_id, body=EpochCreate(min_terminals=5), max_terminals=4
        )
    assert _fields(refused) == ["min_terminals"]
