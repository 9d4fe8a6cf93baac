"""Accuracy on a measured survey, through the public API, as a facility works.

Run from the repository root on a fetched copy of the Massey University public VLP survey
(a directory holding its two CSV files, or its bare git directory and the commit)::

    python -m bench.measured /path/to/Public-VLP-Dataset
    python -m bench.measured /path/to/repo.git --commit 58d0c0f608de561901dec29a2f0ebe055c117f84
    python -m bench.measured DATA --max-test 200 --out bench/out/quick   # a small run

The protocol (see :mod:`bench._massey` for the data):

1. The nominal layout: the luminaires where the dataset says, every beam the API's default
   (60 degrees), the receiver height read off the survey, and one overall scale (the pilot
   amplitude) fitted to the survey's detected readings.
2. A sparse survey, about one point per square metre (:func:`bench._massey.facility_split`),
   sent to ``POST /v1/rooms/{id}/calibrations``; "calibrated" rows use the room after it.
3. Every other point (or ``--max-test`` of them) is localized through
   ``POST /v1/rooms/{id}/localize/batch``: K = 1 as `terminals` (each point its own
   amplitudes, undetected LEDs as ``null``, or as the floor with ``--undetected floor``);
   K = 2 and 4 as the aggregated correlation of disjoint groups of test points.
4. Baselines on the same split: weighted kNN on the survey points, and linear
   least-squares multilateration on the nominal and on the calibrated model.

Each row reports the mean, median and 95th percentile of the error (cm; for K > 1 after
optimal matching), the coverage (how often the truth lies inside ``accuracy_m``) and the
median ``accuracy_m``, the count, and the time per call (ms, wall time of the in-process
request divided by its items). Rows with ``receivers_level`` send the same data with a
layout that says the photodiodes are level (the robot's is). "N luminaires" rows run the
protocol in a smaller room, a subset of the luminaires alone (``--subset``; by default the
five of :data:`~bench._massey.FIVE_LEDS`).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from app.main import create_app
from app.settings import Settings
from app.vlp.channel import concentrator_gain, lambertian_order
from app.vlp.gain_map import MIN_EVIDENCE
from app.vlp.typing import FloatArray

from ._common import REPO_ROOT, machine_markdown, machine_record, write_csv
from ._massey import (
    FIVE_LEDS,
    MIN_DETECTED,
    MasseySurvey,
    Split,
    estimate_receiver_height,
    facility_split,
    load_survey,
    multilateration,
    shown_command,
    weighted_knn,
)

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=r"Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

__all__ = ["Row", "main", "run"]

ADMIN_KEY = "bench-admin-key-0123456789"
HEADERS = {"X-API-Key": ADMIN_KEY}
GRID_STEP_M = 0.1
NOMINAL_HALF_POWER_DEG = 60.0
# The API's default receiver (schemas.rooms): the layout sends it explicitly.
RECEIVER = {"area": 1e-4, "fov_deg": 70.0, "filter_gain": 1.0, "refractive_index": 1.5}
HEIGHT_CANDIDATES_M = np.round(np.arange(0.0, 1.501, 0.05), 2)
BATCH = 500
KS = (1, 2, 4)
HEADER = (
    "method",
    "model",
    "layout",
    "K",
    "count",
    "mean_cm",
    "median_cm",
    "p95_cm",
    "rms_cm",
    "coverage",
    "median_radius_cm",
    "ms_per_call",
)


@dataclass(frozen=True)
class Row:
    """One line of the table (errors in cm, coverage a fraction, NaN when not reported)."""

    method: str
    model: str
    layout: str
    k: int
    errors_cm: FloatArray
    radii_cm: FloatArray
    ms_per_call: float

    def cells(self) -> tuple[object, ...]:
        """The CSV cells, in :data:`HEADER` order."""
        e = self.errors_cm
        has_radius = bool(self.radii_cm.size)
        coverage = float(np.mean(e <= self.radii_cm)) if has_radius else math.nan
        radius = float(np.median(self.radii_cm)) if has_radius else math.nan
        return (
            self.method,
            self.model,
            self.layout,
            self.k,
            len(e),
            round(float(np.mean(e)), 2),
            round(float(np.median(e)), 2),
            round(float(np.percentile(e, 95)), 2),
            round(float(np.sqrt(np.mean(e**2))), 2),
            round(coverage, 3),
            round(radius, 2),
            round(self.ms_per_call, 2),
        )


def room_extent(survey: MasseySurvey) -> tuple[float, float]:
    """Room length and width (whole grid steps) holding every point and LED with 0.2 m."""
    far = np.maximum(survey.points.max(axis=0), survey.leds[:, :2].max(axis=0)) + 0.2
    return tuple(float(math.ceil(v / GRID_STEP_M) * GRID_STEP_M) for v in far)  # type: ignore[return-value]


def nominal_scale(survey: MasseySurvey, indices: np.ndarray, receiver_z: float) -> float:
    """One overall pilot amplitude: the geometric mean ratio of the survey's detected
    readings to the nominal channel gain (60-degree beams, level receiver)."""
    order = float(lambertian_order(NOMINAL_HALF_POWER_DEG))
    gain = _led_constant(np.array([order]))[0]
    dz = float(np.mean(survey.leds[:, 2])) - receiver_z
    r2 = ((survey.points[indices, None, :] - survey.leds[None, :, :2]) ** 2).sum(axis=-1)
    h = gain * dz ** (order + 1) / (dz * dz + r2) ** ((order + 3) / 2)
    readings = survey.readings[indices]
    seen = np.isfinite(readings)
    return float(np.exp(np.mean(np.log(readings[seen] / h[seen]))))


def _led_constant(order: FloatArray) -> FloatArray:
    """``(m+1)/(2 pi) A T G`` of the default receiver, per Lambertian order."""
    g_conc = concentrator_gain(RECEIVER["refractive_index"], RECEIVER["fov_deg"])
    return (order + 1) / (2 * math.pi) * RECEIVER["area"] * RECEIVER["filter_gain"] * g_conc


def layout_body(
    survey: MasseySurvey, receiver_z: float, scale: float, *, level: bool
) -> dict[str, Any]:
    """The nominal layout as a facility would send it."""
    length, width = room_extent(survey)
    return {
        "name": "Massey lobby" + (" (level)" if level else ""),
        "room": {"length": length, "width": width, "height": float(survey.leds[:, 2].max())},
        "grid": {"step": GRID_STEP_M, "receiver_height": receiver_z, "receivers_level": level},
        "receiver": RECEIVER,
        "leds": [
            {
                "x": float(x),
                "y": float(y),
                "z": float(z),
                "half_power_angle_deg": NOMINAL_HALF_POWER_DEG,
                "pilot_amplitude": scale,
            }
            for x, y, z in survey.leds
        ],
    }


def _wait(client: TestClient, path: str, done: Any, timeout_s: float = 600.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        body: dict[str, Any] = client.get(path, headers=HEADERS).json()
        if done(body):
            return body
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path} not done in {timeout_s:g} s: {body}")
        time.sleep(0.05)


def _job(client: TestClient, job_id: str) -> dict[str, Any]:
    job = _wait(client, f"/v1/jobs/{job_id}", lambda j: j["status"] in ("succeeded", "failed"))
    if job["status"] != "succeeded":
        raise RuntimeError(f"job failed: {job['error']}")
    return job


def _ready(client: TestClient, room_id: str) -> None:
    _wait(client, f"/v1/rooms/{room_id}", lambda r: r["fingerprint"]["status"] == "ready")


def create_room(client: TestClient, layout: dict[str, Any]) -> str:
    """POST the layout and wait for its fingerprint."""
    response = client.post("/v1/rooms", json=layout, headers=HEADERS)
    response.raise_for_status()
    room_id = str(response.json()["id"])
    _ready(client, room_id)
    return room_id


def _amplitudes(readings: FloatArray, undetected: str, floor: float) -> list[float | None]:
    if undetected == "null":
        return [None if not math.isfinite(v) else float(v) for v in readings]
    return [float(v) if math.isfinite(v) else floor for v in readings]


def calibrate(
    client: TestClient,
    room_id: str,
    survey: MasseySurvey,
    indices: np.ndarray,
    undetected: str,
    tilt_bound_deg: float | None = None,
    fit_beams: bool | None = None,
    fit_gain_map: bool | None = None,
) -> dict[str, Any]:
    """Send the survey points' readings; wait for the calibrated fingerprint; the report.

    ``tilt_bound_deg``, ``fit_beams``, ``fit_gain_map``: the request's
    ``led_tilt_bound_deg``, ``fit_beams`` and ``fit_gain_map`` (None: the API's default)."""
    # Without "null" a survey cannot say "not detected": those rows are left out.
    rows = [
        {"x": float(x), "y": float(y), "led": led, "amplitude": amp}
        for (x, y), readings in zip(survey.points[indices], survey.readings[indices], strict=True)
        for led, amp in enumerate(_amplitudes(readings, "null", survey.floor))
        if amp is not None or undetected == "null"
    ]
    body: dict[str, Any] = {"survey": rows}
    if tilt_bound_deg is not None:
        body["led_tilt_bound_deg"] = tilt_bound_deg
    if fit_beams is not None:
        body["fit_beams"] = fit_beams
    if fit_gain_map is not None:
        body["fit_gain_map"] = fit_gain_map
    response = client.post(f"/v1/rooms/{room_id}/calibrations", json=body, headers=HEADERS)
    response.raise_for_status()
    job = _job(client, response.json()["id"])
    calibration_id = job["result"]["calibration_id"]
    report = client.get(f"/v1/rooms/{room_id}/calibrations/{calibration_id}", headers=HEADERS)
    _wait(
        client,
        f"/v1/rooms/{room_id}",
        lambda r: (
            r["fingerprint"]["status"] == "ready"
            and r["fingerprint"]["version"] == report.json()["fingerprint_version"]
        ),
    )
    return dict(report.json())


def _localize(
    client: TestClient, room_id: str, items: list[dict[str, Any]]
) -> tuple[list[dict[str, Any]], float]:
    answers: list[dict[str, Any]] = []
    started = time.perf_counter()
    for first in range(0, len(items), BATCH):
        response = client.post(
            f"/v1/rooms/{room_id}/localize/batch",
            json={"items": items[first : first + BATCH]},
            headers=HEADERS,
        )
        response.raise_for_status()
        answers.extend(response.json()["items"])
    per_call_ms = 1e3 * (time.perf_counter() - started) / max(len(items), 1)
    for answer in answers:
        if "estimates" not in answer:
            raise RuntimeError(f"a localization failed: {answer}")
    return answers, per_call_ms


def _groups(test: np.ndarray, k: int, seed: int) -> np.ndarray:
    order = np.random.default_rng(seed + k).permutation(test)
    return order[: len(order) // k * k].reshape(-1, k)


def service_rows(
    client: TestClient,
    room_id: str,
    survey: MasseySurvey,
    test: np.ndarray,
    layout: str,
    undetected: str,
    seed: int,
) -> list[Row]:
    """K = 1 (`terminals`) and K = 2, 4 (aggregated correlation) through the batch API."""
    rows = []
    for k in KS:
        groups = _groups(test, k, seed) if k > 1 else test[:, None]
        items: list[dict[str, Any]]
        if k == 1:
            items = [
                {
                    "terminals": [
                        {
                            "id": "robot",
                            "amplitudes": _amplitudes(
                                survey.readings[g[0]], undetected, survey.floor
                            ),
                        }
                    ]
                }
                for g in groups
            ]
        else:
            filled = np.nan_to_num(survey.readings, nan=survey.floor)
            items = [
                {
                    "model": "correlation",
                    "correlation": (filled[g].T @ filled[g]).tolist(),
                    "targets": k,
                }
                for g in groups
            ]
        answers, per_call_ms = _localize(client, room_id, items)
        errors: list[float] = []
        radii: list[float] = []
        for g, answer in zip(groups, answers, strict=True):
            estimates = answer["estimates"]
            found = np.array([[e["x"], e["y"]] for e in estimates])
            truth = survey.points[g]
            cost = np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=-1)
            rows_i, cols_i = linear_sum_assignment(cost)
            errors.extend(cost[rows_i, cols_i])
            radii.extend(estimates[i].get("accuracy_m") or math.nan for i in rows_i)
        model = "terminals" if k == 1 else "correlation"
        rows.append(
            Row(
                "service (gridless)",
                model,
                layout,
                k,
                100 * np.array(errors),
                100 * np.array(radii),
                per_call_ms,
            )
        )
    return rows


def baseline_rows(
    survey: MasseySurvey,
    split_survey: np.ndarray,
    test: np.ndarray,
    receiver_z: float,
    scale: float,
    report: dict[str, Any],
) -> list[Row]:
    """Weighted kNN on the survey points; multilateration on the nominal and calibrated
    model (one reading vector per call)."""
    truth = survey.points[test]
    readings = survey.readings[test]
    dz = float(np.mean(survey.leds[:, 2])) - receiver_z
    centre = survey.points[split_survey].mean(axis=0)
    rows = []
    started = time.perf_counter()
    knn = weighted_knn(survey.points[split_survey], survey.readings[split_survey], readings)
    rows.append(_plain_row("weighted kNN (k = 4)", "nominal", knn, truth, started))
    nominal_order = np.full(len(survey.leds), float(lambertian_order(NOMINAL_HALF_POWER_DEG)))
    started = time.perf_counter()
    found = multilateration(
        survey.leds[:, :2],
        scale * _led_constant(nominal_order),
        nominal_order,
        dz,
        readings,
        fallback=centre,
    )
    rows.append(_plain_row("multilateration (LLS)", "nominal", found, truth, started))
    leds = report["leds"]
    order = np.array([led["lambertian_order"] for led in leds])
    amplitude = np.array([led["pilot_amplitude"] for led in leds]) * report["receiver_gain"]
    xy = np.array(
        [
            [led["x"] if led["x"] is not None else x, led["y"] if led["y"] is not None else y]
            for led, (x, y) in zip(leds, survey.leds[:, :2], strict=True)
        ]
    )
    started = time.perf_counter()
    found = multilateration(
        xy, amplitude * _led_constant(order), order, dz, readings, fallback=centre
    )
    rows.append(_plain_row("multilateration (LLS)", "calibrated", found, truth, started))
    return rows


def _plain_row(
    method: str, layout: str, found: FloatArray, truth: FloatArray, started: float
) -> Row:
    per_call_ms = 1e3 * (time.perf_counter() - started) / len(truth)
    errors = 100 * np.linalg.norm(found - truth, axis=1)
    return Row(method, "terminals", layout, 1, errors, np.array([]), per_call_ms)


@contextmanager
def _service(data_dir: Path) -> Iterator[TestClient]:
    settings = Settings(data_dir=data_dir, admin_keys=ADMIN_KEY, embedded_workers=1, demo=False)
    with TestClient(create_app(settings)) as client:
        yield client


# Rows of the default calibration with one step left out: name, ``calibrate``'s settings.
_CALIBRATION_VARIANTS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("calibrated, led_tilt_bound_deg 0", {"tilt_bound_deg": 0.0}),
    ("calibrated, fit_beams false", {"fit_beams": False}),
    ("calibrated, fit_gain_map false", {"fit_gain_map": False}),
)


