"""Measurements (body of localize) and localizations (its answer)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import AwareDatetime, ConfigDict, Field

from app.vlp.constants import MAX_TARGETS

from .common import (
    MAX_VERSION,
    FiniteFloat,
    RequestInt,
    RequestModel,
    ResponseModel,
    lazy_examples,
)
from .tracking import TrackedState

if TYPE_CHECKING:
    from app.vlp.typing import FloatArray

__all__ = [
    "EXAMPLE_POSITIONS_M",
    "TERMINAL_ID_PATTERN",
    "DetectedAmplitudes",
    "DetectionFloor",
    "Estimate",
    "Fit",
    "Localization",
    "Measurement",
    "ModelName",
    "SolverName",
    "TerminalAmplitudes",
    "localize_example",
    "terminals_example",
]

ModelName = Literal["power", "correlation"]
# The solvers the HTTP contract offers: the science core registers exactly these
# (app.vlp.solvers.solver_names; tests/api/test_localize.py pins the two equal).
SolverName = Literal["gridless", "nnls", "omp", "l1"]
TERMINAL_ID_PATTERN = r"^[A-Za-z0-9._:-]{1,64}$"


# Where the example terminals stand in the paper (demo) room, metres.
EXAMPLE_POSITIONS_M = ((1.0, 1.2), (2.9, 3.1), (2.1, 0.7))


def _significant(value: float) -> float:
    """``value`` to 4 significant digits (short examples; far below the noise of real data)."""
    return float(f"{value:.4g}")


def _example_amplitudes() -> FloatArray:
    """Noiseless amplitudes ``a_ik = h_ik x_i`` (K x M) at :data:`EXAMPLE_POSITIONS_M`.

    The science core is imported here, not at module level, so that importing the schemas
    (every client does) does not load numpy.
    """
    import numpy as np

    from app.vlp.presets import paper_layout
    from app.vlp.simulation import true_amplitudes

    return true_amplitudes(paper_layout(), np.array(EXAMPLE_POSITIONS_M))


def localize_example() -> dict[str, Any]:
    """Three terminals in the paper room as a 16 x 16 correlation matrix (CoCSM-VLP).

    ``R = A^T A`` of the noiseless amplitudes ``a_ik = h_ik x_i`` at
    :data:`EXAMPLE_POSITIONS_M`; it localizes to those points on the demo room.
    """
    amplitudes = _example_amplitudes()
    correlation = amplitudes.T @ amplitudes
    return {
        "model": "correlation",
        "correlation": [[_significant(value) for value in row] for row in correlation],
        "targets": len(EXAMPLE_POSITIONS_M),
        "solver": "gridless",
    }


def terminals_example() -> dict[str, Any]:
    """The same three terminals, each sending its own amplitudes (the service aggregates)."""
    amplitudes = _example_amplitudes()
    return {
        "model": "correlation",
        "terminals": [
            {"id": f"t{k + 1}", "amplitudes": [_significant(a) for a in row]}
            for k, row in enumerate(amplitudes)
        ],
        "targets": len(EXAMPLE_POSITIONS_M),
        "solver": "gridless",
    }


# One terminal's per-LED amplitudes and its floor: a localize terminal and an epoch post
# take them alike (one definition, so the two validate and document them the same way).
DetectedAmplitudes = Annotated[
    list[FiniteFloat | None],
    Field(
        min_length=1,
        description="a_ik for each LED i, in the layout's LED order; null where the LED was "
        "not detected (below this terminal's detection floor, never taken as zero)",
    ),
]
DetectionFloor = Annotated[
    FiniteFloat | None,
    Field(
        gt=0.0,
        description="the amplitude below which this terminal does not detect an LED (same "
        "units as its amplitudes); default: the weakest amplitude it detected",
    ),
]


class TerminalAmplitudes(RequestModel):
    """One terminal's pilot amplitude estimates, one per LED (in the layout's LED order)."""

    id: str = Field(
        pattern=TERMINAL_ID_PATTERN, description="the terminal's own id", examples=["t1"]
    )
    amplitudes: DetectedAmplitudes
    detection_floor: DetectionFloor = None
    height: FiniteFloat | None = Field(
        default=None,
        ge=0.0,
        le=1000.0,
        description="the photodiode's height above the floor, metres, when the terminal knows it",
    )
    normal: list[FiniteFloat] | None = Field(
        default=None,
        min_length=3,
        max_length=3,
        description="the photodiode's normal [nx, ny, nz] in room coordinates (nz > 0; "
        "normalised by the service), e.g. from the phone's IMU; default straight up",
    )


class Measurement(RequestModel):
    """An aggregated measurement: exactly one of `power`, `correlation`, `terminals`.

    - `power` (model `power`, CSM-VLP): `p_i = sum_k a_ik^2`, M numbers.
    - `correlation` (model `correlation`, CoCSM-VLP): `R_il = sum_k a_ik a_lk` as the full
      M x M matrix or its M(M+1)/2 entries with `i <= l` in `numpy.triu_indices(M)` order.
    - `terminals`: each terminal's own amplitudes (and, when known, its `height` and
      photodiode `normal`). The default `gridless` solver fits every terminal from its own
      amplitudes (strictly more information than their sums), so every estimate carries its
      terminal's id; the grid solvers (`nnls`, `omp`, `l1`) aggregate them under `model`.
      Left out, `targets` is the number of terminals.

    `model` defaults to `correlation`, or to `power` when `power` is sent.
    """

    model_config = ConfigDict(json_schema_extra=lazy_examples(localize_example, terminals_example))

    model: ModelName = Field(default="correlation", description="measurement model")
    power: list[FiniteFloat] | None = Field(
        default=None, min_length=1, description="M received powers"
    )
    correlation: list[list[FiniteFloat]] | list[FiniteFloat] | None = Field(
        default=None, min_length=1, description="M x M matrix or its M(M+1)/2 upper triangle"
    )
    terminals: list[TerminalAmplitudes] | None = Field(default=None, min_length=1, max_length=4096)
    targets: RequestInt | None = Field(
        default=None,
        ge=1,
        le=MAX_TARGETS,
        description="K; estimated by the service when left out (the number of `terminals`; "
        "for a `correlation` summed from the terminals' amplitudes, also read off its rank)",
    )
    solver: SolverName = Field(
        default="gridless",
        description="`gridless` (default: best accuracy, off-grid positions), `nnls`, "
        "`omp`, `l1` (the seed paper's algorithms)",
    )
    fingerprint_version: RequestInt | None = Field(
        default=None, ge=1, le=MAX_VERSION, description="default: the current version"
    )
    track: bool = Field(
        default=False,
        strict=True,
        description="update the room's tracks with the estimates (each estimate then carries "
        "`track_id` and `tracked`); false: the answer is as without tracking and no state "
        "changes",
    )
    time: AwareDatetime | None = Field(
        default=None,
        description="when the terminals measured (RFC 3339 with an offset); default: when "
        "the service received it. Used with `track`",
    )


def _unset(value: object) -> bool:
    """Fields added by tracking are left out of answers without it (as before tracking)."""
    return value is None


class Estimate(ResponseModel):
    """One located target."""

    x: float = Field(description="m")
    y: float = Field(description="m")
    grid_index: int = Field(description="the nearest grid point j = ix * ny + iy")
    weight: float = Field(description="fitted occupancy (about 1 per terminal)")
    terminal_id: str | None = Field(description="whose estimate it is, when terminals were sent")
    accuracy_m: float | None = Field(
        default=None,
        description="radius of the 95 % confidence circle around (x, y), metres (solver "
        "`gridless`; from the fit's noise and the model errors its residuals show: per-LED "
        "gain errors, tilts, heights not sent; docs/results/coverage.md measures how often it "
        "holds). "
        "The floor's diagonal where the data leave the position open (a receiver that sees "
        "one LED or none); wide enough to hold the mirror image where the LEDs a receiver "
        "sees lie on one line, and any other place where the target would fit the "
        "measurement about as well, the others held (`fit.detail` says so)",
    )
    covariance: list[list[float]] | None = Field(
        default=None, description="[[sxx, sxy], [sxy, syy]] of (x, y), m^2 (solver `gridless`)"
    )
    gain: float | None = Field(
        default=None,
        description="fitted amplitude gain of this target relative to the fingerprint "
        "(1 = exactly as modelled; solver `gridless`)",
    )
    z: float | None = Field(
        default=None, description="the target's height, metres, when heights are free or sent"
    )
    track_id: str | None = Field(
        default=None,
        exclude_if=_unset,
        description="the track this estimate updated (with `track: true`; stable for a "
        "terminal_id, never reused)",
    )
    tracked: TrackedState | None = Field(
        default=None,
        exclude_if=_unset,
        description="the track's state after this estimate (with `track: true`)",
    )


class Fit(ResponseModel):
    """How well the model explains the measurement (solver `gridless`)."""

    quality: Literal["ok", "poor", "scale_mismatch"] = Field(
        description="`ok`; `poor`: the room differs from its layout (calibrate it), or a "
        "`power` vector has fewer values than the targets need (2K + 1 unknowns); "
        "`scale_mismatch`: the measurement is not in the fingerprint's scale (units, pilots)"
    )
    chi2_per_dof: float = Field(
        description="whitened residual sum of squares per degree of freedom (about 1: the "
        "model explains the measurement down to its noise; no test for the `power` model, "
        "whose noise level cannot be told from its signal: see `detail`)"
    )
    scale: float = Field(
        description="fitted common amplitude scale of the measurement relative to the "
        "fingerprint (1 = as modelled; a correlation 4x too large has scale 2)"
    )
    detail: str


class Localization(ResponseModel):
    """Where the targets are."""

    room_id: str
    fingerprint_version: int
    model: ModelName
    solver: str
    targets: int = Field(description="K, the number of estimates")
    estimates: list[Estimate]
    residual_norm: float = Field(description="norm of measurement minus model prediction")
    noise_power: float = Field(description="fitted noise power sigma^2 (squared amplitudes)")
    elapsed_ms: float = Field(description="solver time, milliseconds")
    converged: bool = Field(
        default=True,
        description="false when the solver stopped at its iteration limit: the estimates are "
        "its last iterate, usable but less certain than the fit's figures suggest",
    )
    fit: Fit | None = Field(default=None, description="goodness of fit (solver `gridless`)")
