"""The ``vlp`` console script: ``serve``, ``worker``, ``openapi``, ``rooms``, ``simulate``.

Heavy imports happen inside the commands, so ``vlp serve`` can pin the BLAS thread pools to
one thread before numpy loads.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["main", "openapi_document"]

_BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
DEFAULT_OPENAPI_PATH = Path("openapi/openapi.json")


def _pin_blas() -> None:
    for name in _BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")


def openapi_document() -> str:
    """The OpenAPI document of the app, as written to ``openapi/openapi.json``."""
    from app.main import create_app
    from app.settings import Settings

    schema = create_app(Settings(demo=False, embedded_workers=0)).openapi()
    return json.dumps(schema, sort_keys=True, indent=2) + "\n"


def _serve(args: argparse.Namespace) -> int:
    _pin_blas()
    import uvicorn

    from app.api.logs import configure_logging
    from app.main import create_app

    configure_logging(args.log_level)
    uvicorn.run(
        create_app(),
        host=args.host,
        port=args.port,
        log_config=None,
        access_log=False,
        proxy_headers=False,
    )
    return 0


def _worker(args: argparse.Namespace) -> int:
    _pin_blas()
    from app.api.logs import configure_logging
    from app.jobs import run_worker
    from app.settings import get_settings

    configure_logging(args.log_level)
    run_worker(settings=get_settings())
    return 0


def _openapi(args: argparse.Namespace) -> int:
    document = openapi_document()
    path: Path = args.output
    if args.check:
        if not path.exists() or path.read_text(encoding="utf-8") != document:
            print(f"{path} is out of date; run `vlp openapi`", file=sys.stderr)
            return 1
        return 0
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(document, encoding="utf-8")
    print(f"wrote {path}")
    return 0


def _client(args: argparse.Namespace) -> Any:
    import httpx

    key = args.key or os.environ.get("VLP_API_KEY")
    headers = {"X-API-Key": key} if key else {}
    return httpx.Client(base_url=args.url, headers=headers, timeout=60.0)


def _show(response: Any) -> int:
    try:
        print(json.dumps(response.json(), indent=2))
    except ValueError:
        print(response.text)
    return 0 if response.is_success else 1


def _rooms(args: argparse.Namespace) -> int:
    with _client(args) as client:
        if args.room_id:
            return _show(client.get(f"/v1/rooms/{args.room_id}"))
        return _show(client.get("/v1/rooms", params={"limit": 100}))


def _simulate(args: argparse.Namespace) -> int:
    body: dict[str, Any] = {
        "targets": args.targets,
        "snr_db": args.snr_db,
        "model": args.model,
        "form": args.form,
        "solver": args.solver,
    }
    if args.seed is not None:
        body["seed"] = args.seed
    with _client(args) as client:
        simulation = client.post(f"/v1/rooms/{args.room_id}/simulate", json=body)
        if not simulation.is_success or not args.localize:
            return _show(simulation)
        result = simulation.json()
        located = client.post(f"/v1/rooms/{args.room_id}/localize", json=result["measurement"])
        if not located.is_success:
            return _show(located)
        print(json.dumps({"truth": result["truth"], "localization": located.json()}, indent=2))
        return 0


def _add_client_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="service base URL")
    parser.add_argument("--key", default=None, help="API key (default: $VLP_API_KEY)")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vlp", description="Visible-light positioning service")
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser("serve", help="serve the HTTP API (uvicorn)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--log-level", default="info")
    serve.set_defaults(handler=_serve)

    worker = commands.add_parser("worker", help="run fingerprint-build workers")
    worker.add_argument("--log-level", default="info")
    worker.set_defaults(handler=_worker)

    openapi = commands.add_parser("openapi", help="write the OpenAPI document")
    openapi.add_argument("--output", type=Path, default=DEFAULT_OPENAPI_PATH)
    openapi.add_argument(
        "--check",
        action="store_true",
        help="only check that the file is up to date (exit 1 if not)",
    )
    openapi.set_defaults(handler=_openapi)

    rooms = commands.add_parser("rooms", help="list the rooms of a running service, or show one")
    rooms.add_argument("room_id", nargs="?", default=None)
    _add_client_options(rooms)
    rooms.set_defaults(handler=_rooms)

    simulate = commands.add_parser(
        "simulate", help="simulate a measurement on a running service (and localize it)"
    )
    simulate.add_argument("room_id")
    simulate.add_argument("--targets", type=int, default=2)
    simulate.add_argument("--snr-db", type=float, default=30.0)
    simulate.add_argument("--model", choices=("power", "correlation"), default="correlation")
    simulate.add_argument("--form", choices=("matrix", "upper", "terminals"), default="matrix")
    simulate.add_argument("--solver", default="gridless")
    simulate.add_argument("--seed", type=int, default=None)
    simulate.add_argument("--localize", action="store_true", help="also localize it")
    _add_client_options(simulate)
    simulate.set_defaults(handler=_simulate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vlp`` console script."""
    args = _parser().parse_args(argv)
    code: int = args.handler(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
