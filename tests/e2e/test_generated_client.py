"""A client generated from ``openapi/openapi.json`` by an independent generator works.

``openapi-python-client`` (not our code) generates a package from the document; a fresh
interpreter that sees only that package then runs the walkthrough against a real
``vlp serve``: create a room, wait until its fingerprint is ready, simulate two terminals and
localize them. The answers arrive as the generator's typed models (``Room.layout`` is a
``RoomLayout``, ``Simulation.measurement`` a ``Measurement``).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from app.schemas.rooms import paper_room_example
from tests.processes import ADMIN, TERMINAL, process_fleet

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
GENERATOR = Path(sys.executable).with_name("openapi-python-client")
PACKAGE = "vlp_generated_client"
# No post-hooks: the generated code is used as the generator wrote it.
CONFIG = f"project_name_override: vlp-generated-client\npackage_name_override: {PACKAGE}\n"
CONFIG += "post_hooks: []\n"

WALKTHROUGH = """
import json, sys, time

from vlp_generated_client import AuthenticatedClient
from vlp_generated_client.api.localization import localize, simulate
from vlp_generated_client.api.rooms import create_room, get_room
from vlp_generated_client.models import Localization, Room, RoomLayout, Simulation
from vlp_generated_client.models import SimulationRequest

url, admin_key, terminal_key, layout = sys.argv[1:5]


def client(key):
    return AuthenticatedClient(base_url=url, token=key, prefix="", auth_header_name="X-API-Key")


admin, terminal = client(admin_key), client(terminal_key)
room = create_room.sync(client=admin, body=RoomLayout.from_dict(json.loads(layout)))
assert isinstance(room, Room), room
deadline = time.monotonic() + 300  # a safety net only; the build takes about a second
while room.fingerprint.status.value != "ready":
    assert room.fingerprint.status.value != "failed", room
    assert time.monotonic() < deadline, "the room was not built"
    time.sleep(0.2)
    room = get_room.sync(room.id, client=admin)
    assert isinstance(room, Room), room
simulation = simulate.sync(
    room.id, client=terminal, body=SimulationRequest(targets=2, snr_db=40.0, seed=5)
)
assert isinstance(simulation, Simulation), simulation
located = localize.sync(room.id, client=terminal, body=simulation.measurement)
assert isinstance(located, Localization), located
print(json.dumps({
    "layout_type": type(room.layout).__name__,
    "leds": len(room.layout.leds),
    "measurement_type": type(simulation.measurement).__name__,
    "truth": [[t.x, t.y] for t in simulation.truth],
    "estimates": [[e.x, e.y] for e in located.estimates],
}))
"""


def generate(output: Path) -> Path:
    """Generate the client package from the committed document; the directory holding it."""
    config = output.parent / "generator.yaml"
    config.write_text(CONFIG, encoding="utf-8")
    completed = subprocess.run(
        [
            str(GENERATOR),
            "generate",
            "--path",
            str(REPO / "openapi" / "openapi.json"),
            "--config",
            str(config),
            "--output-path",
            str(output),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert completed.returncode == 0, completed.stdout + completed.stderr
    assert (output / PACKAGE / "client.py").is_file()
    return output


def test_a_generated_client_runs_the_walkthrough_against_a_live_server(tmp_path: Path) -> None:
    generated = generate(tmp_path / "generated")
    with process_fleet(tmp_path / "data", VLP_DEMO="0") as fleet:
        server = fleet.serve()
        completed = subprocess.run(
            [
                sys.executable,
                "-c",
                WALKTHROUGH,
                server.url,
                ADMIN["X-API-Key"],
                TERMINAL["X-API-Key"],
                json.dumps(paper_room_example()),
            ],
            cwd=tmp_path,  # the script imports only the generated package (and its deps)
            env={"PYTHONPATH": str(generated), "PATH": "/usr/bin:/bin"},
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )
    assert completed.returncode == 0, completed.stderr
    outcome: dict[str, Any] = json.loads(completed.stdout.splitlines()[-1])
    assert outcome["layout_type"] == "RoomLayout" and outcome["leds"] == 16
    assert outcome["measurement_type"] == "Measurement"
    assert len(outcome["estimates"]) == len(outcome["truth"]) == 2
    for x, y in outcome["truth"]:  # 40 dB, two terminals: each found within 10 cm
        nearest = min(math.dist((x, y), estimate) for estimate in outcome["estimates"])
        assert nearest < 0.1, outcome
