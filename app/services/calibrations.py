"""Survey calibrations: a request checked against the room's layout, then queued as a job.

The job (:mod:`app.jobs.calibrate`) fits and masks; this module only decides whether the
request can apply to the room, naming each field that cannot.
"""

from __future__ import annotations

from typing import Any

from app.errors import InvalidFields
from app.registry import JobRecord, Registry
from app.schemas import CalibrationCreate
from app.vlp.layout import Layout
from app.vlp.layout_mapping import layout_from_mapping

__all__ = ["MAX_SURVEY_ERRORS", "request_calibration"]

# A survey of thousands of rows off the room names its first rows, not all of them.
MAX_SURVEY_ERRORS = 20


def request_calibration(registry: Registry, *, room_id: str, body: CalibrationCreate) -> JobRecord:
    """Queue a calibration of the room's current layout from ``body``: its job.

    Raises
    ------
    RoomNotFound
    InvalidFields
        A survey row or masked LED that is not in the room, every LED masked, or
        ``dead_below`` above ``dimmed_below``.
    """
    record = registry.get_room(room_id=room_id)
    request = _checked_request(body, layout_from_mapping(record.layout))
    calibration = registry.create_calibration(
        room_id=room_id, layout_version=record.layout_version, request=request
    )
    return registry.get_job(job_id=calibration.job_id)


def _checked_request(body: CalibrationCreate, layout: Layout) -> dict[str, Any]:
    """The request as stored, after checking it against the room's layout."""
    n_leds, room = layout.n_leds, layout.room
    errors: list[tuple[str, str]] = []
    for k, row in enumerate(body.survey):
        if row.led >= n_leds:
            errors.append(
                (f"survey[{k}].led", f"LED {row.led} is not in [0, {n_leds}) of this room")
            )
        if row.x > room.length or row.y > room.width:
            errors.append(
                (
                    f"survey[{k}]",
                    f"({row.x!r}, {row.y!r}) m lies outside the room [0, {room.length}] x "
                    f"[0, {room.width}]",
                )
            )
        if len(errors) >= MAX_SURVEY_ERRORS:
            break
    errors += [
        (f"masked_leds[{k}]", f"LED {index} is not in [0, {n_leds}) of this room")
        for k, index in enumerate(body.masked_leds)
        if index >= n_leds
    ]
    if len(set(body.masked_leds)) >= n_leds:
        errors.append(("masked_leds", f"at least one of the {n_leds} LEDs must stay"))
    if body.dead_below > body.dimmed_below:
        errors.append(("dead_below", "dead_below must not exceed dimmed_below"))
    # "Not detected" rows say only that the amplitude is below the receiver's floor: the fit
    # takes them as censored, which needs at least one detected row to set the floor.
    detected = [row for row in body.survey if row.amplitude is not None]
    if body.survey and not detected:
        errors.append(("survey", "every row is null (not detected): nothing to fit"))
    if errors:
        raise InvalidFields(errors)
    return {
        "survey": [[row.x, row.y, row.led, row.amplitude] for row in body.survey],
        "masked_leds": sorted(set(body.masked_leds)),
        "mask_dead_leds": body.mask_dead_leds,
        "dimmed_below": body.dimmed_below,
        "dead_below": body.dead_below,
        "led_position_bound_m": body.led_position_bound_m,
        "led_tilt_bound_deg": body.led_tilt_bound_deg,
        "fit_reflectance": body.fit_reflectance,
        "fit_beams": body.fit_beams,
        "fit_gain_map": body.fit_gain_map,
        "apply_receiver_gain": body.apply_receiver_gain,
    }
