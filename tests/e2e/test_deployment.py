"""The deployment files: ``deploy/compose.yaml`` and the ``Dockerfile``.

There is no Docker engine on the test machines; ``docker compose config`` parses and
validates the compose file without one (run when the compose plugin is installed). The
structure is checked with a YAML parser in any case: PostgreSQL, a one-shot migration, two
APIs and two workers, each on its own data volume, none seeding the demo room.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from app.cli import _parser
from app.registry import Registry

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
COMPOSE = REPO / "deploy" / "compose.yaml"
# Values the compose file requires from the operator's environment.
OPERATOR_ENV = {
    "VLP_POSTGRES_PASSWORD": "compose-test-password",
    "VLP_ADMIN_KEYS": "compose-test-admin-key-0123456789",
    "VLP_TERMINAL_KEYS": "compose-test-terminal-key-0123456789",
}


def vlp_services(services: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The services that run the ``vlp`` command."""
    return {
        name: service
        for name, service in services.items()
        if list(service.get("command", []))[:1] == ["vlp"]
    }


def check_topology(services: dict[str, Any]) -> None:
    """What a compose document (raw or as ``docker compose config`` prints it) must hold."""
    vlp = vlp_services(services)
    commands = sorted(tuple(service["command"][:2]) for service in vlp.values())
    assert commands == [
        ("vlp", "migrate"),
        ("vlp", "serve"),
        ("vlp", "serve"),
        ("vlp", "worker"),
        ("vlp", "worker"),
    ]
    assert "postgres" in services
    volumes = [tuple(str(v) for v in service["volumes"]) for service in vlp.values()]
    assert len(set(volumes)) == len(volumes), "two vlp services share a data volume"
    for name, service in vlp.items():
        env = service["environment"]
        assert str(env["VLP_DEMO"]) == "0", name
        assert str(env["VLP_DATABASE_URL"]).startswith("postgresql+psycopg://"), name
        assert env["VLP_MATRIX_STORE"] == "database", name
        _parser().parse_args(service["command"][1:])  # a real vlp command line
        if service["command"][1] != "migrate":
            assert "migrate" in service["depends_on"], name


def test_the_compose_file_runs_postgres_a_migration_two_apis_and_two_workers() -> None:
    document = yaml.safe_load(COMPOSE.read_text(encoding="utf-8"))
    check_topology(document["services"])
    workers = [s for s in vlp_services(document["services"]).values() if "worker" in s["command"]]
    assert all(str(w["environment"]["VLP_EMBEDDED_WORKERS"]) == "1" for w in workers)


def _compose_plugin() -> str | None:
    docker = shutil.which("docker")
    if docker is None:
        return None
    probe = subprocess.run(
        [docker, "compose", "version"], capture_output=True, text=True, timeout=60, check=False
    )
    return docker if probe.returncode == 0 else None


def test_docker_compose_config_accepts_the_file() -> None:
    docker = _compose_plugin()
    if docker is None:
        pytest.skip("the docker compose plugin is not installed (docker compose version fails)")
    completed = subprocess.run(
        [docker, "compose", "-f", str(COMPOSE), "config", "--format", "json"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={"PATH": "/usr/bin:/bin:/usr/local/bin", **OPERATOR_ENV},
    )
    assert completed.returncode == 0, completed.stderr
    check_topology(yaml.safe_load(completed.stdout)["services"])


def test_the_container_image_does_not_seed_the_demo_room() -> None:
    dockerfile = (REPO / "Dockerfile").read_text(encoding="utf-8")
    runtime = dockerfile[dockerfile.index("AS runtime") :]
    env_block = re.search(r"^ENV (.*?)(?=^\S)", runtime, flags=re.MULTILINE | re.DOTALL)
    assert env_block is not None
    assert re.search(r"\bVLP_DEMO=0\b", env_block.group(1))


def test_vlp_migrate_brings_a_fresh_registry_to_the_newest_schema(tmp_path: Path) -> None:
    # The compose file's one-shot step: it must leave a database the services accept.
    vlp = Path(sys.executable).with_name("vlp")
    env = {"PATH": "/usr/bin:/bin", "VLP_DATA_DIR": str(tmp_path)}
    completed = subprocess.run(
        [str(vlp), "migrate"], env=env, capture_output=True, text=True, timeout=300, check=False
    )
    assert completed.returncode == 0, completed.stderr
    registry = Registry(
        database_url=f"sqlite:///{tmp_path / 'registry.sqlite3'}", data_dir=tmp_path
    )
    try:
        assert registry.migrations_current()
    finally:
        registry.dispose()
