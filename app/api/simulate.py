"""Simulation: a ready-to-send measurement for given or random terminals, with the truth."""

from __future__ import annotations

from typing import Any

import numpy as np
from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app.schemas import Measurement, Simulation, SimulationRequest, TruthTarget
from app.schemas.simulate import ImpairmentsSpec
from app.services.fingerprint_cache import FingerprintCache
from app.vlp import measurements as vlp_measurements
from app.vlp.layout import Layout, Reflectance
from app.vlp.rng import as_generator
from app.vlp.simulation import (
    Impairments,
    noise_std_for_snr,
    noisy_amplitudes,
    random_positions,
    simulate_terminals,
)

from .deps import AnyRole, CacheDep, RoomId
from .errors import InvalidInput, problem_responses

__all__ = ["DEFAULT_SNR_DB", "router"]

router = APIRouter(prefix="/v1/rooms", tags=["localization"])
DEFAULT_SNR_DB = 30.0


def _check(body: SimulationRequest) -> None:
    errors = []
    if (body.targets is None) == (body.positions is None):
        errors += [
            (f"body.{name}", "send exactly one of targets (random terminals) or positions")
            for name in ("targets", "positions")
        ]
    if body.snr_db is not None and body.noise_std is not None:
        errors += [
            (f"body.{name}", "send snr_db or noise_std, not both")
            for name in ("snr_db", "noise_std")
        ]
    if body.impairments is not None and body.noise_std is not None:
        errors.append(
            ("body.noise_std", "with impairments, give the noise as snr_db (default 30 dB)")
        )
    if errors:
        raise InvalidInput(errors)


def _given_positions(body: SimulationRequest, layout: Layout) -> np.ndarray[Any, Any]:
    positions = np.array(body.positions, dtype=np.float64).reshape(-1, 2)
    errors = [
        (
            f"body.positions.{index}",
            f"({x!r}, {y!r}) lies outside the room [0, {layout.room.length}] x "
            f"[0, {layout.room.width}] m",
        )
        for index, (x, y) in enumerate(positions.tolist())
        if not (0 <= x <= layout.room.length and 0 <= y <= layout.room.width)
    ]
    if errors:
        raise InvalidInput(errors)
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


def _simulate(room_id: str, body: SimulationRequest, cache: FingerprintCache) -> Simulation:
    version = cache.current_version(room_id)
    fingerprint = cache.fingerprint(room_id, version)
    layout = fingerprint.layout
    rng = as_generator(body.seed)
    if body.positions is not None:
        positions = _given_positions(body, layout)
    else:
        positions = random_positions(layout, int(body.targets or 1), rng=rng)
    noise_std = (
        body.noise_std
        if body.noise_std is not None
        else noise_std_for_snr(
            fingerprint, body.snr_db if body.snr_db is not None else DEFAULT_SNR_DB
        )
    )
    simulated = None
    if body.impairments is not None:
        simulated = simulate_terminals(
            layout,
            positions,
            _impairments(body.impairments),
            snr_db=body.snr_db if body.snr_db is not None else DEFAULT_SNR_DB,
            rng=rng,
        )
        amplitudes = simulated.amplitudes
        noise_std = simulated.noise_std
    else:
        amplitudes = noisy_amplitudes(layout, positions, noise_std, rng=rng)
    n_targets = int(positions.shape[0])
    measurement: dict[str, Any] = {
        "model": body.model,
        "targets": n_targets,
        "solver": body.solver,
        "fingerprint_version": version,
    }
    ids = [f"t{index + 1}" for index in range(n_targets)]
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
    cells = layout.nearest_cell(positions)
    truth = [
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
    return Simulation(
        measurement=Measurement.model_validate(measurement),
        truth=truth,
        noise_std=float(noise_std),
        fingerprint_version=version,
    )


@router.post(
    "/{room_id}/simulate",
    summary="Simulate a measurement with its ground truth",
    responses=problem_responses(401, 404, 409, 413, 422, 503),
    # The measurement carries only the fields it was built with (as a client sends it).
    response_model_exclude_unset=True,
)
async def simulate(
    room_id: RoomId, body: SimulationRequest, cache: CacheDep, _role: AnyRole
) -> Simulation:
    """Place `targets` random terminals (or the given `positions`), add Gaussian noise at
    `snr_db` (default 30 dB; or an explicit `noise_std`) and answer with a `measurement`
    you can send unchanged to `POST /v1/rooms/{room_id}/localize`, plus the truth.
    """
    _check(body)
    return await run_in_threadpool(_simulate, room_id, body, cache)
