"""Survey calibration over HTTP, end to end, with surveys simulated from a perturbed room."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from app.pictures.localization import match_estimates
from app.schemas.calibrations import calibration_example
from app.schemas.rooms import paper_room_example
from app.vlp.calibration import simulate_survey
from app.vlp.layout import Layout, Reflectance
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.presets import paper_layout
from app.vlp.simulation import noisy_amplitudes, true_amplitudes

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, wait_for_job, wait_for_room

DIMMED, DEAD = 5, 10


def _paper_room(client: TestClient) -> str:
    response = client.post("/v1/rooms", json=paper_room_example(), headers=ADMIN)
    assert response.status_code == 201, response.text
    room_id: str = response.json()["id"]
    wait_for_room(client, room_id)
    return room_id


def _perturbed(nominal: Layout) -> Layout:
    """The real room: LED 5 at half power, LED 10 dead, every beam off by up to 6 degrees."""
    rng = np.random.default_rng(3)
    angles = 60.0 + rng.uniform(-6.0, 6.0, nominal.n_leds)
    scale = {DIMMED: 0.5, DEAD: 1e-9}
    leds = tuple(
        replace(led, half_power_angle_deg=float(angles[i]), pilot_amplitude=scale.get(i, 1.0))
        for i, led in enumerate(nominal.leds)
    )
    return replace(nominal, leds=leds)


def _survey_body(true: Layout, noise_std: float) -> dict[str, Any]:
    ticks = np.arange(0.25, 4.0, 0.5)
    points = np.array([(x, y) for x in ticks for y in ticks])
    survey = simulate_survey(true, points, noise_std, rng=11)
    rows = [
        {"x": float(x), "y": float(y), "led": int(led), "amplitude": float(amp)}
        for (x, y), led, amp in zip(
            survey.points, survey.led_indices, survey.amplitudes, strict=True
        )
    ]
    return {"survey": rows}


def _mean_error_m(
    client: TestClient, room_id: str, version: int, true: Layout, noise_std: float
) -> float:
    """Mean matched error over 8 trials of 3 terminals measured in the real room."""
    rng = np.random.default_rng(5)
    errors = []
    for _ in range(8):
        positions = rng.uniform(0.3, 3.7, (3, 2))
        amplitudes = noisy_amplitudes(true, positions, noise_std, rng=rng)
        body = {
            "terminals": [
                {"id": f"t{k}", "amplitudes": row.tolist()} for k, row in enumerate(amplitudes)
            ],
            "targets": 3,
            "fingerprint_version": version,
        }
        response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
        assert response.status_code == 200, response.text
        estimates = np.array([[e["x"], e["y"]] for e in response.json()["estimates"]])
        rows, cols = match_estimates(estimates, positions)
        errors.extend(np.linalg.norm(estimates[rows] - positions[cols], axis=1))
    return float(np.mean(errors))


def test_calibration_end_to_end(worker_app: TestClient) -> None:
    client = worker_app
    room_id = _paper_room(client)
    nominal = layout_from_mapping(
        client.get(f"/v1/rooms/{room_id}", headers=ADMIN).json()["layout"]
    )
    true = _perturbed(nominal)
    typical = float(np.median(true_amplitudes(nominal, np.array([[2.0, 2.0]]))))
    noise_std = 0.01 * typical

    response = client.post(
        f"/v1/rooms/{room_id}/calibrations", json=_survey_body(true, noise_std), headers=ADMIN
    )
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["kind"] == "calibration" and response.headers["location"] == f"/v1/jobs/{job['id']}"
    result = wait_for_job(client, job["id"])["result"]
    calibrated_version = result["fingerprint_version"]
    assert calibrated_version == 2

    report = client.get(
        f"/v1/rooms/{room_id}/calibrations/{result['calibration_id']}", headers=TERMINAL
    ).json()
    assert report["status"] == "succeeded" and report["active"] and report["survey_rows"] == 1024
    assert report["masked_leds"] == [DEAD]
    assert report["receiver_gain"] == pytest.approx(1.0, rel=0.03)
    flags = {led["index"]: led["flag"] for led in report["leds"]}
    assert flags[DIMMED] == "dimmed" and flags[DEAD] == "dead"
    assert {flag for index, flag in flags.items() if index not in (DIMMED, DEAD)} == {"ok"}
    for led, true_led in zip(report["leds"], true.leds, strict=True):
        assert led["masked"] == (led["index"] == DEAD)
        if led["index"] == DEAD:
            continue
        assert led["half_power_angle_deg"] == pytest.approx(true_led.half_power_angle_deg, abs=1.0)
        assert led["relative_amplitude"] == pytest.approx(true_led.pilot_amplitude, rel=0.03)
        # After the fit only the noise is left (before: the model error as well).
        assert led["residual_rms_after"] <= led["residual_rms_before"]
        assert led["residual_rms_after"] < 1.5 * noise_std
    dimmed = report["leds"][DIMMED]
    assert dimmed["residual_rms_after"] < 0.1 * dimmed["residual_rms_before"]

    fingerprint = client.get(f"/v1/rooms/{room_id}/fingerprints/current", headers=ADMIN).json()
    assert fingerprint["version"] == calibrated_version and fingerprint["leds"] == 15
    assert fingerprint["masked_leds"] == [DEAD]
    assert fingerprint["calibration_id"] == result["calibration_id"]

    # Terminals measure in the real room and send all 16 amplitudes to both versions.
    uncalibrated = _mean_error_m(client, room_id, 1, true, noise_std)
    calibrated = _mean_error_m(client, room_id, calibrated_version, true, noise_std)
    assert calibrated < 0.5 * uncalibrated, (calibrated, uncalibrated)

    listed = client.get(f"/v1/rooms/{room_id}/calibrations", headers=TERMINAL).json()["items"]
    assert [item["id"] for item in listed] == [result["calibration_id"]]


def test_rebuild_keeps_and_put_drops_the_calibration(worker_app: TestClient) -> None:
    client = worker_app
    room_id = _paper_room(client)
    response = client.post(
        f"/v1/rooms/{room_id}/calibrations", json=calibration_example(), headers=ADMIN
    )
    calibration_id = wait_for_job(client, response.json()["id"])["result"]["calibration_id"]
    rebuild = client.post(f"/v1/rooms/{room_id}/fingerprints", headers=ADMIN).json()
    version = wait_for_job(client, rebuild["id"])["result"]["fingerprint_version"]
    rebuilt = client.get(f"/v1/rooms/{room_id}/fingerprints/{version}", headers=ADMIN).json()
    assert rebuilt["calibration_id"] == calibration_id and rebuilt["leds"] == 15

    room = client.get(f"/v1/rooms/{room_id}", headers=ADMIN)
    put = client.put(
        f"/v1/rooms/{room_id}",
        json=paper_room_example(),
        headers={**ADMIN, "If-Match": room.headers["etag"]},
    )
    assert put.status_code == 200, put.text
    version = wait_for_job(client, put.json()["fingerprint"]["job_id"])["result"][
        "fingerprint_version"
    ]
    fresh = client.get(f"/v1/rooms/{room_id}/fingerprints/{version}", headers=ADMIN).json()
    assert fresh["calibration_id"] is None and fresh["leds"] == 16
    report = client.get(f"/v1/rooms/{room_id}/calibrations/{calibration_id}", headers=ADMIN)
    assert report.json()["active"] is False


def test_swagger_example_then_mask_only(worker_app: TestClient) -> None:
    client = worker_app
    room_id = _paper_room(client)
    response = client.post(
        f"/v1/rooms/{room_id}/calibrations", json=calibration_example(), headers=ADMIN
    )
    assert response.status_code == 202, response.text
    first = wait_for_job(client, response.json()["id"])["result"]["calibration_id"]
    report = client.get(f"/v1/rooms/{room_id}/calibrations/{first}", headers=ADMIN).json()
    flags = {led["index"]: led["flag"] for led in report["leds"]}
    assert flags[5] == "dimmed" and flags[10] == "dead" and report["masked_leds"] == [10]

    # Mask one more LED without a survey (and without a new layout).
    response = client.post(
        f"/v1/rooms/{room_id}/calibrations", json={"masked_leds": [3]}, headers=ADMIN
    )
    assert response.status_code == 202, response.text
    result = wait_for_job(client, response.json()["id"])["result"]
    second = client.get(
        f"/v1/rooms/{room_id}/calibrations/{result['calibration_id']}", headers=ADMIN
    ).json()
    assert second["based_on"] == first and second["survey_rows"] == 0
    assert second["masked_leds"] == [3, 10] and second["leds"][5]["flag"] == "dimmed"
    current = client.get(f"/v1/rooms/{room_id}/fingerprints/current", headers=ADMIN).json()
    assert current["leds"] == 14 and current["masked_leds"] == [3, 10]
    # A 16-amplitude measurement and a 14-amplitude one localize alike; 15 is refused.
    amplitudes = true_amplitudes(
        layout_from_mapping(paper_room_example()), np.array([[1.0, 1.2], [2.9, 3.1]])
    )
    answers = []
    for keep in (list(range(16)), [i for i in range(16) if i not in (3, 10)]):
        body = {"power": amplitudes[:, keep].__pow__(2).sum(axis=0).tolist(), "targets": 2}
        answer = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
        assert answer.status_code == 200, answer.text
        answers.append(answer.json()["estimates"])
    assert answers[0] == answers[1]
    bad = client.post(f"/v1/rooms/{room_id}/localize", json={"power": [1.0] * 15}, headers=TERMINAL)
    assert_problem(bad, 422, ["body.power"])
    items = client.get(f"/v1/rooms/{room_id}/calibrations", headers=ADMIN).json()["items"]
    assert [item["active"] for item in items] == [True, False]


@pytest.mark.slow
def test_calibration_fits_led_positions_and_walls(worker_app: TestClient) -> None:
    """A displaced LED and reflecting walls the layout does not know: the report has the
    fitted position (and shift) of every LED and the walls' reflectance with its sd."""
    client = worker_app
    room_id = _paper_room(client)
    nominal = layout_from_mapping(
        client.get(f"/v1/rooms/{room_id}", headers=ADMIN).json()["layout"]
    )
    moved = replace(nominal.leds[6], x=nominal.leds[6].x + 0.15, y=nominal.leds[6].y - 0.1)
    true = replace(
        nominal,
        room=replace(nominal.room, reflectance=Reflectance(walls=0.6, floor=0.0, ceiling=0.0)),
        leds=(*nominal.leds[:6], moved, *nominal.leds[7:]),
    )
    typical = float(np.median(true_amplitudes(nominal, np.array([[2.0, 2.0]]))))
    body = {**_survey_body(true, 0.01 * typical), "fit_reflectance": True}
    response = client.post(f"/v1/rooms/{room_id}/calibrations", json=body, headers=ADMIN)
    assert response.status_code == 202, response.text
    result = wait_for_job(client, response.json()["id"])["result"]
    report = client.get(
        f"/v1/rooms/{room_id}/calibrations/{result['calibration_id']}", headers=TERMINAL
    ).json()
    assert report["fit_reflectance"] is True and report["led_position_bound_m"] == 0.3
    led = report["leds"][6]
    assert (led["nominal_x"], led["nominal_y"]) == (nominal.leds[6].x, nominal.leds[6].y)
    assert led["x"] == pytest.approx(moved.x, abs=0.03) and led["y"] == pytest.approx(
        moved.y, abs=0.03
    )
    assert led["shift_m"] == pytest.approx(np.hypot(0.15, 0.1), abs=0.03)
    others = [item["shift_m"] for item in report["leds"] if item["index"] != 6]
    assert max(others) < 0.03
    walls, sd = report["reflectance"]["walls"], report["reflectance_sd"]["walls"]
    assert 0 < sd < 0.1 and abs(walls - 0.6) < 3 * sd
    assert report["reflectance_sd"]["floor"] is None and report["reflectance"]["floor"] == 0.0


