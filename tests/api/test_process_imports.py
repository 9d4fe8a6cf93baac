"""An API process holds what serving needs: the plotting stack (pictures), PostgreSQL's
driver (a SQLite registry), cvxpy (the l1 solver) and numba (the solvers' compiled kernels)
load only when a request or the registry asks for them. Each
check runs in a fresh interpreter, since this test process has long imported everything."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
ON_DEMAND = ("matplotlib", "PIL", "psycopg", "cvxpy", "numba")

# One fresh interpreter starts the app, then asks for a picture's renderer, then builds an l1
# problem; it prints the modules it holds after each step (a line of JSON each).
_PROBE = """
import json, sys, warnings
from pathlib import Path
from app.main import create_app
from app.settings import Settings
warnings.filterwarnings("ignore", message=r"Using `httpx` with `starlette.testclient`")
from fastapi.testclient import TestClient
settings = Settings(
    data_dir=Path({data_dir!r}), database_url=None, admin_keys="admin-test-key-0123456789",
    terminal_keys="terminal-test-key-0123456789", embedded_workers=0, demo=False,
)
with TestClient(create_app(settings)) as client:
    assert client.get("/healthz").status_code == 200
    print(json.dumps(sorted(sys.modules)))
    from app.pictures import room_map_png
    print(json.dumps(sorted(sys.modules)))
    import numpy as np
    from app.vlp.solvers.l1 import build_l1_problem
    build_l1_problem(np.eye(3), np.ones(3))
    print(json.dumps(sorted(sys.modules)))
"""


@pytest.fixture(scope="module")
def loaded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[str]]:
    """The on-demand packages the probe holds once started, after the picture renderer's
    import and after the first l1 problem."""
    data_dir = tmp_path_factory.mktemp("probe")
    completed = subprocess.run(
        [sys.executable, "-c", _PROBE.format(data_dir=str(data_dir))],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    steps = [set(json.loads(line)) for line in completed.stdout.splitlines()[-3:]]
    return {
        step: [name for name in ON_DEMAND if name in modules]
        for step, modules in zip(("started", "picture", "l1"), steps, strict=True)
    }


def test_a_started_api_process_holds_no_plotting_and_no_postgres_driver(
    loaded: dict[str, list[str]],
) -> None:
    assert loaded["started"] == []


def test_the_first_picture_loads_the_plotting_stack(loaded: dict[str, list[str]]) -> None:
    # The same probe must see matplotlib once a picture is drawn, or the check above
    # proves nothing.
    assert "matplotlib" in loaded["picture"]


def test_the_first_l1_problem_loads_cvxpy(loaded: dict[str, list[str]]) -> None:
    assert "cvxpy" in loaded["l1"]
    assert "cvxpy" not in loaded["picture"]


# One fresh interpreter serves the demo room (built by the embedded worker), then localizes
# one simulated measurement; it prints whether numba was loaded before and after, and the
# answer's estimates with the simulation's truth (a line of JSON each).
_FIRST_SOLVE_PROBE = """
import json, sys, time, warnings
from pathlib import Path
warnings.filterwarnings("ignore", message=r"Using `httpx` with `starlette.testclient`")
from app.main import create_app
from tests.api.conftest import ADMIN, TERMINAL, TestClient, make_settings, wait_for_room
settings = make_settings(Path({data_dir!r}), demo=True, embedded_workers=1)
with TestClient(create_app(settings)) as client:
    room_id = client.get("/v1/rooms", headers=ADMIN).json()["items"][0]["id"]
    wait_for_room(client, room_id)
    print(json.dumps("numba" in sys.modules))
    simulated = client.post(
        f"/v1/rooms/{{room_id}}/simulate", json={{"targets": 3, "snr_db": 40, "seed": 5}},
        headers=TERMINAL,
    ).json()
    answer = client.post(
        f"/v1/rooms/{{room_id}}/localize", json=simulated["measurement"], headers=TERMINAL
    )
    assert answer.status_code == 200, answer.text
    print(json.dumps("numba" in sys.modules))
    print(json.dumps([answer.json()["estimates"], simulated["truth"]]))
"""


def test_the_first_solve_loads_the_compiled_kernels_and_answers(tmp_path: Path) -> None:
    completed = subprocess.run(
        [sys.executable, "-c", _FIRST_SOLVE_PROBE.format(data_dir=str(tmp_path))],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    before, after, pair = (json.loads(line) for line in completed.stdout.splitlines()[-3:])
    estimates, truth = pair
    # A room that is ready to serve, its build done, holds no compiled kernels yet.
    assert before is False
    assert after is True
    # The first answer, which loaded the kernels, finds the simulated targets: each true
    # position has an estimate within 10 cm (the paper room at 40 dB, three targets).
    found = np.array([[e["x"], e["y"]] for e in estimates])
    for target in truth:
        distances = np.hypot(found[:, 0] - target["x"], found[:, 1] - target["y"])
        assert distances.min() < 0.10, (target, estimates)
