"""Rows of the accuracy benchmark and their summary over trials (CSV layout included)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.vlp.measurements import MODELS

__all__ = [
    "CRLB",
    "CRLB_SINGLE",
    "GRID_FLOOR",
    "NO_MODEL",
    "RSS",
    "SUMMARY_HEADER",
    "TRIAL_HEADER",
    "Row",
    "Summary",
    "summarise",
    "summary_tuple",
]

TRIAL_HEADER = (
    "room",
    "snr_db",
    "n_targets",
    "trial",
    "method",
    "model",
    "error_m",
    "time_ms",
    "status",
)
# Methods that are not solvers: the RSS baseline, the grid floor and the two bounds.
RSS, GRID_FLOOR, CRLB, CRLB_SINGLE = "rss", "grid_floor", "crlb", "crlb_single"
NO_MODEL = "-"


@dataclass(frozen=True)
class Row:
    """One method's result in one trial (``error_m`` is NaN when ``status`` is not "ok")."""

    room: str
    snr_db: float
    n_targets: int
    trial: int
    method: str
    model: str
    error_m: float
    time_ms: float
    status: str = "ok"

    def as_tuple(self) -> tuple[object, ...]:
        """The CSV row, in :data:`TRIAL_HEADER` order."""
        return (
            self.room,
            self.snr_db,
            self.n_targets,
            self.trial,
            self.method,
            self.model,
            f"{self.error_m:.6g}",
            f"{self.time_ms:.4g}",
            self.status,
        )


@dataclass(frozen=True)
class Summary:
    """One method x model in one (room, SNR, K) cell, with the bounds beside it (metres)."""

    room: str
    snr_db: float
    n_targets: int
    method: str
    model: str
    trials: int
    failures: int
    median_error_m: float
    mean_error_m: float
    p90_error_m: float
    median_time_ms: float
    grid_floor_m: float
    crlb_m: float
    crlb_single_m: float


SUMMARY_HEADER = tuple(Summary.__dataclass_fields__)


def _stat(values: list[float], how: str) -> float:
    if not values:
        return float("nan")
    array = np.asarray(values)
    if how == "mean":
        return float(np.mean(array))
    if how == "p90":
        return float(np.percentile(array, 90))
    return float(np.median(array))


def summarise(rows: Sequence[Row]) -> list[Summary]:
    """Median, mean and p90 over trials of each method's per-trial mean error."""
    groups: dict[tuple[str, float, int, str, str], list[Row]] = {}
    for row in rows:
        groups.setdefault((row.room, row.snr_db, row.n_targets, row.method, row.model), []).append(
            row
        )

    def errors(key: tuple[str, float, int, str, str]) -> list[float]:
        return [r.error_m for r in groups.get(key, []) if r.status == "ok"]

    out = []
    for key, members in sorted(groups.items()):
        room, snr, k, method, model = key
        if method in (GRID_FLOOR, CRLB, CRLB_SINGLE):
            continue
        ok = [r for r in members if r.status == "ok"]
        crlb = (
            _stat(errors((room, snr, k, CRLB, model)), "median")
            if model in MODELS
            else float("nan")
        )
        out.append(
            Summary(
                room,
                snr,
                k,
                method,
                model,
                len(members),
                len(members) - len(ok),
                _stat([r.error_m for r in ok], "median"),
                _stat([r.error_m for r in ok], "mean"),
                _stat([r.error_m for r in ok], "p90"),
                _stat([r.time_ms for r in ok], "median"),
                _stat(errors((room, snr, k, GRID_FLOOR, NO_MODEL)), "mean"),
                crlb,
                _stat(errors((room, snr, k, CRLB_SINGLE, NO_MODEL)), "median"),
            )
        )
    return out


def summary_tuple(item: Summary) -> tuple[object, ...]:
    """The CSV row of a summary, in :data:`SUMMARY_HEADER` order."""
    return tuple(
        f"{v:.6g}" if isinstance(v, float) else v
        for v in (getattr(item, name) for name in SUMMARY_HEADER)
    )