@pytest.mark.parametrize(
    ("body", "fields"),
    [
        ({"survey": [{"x": 1.0, "y": 1.0, "led": 16, "amplitude": 1e-6}]}, ["body.survey.0.led"]),
        ({"survey": [{"x": 4.5, "y": 1.0, "led": 0, "amplitude": 1e-6}]}, ["body.survey.0"]),
        ({"survey": [{"x": 1.0, "y": 1.0, "led": 0, "amplitude": "loud"}]}, None),
        ({"masked_leds": [16]}, ["body.masked_leds.0"]),
        ({"masked_leds": list(range(16))}, ["body.masked_leds"]),
        ({"dead_below": 0.8, "dimmed_below": 0.5}, ["body.dead_below"]),
        ({"surveys": []}, None),
        ({"led_position_bound_m": 1.5}, ["body.led_position_bound_m"]),
        ({"fit_reflectance": "yes"}, ["body.fit_reflectance"]),
        ({"fit_gain_map": "no"}, ["body.fit_gain_map"]),
        ({"survey": [{"x": 1.0, "y": 1.0, "led": 0, "amplitude": None}]}, ["body.survey"]),
        ({"led_tilt_bound_deg": 46}, ["body.led_tilt_bound_deg"]),
        ({"led_tilt_bound_deg": -1}, ["body.led_tilt_bound_deg"]),
    ],
    ids=[
        "led-range",
        "outside",
        "not-a-number",
        "mask-range",
        "mask-all",
        "thresholds",
        "typo",
        "position-bound",
        "reflectance-flag",
        "gain-map-flag",
        "nothing-detected",
        "tilt-bound-high",
        "tilt-bound-negative",
    ],
)
def test_bad_requests_name_the_field(
    client: TestClient, body: dict[str, Any], fields: list[str] | None
) -> None:
    room_id = client.post("/v1/rooms", json=paper_room_example(), headers=ADMIN).json()["id"]
    response = client.post(f"/v1/rooms/{room_id}/calibrations", json=body, headers=ADMIN)
    problem = assert_problem(response, 422, fields)
    assert problem["errors"]
    assert client.get(f"/v1/rooms/{room_id}/calibrations", headers=ADMIN).json()["items"] == []


