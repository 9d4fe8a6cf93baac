"""The delay from a tracked POST on one ``vlp serve`` to its event on another's stream.

Both processes share one PostgreSQL (a fresh schema of the given database, dropped after);
the first seeds and builds the demo room. One terminal posts its amplitudes with
``track: true`` to the first process, one post at a time; a thread follows the room's stream
on the second. A post's event is the one whose track has the id and the filtered position of
the post's answer (other events, such as a track marked lost after a stall, answer no post):
the delay is from sending the POST to receiving its event (the POST's own solve included).
"""

from __future__ import annotations

import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import psycopg
from sqlalchemy import make_url

from app.client import TransportError, VLPClient
from app.vlp.fingerprints import build_fingerprint
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes

from ._server import TERMINAL_KEY, live_server, ready_demo_room

__all__ = ["stream_latencies_ms"]

_PAUSE_S = 0.05
_SILENCE_S = 30.0
# How long a server may take to start (the first builds the demo room; a shared machine is slow).
_START_S = 600.0


def _schema_url(url: str, schema: str) -> str:
    return (
        make_url(url)
        .update_query_dict({"options": f"-csearch_path={schema}"})
        .render_as_string(hide_password=False)
    )


def _admin(url: str) -> psycopg.Connection[tuple[object, ...]]:
    parsed = make_url(url)
    return psycopg.connect(
        host=parsed.host or "127.0.0.1",
        port=parsed.port or 5432,
        dbname=parsed.database or "postgres",
        user=parsed.username or "postgres",
        password=parsed.password,
        autocommit=True,
    )


def stream_latencies_ms(url: str, posts: int) -> list[float]:
    """Delays of ``posts`` tracked POSTs to their events on the other process, milliseconds."""
    schema = f"bench_{uuid.uuid4().hex[:12]}"
    with _admin(url) as admin:
        admin.execute(f'CREATE SCHEMA "{schema}"')
    try:
        return _measure(_schema_url(url, schema), posts)
    finally:
        with _admin(url) as admin:
            admin.execute(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE')


def _measure(database_url: str, posts: int) -> list[float]:
    layout = paper_layout()
    noise = noise_std_for_snr(build_fingerprint(layout), 30.0)
    with (
        tempfile.TemporaryDirectory() as first_dir,
        tempfile.TemporaryDirectory() as second_dir,
        live_server(
            Path(first_dir), timeout_s=_START_S, VLP_DATABASE_URL=database_url, VLP_DEMO="1"
        ) as first,
    ):
        room_id = ready_demo_room(first.url)
        with live_server(
            Path(second_dir),
            timeout_s=_START_S,
            VLP_DATABASE_URL=database_url,
            VLP_DEMO="0",
            VLP_EMBEDDED_WORKERS="0",
        ) as second:
            received = _Arrivals()

            def follow() -> None:
                with VLPClient(second.url, api_key=TERMINAL_KEY) as client:
                    try:
                        for event in client.stream_tracks(
                            room_id, last_event_id=0, read_timeout_s=_SILENCE_S
                        ):
                            if event.track is not None:
                                received.add((event.track_id, event.track.x, event.track.y))
                    except TransportError:
                        # The server stops when the measurement is done: the stream ends
                        # mid-read; a delay it did not deliver is waited for above.
                        return

            threading.Thread(target=follow, daemon=True).start()
            delays = []
            with VLPClient(first.url, api_key=TERMINAL_KEY) as client:
                for k in range(posts + 1):
                    amplitudes = noisy_amplitudes(layout, np.array([[2.0, 2.0]]), noise, rng=k)
                    body = {
                        "terminals": [{"id": "t1", "amplitudes": amplitudes[0].tolist()}],
                        "track": True,
                    }
                    sent = time.perf_counter()
                    estimate = client.localize(room_id, body).estimates[0]
                    if estimate.track_id is None or estimate.tracked is None:
                        raise RuntimeError("a tracked POST was answered without its track")
                    arrived = received.wait(
                        (estimate.track_id, estimate.tracked.x, estimate.tracked.y), _SILENCE_S
                    )
                    if k:  # the first also waits for the stream to connect
                        delays.append(1e3 * (arrived - sent))
                    time.sleep(_PAUSE_S)
            return delays


class _Arrivals:
    """When each track state (id, x, y) arrived on the stream (``perf_counter``)."""

    def __init__(self) -> None:
        self._times: dict[tuple[str, float, float], float] = {}
        self._changed = threading.Condition()

    def add(self, state: tuple[str, float, float]) -> None:
        with self._changed:
            self._times.setdefault(state, time.perf_counter())
            self._changed.notify_all()

    def wait(self, state: tuple[str, float, float], timeout_s: float) -> float:
        """When ``state`` arrived, waiting for it up to ``timeout_s`` (TimeoutError)."""
        with self._changed:
            if not self._changed.wait_for(lambda: state in self._times, timeout_s):
                raise TimeoutError(f"no event for track state {state} within {timeout_s:g} s")
            return self._times[state]
