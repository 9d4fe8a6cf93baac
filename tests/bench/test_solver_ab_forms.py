"""``bench.solver_ab --forms``: which forms and K an A/B timing run takes."""

from __future__ import annotations

import argparse

import pytest

from bench.solver_ab import _forms


def test_forms_are_read_as_form_and_k_pairs_in_order() -> None:
    assert _forms("power:8, power:1,terminals:4") == (("power", 8), ("power", 1), ("terminals", 4))


@pytest.mark.parametrize("text", ["power", "power:", "power:0", "power:x", "omp:8"])
def test_forms_refuse_what_is_not_a_form_and_k(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        _forms(text)
