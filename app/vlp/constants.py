"""Constants of the public contract that light modules need without the numerics.

Nothing here imports numpy: ``app.schemas`` (and through it ``app.client``) read these, and a
terminal app that only talks HTTP must not load the science stack to do so.
"""

from __future__ import annotations

__all__ = [
    "DEFAULT_FILTER_GAIN",
    "DEFAULT_FOV_DEG",
    "DEFAULT_HALF_POWER_ANGLE_DEG",
    "DEFAULT_LED_NORMAL",
    "DEFAULT_PILOT_AMPLITUDE",
    "DEFAULT_RECEIVER_AREA_M2",
    "DEFAULT_REFRACTIVE_INDEX",
    "MAX_BEAM_ANGLES",
    "MAX_TARGETS",
]

# Defaults of the public contract (the ``RoomLayout`` schema, :mod:`app.schemas.rooms`).
DEFAULT_RECEIVER_AREA_M2 = 1e-4
DEFAULT_FOV_DEG = 70.0
DEFAULT_FILTER_GAIN = 1.0
DEFAULT_REFRACTIVE_INDEX = 1.5
DEFAULT_HALF_POWER_ANGLE_DEG = 60.0
DEFAULT_PILOT_AMPLITUDE = 1.0
# The unit normal of an LED's emitting face when the layout gives none: straight down.
DEFAULT_LED_NORMAL = (0.0, 0.0, -1.0)
# Largest spread of the photodiodes' tilt components (``grid.receiver_tilt_sd``), degrees:
# beyond it a tilt is no small perturbation of a level photodiode (the radii's linearisation).
MAX_RECEIVER_TILT_SD_DEG = 30.0

# Angles an LED's photometric table (``beam``) may hold: 0-90 degrees in half-degree steps.
MAX_BEAM_ANGLES = 181

# Upper bound on K accepted by any solver (and on the estimated count when K is unknown).
MAX_TARGETS = 64
