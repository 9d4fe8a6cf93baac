"""``vlp demo walkers``: simulated people walking in a room, posted to a running service.

Each step, every walker's terminal measures its own pilot amplitudes (the project's
simulator, in the room's layout as the service holds it) and the step is posted as one
``localize`` with ``terminals`` and ``track: true`` through the typed client, at the given
rate, until stopped (Ctrl-C), or for ``--duration`` seconds or ``--steps`` steps. Open
``/view`` to watch the tracks move.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.client import VLPClient

    from ._output import Output

__all__ = ["add_demo_command"]

# Paths are drawn this many seconds at a time (a new stretch starts where the last ended).
_STRETCH_S = 600.0


def _bodies(layout: Any, args: argparse.Namespace) -> Iterator[dict[str, Any]]:
    """Localize bodies, one per step, for ever (or as many as the caller takes)."""
    import numpy as np

    from app.vlp.simulation import Impairments, random_waypoint_paths, simulate_walk

    seed = args.seed
    stretch = 0
    while True:
        paths = random_waypoint_paths(
            layout,
            args.count,
            duration_s=_STRETCH_S,
            rate_hz=args.rate_hz,
            pause_s=(2.0, 6.0),
            rng=None if seed is None else seed + stretch,
        )
        walk = simulate_walk(
            layout,
            paths.positions,
            Impairments.ideal(),
            snr_db=args.snr_db,
            shadowing_probability=args.shadowing,
            rng=None if seed is None else seed + 10_000 + stretch,
        )
        for amplitudes in walk.amplitudes:
            yield {
                "terminals": [
                    {"id": f"walker-{k + 1}", "amplitudes": np.round(row, 12).tolist()}
                    for k, row in enumerate(amplitudes)
                ],
                "track": True,
            }
        stretch += 1


def _room_id(client: VLPClient, wanted: str | None) -> str | None:
    if wanted:
        return wanted
    for room in client.iter_rooms():
        if room.fingerprint.version is not None:
            return room.id
    return None


def _walkers(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    from app.vlp.layout_mapping import layout_from_mapping

    room_id = _room_id(client, args.room)
    if room_id is None:
        out.failure("no room has a ready fingerprint yet; wait for its build or pass --room")
        return 1
    room = client.get_room(room_id)
    layout = layout_from_mapping(room.layout.model_dump(mode="json", exclude_none=True))
    period = 1.0 / args.rate_hz
    limit = args.steps if args.steps is not None else None
    if args.duration is not None:
        limit = round(args.duration * args.rate_hz)
    out.note(
        f"{args.count} walkers in {room.name} ({room_id}) at {args.rate_hz:g} Hz; "
        "watch them at /view; Ctrl-C stops"
    )
    posted = 0
    started = time.monotonic()
    try:
        for body in _bodies(layout, args):
            if limit is not None and posted >= limit:
                break
            body["time"] = datetime.now(UTC).isoformat()
            client.localize(room_id, body)
            posted += 1
            pause = started + posted * period - time.monotonic()
            if pause > 0:
                time.sleep(pause)
    except KeyboardInterrupt:
        pass
    out.result(
        {"room_id": room_id, "steps": posted, "walkers": args.count},
        lambda value: out.table(
            "walkers", ["room", "steps", "walkers"], [[value["room_id"], posted, args.count]]
        ),
    )
    return 0


def _positive(kind: type[float] | type[int]) -> Any:
    def parse(text: str) -> float | int:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {text}")
        return value

    return parse


def add_demo_command(commands: Any, remote: Any) -> None:
    """Add ``demo walkers`` to the ``vlp`` sub-commands (``remote`` registers a remote one)."""
    demo = commands.add_parser("demo", help="demonstrations against a running service")
    sub = demo.add_subparsers(dest="demo_command", required=True)
    walkers = remote(sub, "walkers", _walkers, "post simulated people walking, until stopped")
    walkers.add_argument("--count", type=_positive(int), default=8, help="people walking")
    walkers.add_argument("--room", default=None, help="room id (default: the first ready room)")
    walkers.add_argument("--rate-hz", type=_positive(float), default=5.0, help="steps per second")
    walkers.add_argument("--snr-db", type=float, default=30.0)
    walkers.add_argument(
        "--shadowing",
        type=float,
        default=0.0,
        help="chance that a hand or a body blocks a terminal's strongest LED in a step",
    )
    walkers.add_argument("--seed", type=int, default=None)
    stop = walkers.add_mutually_exclusive_group()
    stop.add_argument("--duration", type=_positive(float), default=None, help="seconds")
    stop.add_argument("--steps", type=_positive(int), default=None, help="steps to post")
