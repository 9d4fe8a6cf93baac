"""Commands that talk to a running service through :class:`app.client.VLPClient`."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.client import Job, VLPClient
    from app.schemas import Localization, Room, Simulation

    from ._output import Output

__all__ = ["InputFileError", "add_remote_commands", "open_client"]

DEFAULT_URL = "http://127.0.0.1:8000"


def _api_key(args: argparse.Namespace) -> str | None:
    """``--key``, else ``$VLP_API_KEY``, else the first admin, else the first terminal key.

    The last two are what ``source var/credentials`` sets, so that works with no flag.
    """
    if args.key:
        return str(args.key)
    for variable in ("VLP_API_KEY", "VLP_ADMIN_KEYS", "VLP_TERMINAL_KEYS"):
        value = os.environ.get(variable, "").split(",")[0].strip()
        if value:
            return value
    return None


def open_client(args: argparse.Namespace) -> VLPClient:
    """The client for ``--url`` / ``--key`` / ``--timeout``."""
    from app.client import VLPClient

    return VLPClient(args.url, api_key=_api_key(args), timeout_s=args.timeout)


class InputFileError(Exception):
    """A JSON file given on the command line cannot be read or parsed."""


def _read_json(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8") if str(path) != "-" else sys.stdin.read()
        return json.loads(text)
    except (OSError, ValueError) as exc:
        raise InputFileError(f"cannot read {path}: {exc}") from exc


def _room_rows(rooms: list[Room]) -> list[list[Any]]:
    return [
        [
            room.id,
            room.name,
            room.layout_version,
            room.fingerprint.status,
            room.fingerprint.version if room.fingerprint.version is not None else "-",
        ]
        for room in rooms
    ]


_ROOM_COLUMNS = ["id", "name", "layout", "fingerprint", "version"]


def _wait(client: VLPClient, out: Output, job: Job, args: argparse.Namespace) -> Job:
    with out.job_progress(f"{job.kind} {job.id}") as on_progress:
        return client.wait_for_job(job.id, timeout_s=args.wait_timeout, on_progress=on_progress)


def _rooms_list(client: VLPClient, out: Output, _args: argparse.Namespace) -> int:
    rooms = list(client.iter_rooms())
    out.result(rooms, lambda value: out.table("rooms", _ROOM_COLUMNS, _room_rows(value)))
    return 0


def _rooms_show(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    out.result(client.get_room(args.room_id))
    return 0


def _rooms_status(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    room = client.get_room(args.room_id)
    job = client.get_job(room.fingerprint.job_id) if room.fingerprint.job_id else None
    status = {"room": room, "job": job}

    def render(_value: Any) -> None:
        out.table("room", _ROOM_COLUMNS, _room_rows([room]))
        if job is not None:
            out.console.print(
                f"latest build {job.id}: {job.status}, {job.progress:.0%}"
                + (f" ({job.error})" if job.error else ""),
                markup=False,
            )

    out.result(status, render)
    return 0


def _rooms_create(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    room = client.create_room(_read_json(args.file))
    if args.wait and room.fingerprint.job_id is not None:
        _wait(client, out, client.get_job(room.fingerprint.job_id), args)
        room = client.get_room(room.id)
    out.result(room, lambda value: out.table("room", _ROOM_COLUMNS, _room_rows([value])))
    return 0


def _rooms_rebuild(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    job = client.rebuild(args.room_id)
    if args.wait:
        job = _wait(client, out, job, args)
    out.result(job)
    return 0


def _calibration_id(job: Job) -> str | None:
    result = job.result or {}
    for key in ("calibration_id", "id"):
        if isinstance(result.get(key), str):
            return str(result[key])
    return None


def _rooms_calibrate(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    document = _read_json(args.file)
    survey = document.get("survey", []) if isinstance(document, dict) else document
    masked = document.get("masked_leds") if isinstance(document, dict) else None
    job = client.calibrate(args.room_id, survey, masked_leds=masked)
    if not args.wait:
        out.result(job)
        return 0
    from ._calibration_report import show_calibration

    job = _wait(client, out, job, args)
    calibration_id = _calibration_id(job)
    if calibration_id is None:
        out.result(job)
    else:
        report = client.get_calibration(args.room_id, calibration_id)
        out.result(report, lambda value: show_calibration(out, value))
    return 0


def _rooms_delete(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    client.delete_room(args.room_id)
    out.result({"deleted": args.room_id}, lambda _v: out.console.print(f"deleted {args.room_id}"))
    return 0


def _rooms_map(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    path: Path = args.output or Path(f"{args.room_id}-map.png")
    path.write_bytes(client.room_map_png(args.room_id))
    out.result({"written": str(path)}, lambda _v: out.console.print(f"wrote {path}"))
    return 0


def _nearest_truth_m(simulation: Simulation, x: float, y: float) -> float:
    return min(math.hypot(t.x - x, t.y - y) for t in simulation.truth)


def _show_localization(out: Output, located: Localization, sim: Simulation | None) -> None:
    columns = ["x (m)", "y (m)", "weight", "terminal"]
    if sim is not None:
        columns.append("to nearest truth (m)")
    rows: list[list[Any]] = []
    for estimate in located.estimates:
        row: list[Any] = [f"{estimate.x:.3f}", f"{estimate.y:.3f}", f"{estimate.weight:.2f}"]
        row.append(estimate.terminal_id or "-")
        if sim is not None:
            row.append(f"{_nearest_truth_m(sim, estimate.x, estimate.y):.3f}")
        rows.append(row)
    title = f"{located.targets} estimates ({located.solver}, {located.elapsed_ms:.1f} ms)"
    out.table(title, columns, rows)


def _simulate(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    request: dict[str, Any] = {
        "targets": args.targets,
        "snr_db": args.snr_db,
        "model": args.model,
        "form": args.form,
        "solver": args.solver,
    }
    if args.seed is not None:
        request["seed"] = args.seed
    simulation = client.simulate(args.room_id, request)
    truth_rows = [[f"{t.x:.3f}", f"{t.y:.3f}", t.terminal_id or "-"] for t in simulation.truth]
    if not args.localize:
        out.result(simulation, lambda _v: out.table("truth", ["x (m)", "y (m)", "id"], truth_rows))
        return 0
    located = client.localize(args.room_id, simulation.measurement)

    def render(_value: Any) -> None:
        out.table("truth", ["x (m)", "y (m)", "id"], truth_rows)
        _show_localization(out, located, simulation)

    out.result({"truth": simulation.truth, "localization": located}, render)
    return 0


def _localize(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    if args.batch:
        return _localize_batch(client, out, args)
    located = client.localize(args.room_id, _read_json(args.file))
    out.result(located, lambda value: _show_localization(out, value, None))
    return 0


def _localize_batch(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    """``localize --batch``: exit 1 when any item is a problem (all answers are shown)."""
    from app.schemas import Localization

    sent = _read_json(args.file)
    items = sent.get("items") if isinstance(sent, dict) else sent
    if not isinstance(items, list):
        raise InputFileError(
            f'{args.file}: expected a JSON list of measurements or {{"items": [...]}}'
        )
    answers = client.localize_batch(args.room_id, items).items
    rows = [
        [index, "ok", answer.targets, f"{answer.elapsed_ms:.1f}"]
        if isinstance(answer, Localization)
        else [index, answer.status, "-", answer.detail]
        for index, answer in enumerate(answers)
    ]
    columns = ["item", "status", "targets", "ms / problem"]
    out.result(answers, lambda _value: out.table(f"{len(answers)} answers", columns, rows))
    return 0 if all(isinstance(answer, Localization) for answer in answers) else 1


def _client_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--url", default=os.environ.get("VLP_URL", DEFAULT_URL), help="service URL ($VLP_URL)"
    )
    parser.add_argument(
        "--key",
        default=None,
        help="API key (default: $VLP_API_KEY, else the first of $VLP_ADMIN_KEYS, "
        "else of $VLP_TERMINAL_KEYS)",
    )
    parser.add_argument("--timeout", type=float, default=30.0, help="per request, seconds")
    parser.add_argument(
        "--json",
        action="store_true",
        help="print one JSON document on stdout (on an error answer: its problem) and no "
        "progress bars",
    )


def _remote(parent: Any, name: str, handler: Any, help_text: str) -> argparse.ArgumentParser:
    parser: argparse.ArgumentParser = parent.add_parser(name, help=help_text)
    _client_options(parser)
    parser.set_defaults(remote=handler)
    return parser


def _waiting(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-wait", dest="wait", action="store_false", help="do not wait")
    parser.add_argument("--wait-timeout", type=float, default=600.0, help="seconds")


def _add_rooms(commands: Any) -> None:
    rooms = commands.add_parser("rooms", help="manage the rooms of a running service")
    sub = rooms.add_subparsers(dest="rooms_command", required=True)
    _remote(sub, "list", _rooms_list, "list all rooms")
    _remote(sub, "show", _rooms_show, "one room in full").add_argument("room_id")
    _remote(sub, "status", _rooms_status, "a room's fingerprint and build").add_argument("room_id")
    create = _remote(sub, "create", _rooms_create, "create a room from a RoomLayout JSON file")
    create.add_argument("file", type=Path, help="RoomLayout JSON ('-': stdin)")
    _waiting(create)
    rebuild = _remote(sub, "rebuild", _rooms_rebuild, "rebuild a room's fingerprint")
    rebuild.add_argument("room_id")
    _waiting(rebuild)
    calibrate = _remote(sub, "calibrate", _rooms_calibrate, "calibrate from a survey JSON file")
    calibrate.add_argument("room_id")
    calibrate.add_argument(
        "file", type=Path, help='{"survey": [{"x","y","led","amplitude"}], "masked_leds": [...]}'
    )
    _waiting(calibrate)
    _remote(sub, "delete", _rooms_delete, "delete a room").add_argument("room_id")
    plan = _remote(sub, "map", _rooms_map, "save the room plan as PNG")
    plan.add_argument("room_id")
    plan.add_argument("--output", "-o", type=Path, default=None, help="default ROOM-map.png")


def add_remote_commands(commands: Any) -> None:
    """Add ``rooms``, ``keys``, ``demo``, ``simulate`` and ``localize`` to the ``vlp``
    sub-commands."""
    from ._demo import add_demo_command
    from ._keys import add_keys_command

    _add_rooms(commands)
    add_keys_command(commands, _remote)
    add_demo_command(commands, _remote)
    simulate = _remote(
        commands, "simulate", _simulate, "simulate a measurement (and localize it with --localize)"
    )
    simulate.add_argument("room_id")
    simulate.add_argument("--targets", type=int, default=8)
    simulate.add_argument("--snr-db", type=float, default=30.0)
    simulate.add_argument("--model", choices=("power", "correlation"), default="correlation")
    simulate.add_argument("--form", choices=("matrix", "upper", "terminals"), default="matrix")
    simulate.add_argument("--solver", default="gridless")
    simulate.add_argument("--seed", type=int, default=None)
    simulate.add_argument("--localize", action="store_true", help="also localize it")
    localize = _remote(commands, "localize", _localize, "localize a Measurement JSON file")
    localize.add_argument("room_id")
    localize.add_argument("file", type=Path, help="Measurement JSON ('-': stdin)")
    localize.add_argument(
        "--batch",
        action="store_true",
        help='FILE holds up to 1000 measurements (a JSON list or {"items": [...]}), '
        "localized in one request; exit 1 when any of them is refused",
    )
