"""VLPClient against the real app in-process: typed answers and problems mapped to errors."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from app.client import (
    AuthenticationError,
    Conflict,
    InvalidRequest,
    Job,
    NotFound,
    PermissionDenied,
    PreconditionError,
    VLPClient,
)
from app.main import create_app
from app.schemas import Localization, Problem, Room, Simulation
from tests.api.conftest import TestClient, make_settings

from .conftest import ADMIN_KEY, TERMINAL_KEY, LiveApp

REPO = Path(__file__).resolve().parents[2]


def _paper_room() -> dict[str, object]:
    layout: dict[str, object] = json.loads(
        (REPO / "examples" / "paper-room.json").read_text(encoding="utf-8")
    )
    return layout


def test_lists_and_reads_the_demo_room(live_app: LiveApp) -> None:
    vlp = live_app.client(TERMINAL_KEY)
    page = vlp.list_rooms()
    assert [room.id for room in page.items] == [live_app.demo_room_id]
    assert [room.id for room in vlp.iter_rooms(page_size=1)] == [live_app.demo_room_id]
    room = vlp.get_room(live_app.demo_room_id)
    assert isinstance(room, Room) and room.fingerprint.status == "ready"
    fingerprint = vlp.get_fingerprint(room.id)
    assert (fingerprint.leds, fingerprint.grid_points) == (16, 400)
    assert vlp.list_fingerprints(room.id).items[0].version == fingerprint.version


def test_readiness_and_metrics(live_app: LiveApp) -> None:
    vlp = live_app.client(None)  # no key needed for operations
    assert vlp.is_ready()
    assert "vlp_jobs{" in vlp.metrics_text()


def test_downloads_a_matrix_as_npy_bytes(live_app: LiveApp) -> None:
    vlp = live_app.client(TERMINAL_KEY)
    gains = np.load(io.BytesIO(vlp.download_matrix(live_app.demo_room_id, "J")))
    assert gains.shape == (16, 400) and gains.dtype == np.float64 and (gains >= 0).all()


def test_simulate_then_localize_finds_the_terminals(live_app: LiveApp) -> None:
    vlp = live_app.client(TERMINAL_KEY)
    simulation = vlp.simulate(live_app.demo_room_id, targets=4, snr_db=40, seed=3)
    assert isinstance(simulation, Simulation) and len(simulation.truth) == 4
    located = vlp.localize(live_app.demo_room_id, simulation.measurement)
    assert isinstance(located, Localization) and located.targets == 4
    distances = [
        [math.hypot(t.x - e.x, t.y - e.y) for e in located.estimates] for t in simulation.truth
    ]
    rows, cols = linear_sum_assignment(distances)
    assert max(distances[r][c] for r, c in zip(rows, cols, strict=True)) < 0.3


def test_localize_batch_answers_each_item_in_order(live_app: LiveApp) -> None:
    vlp = live_app.client(TERMINAL_KEY)
    room_id = live_app.demo_room_id
    measurements = [vlp.simulate(room_id, targets=k, seed=k).measurement for k in (1, 3)]
    answers = vlp.localize_batch(room_id, [measurements[0], {"targets": 1}, measurements[1]])
    first, bad, last = answers.items
    assert isinstance(first, Localization) and isinstance(last, Localization)
    assert (first.targets, last.targets) == (1, 3)
    assert first.estimates == vlp.localize(room_id, measurements[0]).estimates
    assert isinstance(bad, Problem) and bad.status == 422
    assert bad.errors is not None and "body.items.1.power" in {e.field for e in bad.errors}


def test_create_waits_for_the_build_with_progress(live_app: LiveApp) -> None:
    vlp = live_app.client()
    room = vlp.create_room(_paper_room())
    assert room.fingerprint.job_id is not None and room.layout_version == 1
    seen: list[Job] = []
    ready = vlp.wait_for_room(room.id, timeout_s=90, on_progress=seen.append)
    assert ready.fingerprint.status == "ready" and ready.fingerprint.version == 1
    assert seen and seen[-1].status == "succeeded" and seen[-1].progress == 1.0
    job = vlp.wait_for_job(vlp.rebuild(room.id).id, timeout_s=90)
    assert job.result is not None and job.result["fingerprint_version"] == 2
    vlp.delete_room(room.id)
    with pytest.raises(NotFound):
        vlp.get_room(room.id)


def test_replace_needs_the_current_etag(live_app: LiveApp) -> None:
    vlp = live_app.client()
    room = vlp.create_room(_paper_room())
    etag = vlp.room_etag(room.id)
    renamed = vlp.replace_room(room.id, {**_paper_room(), "name": "Renamed"}, if_match=etag)
    assert renamed.name == "Renamed" and renamed.layout_version == 2
    with pytest.raises(PreconditionError) as stale:
        vlp.replace_room(room.id, _paper_room(), if_match=etag)
    assert stale.value.status == 412
    vlp.delete_room(room.id)


def test_problems_become_typed_errors(live_app: LiveApp) -> None:
    vlp = live_app.client()
    with pytest.raises(NotFound) as missing:
        vlp.get_room("no-such-room")
    assert missing.value.status == 404 and "no-such-room" in missing.value.detail
    assert missing.value.instance == "/v1/rooms/no-such-room"

    layout = _paper_room()
    layout["leds"] = [{"x": 0.5, "y": 0.5, "z": 5.0}]
    with pytest.raises(InvalidRequest) as invalid:
        vlp.create_room(layout)
    assert invalid.value.status == 422 and invalid.value.title == "Validation failed"
    assert [error.field for error in invalid.value.errors] == ["body.leds.0.z"]

    with pytest.raises(PermissionDenied) as denied:
        live_app.client(TERMINAL_KEY).create_room(_paper_room())
    assert denied.value.status == 403
    with pytest.raises(AuthenticationError):
        live_app.client(None).list_rooms()


def test_localize_before_any_fingerprint_is_a_conflict(live_app: LiveApp, tmp_path: Path) -> None:
    measurement = live_app.client().simulate(live_app.demo_room_id, targets=2, seed=1).measurement
    # No build workers: the new room stays `pending`, with no fingerprint to localize on.
    with (
        TestClient(create_app(make_settings(tmp_path))) as http,
        VLPClient(api_key=ADMIN_KEY, http_client=http) as vlp,
    ):
        room = vlp.create_room(_paper_room())
        with pytest.raises(Conflict) as conflict:
            # The measurement is typed (a Measurement): drop the demo room's version from it.
            vlp.localize(room.id, measurement.model_copy(update={"fingerprint_version": None}))
    assert conflict.value.status == 409 and conflict.value.title
