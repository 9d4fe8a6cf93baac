"""``vlp serve --workers 2`` for real: two API processes on one port, one SQLite registry.

Both processes answer (each request on a new connection names its process in ``/metrics``),
process 1 starts only once process 0 (which seeds the demo room) is ready, a room posted
through the port is built exactly once (the build workers run in API process 0 only), a
crashed API process is started again, and neither SIGTERM nor ``kill -9`` of the supervisor
leaves an API process behind.
"""

from __future__ import annotations

import asyncio
import errno
import os
import re
import signal
import socket
import subprocess
from collections.abc import Callable
from pathlib import Path
from socket import IPPROTO_TCP, TCP_NODELAY

import httpx
import pytest
import uvicorn

from app.cli import main
from app.cli._workers import SharedPort, bind_listening_socket
from app.vlp.presets import paper_layout
from tests.live_server import VLP, serve_args, server_env
from tests.processes import TERMINAL, VlpProcess, child_pids, pid_alive, process_fleet
from tests.waiting import SAFETY_TIMEOUT_S, wait_for

from .steps import create_room, wait_succeeded

pytestmark = pytest.mark.slow

_PID = re.compile(r'^vlp_api_process_info\{pid="(\d+)"\} 1\.0$', re.MULTILINE)


def answering_pid(url: str) -> int:
    """The pid of the API process that answered a request on a fresh connection."""
    response = httpx.get(f"{url}/metrics", timeout=30.0)
    assert response.status_code == 200
    return _pid_of(response.text)


def api_processes(supervisor: VlpProcess) -> set[int]:
    """The supervisor's API processes (its children, without multiprocessing's tracker)."""
    return {
        pid
        for pid in child_pids(supervisor.pid)
        if "resource_tracker" not in Path(f"/proc/{pid}/cmdline").read_text(errors="replace")
    }


def wait_answering(url: str, expected: set[int]) -> None:
    """Each of ``expected`` answers some request (the kernel picks the process per
    connection, so ask until all were seen)."""
    seen: set[int] = set()

    def all_seen() -> bool:
        seen.add(answering_pid(url))
        assert seen <= expected, f"answered by {seen - expected}, not an API process"
        return seen == expected

    wait_for(all_seen, f"processes {expected} to answer")


def ready_pids(server: VlpProcess) -> set[int]:
    """The API processes that logged their start-up as complete."""
    return {
        int(entry["pid"])
        for entry in server.log()
        if str(entry.get("message", "")).startswith("API process") and "ready" in entry["message"]
    }


def built_jobs(server: VlpProcess) -> list[str]:
    """Ids of the jobs some process of the service started building (one shared log)."""
    return [
        entry["job_id"]
        for entry in server.log()
        if entry.get("message", "").startswith("job ") and "building" in entry["message"]
    ]


def test_two_api_processes_share_the_port_and_build_once(tmp_path: Path) -> None:
    with process_fleet(tmp_path / "data") as fleet:
        server = fleet.serve({"VLP_WORKERS": "2"})
        wait_for(lambda: len(api_processes(server)) == 2, "two API processes")
        pids = api_processes(server)
        assert server.pid not in pids
        wait_answering(server.url, pids)

        room = create_room(server, {**paper_layout().to_mapping(), "name": "two workers"})
        job_id = room["fingerprint"]["job_id"]
        wait_succeeded(server, job_id)
        with server.client() as client:
            body = client.post(
                f"/v1/rooms/{room['id']}/simulate", json={"targets": 2, "seed": 3}
            ).json()["measurement"]
        for _ in range(4):  # fresh connections: whichever process answers knows the room
            response = httpx.post(
                f"{server.url}/v1/rooms/{room['id']}/localize",
                json=body,
                headers=TERMINAL,
                timeout=60.0,
            )
            assert response.status_code == 200, response.text
        assert built_jobs(server).count(job_id) == 1
        started = [e for e in server.log() if e.get("message", "").startswith("service started")]
        assert sorted(e["embedded_workers"] for e in started) == [0, 1]
        # Process 0 (the demo seeding's) was ready before process 1 began its start-up.
        order = [str(e.get("message", "")) for e in server.log()]
        ready_0 = next(i for i, m in enumerate(order) if m.startswith("API process 0 ready"))
        start_1 = next(i for i, m in enumerate(order) if m.startswith("API process 1 starting"))
        assert ready_0 < start_1, order


