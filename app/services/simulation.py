"""Simulation: a ready-to-send measurement for given or random terminals, with the truth.

``POST /v1/rooms/{room_id}/simulate`` calls :func:`simulate`. The ideal model draws noisy
amplitudes from the room version's layout; with ``impairments`` the realistic simulator
(:func:`app.vlp.simulation.simulate_terminals`) draws each terminal's height, tilt and gain
and the room's LED tolerances, and the truth says what it drew.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from app.errors import InvalidFields
from app.schemas import Measurement, Simulation, SimulationRequest, TruthTarget
from app.schemas.simulate import ImpairmentsSpec
from app.vlp import measurements as vlp_measurements
from app.vlp.layout import Layout, Reflectance
from app.vlp.rng import as_generator
from app.vlp.simulation import (
    Impairments,
    SimulatedTerminals,
    noise_std_for_snr,
    noisy_amplitudes,
    random_positions,
    simulate_terminals,
)
from app.vlp.typing import FloatArray

from .fingerprint_cache import FingerprintCache

__all__ = ["DEFAULT_SNR_DB", "check_simulation_request", "simulate"]

DEFAULT_SNR_DB = 30.0


def check_simulation_request(body: SimulationRequest) -> None:
    """Refuse a request whose fields contradict each other (before any room is read).

    Raises
    ------
    InvalidFields
        Both or neither of ``targets`` and ``positions``; ``snr_db`` with ``noise_std``;
        ``impairments`` with ``noise_std``.
    """
    errors = []
    if (body.targets is None) == (body.positions is None):
        errors += [
            (name, "send exactly one of targets (random terminals) or positions")
            for name in ("targets", "positions")
        ]
    if body.snr_db is not None and body.noise_std is not None:
        errors += [(name, "send snr_db or noise_std, not both") for name in ("snr_db", "noise_std")]
    if body.impairments is not None and body.noise_std is not None:
        errors.append(("noise_std", "with impairments, give the noise as snr_db (default 30 dB)"))
    if errors:
        raise InvalidFields(errors)


def simulate(cache: FingerprintCache, *, room_id: str, body: SimulationRequest) -> Simulation:
    """Place the request's terminals in the room's current version, measure them with noise,
    and answer the measurement as a localize body with the truth.

    Raises
    ------
    InvalidFields
        Contradicting fields (:func:`check_simulation_request`) or a position outside the room.
    RoomNotFound, FingerprintNotReady
    """
    check_simulation_request(body)
    version = cache.current_version(room_id)
    fingerprint = cache.fingerprint(room_id, version)
    layout = fingerprint.layout
    rng = as_generator(body.seed)
    if body.positions is not None:
        positions = _given_positions(body.positions, layout)
    else:
        positions = random_positions(layout, int(body.targets or 1), rng=rng)
    snr_db = body.snr_db if body.snr_db is not None else DEFAULT_SNR_DB
    simulated: SimulatedTerminals | None = None
    if body.impairments is not None:
        simulated = simulate_terminals(
            layout, positions, _impairments(body.impairments), snr_db=snr_db, rng=rng
        )
        amplitudes, noise_std = simulated.amplitudes, simulated.noise_std
    else:
        noise_std = (
            body.noise_std if body.noise_std is not None else noise_std_for_snr(fingerprint, snr_db)
        )
        amplitudes = noisy_amplitudes(layout, positions, noise_std, rng=rng)
    ids = [f"t{index + 1}" for index in range(int(positions.shape[0]))]
    return Simulation(
        measurement=_measurement(body, amplitudes, ids, version),
        truth=_truth(body, layout, positions, ids, simulated),
        noise_std=float(noise_std),
        fingerprint_version=version,
    )


def _given_positions(given: Sequence[tuple[float, float]], layout: Layout) -> FloatArray:
    positions = np.array(given, dtype=np.float64).reshape(-1, 2)
    errors = [
        (
            f"positions.{index}",
            f"({x!r}, {y!r}) lies outside the room [0, {layout.room.length}] x "
            f"[0, {layout.room.width}] m",
        )
        for index, (x, y) in enumerate(positions.tolist())
        if not (0 <= x <= layout.room.length and 0 <= y <= layout.room.width)
    ]
    if errors:
        raise InvalidFields(errors)
    return positions


def _impairments(spec: ImpairmentsSpec) -> Impairments:
    """The science core's impairments of a request's."""
    surfaces = spec.reflectance
    return Impairments(
        reflectance=None
        if surfaces is None
        else Reflectance(walls=surfaces.walls, floor=surfaces.floor, ceiling=surfaces.ceiling),
        gain_sd=spec.gain_sd,
        height_sd_m=spec.height_sd_m,
        tilt_max_deg=spec.tilt_max_deg,
        led_amplitude_sd=spec.led_amplitude_sd,
        led_half_power_sd_deg=spec.led_half_power_sd_deg,
        led_position_sd_m=spec.led_position_sd_m,
        common_scale=spec.common_scale,
    )


def _measurement(
    body: SimulationRequest, amplitudes: FloatArray, ids: list[str], version: int
) -> Measurement:
    """The localize body of the request's form: terminals' amplitudes, or their sums."""
    measurement: dict[str, Any] = {
        "model": body.model,
        "targets": len(ids),
        "solver": body.solver,
        "fingerprint_version": version,
    }
    if body.form == "terminals":
        measurement["terminals"] = [
            {"id": tid, "amplitudes": row.tolist()}
            for tid, row in zip(ids, amplitudes, strict=True)
        ]
    elif body.model == "power":
        measurement["power"] = vlp_measurements.power_from_amplitudes(amplitudes).tolist()
    else:
        correlation = vlp_measurements.correlation_from_amplitudes(amplitudes)
        measurement["correlation"] = (
            correlation.tolist()
            if body.form == "matrix"
            else vlp_measurements.vech(correlation).tolist()
        )
    return Measurement.model_validate(measurement)


def _truth(
    body: SimulationRequest,
    layout: Layout,
    positions: FloatArray,
    ids: list[str],
    simulated: SimulatedTerminals | None,
) -> list[TruthTarget]:
    """Where each terminal is (and, from the realistic simulator, what it drew)."""
    cells = layout.nearest_cell(positions)
    return [
        TruthTarget(
            x=float(x),
            y=float(y),
            grid_index=int(cell),
            terminal_id=tid if body.form == "terminals" else None,
            z=None if simulated is None else float(simulated.heights[k]),
            normal=None if simulated is None else simulated.normals[k].tolist(),
            gain=None if simulated is None else float(simulated.gains[k]),
        )
        for k, ((x, y), cell, tid) in enumerate(zip(positions.tolist(), cells, ids, strict=True))
    ]
