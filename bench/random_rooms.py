"""Rooms drawn at random, through a real server: does every answer hold, and say how far?

Run from the repository root::

    python -m bench.random_rooms                      # 40 rooms x 12 requests, prints a table
    python -m bench.random_rooms --out docs           # and writes docs/results/random-rooms.md
    python -m bench.random_rooms --rooms 3 --trials 4 # a quick look
    python -m bench.random_rooms --snr-db 0,5,50,60   # noise levels outside 10-40 dB

The service is judged on rooms nobody tuned it for. This benchmark starts ``vlp serve``
(SQLite, one embedded build worker), uploads ``--rooms`` layouts drawn at random (2-12 m by
2-9 m, ceilings 2.4-5 m; LEDs as a regular array, a single row, a jittered array or
scattered, 1-30 of them, half-power angles 15-70 degrees, pilot amplitudes 0.5-10, lowered
up to 0.5 m; grid steps 0.1-0.5 m; receivers 0-1.5 m high with fields of view of 50-90
degrees; a third of the rooms reflecting), waits for each fingerprint, and sends
``--trials`` localize requests per room: 1-8 terminals (fewer than the LEDs) placed
uniformly, the ideal model or the realistic mix (:meth:`Impairments.realistic_mix`; its
reflections only where the layout has them, else half the time none), at 10, 20, 30 or
40 dB (``--snr-db`` draws from others), as ``correlation``, ``power`` or ``terminals``,
with ``targets`` given in 60 % of them. The amplitudes come from
:func:`app.vlp.simulation.simulate_terminals`.

Per form it reports what a user would check first: answers other than 200, estimates that
are not finite or lie outside the room, the mean matched error, how often the truth lies
within the answer's 95 % radius (``accuracy_m``), and answers that are confidently wrong
(quality ``ok``, the truth more than 0.5 m away and outside the radius). Many of these rooms
are badly lit for positioning (receivers that see one LED or none): errors of metres are
expected there; radii that do not say so are the failures.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.vlp.layout import Grid, Layout, Led, Receiver, Reflectance, Room
from app.vlp.metrics import match_positions
from app.vlp.simulation import Impairments, simulate_terminals

from ._common import measured_section, replace_section, write_csv
from ._server import ADMIN_KEY, TERMINAL_KEY, live_server

__all__ = [
    "FORMS",
    "SNRS_DB",
    "Outcome",
    "draw_request",
    "main",
    "random_layout",
    "replay_request",
    "run",
]

FORMS = ("correlation", "power", "terminals")
# The SNRs a request is drawn at (dB), unless --snr-db says others.
SNRS_DB = (10.0, 20.0, 30.0, 40.0)
MIX_REFLECTANCE = Reflectance(walls=0.7, floor=0.2, ceiling=0.8)
# A confidently wrong answer: quality ok, the truth outside the 95 % radius and this far.
WRONG_M = 0.5
_MAX_GRID_POINTS = 6000
_BUILD_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class Outcome:
    """One localize request and what came back (errors in metres; NaN where not 200)."""

    room: int
    n_leds: int
    form: str
    targets: int
    given: bool
    snr_db: float
    mix: bool
    status: int
    estimates: int = 0
    error_m: float = float("nan")
    covered: float = float("nan")
    quality: str = ""
    finite_inside: bool = True
    confidently_wrong: bool = False


def random_layout(rng: np.random.Generator) -> Layout:
    """A room drawn as the module docstring says."""
    step = float(rng.choice([0.1, 0.2, 0.25, 0.5]))
    length = step * int(rng.integers(round(2 / step), round(12 / step) + 1))
    width = step * int(rng.integers(round(2 / step), round(9 / step) + 1))
    while (length / step) * (width / step) > _MAX_GRID_POINTS:
        step *= 2.0
        length, width = step * max(round(length / step), 1), step * max(round(width / step), 1)
    height = float(rng.uniform(2.4, 5.0))
    kind = int(rng.integers(4))
    spots: list[tuple[float, float]] = []
    if kind in (0, 1):  # a regular array; kind 1 a single row
        nx = int(rng.integers(2, 7))
        ny = 1 if kind == 1 else int(rng.integers(1, 6))
        spots = [
            ((i + 0.5) * length / nx, (j + 0.5) * width / ny) for i in range(nx) for j in range(ny)
        ]
    elif kind == 2:  # an array installed off its nominal spots by up to ~0.3 m
        nx, ny = int(rng.integers(2, 6)), int(rng.integers(2, 5))
        spots = [
            (
                float(np.clip((i + 0.5) * length / nx + rng.normal(0.0, 0.3), 0.0, length)),
                float(np.clip((j + 0.5) * width / ny + rng.normal(0.0, 0.3), 0.0, width)),
            )
            for i in range(nx)
            for j in range(ny)
        ]
    else:  # scattered
        count = int(rng.integers(1, 25))
        spots = [
            (float(rng.uniform(0, length)), float(rng.uniform(0, width))) for _ in range(count)
        ]
    mixed_beams = rng.random() < 0.3
    beam = float(rng.uniform(15.0, 70.0))
    led_z = height - (float(rng.uniform(0.0, 0.5)) if rng.random() < 0.3 else 0.0)
    receiver_height = float(rng.uniform(0.0, min(1.5, led_z - 0.8)))
    leds = tuple(
        Led(
            x=x,
            y=y,
            z=led_z,
            half_power_angle_deg=float(rng.uniform(15.0, 70.0)) if mixed_beams else beam,
            pilot_amplitude=float(rng.choice([1.0, 1.0, 2.0, 0.5, 10.0])),
        )
        for x, y in spots
    )
    reflectance = MIX_REFLECTANCE if rng.random() < 0.3 else None
    return Layout(
        room=Room(length, width, height, reflectance),
        grid=Grid(step, receiver_height),
        leds=leds,
        receiver=Receiver(fov_deg=float(rng.choice([50.0, 70.0, 85.0, 90.0]))),
        name="random room",
    )


def draw_request(
    rng: np.random.Generator, layout: Layout, room: int, snrs_db: Sequence[float] = SNRS_DB
) -> tuple[dict[str, Any], np.ndarray, Outcome]:
    """One localize body, the truth (K, 2) and the outcome's fixed fields; its SNR one of
    ``snrs_db``."""
    n_leds = len(layout.leds)
    count = int(rng.integers(1, max(min(8, n_leds - 1), 1) + 1))
    truth = np.column_stack(
        (rng.uniform(0, layout.room.length, count), rng.uniform(0, layout.room.width, count))
    )
    mix = bool(rng.random() < 0.5)
    impairments = Impairments.realistic_mix() if mix else Impairments.ideal()
    if mix and layout.room.reflectance is None and rng.random() < 0.5:
        impairments = dataclasses.replace(impairments, reflectance=None)
    snr_db = float(rng.choice(np.asarray(snrs_db, dtype=np.float64)))
    amplitudes = simulate_terminals(layout, truth, impairments, snr_db=snr_db, rng=rng).amplitudes
    form = str(rng.choice(FORMS))
    given = bool(rng.random() < 0.6)
    body: dict[str, Any]
    if form == "terminals":
        body = {
            "terminals": [
                {"id": f"t{i}", "amplitudes": a.tolist()} for i, a in enumerate(amplitudes)
            ]
        }
    elif form == "power":
        body = {"model": "power", "power": np.sum(amplitudes**2, axis=0).tolist()}
    else:
        body = {"model": "correlation", "correlation": (amplitudes.T @ amplitudes).tolist()}
    if given:
        body["targets"] = count
    outcome = Outcome(room, n_leds, form, count, given, snr_db, mix, status=0)
    return body, truth, outcome


def replay_request(seed: int, room: int, trial: int) -> tuple[Layout, dict[str, Any], np.ndarray]:
    """Room ``room`` of ``--seed seed`` and its ``trial``-th request (body and truth, (K, 2)),
    drawn as :func:`run` draws them (to look at one answer again)."""
    rng = np.random.default_rng([seed, room])
    layout = random_layout(rng)
    for _ in range(trial + 1):
        body, truth, _outcome = draw_request(rng, layout, room)
    return layout, body, truth


def _judge(answer: dict[str, Any], truth: np.ndarray, layout: Layout, outcome: Outcome) -> Outcome:
    estimates = np.array([[e["x"], e["y"]] for e in answer["estimates"]], dtype=float)
    radii = np.array([e.get("accuracy_m", np.nan) for e in answer["estimates"]], dtype=float)
    finite_inside = bool(
        np.isfinite(estimates).all()
        and np.isfinite(radii).all()
        and (estimates >= 0.0).all()
        and (estimates[:, 0] <= layout.room.length).all()
        and (estimates[:, 1] <= layout.room.width).all()
    )
    rows, cols = match_positions(estimates, truth)
    distances = np.linalg.norm(estimates[rows] - truth[cols], axis=1)
    outside = distances > radii[rows]
    quality = str(answer["fit"]["quality"])
    return dataclasses.replace(
        outcome,
        estimates=len(estimates),
        error_m=float(distances.mean()),
        covered=float(np.mean(~outside)),
        quality=quality,
        finite_inside=finite_inside,
        confidently_wrong=bool(quality == "ok" and np.any(outside & (distances > WRONG_M))),
    )


def _wait_ready(client: httpx.Client, room_id: str, headers: dict[str, str]) -> None:
    deadline = time.monotonic() + _BUILD_TIMEOUT_S
    while True:
        room = client.get(f"/v1/rooms/{room_id}", headers=headers).json()
        status = room["fingerprint"]["status"]
        if status == "ready":
            return
        if status == "failed" or time.monotonic() > deadline:
            raise RuntimeError(f"room {room_id}: fingerprint {status!r}")
        time.sleep(0.1)


def run(rooms: int, trials: int, seed: int, snrs_db: Sequence[float] = SNRS_DB) -> list[Outcome]:
    """Start a server and send every room's requests; one outcome per request."""
    outcomes: list[Outcome] = []
    with (
        tempfile.TemporaryDirectory() as tmp,
        live_server(Path(tmp), VLP_DEMO="0") as server,
        httpx.Client(base_url=server.url, timeout=120.0) as client,
    ):
        admin, terminal = {"X-API-Key": ADMIN_KEY}, {"X-API-Key": TERMINAL_KEY}
        for room in range(rooms):
            rng = np.random.default_rng([seed, room])
            layout = random_layout(rng)
            created = client.post("/v1/rooms", json=layout.to_mapping(), headers=admin)
            created.raise_for_status()
            room_id = created.json()["id"]
            _wait_ready(client, room_id, admin)
            for _ in range(trials):
                body, truth, outcome = draw_request(rng, layout, room, snrs_db)
                response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=terminal)
                outcome = dataclasses.replace(outcome, status=response.status_code)
                if response.status_code == 200:
                    outcome = _judge(response.json(), truth, layout, outcome)
                outcomes.append(outcome)
    return outcomes


