"""Imports go one way (docs/explanation/architecture.md): each part of ``app`` imports only
parts below it.

Lazy imports inside functions count too. The science core's own rule (stdlib, numpy, scipy,
cvxpy, numba only) is tests/vlp/test_imports.py.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

APP = Path(__file__).resolve().parents[1] / "app"

# Each top-level part of `app` and its level: a part imports only parts of a lower level.
LEVELS = {
    "vlp": 0,
    "clock": 0,
    "settings": 0,
    "view": 0,  # static files of the live view, read by app.api.view
    "schemas": 1,
    "pictures": 1,
    "collectors": 2,
    "registry": 2,
    "client": 2,
    "errors": 3,
    "jobs": 3,
    "telemetry": 3,
    "services": 4,
    "api": 5,
    "main": 6,
    "cli": 7,
}
FILES = sorted(APP.rglob("*.py"))


def _part(path: Path) -> str:
    """The top-level part of ``app`` a file belongs to (``app/api/x.py`` -> ``api``)."""
    return path.relative_to(APP).with_suffix("").parts[0]


def _imported_modules(path: Path) -> list[str]:
    """Absolute names of every module a file imports, at any depth of its code."""
    package = list(path.relative_to(APP.parent).with_suffix("").parts[:-1])
    found: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            found.append(".".join([*base, *([node.module] if node.module else [])]))
    return found


def test_every_part_has_a_level() -> None:
    assert {_part(path) for path in FILES if path != APP / "__init__.py"} <= set(LEVELS)


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(APP)))
def test_imports_go_down(path: Path) -> None:
    if path == APP / "__init__.py":
        return
    part = _part(path)
    upward = [
        module
        for module in _imported_modules(path)
        if module.startswith("app.")
        and module.split(".")[1] != part
        and LEVELS[module.split(".")[1]] >= LEVELS[part]
    ]
    assert not upward, f"{path.relative_to(APP)} ({part}) imports from its level or above: {upward}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(APP)))
def test_the_package_never_imports_the_benchmarks(path: Path) -> None:
    # bench/ is the repository's, not the installed package's: `python -m bench.NAME`.
    assert not [m for m in _imported_modules(path) if m == "bench" or m.startswith("bench.")]


ROUTERS = sorted((APP / "api").glob("*.py"))


@pytest.mark.parametrize("path", ROUTERS, ids=lambda p: p.name)
def test_routers_take_errors_from_app_errors_and_leave_science_to_services(path: Path) -> None:
    """Errors come from ``app.errors`` (one tree); the science core is reached through a
    service, so no module of ``app.api`` imports ``app.vlp`` or numpy."""
    modules = _imported_modules(path)
    foreign_errors = {"app.registry.errors", "app.vlp.errors"}
    assert not [m for m in modules if m in foreign_errors]
    assert not [m for m in modules if m.startswith(("app.vlp", "numpy"))]


def test_the_checks_see_relative_and_lazy_imports() -> None:
    modules = _imported_modules(APP / "api" / "errors.py")
    assert "app.errors" in modules and "app.schemas" in modules
    assert "app.api.deps" in _imported_modules(APP / "api" / "rooms.py")
    assert "app.registry" in _imported_modules(APP / "cli" / "__init__.py")  # a lazy import
