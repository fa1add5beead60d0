"""The REST app's answer to a failure nobody foresaw: a 500 with the usual error shape (and the
exception still raised to the server, which logs it), not Starlette's plain-text page."""

from __future__ import annotations

from types import SimpleNamespace

from fastapi.testclient import TestClient

from renderfarm.api.rest import create_app
from renderfarm.app.auth import Authenticator
from renderfarm.infra.config import Settings


class NoTokens:
    async def live_token_count(self):
        return 0


class BrokenFarm:
    """Answers the workers list with an exception no handler knows."""

    def __init__(self, tmp_path):
        self.settings = Settings(data_dir=tmp_path)
        self.store = NoTokens()

    def workers(self):
        raise KeyError("a bug")


def test_an_unexpected_exception_is_a_500_with_detail_and_field(tmp_path):
    farm = BrokenFarm(tmp_path)
    app = create_app(farm, SimpleNamespace(), auth=Authenticator(farm.store, loopback_only=True))
    with TestClient(app, raise_server_exceptions=False) as client:
        r = client.get("/api/v1/workers")
    assert r.status_code == 500
    assert r.headers["content-type"] == "application/json"
    assert r.json() == {"detail": "internal server error", "field": ""}
