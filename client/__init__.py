"""agilegs.client: the torch-free client SDK.

:class:`Client` (blocking) and :class:`AsyncClient` (asyncio) speak HTTP through httpx;
:class:`ZenohClient` speaks Zenoh (``pip install 'agilegs[zenoh]'``). All three offer the same
methods, named after the operations (``create_session``, ``set_pool``, ``select``,
``commit``, ``add_observations``, ...), take numpy arrays or :mod:`agilegs.schemas` models,
return :mod:`agilegs.schemas` models (``Pose.to_matrix()``, ``PoolOut.matrices()``,
``InformationOut.arrays()`` give numpy), and raise the exceptions of
:mod:`agilegs.client.errors`.

Example::

    from agilegs.client import Client

    with Client("http://127.0.0.1:8000") as c:
        c.create_session({"fx": 60, "fy": 60, "cx": 32, "cy": 32, "width": 64, "height": 64},
                         id="scene", gaussians="scene.splat")
        c.set_pool("scene", poses)                     # [D, 4, 4] camera-to-world, OpenCV axes
        d = c.select("scene", method="agile", commit=True)
        next_pose = d.chosen.pose.to_matrix()
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .errors import (
    AgileGSError,
    APIError,
    AuthenticationError,
    BadRequestError,
    ConflictError,
    InsufficientStorageError,
    LimitExceededError,
    NotFoundError,
    PayloadTooLargeError,
    ProtocolError,
    RequestTimeout,
    ServerError,
    SessionDamagedError,
    SessionUnavailableError,
    TooManyError,
    TransportError,
    ValidationError,
)
from .http import AsyncClient, Client

if TYPE_CHECKING:
    from .zenoh_client import ZenohClient

__all__ = [
    "APIError",
    "AgileGSError",
    "AsyncClient",
    "AuthenticationError",
    "BadRequestError",
    "Client",
    "ConflictError",
    "InsufficientStorageError",
    "NotFoundError",
    "LimitExceededError",
    "PayloadTooLargeError",
    "ProtocolError",
    "RequestTimeout",
    "ServerError",
    "SessionDamagedError",
    "SessionUnavailableError",
    "TooManyError",
    "TransportError",
    "ValidationError",
    "ZenohClient",
]


def __getattr__(name: str) -> Any:
    # ZenohClient is imported on first use, so that the HTTP clients need no zenoh install
    if name == "ZenohClient":
        from .zenoh_client import ZenohClient

        return ZenohClient
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