def test_connections_opened_together_are_spread_over_the_api_processes(tmp_path: Path) -> None:
    """32 keep-alive connections opened at once (as a pool of clients starting together):
    each API process takes at least 4 of them, and keeps them (the second request on each
    connection is answered by the same process). Each process listens on a socket of its own
    (SO_REUSEPORT) and the kernel picks one per connection by a hash: 3 or fewer of 32 for
    one process has a probability of 2.6e-6. With one shared socket the first process to wake
    accepted nearly every queued connection
    (docs/decisions/connections-spread-over-processes.md)."""

    async def burst(url: str, count: int) -> list[tuple[int, int]]:
        clients = [httpx.AsyncClient(timeout=60.0) for _ in range(count)]
        try:
            first = await asyncio.gather(*(c.get(f"{url}/metrics") for c in clients))
            second = await asyncio.gather(*(c.get(f"{url}/metrics") for c in clients))
        finally:
            await asyncio.gather(*(c.aclose() for c in clients))
        return [(_pid_of(a.text), _pid_of(b.text)) for a, b in zip(first, second, strict=True)]

    with process_fleet(tmp_path / "data") as fleet:
        server = fleet.serve({"VLP_WORKERS": "2"})
        wait_for(lambda: len(api_processes(server)) == 2, "two API processes")
        pids = api_processes(server)
        wait_answering(server.url, pids)
        answered = asyncio.run(burst(server.url, 32))
    assert all(first == second for first, second in answered)
    counts = {pid: sum(first == pid for first, _ in answered) for pid in pids}
    assert sum(counts.values()) == 32, counts  # every answer came from an API process
    assert min(counts.values()) >= 4, counts


def _pid_of(metrics: str) -> int:
    match = _PID.search(metrics)
    assert match is not None, "no vlp_api_process_info in /metrics"
    return int(match.group(1))


def test_a_crashed_api_process_is_replaced_and_sigterm_stops_all(tmp_path: Path) -> None:
    with process_fleet(tmp_path / "data") as fleet:
        server = fleet.serve({"VLP_WORKERS": "2", "VLP_DEMO": "false"})
        wait_for(lambda: len(api_processes(server)) == 2, "two API processes")
        first = api_processes(server)
        # Killed before its start-up completed, a process is a failed start (the service
        # stops, exit 3): kill one only once both said they are ready.
        wait_for(lambda: ready_pids(server) >= first, "both API processes to be ready")
        victim = min(first)
        os.kill(victim, signal.SIGKILL)
        wait_for(
            lambda: len(api_processes(server)) == 2 and victim not in api_processes(server),
            "the killed API process to be replaced",
        )
        replaced = api_processes(server)
        wait_answering(server.url, replaced)

        server.process.send_signal(signal.SIGTERM)  # the supervisor only, not its group
        assert server.process.wait(timeout=60) == 0
        wait_for(lambda: not any(pid_alive(pid) for pid in replaced), "API processes to exit")


def test_kill_9_of_the_supervisor_leaves_no_api_process(tmp_path: Path) -> None:
    with process_fleet(tmp_path / "data") as fleet:
        server = fleet.serve({"VLP_WORKERS": "2", "VLP_DEMO": "false"})
        wait_for(lambda: len(api_processes(server)) == 2, "two API processes")
        pids = api_processes(server)
        server.kill9()
        wait_for(lambda: not any(pid_alive(pid) for pid in pids), "orphaned API processes to exit")