def test_roles_and_unknown_ids(client: TestClient) -> None:
    room_id = client.post("/v1/rooms", json=paper_room_example(), headers=ADMIN).json()["id"]
    url = f"/v1/rooms/{room_id}/calibrations"
    assert_problem(client.post(url, json={"masked_leds": [1]}, headers=TERMINAL), 403)
    assert_problem(client.post(url, json={"masked_leds": [1]}), 401)
    assert_problem(client.get(f"{url}/nope", headers=TERMINAL), 404)
    assert_problem(client.get("/v1/rooms/nope/calibrations", headers=TERMINAL), 404)
    assert_problem(client.post("/v1/rooms/nope/calibrations", json={}, headers=ADMIN), 404)
    # Accepted while the room's first build is still pending: the job waits in the queue.
    response = client.post(url, json={"masked_leds": [1]}, headers=ADMIN)
    assert response.status_code == 202
    job = client.get(response.headers["location"], headers=TERMINAL).json()
    assert job["kind"] == "calibration" and job["status"] == "queued"
    listed = client.get(url, headers=TERMINAL).json()["items"]
    assert listed[0]["status"] == "queued" and listed[0]["leds"] is None


def test_epoch_posts_on_a_masked_room_send_one_amplitude_per_room_led(
    worker_app: TestClient,
) -> None:
    # Terminals do not know about the mask: they post all 16 amplitudes, the epoch drops
    # the masked LED's, as localize does; 15 (the fingerprint's LEDs) are fine too.
    client = worker_app
    room_id = _paper_room(client)
    response = client.post(
        f"/v1/rooms/{room_id}/calibrations", json={"masked_leds": [3]}, headers=ADMIN
    )
    version = wait_for_job(client, response.json()["id"])["result"]["fingerprint_version"]
    nominal = paper_layout()
    truth = np.array([[1.1, 1.3], [2.8, 2.9]])
    amplitudes = true_amplitudes(nominal, truth)
    epoch = client.post(
        f"/v1/rooms/{room_id}/epochs",
        json={"window_s": 30, "fingerprint_version": version},
        headers=TERMINAL,
    ).json()
    url = f"/v1/rooms/{room_id}/epochs/{epoch['id']}"
    room_sized = {"terminal_id": "t1", "amplitudes": amplitudes[0].tolist()}
    assert client.post(f"{url}/measurements", json=room_sized, headers=TERMINAL).status_code == 202
    kept = np.delete(amplitudes[1], 3).tolist()
    fingerprint_sized = {"terminal_id": "t2", "amplitudes": kept}
    answer = client.post(f"{url}/measurements", json=fingerprint_sized, headers=TERMINAL)
    assert answer.status_code == 202
    wrong = {"terminal_id": "t3", "amplitudes": amplitudes[0][:14].tolist()}
    refused = client.post(f"{url}/measurements", json=wrong, headers=TERMINAL)
    assert refused.status_code == 422 and "amplitudes" in refused.text
    solved = client.post(f"{url}/solve", headers=TERMINAL).json()
    assert solved["status"] == "solved"
    found = {e["terminal_id"]: (e["x"], e["y"]) for e in solved["localization"]["estimates"]}
    assert np.hypot(*(np.array(found["t1"]) - truth[0])) < 0.02
    assert np.hypot(*(np.array(found["t2"]) - truth[1])) < 0.02


