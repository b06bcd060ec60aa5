"""The settings: one source for every ``AGILEGS_*`` environment variable and every
``agilegs serve`` flag.

:class:`Settings` is the server's: every field is settable as ``AGILEGS_<FIELD>`` (e.g.
``AGILEGS_PORT=8001``, ``AGILEGS_ZENOH_LISTEN=tcp/127.0.0.1:7447,tcp/[::1]:7447``,
``AGILEGS_TOKEN=...``; lists are comma-separated, or JSON) and, unless its :class:`Flag` keeps
it to the environment, as the flag ``--<field>`` of ``agilegs serve`` (:func:`add_flags`: the
flag's help is the field's description, its default and its variable, in the help group its
:class:`Flag` names; a flag given wins over the variable, :func:`settings_from_flags`).
:class:`Credentials` is the bearer token alone (the server's, and what ``agilegs view`` sends);
:class:`KernelSettings` are the compiled kernels' (``AGILEGS_KERNELS``,
``AGILEGS_KERNEL_THREADS``), read by :func:`kernel_settings`.
"""

from __future__ import annotations

import argparse
import logging
import os
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

__all__ = [
    "GROUPS",
    "Credentials",
    "Flag",
    "KernelSettings",
    "Settings",
    "add_flags",
    "env_var",
    "kernel_settings",
    "settings_from_flags",
]

log = logging.getLogger(__name__)

Endpoints = Annotated[list[str], NoDecode]
ENV_PREFIX = "AGILEGS_"

GROUPS: dict[str, str] = {
    "network": "where the server listens and what it serves: HTTP, Zenoh, ROS 2",
    "security": "the bearer token (AGILEGS_TOKEN only) and Zenoh's TLS, users and access "
                "control",
    "limits": "what requests, connections and sessions may cost",
    "execution": "the state folder, threads and logging",
    "mapper": "training the sessions' maps from their images",
    "cluster": "several instances as one service, over Zenoh",
}
"""The help groups of ``agilegs serve``'s flags, in the order ``--help`` shows them."""


@dataclass(frozen=True)
class Flag:
    """How a setting appears on ``agilegs serve``'s command line: its help group (a key of
    :data:`GROUPS`) and the placeholder of its value; ``cli=False`` keeps it to the
    environment (a secret on a command line is visible to every user of the machine)."""

    group: str
    metavar: str | None = None
    cli: bool = True


class _Environment(BaseSettings):
    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore")


class Credentials(_Environment):
    """The bearer token: required by the server on every request when set, and sent by the
    clients this package starts (``agilegs view``)."""

    token: Annotated[SecretStr | None, Flag("security", cli=False)] = Field(
        default=None, description="bearer token required on every request when set"
    )

    @field_validator("token", mode="before")
    @classmethod
    def _empty_token(cls, value: Any) -> Any:
        return None if value == "" else value

    def token_value(self) -> str | None:
        return self.token.get_secret_value() if self.token is not None else None


class KernelSettings(_Environment):
    """The compiled CPU kernels' settings (:mod:`agilegs.service.nbv.kernels.backend`)."""

    kernels: Literal["auto", "numba", "torch"] = Field(
        default="auto", description="which path renders and computes the Fisher: the compiled "
        "kernels where they apply (auto), always (numba), or the torch reference (torch)")
    kernel_threads: int | None = Field(
        default=None, ge=1, description="threads each kernel runs on (default: torch's thread "
        "count)")
    gpu_anchor: bool = Field(
        default=True, description="on CUDA, the anchor's proxy psi by its Triton kernels "
        "(kernels/gpu_proxy.py) where the backend is not torch; false: by the torch path")

    @field_validator("kernels", "kernel_threads", "gpu_anchor", mode="before")
    @classmethod
    def _plain(cls, value: Any, info: Any) -> Any:
        if isinstance(value, str):
            value = value.strip().lower()
            if not value:
                return cls.model_fields[info.field_name].default
        return value


_KERNEL_SETTINGS: dict[tuple[str | None, ...], KernelSettings] = {}
_KERNEL_VARS = tuple(f"{ENV_PREFIX}{name.upper()}" for name in KernelSettings.model_fields)


def kernel_settings() -> KernelSettings:
    """The kernels' settings from the environment as it is now (each distinct set of values
    parsed once). Raises ValueError naming the variable when one is invalid."""
    key = tuple(map(os.environ.get, _KERNEL_VARS))
    found = _KERNEL_SETTINGS.get(key)
    if found is None:
        try:
            found = KernelSettings()
        except ValidationError as exc:
            raise ValueError("; ".join(
                f"{env_var(str(e['loc'][0]))}: {e['msg']}, got {e['input']!r}"
                for e in exc.errors())) from None
        _KERNEL_SETTINGS[key] = found
    return found


