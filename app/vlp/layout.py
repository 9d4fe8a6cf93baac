"""Room layouts: the room box, the candidate grid, the receiver and the ceiling LEDs.

Conventions (those of the public ``RoomLayout`` schema, :mod:`app.schemas.rooms`): ``x`` in
[0, length], ``y`` in [0, width], ``z`` up from the floor, metres. The grid has
``n_x = length / step`` by ``n_y = width / step`` cells; the centre of cell ``(ix, iy)`` is
``((ix + 1/2) step, (iy + 1/2) step)`` and its column index is ``j = ix * n_y + iy``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .beams import Beam
from .constants import (
    DEFAULT_FILTER_GAIN,
    DEFAULT_FOV_DEG,
    DEFAULT_HALF_POWER_ANGLE_DEG,
    DEFAULT_LED_NORMAL,
    DEFAULT_PILOT_AMPLITUDE,
    DEFAULT_RECEIVER_AREA_M2,
    DEFAULT_REFRACTIVE_INDEX,
    MAX_RECEIVER_TILT_SD_DEG,
)
from .errors import GeometryError
from .gain_map import GainMap
from .typing import FloatArray, IntArray

__all__ = [
    "DEFAULT_FILTER_GAIN",
    "DEFAULT_FOV_DEG",
    "DEFAULT_HALF_POWER_ANGLE_DEG",
    "DEFAULT_LED_NORMAL",
    "DEFAULT_PILOT_AMPLITUDE",
    "DEFAULT_RECEIVER_AREA_M2",
    "DEFAULT_REFRACTIVE_INDEX",
    "GRID_RELATIVE_TOLERANCE",
    "AmplitudeError",
    "Beam",
    "Grid",
    "Layout",
    "Led",
    "Receiver",
    "Reflectance",
    "Room",
]

# length / step must be a whole number within this relative tolerance.
GRID_RELATIVE_TOLERANCE = 1e-9


def _check_positive(value: float, name: str) -> None:
    if not math.isfinite(value) or value <= 0:
        raise GeometryError(f"{name} must be a positive finite number, got {value!r}", field=name)


def _whole_cells(extent_m: float, step_m: float, name: str) -> int:
    ratio = extent_m / step_m
    cells = round(ratio)
    if cells < 1 or abs(ratio - cells) > GRID_RELATIVE_TOLERANCE * max(ratio, 1.0):
        raise GeometryError(
            f"grid.step {step_m!r} m must divide room.{name} {extent_m!r} m into a whole number "
            f"of cells, got {ratio!r}",
            field="grid.step",
        )
    return cells


@dataclass(frozen=True)
class Reflectance:
    """Diffuse (Lambertian) reflectance of the room's surfaces, each in [0, 1)."""

    walls: float
    floor: float
    ceiling: float

    def __post_init__(self) -> None:
        for name in ("walls", "floor", "ceiling"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and 0 <= value < 1):
                raise GeometryError(
                    f"room.reflectance.{name} must be a number in [0, 1), got {value!r}",
                    field=f"room.reflectance.{name}",
                )

    def to_mapping(self) -> dict[str, float]:
        """``{"walls": ..., "floor": ..., "ceiling": ...}``."""
        return {"walls": self.walls, "floor": self.floor, "ceiling": self.ceiling}


@dataclass(frozen=True)
class Room:
    """The room box in metres and, optionally, its surfaces' reflectance.

    ``reflectance`` None means line of sight only (the paper's model).
    """

    length: float
    width: float
    height: float
    reflectance: Reflectance | None = None

    def __post_init__(self) -> None:
        for name in ("length", "width", "height"):
            _check_positive(getattr(self, name), f"room.{name}")


