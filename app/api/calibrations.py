"""Survey calibrations of a room: submit (admin), list and read the reports."""

from __future__ import annotations

from typing import Annotated, Any, TypeVar

from fastapi import APIRouter, Path, Response, status

from app.registry import CalibrationRecord
from app.schemas import Calibration, CalibrationCreate, CalibrationsList, Job, LedCalibration
from app.schemas.calibrations import CalibratedReflectance, ReflectanceSd
from app.vlp.layout import Layout, layout_from_mapping

from .deps import AdminRole, AnyRole, RegistryDep, RoomId
from .errors import InvalidInput, problem_responses
from .fingerprints import JOB_ACCEPTED_HEADERS, JOB_POLL_AFTER_S, job_public

__all__ = ["calibration_public", "router"]

_Model = TypeVar("_Model", CalibratedReflectance, ReflectanceSd)

router = APIRouter(prefix="/v1/rooms/{room_id}/calibrations", tags=["calibration"])

CalibrationId = Annotated[
    str, Path(max_length=64, description="the calibration's id (from the POST or the list)")
]


def calibration_public(record: CalibrationRecord) -> Calibration:
    """The public form of a calibration record (its report once the job succeeded)."""
    report = record.report or {}
    leds = report.get("leds")
    return Calibration(
        id=record.id,
        room_id=record.room_id,
        layout_version=record.layout_version,
        status=record.status,
        error=record.error,
        job_id=record.job_id,
        created_at=record.created_at,
        finished_at=record.finished_at,
        active=record.active,
        based_on=record.based_on,
        survey_rows=len(record.request.get("survey") or ()),
        requested_masked_leds=list(record.request.get("masked_leds") or ()),
        mask_dead_leds=bool(record.request.get("mask_dead_leds", True)),
        fingerprint_version=record.fingerprint_version,
        masked_leds=None if record.masked_leds is None else list(record.masked_leds),
        receiver_gain=report.get("receiver_gain"),
        noise_std=report.get("noise_std"),
        converged=report.get("converged"),
        leds=None if leds is None else [LedCalibration(**led) for led in leds],
        led_position_bound_m=float(record.request.get("led_position_bound_m", 0.0)),
        fit_reflectance=bool(record.request.get("fit_reflectance", False)),
        apply_receiver_gain=bool(record.request.get("apply_receiver_gain", True)),
        reflectance=_optional(CalibratedReflectance, report.get("reflectance")),
        reflectance_sd=_optional(ReflectanceSd, report.get("reflectance_sd")),
    )


def _optional(model: type[_Model], value: dict[str, Any] | None) -> _Model | None:
    return None if value is None else model(**value)


def _checked_request(body: CalibrationCreate, layout: Layout) -> dict[str, Any]:
    """The request as stored, after checking it against the room's layout (422 per field)."""
    n_leds, room = layout.n_leds, layout.room
    errors: list[tuple[str, str]] = []
    for k, row in enumerate(body.survey):
        if row.led >= n_leds:
            errors.append(
                (f"body.survey.{k}.led", f"LED {row.led} is not in [0, {n_leds}) of this room")
            )
        if row.x > room.length or row.y > room.width:
            errors.append(
                (
                    f"body.survey.{k}",
                    f"({row.x!r}, {row.y!r}) m lies outside the room [0, {room.length}] x "
                    f"[0, {room.width}]",
                )
            )
        if len(errors) >= 20:
            break
    errors += [
        (f"body.masked_leds.{k}", f"LED {index} is not in [0, {n_leds}) of this room")
        for k, index in enumerate(body.masked_leds)
        if index >= n_leds
    ]
    if len(set(body.masked_leds)) >= n_leds:
        errors.append(("body.masked_leds", f"at least one of the {n_leds} LEDs must stay"))
    if body.dead_below > body.dimmed_below:
        errors.append(("body.dead_below", "dead_below must not exceed dimmed_below"))
    if errors:
        raise InvalidInput(errors)
    return {
        "survey": [[row.x, row.y, row.led, row.amplitude] for row in body.survey],
        "masked_leds": sorted(set(body.masked_leds)),
        "mask_dead_leds": body.mask_dead_leds,
        "dimmed_below": body.dimmed_below,
        "dead_below": body.dead_below,
        "led_position_bound_m": body.led_position_bound_m,
        "fit_reflectance": body.fit_reflectance,
        "apply_receiver_gain": body.apply_receiver_gain,
    }


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    summary="Calibrate from a survey, or mask LEDs",
    responses={
        202: {"headers": JOB_ACCEPTED_HEADERS},
        **problem_responses(401, 403, 404, 412, 413, 422),
    },
)
def create_calibration(
    room_id: RoomId,
    body: CalibrationCreate,
    response: Response,
    registry: RegistryDep,
    _role: AdminRole,
) -> Job:
    """Queue a `calibration` job; poll `Location` (the job) until it `succeeded`.

    The job fits each LED's pilot amplitude, Lambertian order and `x`, `y` (within
    `led_position_bound_m`), the receiver gain and, with `fit_reflectance`, the surfaces'
    reflectances to the `survey` (least squares), stores the report
    (`GET .../calibrations/{id}`, id in the job's `result.calibration_id`) and builds a new
    fingerprint version from the calibrated model, which localization then uses. Later
    rebuilds of the same layout keep the calibration; a `PUT` of the layout drops it (it no
    longer applies to the new LEDs).

    Without a `survey`, only the mask changes (re-using the active calibration): e.g.
    `{"masked_leds": [10]}` drops a dead LED without a new layout or survey. Masked LEDs'
    rows leave the fingerprint; terminals keep sending the room's M amplitudes and the
    service drops the masked entries (a measurement over the M - masked LEDs is also taken).
    """
    record = registry.get_room(room_id=room_id)
    request = _checked_request(body, layout_from_mapping(record.layout))
    calibration = registry.create_calibration(
        room_id=room_id, layout_version=record.layout_version, request=request
    )
    response.headers["Location"] = f"/v1/jobs/{calibration.job_id}"
    response.headers["Retry-After"] = str(JOB_POLL_AFTER_S)
    return job_public(registry.get_job(job_id=calibration.job_id))


@router.get("", summary="List calibrations", responses=problem_responses(401, 404))
def list_calibrations(room_id: RoomId, registry: RegistryDep, _role: AnyRole) -> CalibrationsList:
    """The room's calibrations, newest first, with their reports."""
    records = registry.list_calibrations(room_id=room_id)
    return CalibrationsList(items=[calibration_public(record) for record in records])


@router.get(
    "/{calibration_id}", summary="Read a calibration report", responses=problem_responses(401, 404)
)
def get_calibration(
    room_id: RoomId, calibration_id: CalibrationId, registry: RegistryDep, _role: AnyRole
) -> Calibration:
    """Per LED: fitted pilot amplitude, Lambertian order and position, RMS residual before
    and after, flag (`ok`, `dimmed`, `dead`, `unsurveyed`) and whether it is masked; the
    receiver gain and the reflectances (fitted, with their sd, when asked).
    """
    return calibration_public(
        registry.get_calibration(room_id=room_id, calibration_id=calibration_id)
    )
