"""Tests of app/pictures/localization.py: Hungarian matching and the estimates picture."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from app.pictures import localization_png
from app.pictures.localization import match_estimates
from app.vlp.errors import MeasurementError
from app.vlp.layout import Layout
from app.vlp.typing import FloatArray

from .conftest import decode, png_size


def _brute_force_cost(estimates: FloatArray, truth: FloatArray) -> float:
    k = min(len(estimates), len(truth))
    best = np.inf
    for est_rows in itertools.permutations(range(len(estimates)), k):
        for true_rows in itertools.combinations(range(len(truth)), k):
            cost = np.linalg.norm(estimates[list(est_rows)] - truth[list(true_rows)], axis=1)
            best = min(best, float(cost.sum()))
    return best


@pytest.mark.parametrize(
    ("n_est", "n_true"),
    [(5, 5), (3, 5), (5, 3)],
    ids=["square", "fewer-estimates", "more-estimates"],
)
def test_matching_is_the_minimum_total_distance(n_est: int, n_true: int) -> None:
    rng = np.random.default_rng(n_est * 10 + n_true)
    estimates, truth = rng.uniform(0, 4, (n_est, 2)), rng.uniform(0, 4, (n_true, 2))
    rows, cols = match_estimates(estimates, truth)
    assert len(rows) == len(set(rows.tolist())) == min(n_est, n_true)
    assert len(set(cols.tolist())) == len(cols)
    total = float(np.linalg.norm(estimates[rows] - truth[cols], axis=1).sum())
    assert total == pytest.approx(_brute_force_cost(estimates, truth))


def _red_fraction(pixels: FloatArray) -> float:
    red = (pixels[:, :, 0] > 0.95) & (pixels[:, :, 1] < 0.05) & (pixels[:, :, 2] < 0.05)
    return float(red.mean())


def test_picture_is_valid_deterministic_and_shows_truth(paper_room: Layout) -> None:
    rng = np.random.default_rng(4)
    truth = rng.uniform(0.2, 3.8, (6, 2))
    estimates = truth[::-1] + rng.normal(0.0, 0.05, (6, 2))
    labels = [f"t{k}" for k in range(6)]
    png = localization_png(paper_room, estimates, truth, labels=labels, width_px=640)
    assert png_size(png)[0] == 640
    assert png == localization_png(paper_room, estimates, truth, labels=labels, width_px=640)
    without_truth = localization_png(paper_room, estimates, width_px=640)
    assert _red_fraction(decode(png)) > 1e-4
    assert _red_fraction(decode(without_truth)) == 0.0


def test_empty_estimates_render(paper_room: Layout) -> None:
    png = localization_png(paper_room, np.empty((0, 2)), np.array([[1.0, 1.0]]))
    assert png_size(png)[0] == 800


@pytest.mark.parametrize(
    ("estimates", "truth", "labels", "field"),
    [
        (np.zeros((3, 3)), None, None, "estimates"),
        (np.array([[1.0, np.nan]]), None, None, "estimates"),
        (np.zeros((2, 2)), np.zeros(2), None, "truth"),
        (np.zeros((2, 2)), None, ["a"], "labels"),
    ],
    ids=["est-shape", "est-nan", "truth-shape", "labels-length"],
)
def test_bad_input_raises_with_field(
    paper_room: Layout,
    estimates: FloatArray,
    truth: FloatArray | None,
    labels: list[str] | None,
    field: str,
) -> None:
    with pytest.raises(MeasurementError) as info:
        localization_png(paper_room, estimates, truth, labels=labels)
    assert info.value.field == field
