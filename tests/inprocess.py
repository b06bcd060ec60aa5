"""An agilegs server in this process: the FastAPI app (its lifespan run) behind a synchronous
httpx transport, so that ``Client(..., transport=...)`` and plain ``httpx.Client`` tests need
no subprocess and no port."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import anyio.from_thread
import httpx

from agilegs.client import Client
from agilegs.service.server import Server
from agilegs.service.settings import Settings
from agilegs.service.transports.http.app import create_app

BASE_URL = "http://agilegs.test"


class ASGIThreadTransport(httpx.BaseTransport):
    """Runs an ASGI app on an event loop in a helper thread; each request is handed to
    ``httpx.ASGITransport`` there. Several threads may send requests at once."""

    def __init__(self, app: Any, portal: Any) -> None:
        self._asgi = httpx.ASGITransport(app=app)
        self._portal = portal

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        content = request.read()

        async def send() -> tuple[int, list[tuple[bytes, bytes]], bytes]:
            req = httpx.Request(request.method, request.url, headers=request.headers,
                                content=content)
            resp = await self._asgi.handle_async_request(req)
            body = await resp.aread()
            return resp.status_code, resp.headers.raw, body

        status, headers, body = self._portal.call(send)
        return httpx.Response(status, headers=headers, content=body)


class InProcess:
    """A started in-process server: ``server`` (its sessions, gateway, metrics), ``app``,
    ``transport``; ``client()`` gives an SDK client, ``http()`` a plain httpx client."""

    def __init__(self, server: Server, app: Any, transport: ASGIThreadTransport) -> None:
        self.server = server
        self.app = app
        self.transport = transport
        self.url = BASE_URL

    def client(self, **kwargs: Any) -> Client:
        return Client(BASE_URL, transport=self.transport, **kwargs)

    def http(self, **kwargs: Any) -> httpx.Client:
        return httpx.Client(base_url=BASE_URL, transport=self.transport, **kwargs)


@contextmanager
def serve_in_process(state_dir: Path, **settings: Any) -> Iterator[InProcess]:
    """An agilegs server on ``state_dir`` in this process (HTTP only; the mapper off unless
    ``mapper=True``; no warm-up unless ``warmup=True``), started and, on exit, stopped."""
    settings.setdefault("zenoh", False)
    settings.setdefault("mapper", False)
    settings.setdefault("workers", 4)
    settings.setdefault("warmup", False)
    server = Server(Settings(state_dir=state_dir, **settings))
    app = create_app(server)
    with anyio.from_thread.start_blocking_portal() as portal:
        with portal.wrap_async_context_manager(app.router.lifespan_context(app)):
            yield InProcess(server, app, ASGIThreadTransport(app, portal))
