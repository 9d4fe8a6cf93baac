"""The science core imports only the standard library, numpy, scipy, cvxpy and numba."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "app" / "vlp"
ALLOWED = {"numpy", "scipy", "cvxpy", "numba"}
FILES = sorted(PACKAGE.rglob("*.py"))


def _imports(path: Path) -> list[tuple[str, int]]:
    """Top-level module names imported by a file (level > 0 means relative)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((alias.name, 0) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            found.append((node.module or "", node.level))
    return found


def _allowed(module: str, level: int) -> bool:
    root = module.split(".")[0]
    if level > 0:
        return True  # relative, inside app.vlp (deeper levels are checked below)
    return root in ALLOWED or root in sys.stdlib_module_names or module.startswith("app.vlp")


def test_files_found() -> None:
    assert len(FILES) >= 10


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_only_allowed_imports(path: Path) -> None:
    depth = len(path.relative_to(PACKAGE).parts) - 1  # 0 for app/vlp/x.py
    bad = [
        (module, level)
        for module, level in _imports(path)
        if not _allowed(module, level) or level > depth + 1
    ]
    assert not bad, f"{path}: imports outside stdlib/numpy/scipy/cvxpy/numba/app.vlp: {bad}"


def test_checker_rejects_web_imports() -> None:
    for module in ("fastapi", "sqlalchemy.orm", "pydantic", "app.api.deps", "app.settings"):
        assert not _allowed(module, 0)
    assert _allowed("numpy.linalg", 0) and _allowed("dataclasses", 0)
