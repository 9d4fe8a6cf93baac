"""Measurements over a room's M LEDs, mapped onto a fingerprint with masked LEDs.

A calibration may mask LEDs (dead ones, say): the fingerprint then has rows for the other
M' = M - masked LEDs only. Terminals keep sending per-LED values in the room's LED order (M
entries); the service drops the masked entries here, before validation. Values already over
the M' fingerprint LEDs (as `simulate` answers for such a version) pass unchanged. The rule
lives in :func:`fit_to_fingerprint`; localize and epoch posts both use it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

from app.schemas import Measurement
from app.vlp.errors import MeasurementError

__all__ = ["drop_masked_leds", "fit_to_fingerprint"]


# Per-LED values: numbers, or numbers and nulls (terminals' LEDs not detected).
_Value = TypeVar("_Value", float, float | None)


def fit_to_fingerprint(
    values: Sequence[_Value],
    masked_leds: Sequence[int],
    n_fingerprint_leds: int,
    *,
    field: str,
) -> list[_Value]:
    """One value per fingerprint LED: values sent for the room's M LEDs lose the masked
    LEDs' entries; values already sized for the fingerprint's M' LEDs pass unchanged.

    Parameters
    ----------
    values : sequence of float (or None: an LED not detected)
        Per-LED values (power or amplitudes), M or M' of them.
    masked_leds : sequence of int
        Room LED indices that the fingerprint leaves out (ascending); may be empty.
    n_fingerprint_leds : int
        M', the fingerprint's LED count.
    field : str
        The request field ``values`` came from (named by the error).

    Raises
    ------
    MeasurementError
        When ``values`` is sized for neither M nor M' LEDs.
    """
    if len(values) == n_fingerprint_leds:
        return list(values)
    n_room = n_fingerprint_leds + len(masked_leds)
    if masked_leds and len(values) == n_room:
        masked = set(masked_leds)
        return [value for i, value in enumerate(values) if i not in masked]
    noun = "amplitudes" if field.endswith("amplitudes") else "entries"
    expected = (
        f"{n_fingerprint_leds} {noun} (one per LED)"
        if not masked_leds
        else f"{n_room} {noun} (one per room LED; the masked ones are dropped) or "
        f"{n_fingerprint_leds} (one per unmasked LED)"
    )
    raise MeasurementError(f"expected {expected}, got {len(values)}", field=field)


def drop_masked_leds(
    body: Measurement, masked_leds: Sequence[int], n_fingerprint_leds: int
) -> Measurement:
    """``body`` with the masked LEDs' entries removed when it is sized for the whole room.

    Each terminal's amplitudes are fitted (and their count checked) here, masked LEDs or not.

    Parameters
    ----------
    body : Measurement
    masked_leds : sequence of int
        Room LED indices that the fingerprint leaves out (ascending).
    n_fingerprint_leds : int
        M', the fingerprint's LED count.

    Raises
    ------
    MeasurementError
        When power or a terminal's amplitudes are sized for neither M nor M' LEDs.
    """
    if body.power is not None:
        if not masked_leds:
            return body  # its length is the science core's rule (measurement_from_power)
        power = fit_to_fingerprint(body.power, masked_leds, n_fingerprint_leds, field="power")
        return body.model_copy(update={"power": power})
    if body.correlation is not None:
        if not masked_leds:
            return body
        masked = set(masked_leds)
        n_room = n_fingerprint_leds + len(masked)
        keep = [i for i in range(n_room) if i not in masked]
        return body.model_copy(update={"correlation": _correlation(body.correlation, keep, n_room)})
    changed = [
        terminal.model_copy(
            update={
                "amplitudes": fit_to_fingerprint(
                    terminal.amplitudes,
                    masked_leds,
                    n_fingerprint_leds,
                    field=f"terminals[{index}].amplitudes",
                )
            }
        )
        for index, terminal in enumerate(body.terminals or [])
    ]
    return body.model_copy(update={"terminals": changed})


def _correlation(
    correlation: list[list[float]] | list[float], keep: list[int], n_room: int
) -> list[list[float]] | list[float]:
    """The kept rows and columns of a full matrix, or the kept pairs of its upper triangle.

    ``numpy.triu_indices`` order restricted to kept pairs is the triangle order of the
    kept sub-matrix, since ``keep`` is ascending.
    """
    if correlation and isinstance(correlation[0], list):
        rows = [row for row in correlation if isinstance(row, list)]
        if len(rows) == n_room and all(len(row) == n_room for row in rows):
            return [[rows[i][j] for j in keep] for i in keep]
        return correlation
    flat = [value for value in correlation if not isinstance(value, list)]
    if len(flat) != n_room * (n_room + 1) // 2:
        return correlation
    kept = set(keep)
    pairs = [(i, j) for i in range(n_room) for j in range(i, n_room)]
    return [value for (i, j), value in zip(pairs, flat, strict=True) if i in kept and j in kept]
