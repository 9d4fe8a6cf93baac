"""Every row of the kernel table: the compiled kernel gives its NumPy reference's numbers.

The table (``app/vlp/solvers/_kernel_table.py``) pairs each kernel with its reference and
example arguments; ``warm_up`` runs the same examples. Tolerance: the row's, relative to the
reference's largest magnitude (0: bit for bit).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from app.vlp._kernels import kernel_mode, use_kernels
from app.vlp.solvers import _warm_up
from app.vlp.solvers._kernel_table import KERNEL_TABLE, KernelRow


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