def test_rows_not_detected_enter_the_fit_as_censored(worker_app: TestClient) -> None:
    # The weak rows of an exact survey sent as "not detected": the fit takes them as below
    # the survey's floor (its weakest detected amplitude), never as a number, and finds the
    # same LEDs as from the exact values. Nulls where a strong amplitude is due (the model far
    # above the floor) do pull the fit.
    client = worker_app
    nominal = paper_layout()
    body = _survey_body(_perturbed(nominal), 0.0)
    strongest = max(row["amplitude"] for row in body["survey"])
    weak = [
        {**row, "amplitude": None} if row["amplitude"] < 0.05 * strongest else row
        for row in body["survey"]
    ]
    assert sum(row["amplitude"] is None for row in weak) > 50
    contradicting = [
        {**row, "amplitude": None}
        if row["led"] == 0 and row["amplitude"] > 0.5 * strongest
        else row
        for row in body["survey"]
    ]
    reports = []
    for survey in (body["survey"], weak, contradicting):
        room_id = _paper_room(client)
        sent = {"survey": survey, "led_tilt_bound_deg": 0.0}
        response = client.post(f"/v1/rooms/{room_id}/calibrations", json=sent, headers=ADMIN)
        assert response.status_code == 202, response.text
        result = wait_for_job(client, response.json()["id"])["result"]
        url = f"/v1/rooms/{room_id}/calibrations/{result['calibration_id']}"
        reports.append(client.get(url, headers=ADMIN).json())
    plain, censored, pulled = (
        [led["pilot_amplitude"] for i, led in enumerate(r["leds"]) if i != DEAD] for r in reports
    )
    assert censored == pytest.approx(plain, rel=1e-5)
    assert [led["flag"] for led in reports[1]["leds"]][DEAD] == "dead"
    assert reports[1]["survey_rows"] == len(weak) and reports[1]["led_tilt_bound_deg"] == 0.0
    assert pulled[0] < 0.9 * plain[0]


