"""The client's methods for a room's tracks, and the events of its live stream."""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any, TypeVar

import httpx
from pydantic import BaseModel

from app.schemas import (
    AccuracyMap,
    Track,
    TrackingSettings,
    TrackPointsPage,
    TracksPage,
)

from ._errors import TransportError, api_error_from_answer

__all__ = ["TrackEvent", "TrackMethods"]

_Model = TypeVar("_Model", bound=BaseModel)


@dataclass(frozen=True)
class TrackEvent:
    """One event of a room's track stream.

    ``kind`` is ``"track"`` (``track`` holds the track as it is now) or ``"removed"``
    (``track_id`` ended); ``sequence`` is the room's event number (resume after it with
    ``last_event_id``).
    """

    kind: str
    sequence: int
    track_id: str
    track: Track | None


def _events(lines: Iterator[str]) -> Iterator[TrackEvent]:
    """Server-Sent Events (``event``, ``id``, ``data`` fields; comments skipped)."""
    kind, event_id = "message", ""
    data: list[str] = []
    for line in lines:
        if line == "":
            if data and event_id.isdigit():
                payload = json.loads("\n".join(data))
                track = Track.model_validate(payload) if kind == "track" else None
                yield TrackEvent(kind, int(event_id), str(payload["id"]), track)
            kind, event_id, data = "message", "", []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "event":
            kind = value
        elif name == "id":
            event_id = value
        elif name == "data":
            data.append(value)


class TrackMethods:
    """Tracks of a room (mixed into :class:`~app.client.VLPClient`)."""

    _http: httpx.Client
    _headers: dict[str, str]

    if TYPE_CHECKING:

        def request(
            self,
            method: str,
            path: str,
            *,
            json: Any = None,
            params: Mapping[str, Any] | None = None,
            headers: Mapping[str, str] | None = None,
        ) -> httpx.Response: ...

        def _get(self, path: str, model: type[_Model], **params: Any) -> _Model: ...

    def list_tracks(
        self,
        room_id: str,
        *,
        status: list[str] | None = None,
        limit: int = 100,
        cursor: str | None = None,
    ) -> TracksPage:
        """A page of the room's tracks (default statuses: tentative and confirmed)."""
        params: dict[str, Any] = {"limit": limit}
        if status:
            params["status"] = status
        if cursor:
            params["cursor"] = cursor
        return TracksPage.model_validate(
            self.request("GET", f"/v1/rooms/{room_id}/tracks", params=params).json()
        )

    def get_track(self, room_id: str, track_id: str) -> Track:
        """One track."""
        return self._get(f"/v1/rooms/{room_id}/tracks/{track_id}", Track)

    def track_points(
        self,
        room_id: str,
        track_id: str,
        *,
        since: datetime | None = None,
        limit: int = 1000,
        cursor: str | None = None,
    ) -> TrackPointsPage:
        """A page of a track's history, oldest first (from ``since`` on)."""
        params: dict[str, Any] = {"limit": limit}
        if since is not None:
            params["since"] = since.isoformat()
        if cursor:
            params["cursor"] = cursor
        return TrackPointsPage.model_validate(
            self.request(
                "GET", f"/v1/rooms/{room_id}/tracks/{track_id}/points", params=params
            ).json()
        )

    def delete_track(self, room_id: str, track_id: str) -> None:
        """End a track now (admin)."""
        self.request("DELETE", f"/v1/rooms/{room_id}/tracks/{track_id}")

    def tracking_settings(self, room_id: str) -> TrackingSettings:
        """The room's tracking settings in force."""
        return self._get(f"/v1/rooms/{room_id}/tracking", TrackingSettings)

    def update_tracking_settings(self, room_id: str, **fields: Any) -> TrackingSettings:
        """Change some of the room's tracking settings (admin; ``None`` restores a default)."""
        answer = self.request("PUT", f"/v1/rooms/{room_id}/tracking", json=fields)
        return TrackingSettings.model_validate(answer.json())

    def accuracy_map(self, room_id: str) -> AccuracyMap:
        """The room's single-terminal accuracy bound on blocks of its grid."""
        return self._get(f"/v1/rooms/{room_id}/tracking/accuracy", AccuracyMap)

    def stream_tracks(
        self, room_id: str, *, last_event_id: int | None = None, read_timeout_s: float = 60.0
    ) -> Iterator[TrackEvent]:
        """Follow the room's tracks: events as they come, until the caller stops iterating.

        Without ``last_event_id`` the stream opens with the current tracks; with it, it
        resumes after that event (nothing kept is missed). ``read_timeout_s`` bounds a silence
        (the service sends a comment every 15 s).
        """
        headers = {**self._headers, "Accept": "text/event-stream"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = str(last_event_id)
        timeout = httpx.Timeout(self._http.timeout.connect, read=read_timeout_s)
        path = f"/v1/rooms/{room_id}/tracks/stream"
        try:
            with self._http.stream("GET", path, headers=headers, timeout=timeout) as response:
                if response.is_error:
                    response.read()
                    try:
                        body = response.json()
                    except ValueError:
                        body = None
                    raise api_error_from_answer(response.status_code, body, response.reason_phrase)
                yield from _events(response.iter_lines())
        except httpx.HTTPError as exc:
            raise TransportError(f"GET {path}: {exc}") from exc
