"""Two ``vlp serve`` processes on one PostgreSQL share tracks: a stream served by one carries
the updates posted through the other, and a reconnect with ``Last-Event-ID`` to either loses
nothing.

Each process reads the registry again only every 60 s without news (the longest setting), and
the stream's reads give up after 30 s of silence: an event that arrives at all arrived through
the PostgreSQL notification, not the fallback poll.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from app.client import TrackEvent, VLPClient
from app.vlp.fingerprints import build_fingerprint
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes
from tests.live_server import TERMINAL_KEY
from tests.processes import VlpProcess, process_fleet

from .steps import create_room, wait_succeeded

pytestmark = [pytest.mark.slow, pytest.mark.postgres]

SILENCE_S = 30.0
LONG_POLL = {"VLP_TRACK_STREAM_POLL_SECONDS": "60"}


def _post(api: VlpProcess, room_id: str, step: int) -> list[str]:
    """One tracked localize of two walkers through ``api``; their track ids."""
    layout = paper_layout()
    noise = noise_std_for_snr(build_fingerprint(layout), 30.0)
    positions = np.array([[1.0 + 0.1 * step, 1.0], [3.0, 3.0 - 0.1 * step]])
    amplitudes = noisy_amplitudes(layout, positions, noise, rng=step)
    body = {
        "terminals": [
            {"id": f"w{k}", "amplitudes": row.tolist()} for k, row in enumerate(amplitudes)
        ],
        "track": True,
    }
    with VLPClient(api.url, api_key=TERMINAL_KEY) as client:
        answer = client.localize(room_id, body)
    return [str(estimate.track_id) for estimate in answer.estimates]


def _follow(
    api: VlpProcess, room_id: str, after: int, sink: queue.Queue[TrackEvent | Exception]
) -> threading.Thread:
    def run() -> None:
        try:
            with VLPClient(api.url, api_key=TERMINAL_KEY) as client:
                for event in client.stream_tracks(
                    room_id, last_event_id=after, read_timeout_s=SILENCE_S
                ):
                    sink.put(event)
        except Exception as exc:  # the test's thread reports it
            sink.put(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def _take(sink: queue.Queue[TrackEvent | Exception], count: int) -> Iterator[TrackEvent]:
    for _ in range(count):
        item = sink.get(timeout=SILENCE_S + 10)
        if isinstance(item, Exception):
            raise item
        yield item


def test_a_stream_on_one_process_carries_updates_made_through_another(
    postgres_url: str, tmp_path: Path
) -> None:
    env = {"VLP_DATABASE_URL": postgres_url, "VLP_DEMO": "0"}
    with process_fleet(tmp_path / "data", **env) as fleet:
        apis = [
            fleet.serve({**LONG_POLL, "VLP_EMBEDDED_WORKERS": "1"}),
            fleet.serve({**LONG_POLL, "VLP_EMBEDDED_WORKERS": "0"}),
        ]
        room = create_room(apis[0], {**paper_layout().to_mapping(), "name": "fleet"})
        wait_succeeded(apis[0], room["fingerprint"]["job_id"])
        room_id = str(room["id"])

        sink: queue.Queue[TrackEvent | Exception] = queue.Queue()
        _follow(apis[1], room_id, 0, sink)
        posted = [_post(apis[0], room_id, step) for step in range(3)]
        seen = list(_take(sink, 6))  # two tracks changed per post
        assert [e.sequence for e in seen] == list(range(1, 7))
        # Each post's two events come together (their order among themselves is the tracks').
        assert [{e.track_id for e in seen[k : k + 2]} for k in (0, 2, 4)] == [
            set(ids) for ids in posted
        ]
        assert all(e.kind == "track" and e.track is not None for e in seen)

        # Posts through the other process while nobody listens, then resume on the first.
        missed = [_post(apis[1], room_id, step) for step in range(3, 5)]
        resumed_sink: queue.Queue[TrackEvent | Exception] = queue.Queue()
        _follow(apis[0], room_id, seen[-1].sequence, resumed_sink)
        resumed = list(_take(resumed_sink, 4))
        assert [e.sequence for e in resumed] == list(range(7, 11))
        assert [{e.track_id for e in resumed[k : k + 2]} for k in (0, 2)] == [
            set(ids) for ids in missed
        ]
        assert all(e.track is not None and e.track.updates == 5 for e in resumed[2:])
