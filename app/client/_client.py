"""The synchronous VLP client over httpx."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from types import TracebackType
from typing import Any, Self, TypeVar

import httpx
from pydantic import BaseModel

from app.schemas import (
    ApiKeyCreated,
    ApiKeysList,
    Fingerprint,
    FingerprintsList,
    Localization,
    LocalizationBatch,
    Measurement,
    Room,
    RoomLayout,
    RoomsPage,
    Simulation,
    SimulationRequest,
)

from ._errors import APIError, JobFailed, JobTimeout, TransportError, api_error_from_answer
from ._models import Epoch, Job
from ._tracks import TrackMethods

__all__ = ["DEFAULT_TIMEOUT_S", "ProgressCallback", "VLPClient"]

DEFAULT_TIMEOUT_S = 30.0
ProgressCallback = Callable[[Job], None]
_Model = TypeVar("_Model", bound=BaseModel)
Body = BaseModel | Mapping[str, Any]


def _json_body(body: Body) -> Any:
    if isinstance(body, BaseModel):
        return body.model_dump(mode="json", exclude_unset=True)
    return dict(body)


class VLPClient(TrackMethods):
    """A typed client of the VLP service (``/v1``).

    Every method sends one request (``wait_for_*`` poll) and returns the answer parsed into
    a model; an error answer raises the matching :class:`~app.client.APIError` subclass,
    no answer raises :class:`~app.client.TransportError`.

    Parameters
    ----------
    base_url : str, default="http://127.0.0.1:8000"
        The service's root URL.
    api_key : str or None
        Sent as ``X-API-Key``; the admin role may do everything, terminals read, simulate
        and localize.
    timeout_s : float, default=30.0
        Per-request timeout in seconds (connect, read, write, pool).
    transport : httpx.BaseTransport, optional
        A custom transport (tests use ``httpx.MockTransport``).
    http_client : httpx.Client, optional
        Use this client instead of making one (e.g. a Starlette ``TestClient``); it is not
        closed by :meth:`close`.

    Examples
    --------
    >>> with VLPClient("http://127.0.0.1:8000", api_key="...") as vlp:  # doctest: +SKIP
    ...     room = vlp.list_rooms().items[0]
    ...     sim = vlp.simulate(room.id, targets=8, snr_db=30, seed=7)
    ...     located = vlp.localize(room.id, sim.measurement)
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        api_key: str | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        transport: httpx.BaseTransport | None = None,
        http_client: httpx.Client | None = None,
    ) -> None:
        self._headers = {"X-API-Key": api_key} if api_key else {}
        self._owns_http = http_client is None
        self._http = http_client or httpx.Client(
            base_url=base_url, timeout=timeout_s, transport=transport
        )

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection pool (unless the httpx client was passed in)."""
        if self._owns_http:
            self._http.close()

    # -- plumbing ---------------------------------------------------------------------------

    def request(
        self,
        method: str,
        path: str,
        *,
        json: Any = None,
        params: Mapping[str, Any] | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> httpx.Response:
        """Send one request; raise the mapped error on a 4xx/5xx answer or no answer."""
        try:
            response = self._http.request(
                method,
                path,
                json=json,
                params=params,
                headers={**self._headers, **(headers or {})},
            )
        except httpx.TimeoutException as exc:
            raise TransportError(f"{method} {path}: timed out ({exc})") from exc
        except httpx.HTTPError as exc:
            raise TransportError(f"{method} {path}: {exc}") from exc
        if response.is_error:
            try:
                body = response.json()
            except ValueError:
                body = None
            raise api_error_from_answer(response.status_code, body, response.reason_phrase)
        return response

    def _get(self, path: str, model: type[_Model], **params: Any) -> _Model:
        answer = self.request("GET", path, params=params or None)
        return model.model_validate(answer.json())

    def _post(self, path: str, model: type[_Model], body: Any = None) -> _Model:
        return model.model_validate(self.request("POST", path, json=body).json())

    # -- operations -------------------------------------------------------------------------

    def is_ready(self) -> bool:
        """Whether the service answers ``/readyz`` with 200 (its registry is reachable).

        An error answer or no answer is ``False``; this never raises.
        """
        try:
            self.request("GET", "/readyz")
        except (APIError, TransportError):
            return False
        return True

    def metrics_text(self) -> str:
        """The Prometheus exposition text of ``/metrics``."""
        return self.request("GET", "/metrics").text

    # -- rooms ------------------------------------------------------------------------------

    def list_rooms(self, *, limit: int = 20, cursor: str | None = None) -> RoomsPage:
        """One page of rooms, oldest first (``next_cursor`` leads on)."""
        params: dict[str, Any] = {"limit": limit}
        if cursor is not None:
            params["cursor"] = cursor
        return self._get("/v1/rooms", RoomsPage, **params)

    def iter_rooms(self, *, page_size: int = 100) -> Iterator[Room]:
        """Every room, following the pages."""
        cursor: str | None = None
        while True:
            page = self.list_rooms(limit=page_size, cursor=cursor)
            yield from page.items
            if page.next_cursor is None:
                return
            cursor = page.next_cursor

    def get_room(self, room_id: str) -> Room:
        """The room with its fingerprint state."""
        return self._get(f"/v1/rooms/{room_id}", Room)

    def room_etag(self, room_id: str) -> str:
        """The room's current ``ETag`` (for :meth:`replace_room`)."""
        return self.request("GET", f"/v1/rooms/{room_id}").headers["ETag"]

    def create_room(self, layout: RoomLayout | Mapping[str, Any]) -> Room:
        """Create a room (admin); its first fingerprint build is queued."""
        return self._post("/v1/rooms", Room, _json_body(layout))

    def replace_room(
        self, room_id: str, layout: RoomLayout | Mapping[str, Any], *, if_match: str
    ) -> Room:
        """Replace a room's layout (admin); ``if_match`` is the ETag the change is based on."""
        answer = self.request(
            "PUT", f"/v1/rooms/{room_id}", json=_json_body(layout), headers={"If-Match": if_match}
        )
        return Room.model_validate(answer.json())

    def delete_room(self, room_id: str) -> None:
        """Delete a room with its fingerprints and jobs (admin)."""
        self.request("DELETE", f"/v1/rooms/{room_id}")

    def room_map_png(self, room_id: str) -> bytes:
        """The room plan as a PNG picture (LEDs, grid, coverage)."""
        return self.request("GET", f"/v1/rooms/{room_id}/map.png").content

    # -- fingerprints and jobs --------------------------------------------------------------

    def list_fingerprints(self, room_id: str) -> FingerprintsList:
        """The room's fingerprint versions, newest first."""
        return self._get(f"/v1/rooms/{room_id}/fingerprints", FingerprintsList)

    def get_fingerprint(self, room_id: str, version: int | str = "current") -> Fingerprint:
        """Metadata of one fingerprint version (``"current"``: the one localization uses)."""
        return self._get(f"/v1/rooms/{room_id}/fingerprints/{version}", Fingerprint)

    def download_matrix(self, room_id: str, matrix: str, version: int | str = "current") -> bytes:
        """A fingerprint matrix (``H``, ``J`` or ``psi``) as the bytes of a ``.npy`` file."""
        path = f"/v1/rooms/{room_id}/fingerprints/{version}/{matrix}.npy"
        return self.request("GET", path).content

    def download_sparse_gains(self, room_id: str, version: int | str = "current") -> bytes:
        """A large room's sparse ``H`` as the bytes of a ``.npz`` file (``scipy.sparse``)."""
        path = f"/v1/rooms/{room_id}/fingerprints/{version}/H.npz"
        return self.request("GET", path).content

    def rebuild(self, room_id: str) -> Job:
        """Queue a fingerprint build of the room's current layout (admin)."""
        return self._post(f"/v1/rooms/{room_id}/fingerprints", Job)

    def get_job(self, job_id: str) -> Job:
        """A background job's state."""
        return self._get(f"/v1/jobs/{job_id}", Job)

    def wait_for_job(
        self,
        job_id: str,
        *,
        timeout_s: float = 300.0,
        poll_s: float = 0.2,
        on_progress: ProgressCallback | None = None,
    ) -> Job:
        """Poll a job until it has finished.

        Parameters
        ----------
        job_id : str
            The job to watch.
        timeout_s : float, default=300.0
            Give up after this many seconds.
        poll_s : float, default=0.2
            Pause between polls, seconds.
        on_progress : callable, optional
            Called with the job after every poll (including the last).

        Returns
        -------
        Job
            The succeeded job.

        Raises
        ------
        JobFailed
            The job ended `failed` (its ``error`` says why).
        JobTimeout
            It had not finished after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.get_job(job_id)
            if on_progress is not None:
                on_progress(job)
            if job.status == "succeeded":
                return job
            if job.status == "failed":
                raise JobFailed(f"job {job_id} failed: {job.error}", job)
            if time.monotonic() >= deadline:
                raise JobTimeout(f"job {job_id} still {job.status} after {timeout_s} s", job)
            time.sleep(poll_s)

    def wait_for_room(
        self,
        room_id: str,
        *,
        timeout_s: float = 300.0,
        poll_s: float = 0.2,
        on_progress: ProgressCallback | None = None,
    ) -> Room:
        """Wait for the room's latest fingerprint build; the room once it is ready.

        ``on_progress`` sees the build job at least once, in its final state last.
        Raises :class:`JobFailed` when the latest build failed.
        """
        room = self.get_room(room_id)
        if room.fingerprint.job_id is not None:
            self.wait_for_job(
                room.fingerprint.job_id,
                timeout_s=timeout_s,
                poll_s=poll_s,
                on_progress=on_progress,
            )
            room = self.get_room(room_id)
        return room

    # -- localization -----------------------------------------------------------------------

    def localize(self, room_id: str, measurement: Measurement | Mapping[str, Any]) -> Localization:
        """Locate the targets behind an aggregated measurement."""
        return self._post(f"/v1/rooms/{room_id}/localize", Localization, _json_body(measurement))

    def localize_batch(
        self, room_id: str, measurements: Sequence[Measurement | Mapping[str, Any]]
    ) -> LocalizationBatch:
        """Locate the targets behind up to 1000 measurements of one room in one request.

        The answer's ``items`` are in the order of ``measurements``: each a
        :class:`~app.schemas.Localization`, or the :class:`~app.schemas.Problem` (with its
        ``status``) that a single :meth:`localize` of that measurement would have raised.
        """
        body = {"items": [_json_body(measurement) for measurement in measurements]}
        return self._post(f"/v1/rooms/{room_id}/localize/batch", LocalizationBatch, body)

    def simulate(
        self,
        room_id: str,
        request: SimulationRequest | Mapping[str, Any] | None = None,
        **fields: Any,
    ) -> Simulation:
        """Simulate a measurement with its ground truth.

        Pass a whole ``request`` or its fields as keywords, e.g.
        ``simulate(room_id, targets=8, snr_db=30, seed=7)``.
        """
        body = _json_body(request) if request is not None else {}
        body.update(fields)
        return self._post(f"/v1/rooms/{room_id}/simulate", Simulation, body)

    # -- epochs -----------------------------------------------------------------------------

    def create_epoch(self, room_id: str, **options: Any) -> Epoch:
        """Open a cooperation window (``model``, ``targets``, ``solver``, ``min_terminals``,
        ``window_s``; all optional)."""
        return self._post(f"/v1/rooms/{room_id}/epochs", Epoch, options)

    def post_epoch_measurement(
        self,
        room_id: str,
        epoch_id: str,
        *,
        terminal_id: str,
        amplitudes: Sequence[float | None],
        detection_floor: float | None = None,
    ) -> None:
        """One terminal's amplitudes for an open epoch (posting again replaces them); None for
        an LED it did not detect, with its ``detection_floor`` when it knows it."""
        body: dict[str, Any] = {"terminal_id": terminal_id, "amplitudes": list(amplitudes)}
        if detection_floor is not None:
            body["detection_floor"] = detection_floor
        self.request("POST", f"/v1/rooms/{room_id}/epochs/{epoch_id}/measurements", json=body)

    def solve_epoch(self, room_id: str, epoch_id: str) -> Epoch:
        """Close the window now and solve it."""
        return self._post(f"/v1/rooms/{room_id}/epochs/{epoch_id}/solve", Epoch)

    def get_epoch(self, room_id: str, epoch_id: str) -> Epoch:
        """An epoch's state (and its localization once solved)."""
        return self._get(f"/v1/rooms/{room_id}/epochs/{epoch_id}", Epoch)

    # -- calibration ------------------------------------------------------------------------

    def calibrate(
        self,
        room_id: str,
        survey: Sequence[Mapping[str, Any]],
        *,
        masked_leds: Sequence[int] | None = None,
    ) -> Job:
        """Queue a calibration from survey rows ``{"x", "y", "led", "amplitude"}`` (admin)."""
        body: dict[str, Any] = {"survey": [dict(row) for row in survey]}
        if masked_leds is not None:
            body["masked_leds"] = list(masked_leds)
        return self._post(f"/v1/rooms/{room_id}/calibrations", Job, body)

    def get_calibration(self, room_id: str, calibration_id: str) -> dict[str, Any]:
        """A calibration's report."""
        report: dict[str, Any] = self.request(
            "GET", f"/v1/rooms/{room_id}/calibrations/{calibration_id}"
        ).json()
        return report

    # -- API keys (admin) -------------------------------------------------------------------

    def create_key(self, role: str, label: str) -> ApiKeyCreated:
        """A new key; its secret (``.key``) is in this answer only."""
        return self._post("/v1/keys", ApiKeyCreated, {"role": role, "label": label})

    def list_keys(self) -> ApiKeysList:
        """The keys in force, without their secrets."""
        return self._get("/v1/keys", ApiKeysList)

    def revoke_key(self, key_id: str) -> None:
        """Revoke a key by its id (every API process refuses it within 2 s)."""
        self.request("DELETE", f"/v1/keys/{key_id}")
