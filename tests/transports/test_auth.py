"""With a token, every HTTP request needs ``Authorization: Bearer <token>`` (in process; the
Zenoh side is in tests/e2e/test_zenoh.py)."""

from __future__ import annotations

from typing import Any

import pytest

from agilegs.client import AuthenticationError

TOKEN = "s3cret-token"


def test_every_request_without_the_token_gets_401(api_factory: Any) -> None:
    srv = api_factory(token=TOKEN)
    with srv.http() as h:
        for method, path in [("GET", "/healthz"), ("GET", "/v1/sessions"), ("GET", "/metrics"),
                             ("GET", "/docs"), ("GET", "/openapi.json"), ("POST", "/v1/sessions"),
                             ("DELETE", "/v1/sessions/x"), ("GET", "/nowhere")]:
            for headers in ({}, {"authorization": "Bearer wrong"}, {"authorization": TOKEN},
                            {"authorization": f"Basic {TOKEN}"}):
                r = h.request(method, path, headers=headers)
                assert r.status_code == 401, (method, path, headers)
                assert r.json()["error"]["code"] == "unauthorized"
                assert r.headers["www-authenticate"] == "Bearer"
        ok = h.get("/v1/sessions", headers={"authorization": f"Bearer {TOKEN}"})
        assert ok.status_code == 200
    with pytest.raises(AuthenticationError):
        srv.client().list_sessions()
    assert srv.client(token=TOKEN).list_sessions().sessions == []
