"""``bench/measured.py`` on a small synthetic survey in the Massey dataset's file format."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from bench import _massey, measured

LEDS = np.array([[0.6, 0.6, 2.35], [0.6, 2.4, 2.35], [2.4, 0.6, 2.35], [2.4, 2.4, 2.35]])
RECEIVER_Z = 0.9
ORDER = 1.0
GAIN = 4.0e4


def _readings(points: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
    """Lambertian readings (order 1, level receiver), 5 % multiplicative noise, floored."""
    dz = LEDS[0, 2] - RECEIVER_Z
    r2 = ((points[:, None, :] - LEDS[None, :, :2]) ** 2).sum(axis=-1)
    clean = GAIN * dz ** (ORDER + 1) / (dz * dz + r2) ** ((ORDER + 3) / 2)
    noisy = clean if rng is None else clean * np.exp(0.05 * rng.standard_normal(clean.shape))
    return np.where(noisy < _massey.NOT_DETECTED, _massey.NOT_DETECTED, noisy)


def _write_dataset(directory: Path, points: np.ndarray, readings: np.ndarray) -> None:
    names = [f"L{i + 1}" for i in range(len(LEDS))]
    with (directory / _massey.LUMINAIRE_FILE).open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["Luminaire", "x", "y", "z"])
        writer.writerows([name, *led] for name, led in zip(names, LEDS, strict=True))
    with (directory / _massey.DATA_FILE).open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["index", *names, "x", "y"])
        writer.writerows(
            [i, *row, *point] for i, (row, point) in enumerate(zip(readings, points, strict=True))
        )


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    rng = np.random.default_rng(7)
    points = rng.uniform(0.25, 2.75, size=(300, 2))
    _write_dataset(tmp_path, points, _readings(points, rng))
    return tmp_path


def test_the_loader_reads_the_floor_as_not_detected(tmp_path: Path) -> None:
    # Far points (about 8 m from every LED) fall below the floor: NaN, not 15.
    points = np.array([[1.5, 1.5], [9.0, 9.0]])
    _write_dataset(tmp_path, points, _readings(points, None))
    survey = _massey.load_survey(tmp_path)
    np.testing.assert_allclose(survey.points, points)
    np.testing.assert_allclose(survey.leds, LEDS)
    assert survey.detected[0].all() and not survey.detected[1].any()
    np.testing.assert_allclose(survey.readings[0], _readings(points[:1], None)[0])


def test_the_split_takes_one_point_per_square_metre() -> None:
    ticks = np.arange(0.05, 3.0, 0.1)
    points = np.array([(x, y) for x in ticks for y in ticks])
    split = _massey.facility_split(points)
    # 3 x 3 cells from the lowest point (0.05); each keeps the point nearest its centre.
    assert len(split.survey) == 9
    centres = {(round(x, 2), round(y, 2)) for x, y in points[split.survey]}
    assert centres == {(x, y) for x in (0.55, 1.55, 2.55) for y in (0.55, 1.55, 2.55)}
    assert len(split.test) == len(points) - 9
    assert not set(split.survey) & set(split.test)


def test_the_receiver_height_is_read_off_the_survey(dataset: Path) -> None:
    survey = _massey.load_survey(dataset)
    candidates = np.round(np.arange(0.0, 1.51, 0.1), 2)
    height, nll = _massey.estimate_receiver_height(survey, np.arange(300), candidates)
    assert height == pytest.approx(RECEIVER_Z, abs=0.1)
    assert nll.shape == candidates.shape and nll[0] > nll.min() + 10


def test_multilateration_inverts_the_lambertian_model_exactly() -> None:
    points = np.array([[1.1, 0.7], [2.0, 1.9], [1.5, 1.5]])
    found = _massey.multilateration(
        LEDS[:, :2],
        np.full(len(LEDS), GAIN),
        np.full(len(LEDS), ORDER),
        LEDS[0, 2] - RECEIVER_Z,
        _readings(points, None),
        fallback=np.zeros(2),
    )
    np.testing.assert_allclose(found, points, atol=1e-9)


def test_weighted_knn_returns_the_survey_point_it_sees() -> None:
    reference = np.array([[0.5, 0.5], [2.5, 2.5], [0.5, 2.5]])
    readings = _readings(reference, None)
    found = _massey.weighted_knn(reference, readings, readings[1:2], k=2)
    np.testing.assert_allclose(found, reference[1:2], atol=1e-6)


@pytest.mark.slow
def test_the_protocol_runs_through_the_api_and_writes_its_page(
    dataset: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    argv = [str(dataset), "--max-test", "8", "--level", "no", "--subset", "1,2,3"]
    argv += ["--out", str(out)]
    assert measured.main(argv) == 0
    rows = list(csv.DictReader((out / "measured.csv").read_text(encoding="utf-8").splitlines()))
    layouts = {(r["method"], r["layout"], r["K"]) for r in rows}
    assert ("service (gridless)", "calibrated", "1") in layouts
    assert ("multilateration (LLS)", "calibrated", "1") in layouts
    assert ("weighted kNN (k = 4)", "nominal", "1") in layouts
    by_k = {r["K"]: int(r["count"]) for r in rows if r["layout"] == "calibrated"}
    assert by_k == {"1": 8, "2": 8, "4": 8}
    calibrated = next(r for r in rows if r["layout"] == "calibrated" and r["K"] == "1")
    # 5 % noise in a 3 m room of 4 LEDs: a calibrated fix is within decimetres.
    assert float(calibrated["median_cm"]) < 30 and not math.isnan(float(calibrated["coverage"]))
    # a root mean square is never below the mean (Cauchy-Schwarz); both rounded to 0.01
    assert float(calibrated["mean_cm"]) <= float(calibrated["rms_cm"]) + 0.01
    # The smaller room: luminaires 1-3 alone, on the test points that detect all three.
    smaller = {r["layout"]: int(r["count"]) for r in rows if r["layout"].startswith("3 lum")}
    assert set(smaller) == {
        "3 luminaires, nominal",
        "3 luminaires, calibrated",
        "3 luminaires, calibrated, fit_gain_map false",
    }
    assert min(smaller.values()) > 0 and max(smaller.values()) <= 8
    page = (out / "measured.md").read_text(encoding="utf-8")
    assert page.startswith("# Measured survey") and "python -m bench.measured DATA" in page
    assert "## A smaller room" in page


def test_the_shown_command_hides_the_readers_path_to_the_data() -> None:
    given = ["/home/someone/Public-VLP-Dataset", "--max-test", "50", "--commit", "abc"]
    assert (
        _massey.shown_command("python -m bench.measured", given, Path(given[0]))
        == "python -m bench.measured DATA --max-test 50 --commit abc"
    )
