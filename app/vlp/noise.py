"""Physical receiver noise: shot and thermal noise of a PIN photodiode receiver.

The model of Komine and Nakagawa, "Fundamental analysis for visible-light communication
system using LED lights", IEEE Trans. Consumer Electronics 50(1), 2004, eqs. (8)-(10):

.. math::

    \\sigma^2_{shot} = 2 q \\gamma P_r B + 2 q I_{bg} I_2 B,

    \\sigma^2_{thermal} = \\frac{8 \\pi k T}{G} \\eta A I_2 B^2
        + \\frac{16 \\pi^2 k T \\Gamma}{g_m} \\eta^2 A^2 I_3 B^3,

in A^2, with ``eta`` the fixed capacitance per unit detector area (given per cm^2, so the
area is converted from m^2 to cm^2).

Amplitude units. A pilot amplitude ``x_i = 1`` means the LED transmits ``transmit_power_w``
watts of optical pilot power; the photocurrent of LED ``i``'s pilot is then
``gamma * transmit_power_w * h_i x_i``. Dividing currents by ``gamma * transmit_power_w``
puts the noise in the amplitude units of ``a_i = h_i x_i + n_i`` used everywhere else.
"""

from __future__ import annotations

import math

import numpy as np

from .channel import channel_gains
from .errors import MeasurementError
from .layout import Layout
from .typing import FloatArray

__all__ = [
    "BOLTZMANN",
    "ELEMENTARY_CHARGE",
    "amplitude_noise_std",
    "received_power_w",
    "receiver_noise_variance",
]

ELEMENTARY_CHARGE = 1.602176634e-19  # C
BOLTZMANN = 1.380649e-23  # J/K
_CM2_PER_M2 = 1e4


def _positive(value: float, name: str, *, allow_zero: bool = False) -> None:
    ok = math.isfinite(value) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        bound = ">= 0" if allow_zero else "> 0"
        raise MeasurementError(f"{name} must be finite and {bound}, got {value!r}", field=name)


def receiver_noise_variance(
    received_power_w: float,
    area_m2: float,
    *,
    responsivity_a_per_w: float = 0.53,
    bandwidth_hz: float = 100e6,
    background_current_a: float = 5100e-6,
    i2: float = 0.562,
    i3: float = 0.0868,
    temperature_k: float = 295.0,
    open_loop_gain: float = 10.0,
    capacitance_pf_per_cm2: float = 112.0,
    noise_factor: float = 1.5,
    transconductance_s: float = 30e-3,
) -> float:
    """Total (shot + thermal) noise variance of the photocurrent, A^2.

    Parameters
    ----------
    received_power_w : float
        Total optical power on the detector, W (signal-dependent shot noise).
    area_m2 : float
        Detector area, m^2.
    responsivity_a_per_w, bandwidth_hz, background_current_a, i2, i3, temperature_k,
    open_loop_gain, capacitance_pf_per_cm2, noise_factor, transconductance_s : float
        Komine and Nakagawa's values by default (gamma, B, I_bg, I_2, I_3, T_k, G, eta,
        Gamma, g_m).

    Returns
    -------
    variance : float
        A^2.

    Raises
    ------
    MeasurementError
        When an argument is negative, zero where it must not be, or not finite.

    Examples
    --------
    >>> f"{receiver_noise_variance(0.0, 1e-4):.4e}"  # no light: background + thermal
    '1.3330e-13'
    """
    _positive(received_power_w, "received_power_w", allow_zero=True)
    _positive(background_current_a, "background_current_a", allow_zero=True)
    for name, value in (
        ("area_m2", area_m2),
        ("responsivity_a_per_w", responsivity_a_per_w),
        ("bandwidth_hz", bandwidth_hz),
        ("temperature_k", temperature_k),
        ("open_loop_gain", open_loop_gain),
        ("i2", i2),
        ("i3", i3),
        ("capacitance_pf_per_cm2", capacitance_pf_per_cm2),
        ("noise_factor", noise_factor),
        ("transconductance_s", transconductance_s),
    ):
        _positive(value, name)
    q, b = ELEMENTARY_CHARGE, bandwidth_hz
    shot = (
        2.0 * q * responsivity_a_per_w * received_power_w * b
        + 2.0 * q * background_current_a * i2 * b
    )
    # eta * A in farads: pF/cm^2 times cm^2.
    eta_area_f = capacitance_pf_per_cm2 * 1e-12 * area_m2 * _CM2_PER_M2
    kt = BOLTZMANN * temperature_k
    thermal = (
        8.0 * math.pi * kt / open_loop_gain * eta_area_f * i2 * b**2
        + 16.0 * math.pi**2 * kt * noise_factor / transconductance_s * eta_area_f**2 * i3 * b**3
    )
    return float(shot + thermal)


def received_power_w(layout: Layout, position: FloatArray, transmit_power_w: float = 1.0) -> float:
    """Optical pilot power reaching a receiver at ``position`` from all LEDs, W.

    ``transmit_power_w * sum_i h_i(p) x_i`` (see the module docstring for the units).

    Parameters
    ----------
    layout : Layout
    position : ndarray of shape (2,)
        ``(x, y)``, metres.
    transmit_power_w : float, default=1.0
        Optical power of a unit pilot amplitude, W.
    """
    _positive(transmit_power_w, "transmit_power_w")
    gains = channel_gains(layout, np.asarray(position, dtype=np.float64).reshape(1, 2))[:, 0]
    return float(transmit_power_w * gains @ layout.pilot_amplitudes)


def amplitude_noise_std(
    received_power: float,
    area_m2: float,
    *,
    transmit_power_w: float = 1.0,
    responsivity_a_per_w: float = 0.53,
    **receiver: float,
) -> float:
    """Standard deviation of one pilot amplitude's noise, amplitude units.

    ``sqrt(receiver_noise_variance) / (responsivity * transmit_power_w)``: the photocurrent
    noise referred to the amplitude scale on which a unit pilot gives ``h``. Use it as the
    ``noise_std`` of :func:`app.vlp.simulation.noisy_amplitudes`.

    Parameters
    ----------
    received_power : float
        Total optical power on the detector, W (e.g. from :func:`received_power_w`).
    area_m2 : float
        Detector area, m^2.
    transmit_power_w : float, default=1.0
        Optical power of a unit pilot amplitude, W.
    responsivity_a_per_w : float, default=0.53
    **receiver : float
        Other keywords of :func:`receiver_noise_variance`.

    Examples
    --------
    >>> f"{amplitude_noise_std(0.0, 1e-4):.3e}"
    '6.889e-07'
    """
    _positive(transmit_power_w, "transmit_power_w")
    variance = receiver_noise_variance(
        received_power, area_m2, responsivity_a_per_w=responsivity_a_per_w, **receiver
    )
    return float(math.sqrt(variance) / (responsivity_a_per_w * transmit_power_w))