def run(
    survey: MasseySurvey,
    *,
    max_test: int | None,
    seed: int,
    undetected: str,
    levels: Sequence[bool],
    data_dir: Path,
    subset: Sequence[int] = (),
) -> tuple[list[Row], dict[str, Any]]:
    """The whole protocol; the rows and what the report says about the run. ``subset``:
    1-based luminaires of the smaller room's rows (none when empty)."""
    split = facility_split(survey.points, seed=seed, max_test=max_test)
    receiver_z, nll = estimate_receiver_height(survey, split.survey, HEIGHT_CANDIDATES_M)
    scale = nominal_scale(survey, split.survey, receiver_z)
    rows: list[Row] = []
    report: dict[str, Any] = {}
    with _service(data_dir) as client:
        for level in levels:
            tag = ", receivers_level" if level else ""
            body = layout_body(survey, receiver_z, scale, level=level)
            nominal_id = create_room(client, body)
            rows += service_rows(
                client, nominal_id, survey, split.test, "nominal" + tag, undetected, seed
            )
            calibrated_id = create_room(client, body)
            report = calibrate(client, calibrated_id, survey, split.survey, undetected)
            rows += service_rows(
                client, calibrated_id, survey, split.test, "calibrated" + tag, undetected, seed
            )
            if not level:
                # The same survey with one of the default calibration's steps left out.
                for name, settings in _CALIBRATION_VARIANTS:
                    variant_id = create_room(client, body)
                    calibrate(client, variant_id, survey, split.survey, undetected, **settings)
                    rows += service_rows(
                        client, variant_id, survey, split.test, name, undetected, seed
                    )
        subset_rows, subset_report = (
            _subset_rows(client, survey, split, subset, undetected, seed) if subset else ([], {})
        )
    rows += baseline_rows(survey, split.survey, split.test, receiver_z, scale, report)
    rows += subset_rows
    info = {
        "survey_points": len(split.survey),
        "test_points": len(split.test),
        "receiver_z": receiver_z,
        "height_nll": dict(zip(HEIGHT_CANDIDATES_M.tolist(), nll.tolist(), strict=True)),
        "scale": scale,
        "report": report,
        "subset": list(subset),
        "subset_report": subset_report,
        "undetected_share": float(1 - survey.detected.mean()),
        "room": room_extent(survey),
    }
    return rows, info


