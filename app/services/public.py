"""Registry records as public schemas: the one place a record becomes what an answer shows.

Every router and service that answers with a room, job, fingerprint, calibration, epoch or
key turns its record into the schema here, so a resource reads the same in every answer.
"""

from __future__ import annotations

from typing import Any, TypeVar

from app.registry import CalibrationRecord, FingerprintRecord, JobRecord, RoomRecord
from app.registry.records import EpochRecord, KeyRecord
from app.schemas import (
    ApiKey,
    ApiKeyCreated,
    Calibration,
    Epoch,
    Fingerprint,
    FingerprintState,
    Job,
    JobResult,
    LedCalibration,
    Localization,
    MatrixMeta,
    Room,
)
from app.schemas.calibrations import (
    AmplitudeErrorReport,
    CalibratedReflectance,
    GainMapReport,
    ReflectanceSd,
)

__all__ = [
    "calibration_public",
    "created_key_public",
    "epoch_public",
    "fingerprint_public",
    "job_public",
    "key_public",
    "room_public",
]

_Model = TypeVar(
    "_Model", AmplitudeErrorReport, CalibratedReflectance, GainMapReport, ReflectanceSd
)


def room_public(record: RoomRecord) -> Room:
    """The public form of a room record."""
    return Room(
        id=record.id,
        name=record.name,
        layout=record.layout,
        layout_version=record.layout_version,
        created_at=record.created_at,
        updated_at=record.updated_at,
        fingerprint=FingerprintState(
            status=record.fingerprint_status,
            version=record.fingerprint_version,
            job_id=record.job_id,
        ),
    )


def fingerprint_public(record: FingerprintRecord) -> Fingerprint:
    """The public form of a fingerprint record."""
    return Fingerprint(
        version=record.version,
        room_id=record.room_id,
        layout_version=record.layout_version,
        leds=record.leds,
        grid_points=record.grid_points,
        built_at=record.built_at,
        build_seconds=record.build_seconds,
        job_id=record.job_id,
        calibration_id=record.calibration_id,
        masked_leds=list(record.masked_leds),
        matrices={
            name: MatrixMeta(shape=list(info.shape), sha256=info.sha256, format=info.format)
            for name, info in record.matrices.items()
        },
    )


def job_public(record: JobRecord) -> Job:
    """The public form of a job record."""
    result = (
        JobResult(
            fingerprint_version=record.fingerprint_version, calibration_id=record.calibration_id
        )
        if record.fingerprint_version is not None
        else None
    )
    return Job(
        id=record.id,
        kind=record.kind,
        room_id=record.room_id,
        status=record.status,
        progress=record.progress,
        error=record.error,
        created_at=record.created_at,
        started_at=record.started_at,
        finished_at=record.finished_at,
        result=result,
        attempts=record.attempts,
        layout_version=record.layout_version,
    )


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
        led_tilt_bound_deg=float(record.request.get("led_tilt_bound_deg", 0.0)),
        fit_reflectance=bool(record.request.get("fit_reflectance", False)),
        fit_beams=bool(record.request.get("fit_beams", False)),
        fit_gain_map=bool(record.request.get("fit_gain_map", False)),
        gain_map=_optional(GainMapReport, report.get("gain_map")),
        apply_receiver_gain=bool(record.request.get("apply_receiver_gain", True)),
        reflectance=_optional(CalibratedReflectance, report.get("reflectance")),
        reflectance_sd=_optional(ReflectanceSd, report.get("reflectance_sd")),
        amplitude_error=_optional(AmplitudeErrorReport, report.get("amplitude_error")),
    )


def _optional(model: type[_Model], value: dict[str, Any] | None) -> _Model | None:
    return None if value is None else model(**value)


def epoch_public(record: EpochRecord) -> Epoch:
    """The public form of an epoch record (``solving`` is shown as ``open``: the window has
    closed, ``closed`` says so, and the outcome is not there yet)."""
    settings = record.settings
    return Epoch(
        id=record.id,
        room_id=record.room_id,
        status="open" if record.status == "solving" else record.status,
        closed=record.status != "open",
        terminals=record.terminals,
        created_at=record.created_at,
        expires_at=record.expires_at,
        model=settings.model,
        solver=settings.solver,
        targets=settings.targets,
        min_terminals=settings.min_terminals,
        window_s=settings.window_s,
        fingerprint_version=settings.fingerprint_version,
        track=settings.track,
        localization=(None if record.localization is None else Localization(**record.localization)),
        error=record.error,
    )


def key_public(record: KeyRecord) -> ApiKey:
    """The public form of a key record (never its secret, which is not stored)."""
    return ApiKey.model_validate(
        {
            "id": record.id,
            "role": record.role,
            "label": record.label,
            "created_at": record.created_at,
            "last_used_at": record.last_used_at,
            "source": record.source,
        }
    )


def created_key_public(record: KeyRecord, *, key: str) -> ApiKeyCreated:
    """The answer that creates a key: its record with the secret, shown this once."""
    return ApiKeyCreated.model_validate(
        {
            "id": record.id,
            "role": record.role,
            "label": record.label,
            "key": key,
            "created_at": record.created_at,
        }
    )
