"""Survey calibrations of a room: submit (admin), list and read the reports."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response, status

from app.schemas import Calibration, CalibrationCreate, CalibrationsList, Job
from app.services.calibrations import request_calibration
from app.services.public import calibration_public, job_public

from .deps import AdminRole, AnyRole, RegistryDep, RoomId
from .errors import problem_responses
from .fingerprints import JOB_ACCEPTED_HEADERS, JOB_POLL_AFTER_S

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms/{room_id}/calibrations", tags=["calibration"])

CalibrationId = Annotated[
    str, Path(max_length=64, description="the calibration's id (from the POST or the list)")
]


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
    job = request_calibration(registry, room_id=room_id, body=body)
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    response.headers["Retry-After"] = str(JOB_POLL_AFTER_S)
    return job_public(job)


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