def summary(outcomes: Sequence[Outcome]) -> str:
    """Markdown table: per form and in all."""
    lines = [
        "| form | requests | 5xx | other non-200 | not finite or outside | mean error (cm) "
        "| median error (cm) | truth within the 95 % radius | confidently wrong |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for form in (*FORMS, "all"):
        chosen = [o for o in outcomes if form in ("all", o.form)]
        answered = [o for o in chosen if o.status == 200]
        errors = np.array([o.error_m for o in answered])
        covered = np.array([o.covered for o in answered])
        lines.append(
            f"| {form} | {len(chosen)} | {sum(o.status >= 500 for o in chosen)} "
            f"| {sum(o.status != 200 and o.status < 500 for o in chosen)} "
            f"| {sum(not o.finite_inside for o in answered)} "
            f"| {100 * errors.mean():.0f} | {100 * np.median(errors):.0f} "
            f"| {covered.mean():.3f} | {sum(o.confidently_wrong for o in answered)} |"
            if answered
            else f"| {form} | {len(chosen)} | - | - | - | - | - | - | - |"
        )
    return "\n".join(lines)


def _snrs(text: str) -> tuple[float, ...]:
    """``--snr-db``: comma-separated finite numbers."""
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not values or not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"not a list of finite numbers: {text!r}")
    return values


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m bench.random_rooms``."""
    parser = argparse.ArgumentParser(prog="python -m bench.random_rooms", description=__doc__)
    parser.add_argument("--rooms", type=int, default=40, help="rooms drawn (default 40)")
    parser.add_argument("--trials", type=int, default=12, help="requests per room (default 12)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the draws (default 1)")
    parser.add_argument(
        "--snr-db",
        type=_snrs,
        default=SNRS_DB,
        help="comma-separated SNRs (dB) the requests are drawn at (default 10,20,30,40)",
    )
    parser.add_argument("--out", type=Path, default=None, help="write DIR/results/random-rooms.md")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    outcomes = run(args.rooms, args.trials, args.seed, args.snr_db)
    elapsed = time.perf_counter() - started
    table = summary(outcomes)
    print(table)
    if args.out is not None:
        fields = [field.name for field in dataclasses.fields(Outcome)]
        write_csv(
            args.out / "data" / "random_rooms.csv",
            fields,
            ([getattr(o, name) for name in fields] for o in outcomes),
        )
        command = "python -m bench.random_rooms " + " ".join(
            argv if argv is not None else sys.argv[1:]
        )
        body = measured_section(
            "### Measured (`bench/random_rooms.py`)",
            f"Command: `{command.strip()}` ({elapsed:.0f} s); every request in "
            "`docs/data/random_rooms.csv`.",
            table,
        )
        replace_section(
            args.out / "results" / "random-rooms.md",
            "random-rooms",
            body,
            preamble="# Results: rooms drawn at random\n",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
