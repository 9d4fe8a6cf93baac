"""Steps the process tests share: create a room, wait for a job, kill a builder mid-build."""

from __future__ import annotations

from typing import Any

from tests.build_gate import BuildGate
from tests.processes import VlpProcess, pid_alive
from tests.waiting import wait_for

__all__ = [
    "HALL_TIMEOUT_S",
    "MID_BUILD",
    "assert_orphans_exit",
    "create_room",
    "job",
    "kill_mid_build",
    "wait_succeeded",
]

HALL_TIMEOUT_S = 600.0
# Where the gate holds a build that a test kills: well under way, far from done.
MID_BUILD = 0.2


def job(server: VlpProcess, job_id: str) -> dict[str, Any]:
    """The job as the API shows it."""
    with server.client() as client:
        response = client.get(f"/v1/jobs/{job_id}")
    response.raise_for_status()
    body: dict[str, Any] = response.json()
    return body


def create_room(server: VlpProcess, layout: dict[str, Any]) -> dict[str, Any]:
    """POST a room; returns the Room."""
    with server.client() as client:
        response = client.post("/v1/rooms", json=layout)
    assert response.status_code == 201, response.text
    body: dict[str, Any] = response.json()
    return body


def wait_succeeded(server: VlpProcess, job_id: str, timeout_s: float = 120.0) -> dict[str, Any]:
    """Poll the job until it succeeded (fail at once when it failed)."""

    def done() -> bool:
        status = job(server, job_id)["status"]
        assert status != "failed", job(server, job_id)
        return bool(status == "succeeded")

    wait_for(done, f"job {job_id} to succeed", timeout_s)
    return job(server, job_id)


def kill_mid_build(
    process: VlpProcess, server: VlpProcess, job_id: str, gate: BuildGate
) -> list[int]:
    """``kill -9`` ``process`` while its build of ``job_id`` is held at the (shut) gate, at
    ``gate.at`` of the way; open the gate; return the killed process's build children.

    The build cannot finish before the kill, however fast the machine: it waits at the gate.
    """
    assert gate.wait_held(HALL_TIMEOUT_S) == job_id
    state = job(server, job_id)
    assert state["status"] == "running" and state["progress"] >= gate.at, state
    children = process.build_children()
    assert children, "the build runs in a child process"
    process.kill9()
    gate.open()  # the orphan ends by itself (it watches its parent); later builds pass
    return children


def assert_orphans_exit(children: list[int]) -> None:
    """The dead parent's build children end by themselves (no second hall in memory)."""
    wait_for(lambda: not any(pid_alive(pid) for pid in children), "orphaned builds to exit", 30)
