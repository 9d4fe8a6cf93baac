"""Ready-made layouts: the paper's room (section IV) and harder rooms for benchmarks."""

from __future__ import annotations

from .layout import Grid, Layout, Led, Receiver, Room

__all__ = ["paper_layout"]


def paper_layout() -> Layout:
    """The paper's 4 x 4 x 3 m room: 16 LEDs in a 4 x 4 array 0.5 m from the walls, 1 m apart,
    0.2 m grid (N = 400) at 0.85 m, half-power angle 60 deg, FOV 70 deg, 1 cm^2 detector."""
    leds = tuple(
        Led(x=0.5 + ix, y=0.5 + iy, z=3.0, half_power_angle_deg=60.0, pilot_amplitude=1.0)
        for ix in range(4)
        for iy in range(4)
    )
    return Layout(
        room=Room(length=4.0, width=4.0, height=3.0),
        grid=Grid(step=0.2, receiver_height=0.85),
        leds=leds,
        receiver=Receiver(area=1e-4, fov_deg=70.0, filter_gain=1.0, refractive_index=1.5),
        name="Paper room",
    )
