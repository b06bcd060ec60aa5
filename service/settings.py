"""The server's settings: one object, read from ``AGILEGS_*`` environment variables and
overridden by ``agilegs serve`` flags.

Every field is settable as ``AGILEGS_<FIELD>`` (e.g. ``AGILEGS_PORT=8001``,
``AGILEGS_ZENOH_LISTEN=tcp/127.0.0.1:7447,tcp/[::1]:7447``, ``AGILEGS_TOKEN=...``); lists
are comma-separated (or JSON).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

__all__ = ["Settings"]

log = logging.getLogger(__name__)

Endpoints = Annotated[list[str], NoDecode]


class Settings(BaseSettings):
    """Server settings (defaults documented per field)."""

    model_config = SettingsConfigDict(env_prefix="AGILEGS_", extra="ignore")

    host: str = Field(default="127.0.0.1", description="HTTP bind address")
    port: int = Field(default=8000, ge=0, le=65535, description="HTTP port (0: any free port)")
    state_dir: Path = Field(default=Path("agilegs-state"), description="persistent state folder")
    http: bool = Field(default=True, description="serve over HTTP")
    zenoh: bool = Field(default=True, description="serve over Zenoh as well")
    zenoh_listen: Endpoints = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"], description="Zenoh listen endpoints"
    )
    zenoh_connect: Endpoints = Field(default_factory=list, description="Zenoh peers to connect")
    # several instances (see agilegs.service.cluster)
    zenoh_mode: Literal["peer", "client", "router"] = Field(
        default="peer", description="Zenoh mode: peer, or client of a router (zenohd)"
    )
    instance_id: str | None = Field(
        default=None, pattern=r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$",
        description="this instance's id in a cluster (default: <hostname>-<port>)",
    )
    forward_timeout: float = Field(
        default=120.0, gt=0, description="seconds an operation forwarded to another instance "
                                         "may take"
    )
    token: SecretStr | None = Field(
        default=None, description="bearer token required on every request when set"
    )
    # limits
    max_body_bytes: int = Field(default=64 * 2**20, ge=1024, description="largest request body")
    max_pool_size: int = Field(default=10_000, ge=1, description="most candidates per pool")
    max_image_pixels: int = Field(default=4096 * 4096, ge=1, description="most pixels per image")
    max_sessions: int = Field(default=64, ge=1, description="most sessions held")
    max_gaussians: int = Field(default=2_000_000, ge=1, description="most Gaussians per session")
    max_views: int = Field(default=10_000, ge=1, description="most acquired views per session")
    max_shortlist: int = Field(default=256, ge=1, description="largest shortlist size N")
    # ROS 2 over Zenoh (see agilegs.service.ros2)
    ros2: Endpoints = Field(
        default_factory=list, description="ROS 2 namespaces served over Zenoh (CDR on the keys "
        "zenoh-bridge-ros2dds uses), e.g. /bot1/agilegs; needs zenoh"
    )
    # the decisions feed (see agilegs.service.decisions)
    max_poll_wait: float = Field(
        default=25.0, ge=0.0, le=60.0, description="longest wait of a decisions poll, and "
                                                   "longest decisions event stream (s)"
    )
    decision_log: int = Field(
        default=100, ge=1, description="decisions held per session for get_decisions"
    )
    # execution
    workers: int = Field(default=16, ge=1, description="threads running session work")
    torch_threads: int = Field(default=0, ge=0, description="torch intra-op threads (0: default)")
    fsync: bool = Field(default=True, description="fsync files and folders before acknowledging")
    # the mapper (see agilegs.service.sessions.trainer)
    mapper: bool = Field(default=True, description="train sessions' maps from their images")
    mapper_steps_per_view: int = Field(
        default=100, ge=0, description="mapper training steps per view with an image"
    )
    mapper_burst: int = Field(
        default=20, ge=1, description="mapper steps between two publications of the map"
    )
    log_level: str = Field(default="info", description="uvicorn / logging level")

    @field_validator("zenoh_listen", "zenoh_connect", "ros2", mode="before")
    @classmethod
    def _split(cls, value: Any) -> Any:
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                import json

                return json.loads(text)
            return [v.strip() for v in text.split(",") if v.strip()]
        return value

    @model_validator(mode="after")
    def _some_transport(self) -> Settings:
        if not (self.http or self.zenoh):
            raise ValueError("serve over HTTP, Zenoh or both (AGILEGS_HTTP, AGILEGS_ZENOH)")
        if self.ros2 and not self.zenoh:
            raise ValueError("ROS 2 (AGILEGS_ROS2) travels over Zenoh: turn AGILEGS_ZENOH on")
        return self

    @field_validator("ros2")
    @classmethod
    def _namespaces(cls, value: list[str]) -> list[str]:
        from agilegs.client.ros2.keys import normalize_namespace

        out = [normalize_namespace(v) for v in value]
        if len(set(out)) != len(out):
            raise ValueError(f"ROS 2 namespaces repeat: {out}")
        return out

    @field_validator("token", mode="before")
    @classmethod
    def _empty_token(cls, value: Any) -> Any:
        return None if value == "" else value

    def token_value(self) -> str | None:
        return self.token.get_secret_value() if self.token is not None else None

    def warn_if_unsafe(self) -> None:
        """Log what is risky outside a development machine."""
        if self.token is None and self.host not in ("127.0.0.1", "localhost", "::1"):
            log.warning(
                "serving on %s without AGILEGS_TOKEN: anyone who can reach it may change state",
                self.host,
            )