def env_var(name: str) -> str:
    """The environment variable of the setting ``name``."""
    return f"{ENV_PREFIX}{name.upper()}"


class Settings(Credentials):
    """Server settings (defaults documented per field)."""

    host: Annotated[str, Flag("network")] = Field(
        default="127.0.0.1", description="HTTP bind address")
    port: Annotated[int, Flag("network")] = Field(
        default=8000, ge=0, le=65535, description="HTTP port (0: any free port)")
    state_dir: Annotated[Path, Flag("execution", metavar="DIR")] = Field(
        default=Path("agilegs-state"), description="persistent state folder")
    state_url: Annotated[str | None, Flag("execution", metavar="URL")] = Field(
        default=None, pattern=r"^(s3://[^/]+(/.*)?|file://.+)$", description="where the "
        "sessions are kept: s3://bucket/prefix (an object store, any S3 API, shared by a "
        "fleet; credentials and region from the AWS_* variables) or file:///path (a folder, "
        "as --state-dir); default the state folder. The state folder still holds this "
        "instance's scratch files and Zenoh credentials")
    state_endpoint: Annotated[str | None, Flag("execution", metavar="URL")] = Field(
        default=None, description="the S3 API's URL of an s3:// --state-url (MinIO, Ceph, "
        "R2; default AWS_ENDPOINT_URL, else AWS)")
    http: Annotated[bool, Flag("network")] = Field(default=True, description="serve over HTTP")
    zenoh: Annotated[bool, Flag("network")] = Field(
        default=True, description="serve over Zenoh as well")
    zenoh_listen: Annotated[Endpoints, Flag("network", metavar="ENDPOINTS")] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"], description="Zenoh listen endpoints"
    )
    zenoh_connect: Annotated[Endpoints, Flag("network", metavar="ENDPOINTS")] = Field(
        default_factory=list, description="Zenoh peers to connect")
    # several instances (see agilegs.service.transports.zenoh.cluster)
    zenoh_mode: Annotated[Literal["peer", "client", "router"], Flag("network")] = Field(
        default="peer", description="Zenoh mode: peer, or client of a router (zenohd)"
    )
    instance_id: Annotated[str | None, Flag("cluster", metavar="ID")] = Field(
        default=None, pattern=r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$",
        description="this instance's id in a cluster (default: <hostname>-<port>)",
    )
    forward_timeout: Annotated[float, Flag("cluster")] = Field(
        default=120.0, gt=0, description="seconds an operation forwarded to another instance "
                                         "may take"
    )
    # limits
    max_body_bytes: Annotated[int, Flag("limits")] = Field(
        default=64 * 2**20, ge=1024, description="largest request body")
    max_inflight_body_bytes: Annotated[int, Flag("limits")] = Field(
        default=512 << 20, ge=1 << 20, description="most bytes of request bodies being read "
        "or held by requests in flight together, priced from Content-Length before the body "
        "is read (503 with Retry-After beyond)")
    # the HTTP edge (see agilegs.service.transports.http.edge)
    header_timeout: Annotated[float, Flag("limits")] = Field(
        default=10.0, gt=0, description="seconds a connection has to send a request's "
        "complete headers (from its opening, or its previous response); then it is closed")
    body_timeout: Annotated[float, Flag("limits")] = Field(
        default=60.0, gt=0, description="seconds a request's whole body has to arrive once "
        "its headers are in; then the connection is closed and the request cancelled")
    keep_alive_timeout: Annotated[float, Flag("limits")] = Field(
        default=5.0, gt=0, description="seconds an idle connection stays open between two "
        "requests")
    max_connections: Annotated[int, Flag("limits")] = Field(
        default=2048, ge=1, description="most HTTP connections (and requests) at once; a "
        "request beyond gets 503")
    max_header_bytes: Annotated[int, Flag("limits")] = Field(
        default=16384, ge=1024, description="largest request line and headers (400 beyond)")
    max_pool_size: Annotated[int, Flag("limits")] = Field(
        default=10_000, ge=1, description="most candidates per pool")
    max_image_pixels: Annotated[int, Flag("limits")] = Field(
        default=4096 * 4096, ge=1, description="most pixels per image")
    max_sessions: Annotated[int, Flag("limits")] = Field(
        default=64, ge=1, description="most sessions held")
    max_gaussians: Annotated[int, Flag("limits")] = Field(
        default=2_000_000, ge=1, description="most Gaussians per session")
    max_views: Annotated[int, Flag("limits")] = Field(
        default=10_000, ge=1, description="most acquired views per session")
    max_shortlist: Annotated[int, Flag("limits")] = Field(
        default=256, ge=1, description="largest shortlist size N")
    max_body_items: Annotated[int, Flag("limits")] = Field(
        default=1_000_000, ge=1000, description="most values (list items, map entries, "
        "scalars) in a JSON or msgpack body, counted before it is parsed; large arrays travel "
        "as binary NDArray fields")
    max_request_decoded_bytes: Annotated[int, Flag("limits")] = Field(
        default=1 << 30, ge=1 << 20, description="most bytes the images and depth maps of "
        "one request take decoded, summed from their headers before decoding (413)")
    max_inflight_decoded_bytes: Annotated[int, Flag("limits")] = Field(
        default=2 << 30, ge=1 << 20, description="most decoded image and depth bytes of all "
        "requests in flight together (503 with Retry-After beyond)")
    max_select_seconds: Annotated[float, Flag("limits")] = Field(
        default=240.0, gt=0, description="a select whose up-front time bound (the estimate "
        "on the reference CPU times this machine's measured factor times 2) exceeds this is "
        "refused (422 limit_exceeded)")
    max_select_bytes: Annotated[int, Flag("limits")] = Field(
        default=8 << 30, ge=1 << 20, description="a select whose up-front peak memory "
        "estimate exceeds this is refused (422 limit_exceeded)")
    device: Annotated[str, Flag("execution")] = Field(
        default="cpu", pattern=r"^(cpu|cuda(:[0-9]+)?)$", description="where selections and "
        "training run: cpu, cuda or cuda:N (a GPU: each selection runs on a copy of the map, "
        "Hhat and the pool there, the mapper trains there; the sessions' records stay in host "
        "memory)")
    max_session_queue: Annotated[int, Flag("limits")] = Field(
        default=4, ge=1, description="compute requests (writes, selects) of one session "
        "running or waiting at once; more get 429 with Retry-After")
    max_queued: Annotated[int, Flag("limits")] = Field(
        default=64, ge=1, description="compute requests of all sessions running or waiting "
        "at once; more get 503 with Retry-After (/readyz reports saturation)")
    request_deadline: Annotated[float, Flag("limits")] = Field(
        default=300.0, gt=0, description="seconds a request may take before it is cancelled "
        "at its next stage boundary (a request's X-Deadline-Ms header / Zenoh deadline_ms "
        "parameter may shorten it)")
    # Zenoh security (see agilegs.service.transports.zenoh.security)
    zenoh_tls_certificate: Annotated[Path | None, Flag("security", metavar="PEM")] = Field(
        default=None, description="PEM certificate of the tls/ listen endpoints (with "
        "zenoh_tls_private_key)")
    zenoh_tls_private_key: Annotated[Path | None, Flag("security", metavar="PEM")] = Field(
        default=None, description="its PEM private key")
    zenoh_tls_root_ca: Annotated[Path | None, Flag("security", metavar="PEM")] = Field(
        default=None, description="PEM CA certificate verifying the tls/ endpoints this "
        "instance connects to and, with zenoh_mtls, the certificates of peers connecting")
    zenoh_mtls: Annotated[bool, Flag("security")] = Field(
        default=False, description="mutual TLS: a peer connecting over tls/ must present a "
        "certificate signed by zenoh_tls_root_ca (this instance presents its own)")
    zenoh_users_file: Annotated[Path | None, Flag("security", metavar="FILE")] = Field(
        default=None, description="user:password lines: a peer connecting must authenticate "
        "as one of them (Zenoh usrpwd); access control then allows the agilegs keys only to "
        "those users (and to mTLS peers)")
    zenoh_user: Annotated[str | None, Flag("security", metavar="USER")] = Field(
        default=None, description="the Zenoh username this instance presents when connecting "
        "(to a router or another instance)")
    zenoh_password: Annotated[SecretStr | None, Flag("security", cli=False)] = Field(
        default=None, description="its password")
    zenoh_dev_certs: Annotated[Path | None, Flag("security", metavar="DIR")] = Field(
        default=None, description="a folder: a development CA, server and client certificate "
        "are made there (once) and the tls/ endpoints serve with them")
    zenoh_insecure: Annotated[bool, Flag("security")] = Field(
        default=False, description="INSECURE: with AGILEGS_TOKEN set, serve Zenoh without "
        "authentication (any peer that reaches the endpoints reads every session's data); "
        "by default a server with a token and no users file or mutual TLS makes its own "
        "Zenoh credentials in <state_dir>/zenoh")
    # ROS 2 over Zenoh (see agilegs.service.transports.ros2)
    ros2: Annotated[Endpoints, Flag("network", metavar="NAMESPACE")] = Field(
        default_factory=list, description="ROS 2 namespaces served over Zenoh (CDR on the keys "
        "zenoh-bridge-ros2dds uses), e.g. /bot1/agilegs; needs zenoh"
    )
    # the decisions feed (see agilegs.service.sessions.decisions)
    max_poll_wait: Annotated[float, Flag("limits")] = Field(
        default=25.0, ge=0.0, le=60.0, description="longest wait of a decisions poll, and "
                                                   "longest decisions event stream (s)"
    )
    decision_log: Annotated[int, Flag("limits")] = Field(
        default=100, ge=1, description="decisions held per session for get_decisions"
    )
    # execution
    workers: Annotated[int, Flag("execution")] = Field(
        default=16, ge=1, description="threads running compute (writes, selects)")
    read_workers: Annotated[int, Flag("execution")] = Field(
        default=8, ge=1, description="threads running reads (never behind compute)")
    background_nice: Annotated[int, Flag("execution")] = Field(
        default=10, ge=0, le=19, description="how much lower the OS priority (nice) of the "
        "threads serving a session that keeps compute queued is (0: the same)")
    torch_threads: Annotated[int, Flag("execution")] = Field(
        default=0, ge=0, description="torch intra-op threads (0: default)")
    fsync: Annotated[bool, Flag("execution")] = Field(
        default=True, description="fsync files and folders before acknowledging")
    warmup: Annotated[bool, Flag("execution")] = Field(
        default=True, description="compile (or load from numba's cache) the kernels of every "
        "method at start, in the background; /readyz answers 503 until done")
    # the mapper (see agilegs.service.sessions.trainer)
    mapper: Annotated[bool, Flag("mapper")] = Field(
        default=True, description="train sessions' maps from their images")
    mapper_steps_per_view: Annotated[int, Flag("mapper")] = Field(
        default=100, ge=0, description="mapper training steps per view with an image"
    )
    mapper_burst: Annotated[int, Flag("mapper")] = Field(
        default=20, ge=1, description="mapper steps between two publications of the map"
    )
    log_level: Annotated[str, Flag("execution", metavar="LEVEL")] = Field(
        default="info", description="uvicorn / logging level")

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
    def _state_folder_url(self) -> Settings:
        if self.state_url is not None and self.state_url.startswith("file://"):
            from urllib.parse import unquote, urlsplit

            parts = urlsplit(self.state_url)
            if parts.netloc not in ("", "localhost"):
                raise ValueError(f"state_url {self.state_url!r}: a file:// URL names a local "
                                 "folder (file:///path)")
            object.__setattr__(self, "state_dir", Path(unquote(parts.path)))
            object.__setattr__(self, "state_url", None)
        return self

    def state_location(self) -> str:
        """Where the sessions are kept, in words: the object store's URL, or the folder."""
        return self.state_url or str(self.state_dir)

    @model_validator(mode="after")
    def _some_transport(self) -> Settings:
        if not (self.http or self.zenoh):
            raise ValueError("serve over HTTP, Zenoh or both (AGILEGS_HTTP, AGILEGS_ZENOH)")
        if self.ros2 and not self.zenoh:
            raise ValueError("ROS 2 (AGILEGS_ROS2) travels over Zenoh: turn AGILEGS_ZENOH on")
        return self

    @model_validator(mode="after")
    def _zenoh_security(self) -> Settings:
        if self.zenoh_dev_certs is not None:
            d = Path(self.zenoh_dev_certs)
            for name, file in (("zenoh_tls_certificate", "server.pem"),
                               ("zenoh_tls_private_key", "server.key"),
                               ("zenoh_tls_root_ca", "ca.pem")):
                if getattr(self, name) is None:
                    object.__setattr__(self, name, d / file)
        if (self.zenoh_tls_certificate is None) != (self.zenoh_tls_private_key is None):
            raise ValueError("AGILEGS_ZENOH_TLS_CERTIFICATE and AGILEGS_ZENOH_TLS_PRIVATE_KEY "
                             "go together")
        if self.zenoh_mtls and (self.zenoh_tls_root_ca is None
                                or self.zenoh_tls_certificate is None):
            raise ValueError("AGILEGS_ZENOH_MTLS needs AGILEGS_ZENOH_TLS_ROOT_CA and the "
                             "instance's certificate and key")
        if (self.zenoh_user is None) != (self.zenoh_password is None):
            raise ValueError("AGILEGS_ZENOH_USER and AGILEGS_ZENOH_PASSWORD go together")
        return self

    @field_validator("zenoh_password", mode="before")
    @classmethod
    def _empty_password(cls, value: Any) -> Any:
        return None if value == "" else value

    def warn_if_unsafe(self) -> None:
        """Log what is risky outside a development machine."""
        if self.token is None and self.host not in ("127.0.0.1", "localhost", "::1"):
            log.warning(
                "serving on %s without AGILEGS_TOKEN: anyone who can reach it may change state",
                self.host,
            )
        secured = self.zenoh_users_file is not None or self.zenoh_mtls
        if self.token is None:
            served = ([f"HTTP ({self.host}:{self.port})"] if self.http else []) + (
                [f"Zenoh ({','.join(self.zenoh_listen) or 'no listen endpoint'})"]
                if self.zenoh and not secured else [])
            log.warning(
                "development mode: no AGILEGS_TOKEN, so %s %s open: any client or peer that "
                "reaches %s reads and changes every session; set AGILEGS_TOKEN to require the "
                "token and Zenoh credentials", " and ".join(served),
                "is" if len(served) == 1 else "are", "it" if len(served) == 1 else "them")
        if self.zenoh and not secured:
            if self.token is not None and self.zenoh_insecure:
                log.warning(
                    "INSECURE (AGILEGS_ZENOH_INSECURE): Zenoh (%s) authenticates no peer: any "
                    "peer that reaches it sees every session's decisions, frames and "
                    "candidates (the token guards requests, not subscriptions)",
                    ",".join(self.zenoh_listen) or "no listen endpoint")


