"""``vlp serve --workers N``: N API processes on one port.

The supervisor (the ``vlp serve`` process) binds the port once, starts N API processes
(``multiprocessing`` *spawn*: each imports the app afresh, nothing is shared but the port
and the registry) and the kernel spreads the connections among them. It serves no request
itself and imports no numpy.

On Linux each API process listens on a socket of its own, bound to the same address with
``SO_REUSEPORT``, and the kernel hands each new connection to one of them by a hash of its
addresses; the supervisor's socket only holds the port and never listens. With one shared
listening socket every process woke on a new connection and the first to run accepted all
that were queued: a burst of keep-alive connections (clients starting at once) mostly
landed on one process and stayed there, so a second process added nothing for them
(docs/decisions/connections-spread-over-processes.md). Elsewhere the shared socket
remains.

What must run once per deployment runs in API process 0 only: the embedded build workers,
the epoch sweeper and the demo-room seeding (whose "no rooms yet?" check is not atomic).
The other processes run with ``embedded_workers=0``, ``epoch_sweep_seconds=0`` (epochs are
still settled lazily, on reads and solve requests, in every process) and ``demo=False``.
Process 0 starts first and the others only once its lifespan has run, so whichever process
answers a client's first request, the demo room is already there.

A process that exits after it had started (a crash, ``kill -9``, the OOM killer) is started
again with the same index, so process 0's duties come back with it. One that fails during
start-up (e.g. the registry is unreachable) ends the whole service with exit code 3, as a
single ``vlp serve`` would. SIGTERM, SIGINT or SIGHUP to the supervisor stop every API
process gracefully (each finishes its requests and stops its build workers). The API
processes ask the kernel for SIGTERM when the supervisor dies, so even ``kill -9`` of the
supervisor leaves no orphans.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import signal
import socket
import sys
import threading
from dataclasses import dataclass
from multiprocessing.context import SpawnProcess
from multiprocessing.sharedctypes import Synchronized
from types import FrameType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import uvicorn

    from app.settings import Settings

__all__ = [
    "EXIT_STARTUP_FAILURE",
    "SharedPort",
    "api_process_settings",
    "bind_listening_socket",
    "reuse_port_available",
    "serve_workers",
]

# What `vlp serve` (an API process, the supervisor) exits with when the app does not start
# (e.g. the registry is away).
EXIT_STARTUP_FAILURE = 3
# How long stopping API processes may take (they finish requests, stop build workers).
_STOP_TIMEOUT_S = 30.0
_POLL_S = 0.2
_PR_SET_PDEATHSIG = 1

_log = logging.getLogger("app.serve")


def bind_listening_socket(config: uvicorn.Config) -> socket.socket:
    """The socket uvicorn binds for ``config``, with its protocol read back from the kernel.

    uvicorn makes it with protocol 0; asyncio sets ``TCP_NODELAY`` only on connections of a
    socket whose protocol is ``IPPROTO_TCP``, and without it a response written in two pieces
    (headers, body) waits about 40 ms for the client's delayed ACK.
    """
    return socket.socket(fileno=config.bind_socket().detach())


def reuse_port_available() -> bool:
    """True where each API process can listen on a socket of its own (Linux's
    ``SO_REUSEPORT`` balances connections among the sockets; other systems' does not)."""
    return sys.platform.startswith("linux") and hasattr(socket, "SO_REUSEPORT")


@dataclass(frozen=True)
class SharedPort:
    """An address every API process listens on with a socket of its own (``SO_REUSEPORT``):
    what the supervisor passes to them instead of a socket."""

    family: int
    address: tuple[object, ...]
    v6only: int

    @classmethod
    def bind(cls, host: str, port: int) -> tuple[SharedPort, socket.socket]:
        """Bind ``host:port`` (port 0: the kernel's choice) with ``SO_REUSEPORT``, not
        listening: the port and the socket that holds it for the service's lifetime (a
        socket that does not listen receives no connection).

        Raises OSError (``EADDRINUSE``) when anything holds the port, as a plain bind would:
        ``SO_REUSEPORT`` alone would let a second service of the same user share it and
        take half of this one's connections.
        """
        # As uvicorn picks the family; IPPROTO_TCP so that asyncio sets TCP_NODELAY on the
        # accepted connections (bind_listening_socket).
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        if port != 0:
            # A plain bind first (as uvicorn's, SO_REUSEADDR only): it fails on any socket
            # bound there, SO_REUSEPORT or not.
            with socket.socket(family, socket.SOCK_STREAM) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                probe.bind((host, port))
        holder = _reuse_port_socket(family)
        try:
            holder.bind((host, port))
        except OSError:
            holder.close()
            raise
        v6only = (
            holder.getsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY)
            if family == socket.AF_INET6
            else 0
        )
        return cls(family, tuple(holder.getsockname()), v6only), holder

    def listener(self) -> socket.socket:
        """A socket of this process bound to the port (uvicorn makes it listen)."""
        sock = _reuse_port_socket(self.family)
        if self.family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, self.v6only)
        try:
            sock.bind(self.address)
        except OSError:
            sock.close()
            raise
        return sock


def _reuse_port_socket(family: int) -> socket.socket:
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    return sock


