"""Opening epochs and taking terminals' posts (the registry's epoch store does the storing).

A post is fitted to the epoch's fingerprint here (:func:`app.services.masking.fit_to_fingerprint`,
the rule localize uses), so the store only ever sees one amplitude per fingerprint LED.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from app.registry import Registry
from app.registry.records import EpochRecord, EpochSettings

from .masking import fit_to_fingerprint

__all__ = ["open_epoch", "post_to_epoch"]


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
    amplitudes: Sequence[float],
) -> EpochRecord:
    """Store or replace one terminal's amplitudes (one per room LED, or per fingerprint LED)
    while the epoch is open.

    Raises
    ------
    EpochNotFound, EpochClosed, EpochFull
    MeasurementError
        Amplitudes sized for neither the room's nor the fingerprint's LEDs.
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
    return registry.epochs.post_measurement(
        room_id=room_id, epoch_id=epoch_id, terminal_id=terminal_id, amplitudes=fitted, now=now
    )