def test_a_failed_start_up_ends_the_service_with_exit_code_3(tmp_path: Path) -> None:
    """With the registry unreachable no API process starts: exit 3, as a single process."""
    unreachable = "postgresql+psycopg://vlp:vlp@127.0.0.1:1/vlp?connect_timeout=2"
    port_file = tmp_path / "serve.port"
    process = subprocess.run(
        [str(VLP), "serve", "--workers", "2", *serve_args(port_file)],
        env=server_env(tmp_path / "data", VLP_DATABASE_URL=unreachable),
        capture_output=True,
        timeout=SAFETY_TIMEOUT_S,
        check=False,
    )
    assert process.returncode == 3, process.stderr.decode(errors="replace")[-2000:]
    assert port_file.exists()


def test_a_shared_port_takes_its_own_listeners_and_nobody_else() -> None:
    """A :class:`SharedPort` hands out any number of listening sockets on its port, each
    accepting connections (its holder does not listen: every connection of a burst is
    accepted by a listener); a second service binding the same port is refused, whether it
    asks for SO_REUSEPORT too (another `vlp serve --workers 2` of the same user) or not."""
    shared, holder = SharedPort.bind("127.0.0.1", 0)
    listeners = [shared.listener(), shared.listener()]
    port = int(holder.getsockname()[1])
    try:
        for listener in listeners:
            listener.listen(64)
        clients = [socket.create_connection(("127.0.0.1", port)) for _ in range(16)]
        accepted = 0
        for listener in listeners:
            listener.setblocking(False)
            while True:
                try:
                    connection, _ = listener.accept()
                except BlockingIOError:
                    break
                connection.close()
                accepted += 1
        for client in clients:
            client.close()
        assert accepted == 16
        with pytest.raises(OSError) as taken:
            SharedPort.bind("127.0.0.1", port)
        assert taken.value.errno == errno.EADDRINUSE
    finally:
        for sock in (*listeners, holder):
            sock.close()
    with socket.socket() as plain:
        plain.bind(("127.0.0.1", 0))
        plain.listen(1)
        with pytest.raises(OSError) as taken:
            SharedPort.bind("127.0.0.1", int(plain.getsockname()[1]))
        assert taken.value.errno == errno.EADDRINUSE


def test_workers_on_a_taken_port_end_with_exit_code_3(tmp_path: Path) -> None:
    """`vlp serve --workers 2` on a port something listens on: exit 3, as uvicorn's own bind."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = str(taken.getsockname()[1])
        process = subprocess.run(
            [str(VLP), "serve", "--workers", "2", "--host", "127.0.0.1", "--port", port],
            env=server_env(tmp_path / "data"),
            capture_output=True,
            timeout=SAFETY_TIMEOUT_S,
            check=False,
        )
    assert process.returncode == 3, process.stderr.decode(errors="replace")[-2000:]
    assert "cannot bind" in process.stderr.decode(errors="replace")


def test_workers_must_be_a_positive_count(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["serve", "--workers", "0"])
    assert exited.value.code == 2
    assert "--workers: must be from 1 to 64, got 0" in capsys.readouterr().err


def test_the_served_connections_send_without_delay() -> None:
    """Connections accepted on `vlp serve`'s socket have TCP_NODELAY (asyncio sets it only for
    an IPPROTO_TCP socket): a response's header and body writes never wait for an ACK."""
    config = uvicorn.Config("app.main:create_app", host="127.0.0.1", port=0)
    sock = bind_listening_socket(config)
    nodelay: list[int] = []

    async def serve_one() -> None:
        async def accepted(_reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            nodelay.append(writer.get_extra_info("socket").getsockopt(IPPROTO_TCP, TCP_NODELAY))
            writer.close()

        server = await asyncio.start_server(accepted, sock=sock)
        port = server.sockets[0].getsockname()[1]
        _, writer = await asyncio.open_connection("127.0.0.1", port)
        await asyncio.wait_for(asyncio.shield(_until(lambda: bool(nodelay))), SAFETY_TIMEOUT_S)
        writer.close()
        server.close()
        await server.wait_closed()

    asyncio.run(serve_one())
    assert nodelay and nodelay[0] != 0


async def _until(condition: Callable[[], bool]) -> None:
    while not condition():
        await asyncio.sleep(0.01)