def api_process_settings(settings: Settings, index: int) -> Settings:
    """The settings API process ``index`` runs with: process 0 keeps the once-per-service
    duties (build workers, epoch sweeper, demo seeding); the others have them switched off."""
    if index == 0:
        return settings
    return settings.model_copy(
        update={"embedded_workers": 0, "epoch_sweep_seconds": 0.0, "demo": False}
    )


def _die_with_parent(parent_pid: int) -> None:
    """Ask Linux to send SIGTERM to this process when its parent exits (no orphans after a
    ``kill -9`` of the supervisor); exit at once if the parent is already gone."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent_pid:
        os._exit(0)


def _run_api_process(
    index: int,
    settings: Settings,
    port: socket.socket | SharedPort,
    log_level: str,
    parent_pid: int,
    started: Synchronized[int],
) -> None:
    """Body of one API process: the app on its own socket of the shared port (or on the
    inherited socket), until SIGTERM."""
    _die_with_parent(parent_pid)
    sock = port.listener() if isinstance(port, SharedPort) else port
    import uvicorn

    from app.api.logs import configure_logging
    from app.main import create_app

    configure_logging(log_level)
    app = create_app(api_process_settings(settings, index))
    config = uvicorn.Config(app, log_config=None, access_log=False, proxy_headers=False)

    class _Server(uvicorn.Server):
        async def startup(self, sockets: list[socket.socket] | None = None) -> None:
            await super().startup(sockets=sockets)
            if not self.should_exit:
                _log.info(
                    "API process %d ready (pid %d)",
                    index,
                    os.getpid(),
                    extra={"worker_index": index, "pid": os.getpid()},
                )
                # The lifespan has run: from now on an exit is a crash to recover from,
                # not a failed start-up. Set after the log line, which then precedes
                # every later process's.
                started.value = 1

    server = _Server(config)
    _log.info(
        "API process %d starting (pid %d)",
        index,
        os.getpid(),
        extra={"worker_index": index, "pid": os.getpid()},
    )
    server.run(sockets=[sock])
    sys.exit(0 if server.started else EXIT_STARTUP_FAILURE)


@dataclass
class _ApiProcess:
    index: int
    process: SpawnProcess
    started: Synchronized[int]


class _Supervisor:
    def __init__(
        self,
        *,
        settings: Settings,
        port: socket.socket | SharedPort,
        count: int,
        log_level: str,
    ) -> None:
        self._context = multiprocessing.get_context("spawn")
        self._settings = settings
        self._port = port
        self._count = count
        self._log_level = log_level
        self._stop = threading.Event()
        self._processes: list[_ApiProcess] = []

    def _start(self, index: int) -> _ApiProcess:
        started: Synchronized[int] = self._context.Value("i", 0)
        process = self._context.Process(
            target=_run_api_process,
            args=(index, self._settings, self._port, self._log_level, os.getpid(), started),
            name=f"vlp-api-{index}",
        )
        process.start()
        return _ApiProcess(index=index, process=process, started=started)

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        del frame
        _log.info("supervisor got signal %d: stopping the API processes", signum)
        self._stop.set()

    def run(self) -> int:
        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(signum, self._on_signal)
        # Process 0 first, alone: once any process answers, the once-per-service duties
        # (demo seeding above all) have run, so a client that sees /readyz also sees the rooms.
        self._processes = [self._start(0)]
        code = self._await_first_start()
        if code == 0 and not self._stop.is_set():
            self._processes += [self._start(index) for index in range(1, self._count)]
        while code == 0 and not self._stop.wait(_POLL_S):
            for slot, api in enumerate(self._processes):
                if api.process.is_alive():
                    continue
                if not api.started.value:
                    _log.error(
                        "API process %d failed to start (exit code %s): stopping",
                        api.index,
                        api.process.exitcode,
                    )
                    code = EXIT_STARTUP_FAILURE
                    self._stop.set()
                    break
                _log.warning(
                    "API process %d (pid %s) exited with code %s: starting it again",
                    api.index,
                    api.process.pid,
                    api.process.exitcode,
                )
                self._processes[slot] = self._start(api.index)
        self._stop_all()
        return code

    def _await_first_start(self) -> int:
        """Wait until API process 0 has run its lifespan; EXIT_STARTUP_FAILURE if it
        exits before that, 0 otherwise (also when a stop signal came first)."""
        first = self._processes[0]
        while not first.started.value:
            if not first.process.is_alive():
                _log.error(
                    "API process 0 failed to start (exit code %s): stopping",
                    first.process.exitcode,
                )
                return EXIT_STARTUP_FAILURE
            if self._stop.wait(_POLL_S):
                break
        return 0

    def _stop_all(self) -> None:
        for api in self._processes:
            if api.process.is_alive() and api.process.pid is not None:
                os.kill(api.process.pid, signal.SIGTERM)
        for api in self._processes:
            api.process.join(_STOP_TIMEOUT_S)
            if api.process.is_alive():
                _log.warning("API process %d did not stop in time: killing it", api.index)
                api.process.kill()
                api.process.join()


def serve_workers(
    *, settings: Settings, port: socket.socket | SharedPort, count: int, log_level: str
) -> int:
    """Run ``count`` API processes on ``port`` (a :class:`SharedPort`, each process with a
    socket of its own, or one listening socket they share) until a stop signal; the exit
    code."""
    return _Supervisor(settings=settings, port=port, count=count, log_level=log_level).run()
