"""Layouts from their public ``RoomLayout`` mapping (:meth:`~.layout.Layout.to_mapping`'s
inverse), each field checked and named when it is wrong."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from .beams import Beam
from .constants import (
    DEFAULT_HALF_POWER_ANGLE_DEG,
    DEFAULT_LED_NORMAL,
    DEFAULT_PILOT_AMPLITUDE,
)
from .errors import GeometryError
from .gain_map import GainMap
from .layout import AmplitudeError, Grid, Layout, Led, Receiver, Reflectance, Room

__all__ = ["layout_from_mapping"]


def layout_from_mapping(data: Mapping[str, Any]) -> Layout:
    """Build a :class:`Layout` from the public ``RoomLayout`` mapping (defaults applied).

    Raises
    ------
    GeometryError
        On a missing or invalid field; ``field`` names it.
    """
    try:
        room = Room(
            **{k: float(data["room"][k]) for k in ("length", "width", "height")},
            reflectance=_reflectance_from_mapping(data["room"].get("reflectance")),
        )
        grid = Grid(
            step=float(data["grid"]["step"]),
            receiver_height=float(data["grid"]["receiver_height"]),
            receiver_height_sd=_float_field(
                data["grid"].get("receiver_height_sd", 0.0), "grid.receiver_height_sd"
            ),
            receiver_tilt_sd=_float_field(
                data["grid"].get("receiver_tilt_sd", 0.0), "grid.receiver_tilt_sd"
            ),
            receivers_level=_bool_field(
                data["grid"].get("receivers_level", False), "grid.receivers_level"
            ),
        )
        receiver = Receiver(**{k: float(v) for k, v in dict(data.get("receiver") or {}).items()})
        leds_in: Sequence[Mapping[str, Any]] = data["leds"]
        leds = tuple(
            Led(
                x=float(led["x"]),
                y=float(led["y"]),
                z=float(room.height if led.get("z") is None else led["z"]),
                half_power_angle_deg=float(
                    led.get("half_power_angle_deg", DEFAULT_HALF_POWER_ANGLE_DEG)
                ),
                pilot_amplitude=float(led.get("pilot_amplitude", DEFAULT_PILOT_AMPLITUDE)),
                normal=_normal_field(led.get("normal"), index),
                beam=_beam_field(led.get("beam"), index),
            )
            for index, led in enumerate(leds_in)
        )
    except (KeyError, TypeError) as exc:
        raise GeometryError(f"incomplete layout: missing or invalid {exc}", field=None) from exc
    return Layout(
        room=room,
        grid=grid,
        leds=leds,
        receiver=receiver,
        name=str(data.get("name", "")),
        amplitude_error=_amplitude_error_from_mapping(data.get("amplitude_error")),
        gain_map=_gain_map_from_mapping(data.get("gain_map")),
    )


def _gain_map_from_mapping(value: object) -> GainMap | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise GeometryError(
            f"gain_map must be an object with points, weights and length_scale_m, got {value!r}",
            field="gain_map",
        )
    try:
        points = tuple((float(x), float(y)) for x, y in value["points"])
        weights = tuple(tuple(float(w) for w in row) for row in value["weights"])
        scale = float(value["length_scale_m"])
    except (KeyError, TypeError, ValueError) as exc:
        raise GeometryError(
            f"gain_map is incomplete or not numeric: {exc}", field="gain_map"
        ) from exc
    return GainMap(points, weights, scale)


def _amplitude_error_from_mapping(value: object) -> AmplitudeError | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise GeometryError(
            f"amplitude_error must be an object with noise_sd, relative_sd and dof, got {value!r}",
            field="amplitude_error",
        )
    tail_dof = value.get("tail_dof")
    return AmplitudeError(
        **{
            name: _float_field(value.get(name), f"amplitude_error.{name}")
            for name in ("noise_sd", "relative_sd", "dof")
        },
        tail_dof=None if tail_dof is None else _float_field(tail_dof, "amplitude_error.tail_dof"),
    )


def _float_field(value: object, name: str) -> float:
    if value is None:
        return 0.0
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise GeometryError(f"{name} must be a number, got {value!r}", field=name)
    try:
        return float(value)
    except ValueError as exc:
        raise GeometryError(f"{name} must be a number, got {value!r}", field=name) from exc


def _bool_field(value: object, name: str) -> bool:
    if value is None:
        return False
    if not isinstance(value, bool):
        raise GeometryError(f"{name} must be true or false, got {value!r}", field=name)
    return value


def _reflectance_from_mapping(value: object) -> Reflectance | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise GeometryError(
            f"room.reflectance must be an object with walls, floor and ceiling, got {value!r}",
            field="room.reflectance",
        )
    parts: dict[str, float] = {}
    for name in ("walls", "floor", "ceiling"):
        where = f"room.reflectance.{name}"
        if value.get(name) is None:
            raise GeometryError(f"{where} is missing", field=where)
        parts[name] = _float_field(value[name], where)
    return Reflectance(**parts)


def _normal_field(value: object, index: int) -> tuple[float, float, float]:
    """An LED's ``normal``: absent or null is straight down; else three numbers."""
    if value is None:
        return DEFAULT_LED_NORMAL
    name = f"leds[{index}].normal"
    if isinstance(value, str | bytes) or not isinstance(value, Sequence) or len(value) != 3:
        raise GeometryError(f"{name} must be three numbers [nx, ny, nz], got {value!r}", field=name)
    nx, ny, nz = (_float_field(v, name) for v in value)
    return (nx, ny, nz)


def _beam_field(value: object, index: int) -> Beam | None:
    """An LED's ``beam``: absent or null is Lambertian; else angles and intensities."""
    if value is None:
        return None
    name = f"leds[{index}].beam"
    if not isinstance(value, Mapping):
        raise GeometryError(
            f"{name} must be an object with angles_deg and relative_intensity, got {value!r}",
            field=name,
        )
    parts: dict[str, tuple[float, ...]] = {}
    for key in ("angles_deg", "relative_intensity"):
        items = value.get(key)
        if isinstance(items, str | bytes) or not isinstance(items, Sequence):
            raise GeometryError(f"{name}.{key} must be a list of numbers", field=f"{name}.{key}")
        parts[key] = tuple(_float_field(v, f"{name}.{key}") for v in items)
    try:
        return Beam(**parts)
    except GeometryError as exc:
        raise GeometryError(str(exc), field=f"{name}.{exc.field}") from exc
