"""An API process holds what serving needs: the plotting stack (pictures), PostgreSQL's
driver (a SQLite registry) and cvxpy (the l1 solver) load only when a request or the
registry asks for them. Each
check runs in a fresh interpreter, since this test process has long imported everything."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ON_DEMAND = ("matplotlib", "PIL", "psycopg", "cvxpy")

_STARTED_APP = """
import warnings
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
    {then}
"""


def _loaded_after(code: str) -> list[str]:
    """The on-demand packages a fresh interpreter holds after running ``code``."""
    script = f"{code}\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))\n"
    completed = subprocess.run(
        [sys.executable, "-c", script],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    loaded = set(json.loads(completed.stdout.splitlines()[-1]))
    return [name for name in ON_DEMAND if name in loaded]


def test_a_started_api_process_holds_no_plotting_and_no_postgres_driver(tmp_path: Path) -> None:
    code = _STARTED_APP.format(data_dir=str(tmp_path), then="pass")
    assert _loaded_after(code) == []


def test_the_first_picture_loads_the_plotting_stack(tmp_path: Path) -> None:
    # The same probe must see matplotlib once a picture is drawn, or the check above
    # proves nothing.
    then = "from app.pictures import room_map_png"
    code = _STARTED_APP.format(data_dir=str(tmp_path), then=then)
    assert "matplotlib" in _loaded_after(code)


def test_the_first_l1_problem_loads_cvxpy(tmp_path: Path) -> None:
    then = (
        "import numpy as np; from app.vlp.solvers.l1 import build_l1_problem; "
        "build_l1_problem(np.eye(3), np.ones(3))"
    )
    code = _STARTED_APP.format(data_dir=str(tmp_path), then=then)
    assert "cvxpy" in _loaded_after(code)
