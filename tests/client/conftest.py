"""Client fixtures: the real app in-process, reached through a Starlette TestClient."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from app.client import VLPClient
from app.main import create_app
from tests.api.conftest import ADMIN_KEY, TERMINAL_KEY, TestClient, make_settings

__all__ = ["ADMIN_KEY", "TERMINAL_KEY", "LiveApp"]


class LiveApp:
    """The running test app and the demo room's id."""

    def __init__(self, http: TestClient, demo_room_id: str) -> None:
        self.http = http
        self.demo_room_id = demo_room_id

    def client(self, api_key: str | None = ADMIN_KEY) -> VLPClient:
        """A VLPClient over the in-process app with ``api_key``."""
        return VLPClient(api_key=api_key, http_client=self.http)


@pytest.fixture(scope="module")
def live_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveApp]:
    """An app with one build worker whose demo (paper) room is ready."""
    settings = make_settings(tmp_path_factory.mktemp("client"), demo=True, embedded_workers=1)
    with TestClient(create_app(settings)) as http:
        vlp = VLPClient(api_key=ADMIN_KEY, http_client=http)
        room = vlp.list_rooms().items[0]
        vlp.wait_for_room(room.id, timeout_s=90)
        yield LiveApp(http, room.id)