@dataclass(frozen=True)
class AmplitudeError:
    """How far measured amplitudes scatter around this room's model, measured by a survey
    calibration at known points: each amplitude ``a`` of model value ``f`` errs with the scale
    ``sqrt(noise_sd^2 + (relative_sd f)^2)`` (the receiver's noise, and what the model misses in
    proportion to the signal: beams that are not Lambertian, reflections), both estimated
    from ``dof`` degrees of freedom. The error is Gaussian of that sd when ``tail_dof`` is
    None, else Student-t with ``tail_dof`` degrees of freedom and that scale (a survey whose
    few errors lie far beyond the rest's scale). Amplitudes in the layout's units (the
    terminals').
    """

    noise_sd: float
    relative_sd: float
    dof: float
    tail_dof: float | None = None

    def __post_init__(self) -> None:
        for name in ("noise_sd", "relative_sd"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise GeometryError(
                    f"amplitude_error.{name} must be a finite number >= 0, got {value!r}",
                    field=f"amplitude_error.{name}",
                )
        _check_positive(self.dof, "amplitude_error.dof")
        if self.tail_dof is not None:
            _check_positive(self.tail_dof, "amplitude_error.tail_dof")

    def to_mapping(self) -> dict[str, float]:
        mapping = {"noise_sd": self.noise_sd, "relative_sd": self.relative_sd, "dof": self.dof}
        if self.tail_dof is not None:
            mapping["tail_dof"] = self.tail_dof
        return mapping


@dataclass(frozen=True)
class Grid:
    """The candidate grid: cell size, the receivers' plane height and its spread, metres.

    ``receiver_height_sd`` is the standard deviation of the terminals' heights around
    ``receiver_height`` (0: all terminals at that height, the paper's model).
    ``receiver_tilt_sd`` is the standard deviation, in degrees, of each of the two tilt
    components of the terminals' photodiodes (hand-held phones): the answers' radii then
    hold what such tilts move an estimate by. ``receivers_level`` says the photodiodes face
    straight up (tags mounted level): no terminal is then fitted tilted and no radius allows
    for a tilt. With neither (0 and False, the default) the photodiodes are modelled level
    but the radii allow for tilts the residuals show, since hand-held phones may tilt.
    """

    step: float
    receiver_height: float
    receiver_height_sd: float = 0.0
    receiver_tilt_sd: float = 0.0
    receivers_level: bool = False

    def __post_init__(self) -> None:
        _check_positive(self.step, "grid.step")
        if not math.isfinite(self.receiver_height) or self.receiver_height < 0:
            raise GeometryError(
                f"grid.receiver_height must be a finite number >= 0, got {self.receiver_height!r}",
                field="grid.receiver_height",
            )
        if not math.isfinite(self.receiver_height_sd) or self.receiver_height_sd < 0:
            raise GeometryError(
                "grid.receiver_height_sd must be a finite number >= 0, "
                f"got {self.receiver_height_sd!r}",
                field="grid.receiver_height_sd",
            )
        tilt = self.receiver_tilt_sd
        if not math.isfinite(tilt) or not 0 <= tilt <= MAX_RECEIVER_TILT_SD_DEG:
            raise GeometryError(
                f"grid.receiver_tilt_sd must be a number of degrees in [0, "
                f"{MAX_RECEIVER_TILT_SD_DEG:g}], got {tilt!r}",
                field="grid.receiver_tilt_sd",
            )
        if not isinstance(self.receivers_level, bool):
            raise GeometryError(
                f"grid.receivers_level must be true or false, got {self.receivers_level!r}",
                field="grid.receivers_level",
            )
        if self.receivers_level and tilt > 0:
            raise GeometryError(
                "grid.receivers_level says the photodiodes face straight up, which "
                f"contradicts grid.receiver_tilt_sd = {tilt!r} degrees: set one of them",
                field="grid.receivers_level",
            )


@dataclass(frozen=True)
class Receiver:
    """The photodetector: area (m^2), field of view (degrees), filter gain, lens index."""

    area: float = DEFAULT_RECEIVER_AREA_M2
    fov_deg: float = DEFAULT_FOV_DEG
    filter_gain: float = DEFAULT_FILTER_GAIN
    refractive_index: float = DEFAULT_REFRACTIVE_INDEX

    def __post_init__(self) -> None:
        _check_positive(self.area, "receiver.area")
        _check_positive(self.filter_gain, "receiver.filter_gain")
        if not (math.isfinite(self.fov_deg) and 0 < self.fov_deg <= 90):
            raise GeometryError(
                f"receiver.fov_deg must be in (0, 90], got {self.fov_deg!r}",
                field="receiver.fov_deg",
            )
        if not (math.isfinite(self.refractive_index) and self.refractive_index >= 1):
            raise GeometryError(
                f"receiver.refractive_index must be >= 1, got {self.refractive_index!r}",
                field="receiver.refractive_index",
            )


@dataclass(frozen=True)
class Led:
    """A ceiling LED: position (m), half-power angle, pilot amplitude and the unit normal of
    its emitting face in room coordinates (default straight down, ``(0, 0, -1)``).

    ``beam``, when given, is the LED's emission pattern (a photometric table,
    :class:`~app.vlp.beams.Beam`) and the half-power angle is then only informative.

    A finite non-zero ``normal`` is stored normalised; that it points down (``nz < 0``) is
    checked by :class:`Layout`, which names the field.
    """

    x: float
    y: float
    z: float
    half_power_angle_deg: float = DEFAULT_HALF_POWER_ANGLE_DEG
    pilot_amplitude: float = DEFAULT_PILOT_AMPLITUDE
    normal: tuple[float, float, float] = DEFAULT_LED_NORMAL
    beam: Beam | None = None

    def __post_init__(self) -> None:
        values = tuple(float(v) for v in self.normal)
        length = math.sqrt(sum(v * v for v in values)) if len(values) == 3 else math.nan
        if math.isfinite(length) and length > 0 and values != DEFAULT_LED_NORMAL:
            object.__setattr__(self, "normal", tuple(v / length for v in values))
        elif values != self.normal:
            object.__setattr__(self, "normal", values)

    @property
    def tilted(self) -> bool:
        """The LED does not point straight down."""
        return self.normal != DEFAULT_LED_NORMAL


@dataclass(frozen=True)
class Layout:
    """A whole room layout, validated on construction.

    Raises
    ------
    GeometryError
        When a size is not positive, the step does not divide the room, an LED lies outside
        the room or not above the receivers' plane, or an angle is out of range. The error's
        ``field`` names the offending input (e.g. ``"leds[2].z"``).
    """

    room: Room
    grid: Grid
    leds: tuple[Led, ...]
    receiver: Receiver = field(default_factory=Receiver)
    name: str = ""
    # Set by a survey calibration (:func:`app.vlp.calibration.calibrated_layout`), not by
    # the room's admin: the radii of terminals that send their own amplitudes rest on it.
    amplitude_error: AmplitudeError | None = None
    # Set by a survey calibration too: what the survey shows of each LED's gain beyond its
    # model, as log factors over the floor (:mod:`app.vlp.gain_map`).
    gain_map: GainMap | None = None

    def __post_init__(self) -> None:
        room, grid = self.room, self.grid
        _whole_cells(room.length, grid.step, "length")
        _whole_cells(room.width, grid.step, "width")
        if grid.receiver_height >= room.height:
            raise GeometryError(
                f"grid.receiver_height {grid.receiver_height!r} m must be below the ceiling "
                f"(room.height {room.height!r} m)",
                field="grid.receiver_height",
            )
        if not self.leds:
            raise GeometryError("a layout needs at least one LED", field="leds")
        for index, led in enumerate(self.leds):
            self._check_led(index, led)
        if self.gain_map is not None and self.gain_map.n_leds != len(self.leds):
            raise GeometryError(
                f"gain_map has weights for {self.gain_map.n_leds} LEDs, the layout "
                f"{len(self.leds)}",
                field="gain_map.weights",
            )

    def _check_led(self, index: int, led: Led) -> None:
        where = f"leds[{index}]"
        room = self.room
        for name, value, upper in (("x", led.x, room.length), ("y", led.y, room.width)):
            if not (math.isfinite(value) and 0 <= value <= upper):
                raise GeometryError(
                    f"{where}.{name} = {value!r} m lies outside the room [0, {upper!r}]",
                    field=f"{where}.{name}",
                )
        if not (math.isfinite(led.z) and self.grid.receiver_height < led.z <= room.height):
            raise GeometryError(
                f"{where}.z = {led.z!r} m must be above the receivers "
                f"({self.grid.receiver_height!r} m) and at most room.height ({room.height!r} m)",
                field=f"{where}.z",
            )
        if not (math.isfinite(led.half_power_angle_deg) and 0 < led.half_power_angle_deg < 90):
            raise GeometryError(
                f"{where}.half_power_angle_deg must be in (0, 90), "
                f"got {led.half_power_angle_deg!r}",
                field=f"{where}.half_power_angle_deg",
            )
        if not (math.isfinite(led.pilot_amplitude) and led.pilot_amplitude > 0):
            raise GeometryError(
                f"{where}.pilot_amplitude must be positive, got {led.pilot_amplitude!r}",
                field=f"{where}.pilot_amplitude",
            )
        normal = led.normal
        if not (
            len(normal) == 3
            and all(math.isfinite(v) for v in normal)
            and abs(math.hypot(*normal) - 1.0) <= 1e-9
            and normal[2] < 0
        ):
            raise GeometryError(
                f"{where}.normal must be a finite non-zero vector [nx, ny, nz] with nz < 0 "
                f"(the LED faces down), got {list(normal)!r}",
                field=f"{where}.normal",
            )

    # -- grid -----------------------------------------------------------------------------
    @property
    def n_x(self) -> int:
        """Number of grid cells along x."""
        return round(self.room.length / self.grid.step)

    @property
    def n_y(self) -> int:
        """Number of grid cells along y."""
        return round(self.room.width / self.grid.step)

    @property
    def n_cells(self) -> int:
        """Number of grid points N."""
        return self.n_x * self.n_y

    @property
    def n_leds(self) -> int:
        """Number of LEDs M."""
        return len(self.leds)

    def cell_centres(self, indices: IntArray | None = None) -> FloatArray:
        """Centres of grid cells.

        Parameters
        ----------
        indices : ndarray of shape (n,), default=None
            Column indices ``j``; all N cells in column order when None.

        Returns
        -------
        centres : ndarray of shape (n, 2)
            ``(x, y)`` in metres.
        """
        if indices is None:
            indices = np.arange(self.n_cells, dtype=np.intp)
        ix, iy = np.divmod(np.asarray(indices, dtype=np.intp), self.n_y)
        step = self.grid.step
        return np.column_stack(((ix + 0.5) * step, (iy + 0.5) * step)).astype(np.float64)

    def nearest_cell(self, points: FloatArray) -> IntArray:
        """Column index of the grid cell containing each point (clipped to the room).

        Parameters
        ----------
        points : ndarray of shape (n, 2)
            ``(x, y)`` in metres.

        Returns
        -------
        indices : ndarray of shape (n,)
        """
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        n_y = self.n_y
        # Both axes in one pass of each operation (a solve's answer asks for a few points).
        cells = np.floor(pts[:, :2] / self.grid.step)
        np.maximum(cells, 0.0, out=cells)
        np.minimum(cells, np.array([self.n_x - 1, n_y - 1], dtype=np.float64), out=cells)
        index = cells.astype(np.intp)
        return np.asarray(index[:, 0] * n_y + index[:, 1], dtype=np.intp)

    # -- LED arrays -----------------------------------------------------------------------
    @property
    def led_positions(self) -> FloatArray:
        """LED positions, ndarray of shape (M, 3), metres."""
        return np.array([[led.x, led.y, led.z] for led in self.leds], dtype=np.float64)

    @property
    def half_power_angles_deg(self) -> FloatArray:
        """Half-power angles, ndarray of shape (M,), degrees."""
        return np.array([led.half_power_angle_deg for led in self.leds], dtype=np.float64)

    @property
    def pilot_amplitudes(self) -> FloatArray:
        """Pilot amplitudes x_i, ndarray of shape (M,)."""
        return np.array([led.pilot_amplitude for led in self.leds], dtype=np.float64)

    @property
    def led_normals(self) -> FloatArray:
        """Unit normals of the LEDs' emitting faces, ndarray of shape (M, 3)."""
        return np.array([led.normal for led in self.leds], dtype=np.float64)

    @property
    def has_tilted_leds(self) -> bool:
        """Some LED does not point straight down."""
        return any(led.tilted for led in self.leds)

    @property
    def has_beams(self) -> bool:
        """Some LED has a tabulated beam instead of a Lambertian one."""
        return any(led.beam is not None for led in self.leds)

    @property
    def beams(self) -> tuple[Beam | None, ...]:
        """Each LED's tabulated beam, None for a Lambertian one."""
        return tuple(led.beam for led in self.leds)

    def to_mapping(self) -> dict[str, Any]:
        """The layout as the JSON-like mapping of the public ``RoomLayout`` body.

        ``room.reflectance``, ``grid.receiver_height_sd``, ``grid.receiver_tilt_sd`` and
        ``grid.receivers_level`` appear only when set (not None, not 0, not False), so a layout
        without them maps exactly as before they existed; so do ``amplitude_error`` and
        ``gain_map``, which only a calibrated layout carries.
        """
        room: dict[str, Any] = {
            "length": self.room.length,
            "width": self.room.width,
            "height": self.room.height,
        }
        if self.room.reflectance is not None:
            room["reflectance"] = self.room.reflectance.to_mapping()
        grid: dict[str, Any] = {
            "step": self.grid.step,
            "receiver_height": self.grid.receiver_height,
        }
        if self.grid.receiver_height_sd > 0:
            grid["receiver_height_sd"] = self.grid.receiver_height_sd
        if self.grid.receiver_tilt_sd > 0:
            grid["receiver_tilt_sd"] = self.grid.receiver_tilt_sd
        if self.grid.receivers_level:
            grid["receivers_level"] = True
        mapping: dict[str, Any] = {
            "name": self.name,
            "room": room,
            "grid": grid,
            "receiver": {
                "area": self.receiver.area,
                "fov_deg": self.receiver.fov_deg,
                "filter_gain": self.receiver.filter_gain,
                "refractive_index": self.receiver.refractive_index,
            },
            "leds": [_led_mapping(led) for led in self.leds],
        }
        if self.amplitude_error is not None:
            mapping["amplitude_error"] = self.amplitude_error.to_mapping()
        if self.gain_map is not None:
            mapping["gain_map"] = self.gain_map.to_mapping()
        return mapping


def _led_mapping(led: Led) -> dict[str, Any]:
    """One LED of :meth:`Layout.to_mapping`; ``normal`` only when it is not straight down."""
    out: dict[str, Any] = {
        "x": led.x,
        "y": led.y,
        "z": led.z,
        "half_power_angle_deg": led.half_power_angle_deg,
        "pilot_amplitude": led.pilot_amplitude,
    }
    if led.tilted:
        out["normal"] = list(led.normal)
    if led.beam is not None:
        out["beam"] = led.beam.to_mapping()
    return out
