"""Every row of the kernel table: the compiled kernel gives its NumPy reference's numbers.

The table (``app/vlp/solvers/_kernel_table.py``) pairs each kernel with its reference and
example arguments; ``warm_up`` runs the same examples. Tolerance: the row's, relative to the
reference's largest magnitude (0: bit for bit).
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.vlp._kernels import kernel_mode, use_kernels
from app.vlp.solvers import _warm_up
from app.vlp.solvers._kernel_table import KERNEL_TABLE, KernelRow

SCIENCE = Path(__file__).resolve().parents[3] / "app" / "vlp"


def _parts(value: Any) -> list[Any]:
    """The arrays and numbers of a kernel's answer, in order."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return [getattr(value, field.name) for field in dataclasses.fields(value)]
    if isinstance(value, tuple | list):
        return list(value)
    return [value]


def _assert_same(got: Any, want: Any, rtol: float) -> None:
    got_parts, want_parts = _parts(got), _parts(want)
    assert len(got_parts) == len(want_parts)
    for got_part, want_part in zip(got_parts, want_parts, strict=True):
        if isinstance(want_part, list):
            _assert_same(got_part, want_part, rtol)
            continue
        got_array = np.asarray(got_part, dtype=np.float64)
        want_array = np.asarray(want_part, dtype=np.float64)
        assert got_array.shape == want_array.shape
        if rtol == 0.0:
            np.testing.assert_array_equal(got_array, want_array)
            continue
        scale = max(float(np.max(np.abs(want_array))), 1e-300) if want_array.size else 1.0
        np.testing.assert_allclose(got_array, want_array, rtol=0.0, atol=rtol * scale)


def test_the_table_names_each_kernel_once() -> None:
    names = [row.name for row in KERNEL_TABLE]
    assert len(set(names)) == len(names)
    assert len({row.kernel for row in KERNEL_TABLE}) == len(KERNEL_TABLE)
    assert all(row.kernel is not row.reference for row in KERNEL_TABLE)


def _calls(path: Path, function: str) -> list[ast.Call]:
    """The calls of ``function`` (by its bare name) in the module at ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    return [
        node
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == function
    ]


def test_every_dispatch_is_a_row_of_the_table() -> None:
    """Each (kernel, reference) pair that a module of the science package dispatches
    between, read from its source, is a row: compared by the parity test, warmed by
    warm_up."""
    dispatched = set()
    for path in SCIENCE.rglob("*.py"):
        for call in _calls(path, "dispatch"):
            assert all(isinstance(arg, ast.Name) for arg in call.args), path
            dispatched.add(tuple(arg.id for arg in call.args if isinstance(arg, ast.Name)))
    rows = {(row.kernel.__name__, row.reference.__name__) for row in KERNEL_TABLE}
    assert dispatched == rows


def test_a_kernel_and_its_reference_share_their_row_name() -> None:
    """``foo_kernel`` and ``foo_reference`` for the row ``foo``, module-level functions of
    one name each, and a compiled function ``foo_kernel`` in a compiled module."""
    compiled_modules = [*(SCIENCE / "solvers" / "gridless" / "_compiled").glob("*.py")]
    compiled_modules += [
        SCIENCE / "_radii_compiled.py",
        SCIENCE / "tracking" / "_filter_compiled.py",
    ]
    compiled = {
        node.name
        for path in compiled_modules
        for node in ast.parse(path.read_text(encoding="utf-8")).body
        if isinstance(node, ast.FunctionDef)
        and any(isinstance(d, ast.Name) and d.id == "compiled" for d in node.decorator_list)
    }
    for row in KERNEL_TABLE:
        assert row.kernel.__name__ == f"{row.name}_kernel"
        assert row.reference.__name__ == f"{row.name}_reference"
        assert row.kernel.__qualname__ == row.kernel.__name__  # module-level, not a method
        assert row.reference.__qualname__ == row.reference.__name__
        assert row.kernel.__name__ in compiled


@pytest.mark.parametrize("row", KERNEL_TABLE, ids=[row.name for row in KERNEL_TABLE])
def test_kernel_matches_its_reference(row: KernelRow) -> None:
    assert kernel_mode() == "compiled"
    examples = row.examples()
    assert examples
    compared = row.compared or (lambda answer: answer)
    # Fresh arguments for each side (the same seeds): neither sees what the other wrote.
    for reference_args, args in zip(examples, row.examples(), strict=True):
        with use_kernels("reference"):
            want = compared(row.reference(*reference_args))
        _assert_same(compared(row.kernel(*args)), want, row.rtol)


def test_warm_up_runs_every_row(monkeypatch: pytest.MonkeyPatch) -> None:
    """warm_up calls each row's kernel on each of its examples (and nothing else decides
    which kernels are warmed: a new row is warmed by being in the table)."""
    calls: list[str] = []
    rows = tuple(
        row._replace(kernel=lambda *_, name=row.name: calls.append(name)) for row in KERNEL_TABLE
    )
    monkeypatch.setattr(_warm_up, "KERNEL_TABLE", rows)
    _warm_up.warm_table()
    assert calls == [row.name for row in KERNEL_TABLE for _ in row.examples()]
