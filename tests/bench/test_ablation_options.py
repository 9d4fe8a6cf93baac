"""The ablation benchmark's switch: the service's solver built with a variant's options."""

from __future__ import annotations

from dataclasses import fields

import pytest

from app.vlp.fingerprints import build_fingerprint
from app.vlp.solvers import make_solver
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver
from bench.ablation import VARIANTS, Variant, default_options
from bench.rooms import make_room


def test_default_options_reach_the_service_factory_and_are_undone() -> None:
    fingerprint = build_fingerprint(make_room("paper"))
    with default_options({"relocate_passes": 0, "tilt_sd": None}):
        inside = make_solver("gridless", fingerprint, "correlation")
    after = make_solver("gridless", fingerprint, "correlation")
    assert isinstance(inside, GridlessSolver) and isinstance(after, GridlessSolver)
    assert (inside.options.relocate_passes, inside.options.tilt_sd) == (0, None)
    assert after.options == GridlessOptions()


def test_default_options_are_undone_when_the_run_fails() -> None:
    fingerprint = build_fingerprint(make_room("paper"))
    with pytest.raises(RuntimeError), default_options({"restarts": 0}):
        raise RuntimeError("a variant's run failed")
    solver = make_solver("gridless", fingerprint, "power")
    assert isinstance(solver, GridlessSolver) and solver.options.restarts is None


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: v.name)
def test_every_variant_switches_a_stage_off(variant: Variant) -> None:
    names = {f.name for f in fields(GridlessOptions)}
    assert set(variant.options) <= names
    built = GridlessOptions(**variant.options)  # type: ignore[arg-type]
    # Only the default row leaves every option as it is.
    assert (built == GridlessOptions()) == (variant.name == "default")
