"""Opening epochs and taking terminals' posts (the registry's epoch store does the storing).

A post is fitted to the epoch's fingerprint here (:func:`app.services.masking.fit_to_fingerprint`,
the rule localize uses), and refused when it detected no LED
(:func:`app.services.localization.nothing_detected`), so the store only ever sees one
amplitude (or None: not detected) per fingerprint LED.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from app.errors import InvalidFields
from app.registry import Registry
from app.registry.records import EpochRecord, EpochSettings
from app.schemas import EpochCreate

from .localization import nothing_detected
from .masking import fit_to_fingerprint

__all__ = ["open_epoch", "open_requested_epoch", "post_to_epoch"]


def open_requested_epoch(
    registry: Registry, *, room_id: str, body: EpochCreate, max_terminals: int
) -> EpochRecord:
    """Open the epoch a request asks for, with at most ``max_terminals`` terminals.

    Raises
    ------
    InvalidFields
        ``min_terminals`` above ``max_terminals`` (the epoch could never be solved).
    RoomNotFound, FingerprintNotReady, FingerprintNotFound
    """
    if body.min_terminals > max_terminals:
        raise InvalidFields(
            [
                (
                    "min_terminals",
                    f"at most {max_terminals} terminals may join an epoch, "
                    f"so min_terminals {body.min_terminals} could never be reached",
                )
            ]
        )
    wanted = EpochSettings(
        model=body.model,
        solver=body.solver,
        targets=body.targets,
        min_terminals=body.min_terminals,
        max_terminals=max_terminals,
        window_s=body.window_s,
        fingerprint_version=0,  # pinned by open_epoch
        leds=0,
        track=body.track,
    )
    return open_epoch(
        registry, room_id=room_id, settings=wanted, fingerprint_version=body.fingerprint_version
    )


def open_epoch(
    registry: Registry,
    *,
    room_id: str,
    settings: EpochSettings,
    fingerprint_version: int | None = None,
) -> EpochRecord:
    """Open an epoch pinned to ``fingerprint_version`` (default: the current one), whose
    version and LED count replace those in ``settings``.

    Raises
    ------
    RoomNotFound, FingerprintNotReady, FingerprintNotFound
    """
    fingerprint = registry.get_fingerprint(room_id=room_id, version=fingerprint_version)
    pinned = replace(settings, fingerprint_version=fingerprint.version, leds=fingerprint.leds)
    return registry.epochs.create(room_id=room_id, settings=pinned, now=registry.clock.now())


def post_to_epoch(
    registry: Registry,
    *,
    room_id: str,
    epoch_id: str,
    terminal_id: str,
    amplitudes: Sequence[float | None],
    detection_floor: float | None = None,
) -> EpochRecord:
    """Store or replace one terminal's amplitudes (one per room LED, or per fingerprint LED;
    None for an LED it did not detect) and its own ``detection_floor`` while the epoch is open.

    Raises
    ------
    EpochNotFound, EpochClosed, EpochFull
    MeasurementError
        Amplitudes sized for neither the room's nor the fingerprint's LEDs.
    InvalidFields
        No LED detected among the fingerprint's (every amplitude None).
    """
    now = registry.clock.now()
    record = registry.epochs.get(room_id=room_id, epoch_id=epoch_id)
    fitted = list(amplitudes)
    if record.status == "open" and record.expires_at > now:  # else the store says it closed
        pinned = record.settings
        masked = registry.get_fingerprint(
            room_id=room_id, version=pinned.fingerprint_version
        ).masked_leds
        fitted = fit_to_fingerprint(amplitudes, masked, pinned.leds, field="amplitudes")
        errors = nothing_detected(fitted, field="amplitudes")  # as localize's terminals
        if errors:
            raise InvalidFields(errors)
    return registry.epochs.post_measurement(
        room_id=room_id,
        epoch_id=epoch_id,
        terminal_id=terminal_id,
        amplitudes=fitted,
        detection_floor=detection_floor,
        now=now,
    )
