"""What makes a real room differ from the paper's model, and by how much.

Ranges and where they come from (``docs/explanation/real-rooms.md`` keeps the discussion):

- Surface reflectance: lighting-design practice takes ceiling 0.8, walls 0.5, floor 0.2 as
  defaults for ordinary rooms (the "80/50/20" rule); light, matte-painted walls reach 0.7-0.8.
  The realistic mix uses walls 0.7 / floor 0.2 / ceiling 0.8 (the light end for walls, the
  defaults for floor and ceiling).
- LED amplitude: manufacturers bin LEDs by flux in bins about 7 % wide with a stated tester
  tolerance of +-7.5 % (Lumileds LUXEON datasheets), so a 5 % relative sd between fittings is
  a moderate assumption; the 3-degree sd of the half-power angle is an assumption.
- Terminal gain (photodiode, filter, amplifier differ between phones): sd 10 %, an assumption.
- Heights (terminals held at desk or hand height) and tilts (a phone held in the hand):
  sd 5-15 cm and 0-10 / 0-20 degrees are assumptions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import GeometryError
from ..layout import Reflectance

__all__ = ["Impairments"]


@dataclass(frozen=True)
class Impairments:
    """Departures of the true room and terminals from the layout, drawn per simulation.

    Attributes
    ----------
    reflectance : Reflectance or None
        The TRUE surfaces' diffuse reflectance (whatever the layout says); None: no reflection.
    gain_sd : float
        Relative sd of each terminal's gain (log-normal with mean 1).
    height_sd_m : float
        Sd of the terminals' heights around ``grid.receiver_height``, metres.
    tilt_max_deg : float
        Photodiode tilt: polar angle uniform in [0, tilt_max_deg], azimuth uniform.
    led_amplitude_sd : float
        Relative sd of each LED's emitted pilot (log-normal with mean 1).
    led_half_power_sd_deg : float
        Sd of each LED's half-power angle, degrees.
    led_position_sd_m : float
        Sd of each LED's x and y, metres.
    led_tilt_max_deg : float
        Tilt of each LED's face from the layout's normal: polar angle uniform in
        [0, led_tilt_max_deg], azimuth uniform (a fixture hung slightly askew).
    common_scale : float
        One factor on every amplitude (e.g. a calibration gone stale).
    """

    reflectance: Reflectance | None = None
    gain_sd: float = 0.0
    height_sd_m: float = 0.0
    tilt_max_deg: float = 0.0
    led_amplitude_sd: float = 0.0
    led_half_power_sd_deg: float = 0.0
    led_position_sd_m: float = 0.0
    common_scale: float = 1.0
    led_tilt_max_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in (
            "gain_sd",
            "height_sd_m",
            "tilt_max_deg",
            "led_amplitude_sd",
            "led_half_power_sd_deg",
            "led_position_sd_m",
            "led_tilt_max_deg",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise GeometryError(
                    f"impairments.{name} must be a finite number >= 0, got {value!r}",
                    field=f"impairments.{name}",
                )
        for name in ("tilt_max_deg", "led_tilt_max_deg"):
            if getattr(self, name) >= 90:
                raise GeometryError(
                    f"impairments.{name} must be below 90, got {getattr(self, name)!r}",
                    field=f"impairments.{name}",
                )
        if not (math.isfinite(self.common_scale) and self.common_scale > 0):
            raise GeometryError(
                f"impairments.common_scale must be positive, got {self.common_scale!r}",
                field="impairments.common_scale",
            )

    @property
    def is_ideal(self) -> bool:
        """True when nothing departs from the layout (the paper's model)."""
        return self == Impairments()

    @property
    def tilt_component_sd_deg(self) -> float:
        """Standard deviation of each of the two tilt components these tilts have, degrees:
        ``sqrt(E[polar^2] / 2) = tilt_max_deg / sqrt(6)`` for a polar angle uniform in
        ``[0, tilt_max_deg]`` and a uniform azimuth (what a layout's ``receiver_tilt_sd``
        should say of them)."""
        return self.tilt_max_deg / math.sqrt(6.0)

    @classmethod
    def ideal(cls) -> Impairments:
        """The paper's model: nothing departs from the layout."""
        return cls()

    @classmethod
    def reflections(
        cls, walls: float = 0.7, floor: float = 0.0, ceiling: float = 0.0
    ) -> Impairments:
        """Diffuse first-bounce reflections (walls only by default: downward LEDs light neither
        the ceiling nor a floor an upward receiver sees)."""
        return cls(reflectance=Reflectance(walls=walls, floor=floor, ceiling=ceiling))

    @classmethod
    def gain_spread(cls, sd: float = 0.10) -> Impairments:
        """Terminals whose gains differ (relative sd)."""
        return cls(gain_sd=sd)

    @classmethod
    def heights(cls, sd_m: float = 0.15) -> Impairments:
        """Terminals at different heights (sd, metres)."""
        return cls(height_sd_m=sd_m)

    @classmethod
    def tilts(cls, max_deg: float = 20.0) -> Impairments:
        """Tilted photodiodes (polar angle uniform in [0, max_deg])."""
        return cls(tilt_max_deg=max_deg)

    @classmethod
    def led_tolerances(
        cls, amplitude_sd: float = 0.05, half_power_sd_deg: float = 3.0
    ) -> Impairments:
        """LEDs that differ from their data sheet (pilot amplitude, beam width)."""
        return cls(led_amplitude_sd=amplitude_sd, led_half_power_sd_deg=half_power_sd_deg)

    @classmethod
    def realistic_mix(cls) -> Impairments:
        """Tilts 0-10 deg, heights sd 5 cm, reflections 0.7 / 0.2 / 0.8, LEDs 5 % / 3 deg."""
        return cls(
            reflectance=Reflectance(walls=0.7, floor=0.2, ceiling=0.8),
            height_sd_m=0.05,
            tilt_max_deg=10.0,
            led_amplitude_sd=0.05,
            led_half_power_sd_deg=3.0,
        )