def _subset_rows(
    client: TestClient,
    survey: MasseySurvey,
    split: Split,
    subset: Sequence[int],
    undetected: str,
    seed: int,
) -> tuple[list[Row], dict[str, Any]]:
    """The protocol in a smaller room: the luminaires ``subset`` (1-based) alone, their own
    receiver height and scale, the test points that detect at least :data:`MIN_DETECTED`."""
    few = survey.with_leds([name - 1 for name in subset])
    receiver_z, _ = estimate_receiver_height(few, split.survey, HEIGHT_CANDIDATES_M)
    body = layout_body(few, receiver_z, nominal_scale(few, split.survey, receiver_z), level=False)
    seen = np.isfinite(few.readings[split.test]).sum(axis=1)
    test = split.test[seen >= MIN_DETECTED]
    rows: list[Row] = []
    report: dict[str, Any] = {}
    tag = f"{len(subset)} luminaires"
    for name, settings in (
        (f"{tag}, nominal", None),
        (f"{tag}, calibrated", {}),
        (f"{tag}, calibrated, fit_gain_map false", {"fit_gain_map": False}),
    ):
        room_id = create_room(client, body)
        if settings is not None:
            done = calibrate(client, room_id, few, split.survey, undetected, **settings)
            if not settings:  # the default calibration's report is the one the page shows
                report = done
        rows += service_rows(client, room_id, few, test, name, undetected, seed)
    return rows, report


