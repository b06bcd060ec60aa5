"""With AGILEGS_TOKEN set, every request needs the bearer token (HTTP and Zenoh)."""

from __future__ import annotations

from typing import Any

import httpx
import pytest

from agilegs.client import AuthenticationError, Client

TOKEN = "s3cret-token"


def test_every_request_without_the_token_gets_401(server_factory: Any) -> None:
    srv = server_factory(env={"AGILEGS_TOKEN": TOKEN}).start()
    for method, path in [("GET", "/healthz"), ("GET", "/v1/sessions"), ("GET", "/metrics"),
                         ("GET", "/docs"), ("GET", "/openapi.json"), ("POST", "/v1/sessions"),
                         ("DELETE", "/v1/sessions/x"), ("GET", "/nowhere")]:
        for headers in ({}, {"authorization": "Bearer wrong"}, {"authorization": TOKEN},
                        {"authorization": f"Basic {TOKEN}"}):
            r = httpx.request(method, srv.url + path, headers=headers)
            assert r.status_code == 401, (method, path, headers)
            assert r.json()["error"]["code"] == "unauthorized"
            assert r.headers["www-authenticate"] == "Bearer"
    ok = httpx.get(srv.url + "/v1/sessions", headers={"authorization": f"Bearer {TOKEN}"})
    assert ok.status_code == 200
    with pytest.raises(AuthenticationError):
        Client(srv.url).list_sessions()
    assert Client(srv.url, token=TOKEN).list_sessions().sessions == []

    from agilegs.client import ZenohClient

    with pytest.raises(AuthenticationError):
        ZenohClient([srv.zenoh_endpoint], token="wrong")
    with ZenohClient([srv.zenoh_endpoint], token=TOKEN) as z:
        assert z.list_sessions().sessions == []
