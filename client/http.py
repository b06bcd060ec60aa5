"""HTTP clients: :class:`Client` (blocking) and :class:`AsyncClient` (asyncio), over httpx."""

from __future__ import annotations

from typing import Any, Literal

import httpx
from pydantic import BaseModel
from pydantic import ValidationError as PydanticValidationError

from agilegs.schemas import codec
from agilegs.schemas.codec import GAUSSIAN_FILE_TYPES
from agilegs.schemas.requests import REQUEST_ID_HEADER

from ._ops import AsyncOperations, SyncOperations
from ._requests import Call, query_params
from ._retry import RETRY_WINDOW, retry_async, retry_sync
from .errors import ProtocolError, RequestTimeout, TransportError, error_from_body

__all__ = ["AsyncClient", "Client"]

Encoding = Literal["msgpack", "json"]


class _HTTPBase:
    """What both HTTP clients share; does no I/O."""

    def __init__(self, *, token: str | None, encoding: Encoding) -> None:
        if encoding not in ("msgpack", "json"):
            raise ValueError(f"encoding must be 'msgpack' or 'json', got {encoding!r}")
        self.kind = codec.MSGPACK if encoding == "msgpack" else codec.JSON
        self.headers = {"accept": self.kind}
        if token:
            self.headers["authorization"] = f"Bearer {token}"

    def _request_args(self, call: Call) -> dict[str, Any]:
        path = call.op.http_path
        if call.session is not None:
            path = path.replace("{session}", call.session)
        headers = dict(self.headers)
        if call.request_id is not None:
            headers[REQUEST_ID_HEADER] = call.request_id
        if call.file is not None:  # the file, else (an error) the body in our encoding
            headers["accept"] = f"{GAUSSIAN_FILE_TYPES[call.file]}, {self.kind};q=0.5"
        content = None
        params = call.params
        if call.body is not None and call.op.query:
            params = {**query_params(call.body), **(params or {})}
        elif call.body is not None:
            content = codec.dump(call.body, self.kind)
            headers["content-type"] = self.kind
        return {"method": call.op.http_method, "url": path, "content": content,
                "headers": headers, "params": params}

    def _response(self, call: Call, r: httpx.Response) -> BaseModel | bytes:
        kind = codec.media_type(r.headers.get("content-type")) or codec.JSON
        if r.status_code >= 400:
            raise error_from_body(r.status_code, r.content, kind)
        if call.file is not None:
            got = r.headers.get("content-type", "").split(";", 1)[0].strip().lower()
            if got != GAUSSIAN_FILE_TYPES[call.file]:
                raise ProtocolError(f"{call.op.name}: asked for a .{call.file} file, the server "
                                    f"answered {got or 'no type'}")
            return r.content
        try:
            return call.op.response.model_validate(codec.load(r.content, kind))
        except (codec.DecodeError, PydanticValidationError) as exc:
            raise ProtocolError(f"{call.op.name}: the server's answer does not match "
                                f"{call.op.response.__name__}: {exc}") from exc


class Client(_HTTPBase, SyncOperations):
    """Blocking HTTP client.

    Args:
        base_url: the server, e.g. ``http://127.0.0.1:8000``.
        token: bearer token (the server's ``AGILEGS_TOKEN``), if any.
        timeout: seconds per request (selections can take seconds on large pools).
        encoding: request and response bodies, ``"msgpack"`` (compact) or ``"json"``.
        transport: an httpx transport (e.g. ``httpx.MockTransport`` in tests).
        retry_window: seconds an operation answered ``session_unavailable`` with a
            ``retry_after`` (a fleet handing the session over) is retried, with backoff
            (:mod:`agilegs.client._retry`); 0: never.
    """

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        token: str | None = None,
        timeout: float = 120.0,
        encoding: Encoding = "msgpack",
        transport: httpx.BaseTransport | None = None,
        retry_window: float = RETRY_WINDOW,
    ) -> None:
        super().__init__(token=token, encoding=encoding)
        self._http = httpx.Client(base_url=base_url, timeout=timeout, transport=transport)
        self.retry_window = retry_window

    def _send(self, call: Call) -> BaseModel | bytes:
        call = call.with_request_id()
        return retry_sync(lambda: self._send_once(call), self.retry_window, call)

    def _send_once(self, call: Call) -> BaseModel | bytes:
        try:
            r = self._http.request(**self._request_args(call))
        except httpx.TimeoutException as exc:
            raise RequestTimeout(f"{call.op.name}: no answer in time ({exc})") from exc
        except httpx.TransportError as exc:
            raise TransportError(f"{call.op.name}: {exc}") from exc
        return self._response(call, r)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncClient(_HTTPBase, AsyncOperations):
    """asyncio HTTP client; the same arguments and methods as :class:`Client`."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        *,
        token: str | None = None,
        timeout: float = 120.0,
        encoding: Encoding = "msgpack",
        transport: httpx.AsyncBaseTransport | None = None,
        retry_window: float = RETRY_WINDOW,
    ) -> None:
        super().__init__(token=token, encoding=encoding)
        self._http = httpx.AsyncClient(base_url=base_url, timeout=timeout, transport=transport)
        self.retry_window = retry_window

    async def _send(self, call: Call) -> BaseModel | bytes:
        call = call.with_request_id()
        return await retry_async(lambda: self._send_once(call), self.retry_window, call)

    async def _send_once(self, call: Call) -> BaseModel | bytes:
        try:
            r = await self._http.request(**self._request_args(call))
        except httpx.TimeoutException as exc:
            raise RequestTimeout(f"{call.op.name}: no answer in time ({exc})") from exc
        except httpx.TransportError as exc:
            raise TransportError(f"{call.op.name}: {exc}") from exc
        return self._response(call, r)

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
