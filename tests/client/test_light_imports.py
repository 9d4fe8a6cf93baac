"""The client side stays light: talking HTTP never loads the science stack.

A terminal app (or ``vlp rooms list``) imports ``app.client`` and ``app.schemas`` only; the
numerics (numpy, scipy, cvxpy, numba) and the plotting (matplotlib) are server-side. Each
check runs in a fresh interpreter, since this test process has long imported all of them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.processes import ADMIN, process_fleet

HEAVY = frozenset({"numpy", "scipy", "cvxpy", "numba", "matplotlib"})
REPO = Path(__file__).resolve().parents[2]


def _heavy_modules_after(code: str, env: dict[str, str] | None = None) -> tuple[list[str], str]:
    """Run ``code`` in a fresh interpreter; the heavy packages it loaded and its stdout.

    ``code`` runs first; then the interpreter prints the sorted top-level names of
    ``sys.modules`` as one JSON line on stdout, last.
    """
    script = (
        f"{code}\n"
        "import json, sys\n"
        "print(json.dumps(sorted({name.split('.')[0] for name in sys.modules})))\n"
    )
    completed = subprocess.run(
        [sys.executable, "-c", script],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert completed.returncode == 0, completed.stderr
    *output, modules_line = completed.stdout.splitlines()
    loaded = set(json.loads(modules_line))
    return sorted(loaded & HEAVY), "\n".join(output)


def test_importing_the_client_and_the_schemas_loads_no_numerics() -> None:
    heavy, _ = _heavy_modules_after("import app.client\nimport app.schemas")
    assert heavy == []


def test_the_check_sees_a_heavy_import() -> None:
    # The same probe on the server side must see numpy, or the check above proves nothing.
    heavy, _ = _heavy_modules_after("import app.vlp.fingerprints")
    assert "numpy" in heavy and "scipy" in heavy


def test_the_schema_examples_still_come_from_the_science_core() -> None:
    # Examples are computed when the schema is generated (the served OpenAPI document).
    heavy, output = _heavy_modules_after(
        "import json\n"
        "from app.schemas import Measurement\n"
        "print(json.dumps(Measurement.model_json_schema()['examples'][0]['targets']))"
    )
    assert output == "3"
    assert "numpy" in heavy


@pytest.mark.slow
def test_vlp_rooms_list_against_a_live_server_loads_no_numerics(tmp_path: Path) -> None:
    with process_fleet(tmp_path / "data") as fleet:
        server = fleet.serve()
        env = {
            **os.environ,
            "VLP_URL": server.url,
            "VLP_API_KEY": ADMIN["X-API-Key"],
            "COLUMNS": "200",
        }
        heavy, output = _heavy_modules_after(
            "from app.cli import main\ncode = main(['rooms', 'list'])\nassert code == 0, code",
            env,
        )
    assert "Paper room" in output  # the demo room, listed by the real server
    assert heavy == []
