"""The fast lane (``./test --fast``, every test not marked ``slow``) holds unit tests only:
each module of the folders that start servers, browsers, process faults or benchmark runs
marks all its tests ``slow`` (docs/explanation/architecture.md, "Tests and their lanes")."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
SLOW_FOLDERS = ("e2e", "faults", "bench")
# Pure functions of the benchmarks' own code (no process, no run), or such unit tests beside
# a run that is marked slow on its own.
UNIT_MODULES = {
    "bench/test_ablation_options.py",
    "bench/test_tracking_switches.py",
    "bench/test_measured_smoke.py",
    "bench/test_measured_floor.py",
    "bench/test_solver_ab_forms.py",
}


def _marks_module(path: Path, mark: str) -> bool:
    """Whether the module assigns ``pytestmark`` to ``pytest.mark.<mark>`` (or a list holding
    it)."""
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(target, ast.Name) and target.id == "pytestmark" for target in node.targets
        ):
            return f"pytest.mark.{mark}" in ast.unparse(node.value).replace(" ", "")
    return False


@pytest.mark.parametrize(
    "module",
    sorted(
        str(path.relative_to(TESTS))
        for folder in SLOW_FOLDERS
        for path in (TESTS / folder).glob("test_*.py")
    ),
)
def test_modules_that_start_processes_or_run_benchmarks_are_slow(module: str) -> None:
    if module in UNIT_MODULES:
        return
    assert _marks_module(TESTS / module, "slow"), f"{module} lacks pytestmark = pytest.mark.slow"


def test_the_modules_the_workers_do_not_collect_are_serial() -> None:
    """``./test`` keeps modules from its xdist workers' collection (``--ignore``) only when the
    serial pass runs them: marked ``serial`` whole, else no pass would run their tests."""
    script = (TESTS.parent / "test").read_text(encoding="utf-8")
    ignored = re.findall(r"--ignore=(\S+)", script)
    assert ignored, "the check below would check nothing"
    for module in ignored:
        assert _marks_module(TESTS.parent / module, "serial"), f"{module} is not marked serial"


def _uses_mark(path: Path, mark: str) -> bool:
    """Whether the module uses ``<something>.mark.<mark>`` in any spelling (an alias of
    ``pytest``, ``from pytest import mark``)."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Attribute) and node.attr == mark:
            owner = node.value
            if (isinstance(owner, ast.Attribute) and owner.attr == "mark") or (
                isinstance(owner, ast.Name) and owner.id == "mark"
            ):
                return True
    return False


def test_serial_marks_are_spelt_as_the_serial_pass_finds_them() -> None:
    """``./test`` (without arguments) hands its serial pass only the modules whose text holds
    ``pytest.mark.serial``: a module marking tests serial any other way would run in no
    pass."""
    modules = sorted(TESTS.rglob("test_*.py"))
    serial = [path for path in modules if _uses_mark(path, "serial")]
    assert serial, "the check below would check nothing"
    for path in serial:
        assert "pytest.mark.serial" in path.read_text(encoding="utf-8"), path


def test_the_serial_spelling_check_sees_other_spellings(tmp_path: Path) -> None:
    module = tmp_path / "test_x.py"
    module.write_text("from pytest import mark\n\n\n@mark.serial\ndef test_x() -> None: ...\n")
    assert _uses_mark(module, "serial")
    assert "pytest.mark.serial" not in module.read_text(encoding="utf-8")
