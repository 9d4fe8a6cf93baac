"""``kill -9`` of a process in the middle of room updates leaves the old or the new layout.

A child process replaces one room as fast as it can, each layout derived from its version
number, and prints every version the registry acknowledged. It is killed at an arbitrary
moment (most likely inside a transaction: that is nearly all it does). The room must then be
exactly one of the layouts written, whole, with its own name and version, and no
acknowledged update may be missing.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from app.registry import Registry
from tests.db_fixtures import small_layout

pytestmark = pytest.mark.slow

_UPDATER = """
import sys
from pathlib import Path
from app.registry import Registry
from tests.faults.test_update_crash import layout_for

registry = Registry(database_url=sys.argv[1], data_dir=Path(sys.argv[2]))
room_id = sys.argv[3]
version = registry.get_room(room_id=room_id).layout_version
while True:
    name, layout = layout_for(version + 1)
    version = registry.replace_room(
        room_id=room_id, name=name, layout=layout, expected_layout_version=version
    ).layout_version
    print(version, flush=True)
"""


def layout_for(version: int) -> tuple[str, dict[str, Any]]:
    """The name and layout written as ``version``: 1 to 4 LEDs, moved along x each time."""
    layout = small_layout(1 + version % 4)
    for index, led in enumerate(layout["leds"]):
        led["x"] = round(0.1 + (version * 0.013 + index * 0.37) % 1.8, 3)
    return f"v{version}", layout


def test_kill9_during_room_updates_leaves_a_whole_layout(
    registry: Registry, tmp_path: Path
) -> None:
    name, layout = layout_for(1)
    room = registry.create_room(name=name, layout=layout)
    with subprocess.Popen(
        [sys.executable, "-c", _UPDATER, registry.database_url, str(tmp_path / "data"), room.id],
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.PIPE,
        text=True,
    ) as updater:
        acknowledged = read_until_killed(updater, at_least=40)

    stored = registry.get_room(room_id=room.id)
    name, layout = layout_for(stored.layout_version)
    assert stored.name == name
    assert stored.layout == registry_form(registry, name, layout)
    assert stored.layout_version >= acknowledged[-1]  # nothing acknowledged was lost
    assert stored.layout_version <= acknowledged[-1] + 1  # at most the one in flight
    job = registry.get_job(job_id=stored.job_id or "")
    assert (job.status, job.layout_version) == ("queued", stored.layout_version)


def registry_form(registry: Registry, name: str, layout: dict[str, Any]) -> dict[str, Any]:
    """The layout as the registry stores it (defaults applied), via a throwaway room."""
    probe = registry.create_room(name=name, layout=layout)
    try:
        return probe.layout
    finally:
        registry.delete_room(room_id=probe.id)


def read_until_killed(updater: subprocess.Popen[str], *, at_least: int) -> list[int]:
    """The versions the updater printed: wait for ``at_least``, ``kill -9`` it, read the rest."""
    assert updater.stdout is not None
    acknowledged: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while len(acknowledged) < at_least and time.monotonic() < deadline:
            line = updater.stdout.readline()
            assert line, f"the updater exited with {updater.poll()}"
            acknowledged.append(int(line))
        time.sleep(0.0137)  # land somewhere inside the next transactions
    finally:
        updater.send_signal(signal.SIGKILL)
        updater.wait(30)
    acknowledged += [int(line) for line in updater.stdout.read().split()]
    assert len(acknowledged) >= at_least
    return acknowledged
