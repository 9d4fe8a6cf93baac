"""The ``vlp`` console script.

``serve``, ``worker``, ``migrate`` and ``openapi`` run here; ``rooms``, ``simulate`` and
``localize`` talk to a running service through :class:`app.client.VLPClient` (``--json`` for
scripts, tables and progress bars otherwise).

Heavy imports happen inside the commands, so ``vlp serve`` can pin the BLAS thread pools to
one thread before numpy loads.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ._remote import add_remote_commands
from ._workers import EXIT_STARTUP_FAILURE as _EXIT_STARTUP_FAILURE
from ._workers import SharedPort, bind_listening_socket, reuse_port_available

if TYPE_CHECKING:
    from app.settings import Settings

__all__ = ["EXIT_NO_ANSWER", "EXIT_REFUSED", "EXIT_USAGE", "main", "openapi_document"]

_BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
DEFAULT_OPENAPI_PATH = Path("openapi/openapi.json")
EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_NO_ANSWER = 3
_APP_FACTORY = "app.main:create_app"


def _pin_blas() -> None:
    for name in _BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")


def openapi_document() -> str:
    """The OpenAPI document of the app, as written to ``openapi/openapi.json``."""
    from app.main import create_app
    from app.settings import Settings

    schema = create_app(Settings(demo=False, embedded_workers=0)).openapi()
    return json.dumps(schema, sort_keys=True, indent=2) + "\n"


def _settings_or_none(command: str, public_url: str | None = None) -> Settings | None:
    """The environment's settings (with ``public_url`` unless set); None after a clear error."""
    from pydantic import ValidationError

    from app.settings import Settings

    try:
        settings = Settings()
    except ValidationError as exc:
        for error in exc.errors():
            name = "VLP_" + "_".join(str(part) for part in error["loc"]).upper()
            print(f"vlp {command}: {name}: {error['msg']}", file=sys.stderr)
        return None
    if public_url is not None and "VLP_PUBLIC_URL" not in os.environ:
        settings = settings.model_copy(update={"public_url": public_url})
    return settings