def _value_type(field: FieldInfo) -> Any:
    """The field's type without None."""
    kind = field.annotation
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        kind = next(a for a in typing.get_args(kind) if a is not type(None))
    return kind


def _flag(field: FieldInfo) -> Flag:
    return next(m for m in field.metadata if isinstance(m, Flag))


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, list):
        return ",".join(value) or "none"
    return "none" if value is None else str(value)


def _endpoints(text: str) -> list[str]:
    return [e.strip() for e in text.split(",") if e.strip()]


def add_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per field of :class:`Settings` (but those kept to the environment), in the
    help groups of :data:`GROUPS`: ``--<field>`` (and ``--no-<field>`` for a yes/no setting;
    a list flag is comma-separated or repeated), its help the field's
    description, its default and its environment variable. Every flag defaults to None: a
    setting whose flag is not given comes from the environment, else its default."""
    groups = {name: parser.add_argument_group(name, title) for name, title in GROUPS.items()}
    for name, field in Settings.model_fields.items():
        flag = _flag(field)
        if not flag.cli:
            continue
        description = field.description or ""
        default = ("" if "(default:" in description
                   else f"default {_shown(field.get_default(call_default_factory=True))}; ")
        kw: dict[str, Any] = {"dest": name, "default": None, "metavar": flag.metavar,
                              "help": f"{description} ({default}{env_var(name)})"
                              .replace("%", "%%")}
        kind = _value_type(field)
        option = f"--{name.replace('_', '-')}"
        if kind is bool:
            del kw["metavar"]
            both = groups[flag.group].add_mutually_exclusive_group()
            both.add_argument(option, action="store_const", const=True, **kw)
            both.add_argument(f"--no-{option[2:]}", dest=name, action="store_const", const=False,
                              default=None, help=f"the opposite of {option}")
            continue
        if typing.get_origin(kind) is list:
            kw.update(action="append", type=_endpoints)
        elif typing.get_origin(kind) is Literal:
            kw["choices"] = typing.get_args(kind)
        elif kind in (int, float):
            kw.update(type=kind, metavar=flag.metavar or ("N" if kind is int else "SECONDS"))
        groups[flag.group].add_argument(option, **kw)


def settings_from_flags(args: argparse.Namespace) -> Settings:
    """Settings from the environment, overridden by the flags of :func:`add_flags` given."""
    overrides: dict[str, Any] = {}
    for name, field in Settings.model_fields.items():
        value = getattr(args, name, None)
        if value is not None:
            if typing.get_origin(_value_type(field)) is list:
                value = [e for group in value for e in group]
            overrides[name] = value
    return Settings(**overrides)