def test_a_survey_maps_what_no_led_parameter_explains(worker_app: TestClient) -> None:
    """Each LED's amplitudes off by a smooth factor over the floor (a diffuser, a shade): the
    default calibration maps it; asked not to, it does not; the room's fingerprint follows."""
    client = worker_app
    true = paper_layout()
    body = _survey_body(
        true, 1e-3 * float(np.median(true_amplitudes(true, np.array([[2.0, 2.0]]))))
    )
    for row in body["survey"]:
        row["amplitude"] *= float(
            np.exp(0.15 * np.sin(1.3 * row["x"] + row["led"]) * np.cos(0.9 * row["y"]))
        )
    reports: dict[bool | None, dict[str, Any]] = {}
    for asked in (None, False):
        room_id = _paper_room(client)
        request = body if asked is None else {**body, "fit_gain_map": asked}
        response = client.post(f"/v1/rooms/{room_id}/calibrations", json=request, headers=ADMIN)
        assert response.status_code == 202, response.text
        result = wait_for_job(client, response.json()["id"])["result"]
        url = f"/v1/rooms/{room_id}/calibrations/{result['calibration_id']}"
        reports[asked] = client.get(url, headers=ADMIN).json()
    mapped, plain = reports[None], reports[False]
    assert mapped["fit_gain_map"] and not plain["fit_gain_map"]
    assert plain["gain_map"] is None
    assert mapped["gain_map"]["leds"] == list(range(true.n_leds))
    assert mapped["gain_map"]["evidence"] >= 2.0 and mapped["gain_map"]["length_scale_m"] > 0
    # What the map leaves of the survey's scatter, held out row by row, is far less.
    assert mapped["amplitude_error"]["relative_sd"] < 0.5 * plain["amplitude_error"]["relative_sd"]