def _write_port_file(path: Path, port: int) -> None:
    """Write the bound port atomically: a reader sees no file or the whole number."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    temporary.write_text(f"{port}\n", encoding="utf-8")
    os.replace(temporary, path)


def _serve(args: argparse.Namespace) -> int:
    _pin_blas()
    host = "127.0.0.1" if args.host in ("0.0.0.0", "::", "") else args.host
    settings = _settings_or_none("serve", f"http://{host}:{args.port}")
    if settings is None:
        return EXIT_USAGE
    import uvicorn

    from app.api.logs import configure_logging

    configure_logging(args.log_level)
    workers = settings.workers if args.workers is None else args.workers
    config = uvicorn.Config(
        # The app is made below, after binding: with --workers > 1 each API process makes
        # its own and the supervisor never imports it.
        _APP_FACTORY,
        host=args.host,
        port=args.port,
        log_config=None,
        access_log=False,
        proxy_headers=False,
    )
    # Bind here, once, so that `--port 0` takes a free port from the kernel and the port
    # actually bound can be reported: no other process can take it in between. Several API
    # processes each listen on a socket of their own where the kernel balances them.
    shared: SharedPort | None = None
    if workers > 1 and reuse_port_available():
        try:
            shared, sock = SharedPort.bind(args.host, args.port)
        except OSError as exc:  # as uvicorn's own bind: logged, the start-up failure code
            logging.getLogger("app.serve").error("cannot bind %s:%s: %s", args.host, args.port, exc)
            return _EXIT_STARTUP_FAILURE
    else:
        sock = bind_listening_socket(config)
    bound = int(sock.getsockname()[1])
    if args.port == 0 and "VLP_PUBLIC_URL" not in os.environ:
        settings.public_url = f"http://{host}:{bound}"  # read by the lifespan, at start-up
    if args.port_file is not None:
        _write_port_file(args.port_file, bound)
    if workers > 1:
        from ._workers import serve_workers

        return serve_workers(
            settings=settings,
            port=sock if shared is None else shared,
            count=workers,
            log_level=args.log_level,
        )
    from app.main import create_app

    config.app = create_app(settings)
    server = uvicorn.Server(config)
    server.run(sockets=[sock])
    return 0 if server.started else _EXIT_STARTUP_FAILURE


def _worker(args: argparse.Namespace) -> int:
    _pin_blas()
    from app.api.logs import configure_logging
    from app.jobs import run_worker

    settings = _settings_or_none("worker")
    if settings is None:
        return EXIT_USAGE
    configure_logging(args.log_level)
    address = None if args.metrics_port is None else (args.metrics_host, args.metrics_port)
    run_worker(settings=settings, metrics_address=address)
    return 0


def _migrate(args: argparse.Namespace) -> int:
    """Bring the registry schema to the newest migration and exit (a deployment's one-shot
    step; ``serve`` and ``worker`` would also do it, safely, on start)."""
    del args
    from app.registry import Registry
    from app.settings import get_settings

    settings = get_settings()
    registry = Registry(database_url=settings.resolved_database_url(), data_dir=settings.data_dir)
    try:
        registry.migrate()
    finally:
        registry.dispose()
    print("registry schema is up to date")
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


def _positive_count(text: str) -> int:
    """An ``--workers`` value: a whole number from 1 to 64."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not 1 <= value <= 64:
        raise argparse.ArgumentTypeError(f"must be from 1 to 64, got {value}")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vlp", description="Visible-light positioning service")
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser("serve", help="serve the HTTP API (uvicorn)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000, help="0: any free port")
    serve.add_argument(
        "--port-file",
        type=Path,
        default=None,
        help="write the port actually bound to this file (e.g. with --port 0)",
    )
    serve.add_argument(
        "--workers",
        type=_positive_count,
        default=None,
        help="API processes sharing the port (default: VLP_WORKERS, else 1); build workers "
        "and the epoch sweeper run in the first one only",
    )
    serve.add_argument("--log-level", default="info")
    serve.set_defaults(handler=_serve)

    worker = commands.add_parser("worker", help="run fingerprint-build workers")
    worker.add_argument("--log-level", default="info")
    worker.add_argument(
        "--metrics-port",
        type=int,
        default=None,
        help="serve Prometheus metrics (process, jobs by status) at /metrics on this port",
    )
    worker.add_argument("--metrics-host", default="127.0.0.1", help="address for --metrics-port")
    worker.set_defaults(handler=_worker)

    migrate = commands.add_parser("migrate", help="apply the registry's database migrations")
    migrate.set_defaults(handler=_migrate)

    openapi = commands.add_parser("openapi", help="write the OpenAPI document")
    openapi.add_argument("--output", type=Path, default=DEFAULT_OPENAPI_PATH)
    openapi.add_argument(
        "--check",
        action="store_true",
        help="only check that the file is up to date (exit 1 if not)",
    )
    openapi.set_defaults(handler=_openapi)

    add_remote_commands(commands)
    return parser


def _run_remote(args: argparse.Namespace) -> int:
    """Run a command against the service; map client errors to messages and exit codes."""
    from app.client import APIError, ClientError, JobError

    from ._output import Output
    from ._remote import InputFileError, open_client

    out = Output(as_json=args.json)
    try:
        with open_client(args) as client:
            code: int = args.remote(client, out, args)
            return code
    except APIError as exc:
        out.problem(exc)
        return EXIT_REFUSED
    except JobError as exc:
        out.failure(str(exc))
        if args.json:
            out.result(exc.job)
        return EXIT_REFUSED
    except ClientError as exc:
        out.failure(f"no answer from {args.url}: {exc}")
        return EXIT_NO_ANSWER
    except InputFileError as exc:
        out.failure(str(exc))
        return EXIT_USAGE


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vlp`` console script.

    Exit codes: 0 done; 1 the service refused (a problem answer), or a job failed or did
    not finish within ``--wait-timeout``; 2 usage error or unreadable input file; 3 the
    service could not be reached or a request timed out.
    """
    args = _parser().parse_args(argv)
    if getattr(args, "remote", None) is not None:
        return _run_remote(args)
    code: int = args.handler(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