def _subset_section(info: dict[str, Any]) -> str:
    subset = info["subset"]
    if not subset:
        return ""
    return f"""## A smaller room

"{len(subset)} luminaires" rows: the same protocol in a room of {len(subset)} LEDs, the survey's
and the test points' readings of luminaires {", ".join(str(n) for n in subset)} alone (their own
receiver height and scale), on the test points that detect at least {MIN_DETECTED} of them.
{_gain_map_note(info["subset_report"])}
"""


def _table(rows: Sequence[Row]) -> str:
    titles = (
        "method",
        "model",
        "layout",
        "K",
        "count",
        "mean cm",
        "median cm",
        "p95 cm",
        "RMS cm",
        "coverage",
        "median radius cm",
        "ms / call",
    )
    lines = ["| " + " | ".join(titles) + " |", "|" + "---|" * len(titles)]
    for row in rows:
        cells = ["-" if isinstance(c, float) and math.isnan(c) else str(c) for c in row.cells()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _height_lines(info: dict[str, Any]) -> str:
    nll = info["height_nll"]
    best = min(nll.values())
    shown = [z for z in nll if abs(round(z * 10) - z * 10) < 1e-9]
    return "\n".join(
        [
            "| receiver height above floor, m | " + " | ".join(f"{z:.1f}" for z in shown) + " |",
            "|---|" + "---|" * len(shown),
            "| minus log-likelihood above the best | "
            + " | ".join(f"{nll[z] - best:.0f}" for z in shown)
            + " |",
        ]
    )


def _tilt_note(tilts: list[float], angles: list[int]) -> str:
    """What the fitted tilts say about beams fitted far wider than specified."""
    wide = sum(a > NOMINAL_HALF_POWER_DEG + 15 for a in angles)
    if any(t > 0 for t in tilts) or not wide:
        return ""
    return (
        f" The {wide} beams fitted more than 15 degrees wider than the specified "
        f"{NOMINAL_HALF_POWER_DEG:g} are thus not explained by tilted fittings on this survey."
    )


def _beam_note(report: dict[str, Any]) -> str:
    """How many LEDs the survey gave a measured beam, and their median table."""
    beams = [led["beam"] for led in report.get("leds", []) if led.get("beam")]
    if not beams:
        return "The survey told no LED's beam from a Lambertian one."
    angles = beams[0]["angles_deg"]
    relative = np.array(
        [np.array(b["relative_intensity"]) / b["relative_intensity"][0] for b in beams]
    )
    median = np.median(relative, axis=0)
    shown = [i for i, a in enumerate(angles) if a % 15 == 0]
    header = " | ".join(f"{angles[i]:g}" for i in shown)
    values = " | ".join(f"{median[i]:.2f}" for i in shown)
    return (
        f"The survey measured the beam of {len(beams)} of {len(report.get('leds', []))} LEDs "
        "(`fit_beams`). Their median intensity, relative to the axis, by degrees off it:\n\n"
        f"| degrees | {header} |\n|---|{'---|' * len(shown)}\n| intensity | {values} |"
    )


def _gain_map_note(report: dict[str, Any]) -> str:
    """What the survey's gain map is, or that it showed none."""
    gain_map = report.get("gain_map")
    if not gain_map:
        return (
            "The survey showed no gain map (`fit_gain_map`) worth more than its two "
            f"parameters (a log likelihood ratio of {MIN_EVIDENCE:g})."
        )
    return (
        f"The survey showed a gain map (`fit_gain_map`) for {len(gain_map['leds'])} of "
        f"{len(report.get('leds', []))} LEDs: length scale {gain_map['length_scale_m']:g} m, "
        f"log likelihood ratio over independent residuals {gain_map['evidence']:.1f} (kept "
        f"above {MIN_EVIDENCE:g}, the map's two parameters)."
    )


def write_page(
    rows: Sequence[Row], info: dict[str, Any], command: str, out: Path, csv_path: Path
) -> None:
    """The results page (``out``) and its CSV (``csv_path``)."""
    write_csv(csv_path, HEADER, (row.cells() for row in rows))
    leds = info["report"].get("leds") or []
    hpa = [round(led["half_power_angle_deg"]) for led in leds]
    rel = [round(led["relative_amplitude"], 2) for led in leds]
    tilts = [round(led.get("tilt_deg") or 0.0, 1) for led in leds]
    azimuths = [round(led.get("tilt_azimuth_deg") or 0.0) for led in leds]
    length, width = info["room"]
    shown_csv = csv_path.relative_to(REPO_ROOT) if csv_path.is_relative_to(REPO_ROOT) else csv_path
    text = f"""# Measured survey: the Massey University lobby

Generated by `{command}` (CSV: `{shown_csv}`).

The data: Massey University's public VLP survey (Glass et al., Sensors 21(9):3256, 2021), 11
luminaires at z = 2.35 m, a photodiode carried by a robot, HTC Vive ground truth. The
benchmark reads a fetched copy named on its command line; the data is not part of this
repository. {100 * info["undetected_share"]:.0f} % of the readings are at the detector's floor
(not detected). The room sent to the service is {length:.1f} m x {width:.1f} m, grid step
{GRID_STEP_M} m.

Protocol, as a facility works through the public API: the nominal layout (every beam 60
degrees, one overall pilot amplitude {info["scale"]:.4g} fitted to the survey's detected
readings), a survey of {info["survey_points"]} points (about one per square metre) sent to
`POST .../calibrations`, then {info["test_points"]} other points localized through
`POST .../localize/batch`: K = 1 as `terminals`, K = 2 and 4 as the aggregated correlation of
disjoint groups of test points. Errors for K > 1 are after optimal matching. Coverage: how often
the truth lies inside the answer's 95 % radius `accuracy_m`. "calibrated" rows use the API's
default calibration (each LED's normal fitted within 15 degrees, the survey's undetected
readings sent as `null`, each LED's beam measured where the survey tells it from a Lambertian
one, and the map of what the survey shows of each LED's gain beyond its model);
"led_tilt_bound_deg 0" rows the same survey with every LED's normal kept straight down,
"fit_beams false" rows with every beam kept Lambertian, "fit_gain_map false" rows without the
gain map.

{_table(rows)}

## The receiver height

The files do not give it. For each candidate height the survey points' log readings are
fitted with every LED's Lambertian model (its own scale and order, one log-normal noise),
the undetected readings entering as censored below the floor; the height of the highest
profile likelihood is kept: **{info["receiver_z"]:.2f} m above the floor**
({float(np.mean([2.35])) - info["receiver_z"]:.2f} m below the luminaires). The beam width and
the height trade off near each LED's foot, but not in the fall-off's tail, which is what
separates them:

{_height_lines(info)}

A photodiode on a mast of a small robot at about this height (above the robot's body and
clear of its own shadow, with the tracker beside it) is physically plausible; a photodiode
at 0.2 m would need every luminaire's beam to be narrower and is far less likely on this data.

## Calibration on the survey

Fitted half-power angles (degrees, per LED): {hpa}; relative amplitudes: {rel}; tilts
(degrees from straight down): {tilts}, towards azimuths (degrees from +x): {azimuths};
receiver gain {info["report"].get("receiver_gain", float("nan")):.3g}; noise sd
{info["report"].get("noise_std", float("nan")):.3g}. A fitted tilt is kept only where it lowers
that LED's residual sum of squares by more than 8 noise variances (more than chance would for
its two parameters): {sum(t > 0 for t in tilts)} of {len(tilts)} LEDs here, which is why the
`led_tilt_bound_deg 0` rows {"equal" if not any(t > 0 for t in tilts) else "differ from"} the
calibrated ones.{_tilt_note(tilts, hpa)}

{_beam_note(info["report"])}

{_gain_map_note(info["report"])}

{_subset_section(info)}

Machine:

{machine_markdown(machine_record())}
"""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(prog="python -m bench.measured", description=__doc__)
    parser.add_argument("data", type=Path, help="fetched copy (directory or bare git dir)")
    parser.add_argument("--commit", default=None, help="commit to read from a git directory")
    parser.add_argument("--max-test", type=int, default=600, help="test points (0: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--undetected", choices=("null", "floor"), default="null")
    parser.add_argument(
        "--level", choices=("both", "no", "yes"), default="both", help="receivers_level rows"
    )
    parser.add_argument(
        "--leds",
        default=None,
        help="keep only these luminaires (1-based, comma-separated): a room with fewer LEDs",
    )
    parser.add_argument(
        "--subset",
        default=",".join(str(n) for n in FIVE_LEDS),
        help="luminaires of the smaller room's rows (1-based, comma-separated; empty: none)",
    )
    parser.add_argument("--out", type=Path, default=None, help="default: docs/ (full run)")
    args = parser.parse_args(argv)
    survey = load_survey(args.data, args.commit)
    if args.leds:
        survey = survey.with_leds([int(name) - 1 for name in args.leds.split(",")])
    levels = {"both": (False, True), "no": (False,), "yes": (True,)}[args.level]
    with tempfile.TemporaryDirectory(prefix="vlp-measured-") as tmp:
        rows, info = run(
            survey,
            max_test=args.max_test or None,
            seed=args.seed,
            undetected=args.undetected,
            levels=levels,
            data_dir=Path(tmp),
            subset=[int(name) for name in args.subset.split(",") if name.strip()],
        )
    given = sys.argv[1:] if argv is None else argv
    command = shown_command("python -m bench.measured", given, args.data)
    out = args.out or REPO_ROOT / "docs" / "results"
    csv_path = (args.out or REPO_ROOT / "docs" / "data") / "measured.csv"
    write_page(rows, info, command, out / "measured.md", csv_path)
    print(_table(rows))
    print(f"receiver height {info['receiver_z']:.2f} m; scale {info['scale']:.4g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