# Two calibrations, their builds and a localization run: about ten seconds of a core.
@pytest.mark.slow
def test_a_survey_measures_batwing_beams_and_the_fingerprint_uses_them(
    worker_app: TestClient,
) -> None:
    client = worker_app
    from app.vlp.beams import Beam

    batwing = Beam((0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0), (1.0, 1.05, 1.12, 1.1, 0.7, 0.3, 0.0))
    errors, reports = {}, {}
    for fit_beams in (True, False):
        room_id = _paper_room(client)
        nominal = layout_from_mapping(
            client.get(f"/v1/rooms/{room_id}", headers=ADMIN).json()["layout"]
        )
        true = replace(nominal, leds=tuple(replace(led, beam=batwing) for led in nominal.leds))
        noise_std = 0.005 * float(np.median(true_amplitudes(true, np.array([[2.0, 2.0]]))))
        # Without the gain map, which would also follow the survey where the beam is wrong.
        body = {**_survey_body(true, noise_std), "fit_beams": fit_beams, "fit_gain_map": False}
        response = client.post(f"/v1/rooms/{room_id}/calibrations", json=body, headers=ADMIN)
        assert response.status_code == 202, response.text
        result = wait_for_job(client, response.json()["id"])["result"]
        url = f"/v1/rooms/{room_id}/calibrations/{result['calibration_id']}"
        reports[fit_beams] = client.get(url, headers=ADMIN).json()
        errors[fit_beams] = _mean_error_m(
            client, room_id, result["fingerprint_version"], true, noise_std
        )
    assert reports[True]["fit_beams"] and not reports[False]["fit_beams"]
    assert all(led["beam"] is not None for led in reports[True]["leds"])
    assert all(led["beam"] is None for led in reports[False]["leds"])
    assert errors[True] < 0.7 * errors[False], errors
