"""Measurements over a room's M LEDs, mapped onto a fingerprint with masked LEDs.

A calibration may mask LEDs (dead ones, say): the fingerprint then has rows for the other
M' = M - masked LEDs only. Terminals keep sending per-LED values in the room's LED order (M
entries); the service drops the masked entries here, before validation. Values already over
the M' fingerprint LEDs (as `simulate` answers for such a version) pass unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence

from app.schemas import Measurement

from .errors import InvalidInput

__all__ = ["drop_masked_leds"]


def _kept(values: Sequence[float], keep: Sequence[int]) -> list[float]:
    return [values[i] for i in keep]


def _size_error(field: str, what: str, n_room: int, n_kept: int) -> InvalidInput:
    return InvalidInput(
        [
            (
                field,
                f"expected {what} for the room's {n_room} LEDs (the masked ones are dropped) "
                f"or for the fingerprint's {n_kept} unmasked LEDs",
            )
        ]
    )


def drop_masked_leds(
    body: Measurement, masked_leds: Sequence[int], n_fingerprint_leds: int
) -> Measurement:
    """``body`` with the masked LEDs' entries removed when it is sized for the whole room.

    Parameters
    ----------
    body : Measurement
    masked_leds : sequence of int
        Room LED indices that the fingerprint leaves out (ascending).
    n_fingerprint_leds : int
        M', the fingerprint's LED count.

    Raises
    ------
    InvalidInput
        When a value is sized for neither M nor M' LEDs.
    """
    if not masked_leds:
        return body
    masked = set(masked_leds)
    n_room = n_fingerprint_leds + len(masked)
    keep = [i for i in range(n_room) if i not in masked]
    if body.power is not None:
        if len(body.power) == n_room:
            return body.model_copy(update={"power": _kept(body.power, keep)})
        if len(body.power) != n_fingerprint_leds:
            raise _size_error("body.power", f"{n_room} entries", n_room, n_fingerprint_leds)
        return body
    if body.correlation is not None:
        return body.model_copy(update={"correlation": _correlation(body.correlation, keep, n_room)})
    terminals = body.terminals or []
    changed = [
        t.model_copy(update={"amplitudes": _kept(t.amplitudes, keep)})
        if len(t.amplitudes) == n_room
        else t
        for t in terminals
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
