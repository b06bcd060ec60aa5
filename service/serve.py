"""``agilegs serve``: run one server instance (:class:`~agilegs.service.server.Server`) over
HTTP, Zenoh or both, until SIGTERM or SIGINT.

Every flag is a field of :class:`~agilegs.service.settings.Settings` with its ``AGILEGS_*``
environment variable; a flag given on the command line wins. The bearer token is read from
``AGILEGS_TOKEN`` only (a command line is visible to every user of the machine).

The state folder is claimed before anything else (:mod:`agilegs.service.store.state_dir`): a folder
that cannot be created, is read-only, or is held by another server ends the command with one
line on stderr and exit status 2. So do an HTTP address that cannot be bound (a port already
taken: the HTTP socket is bound next, before the sessions load) and a Zenoh session that
cannot start (a listen endpoint already taken, an address not on this machine:
:func:`zenoh_start_error`); each line names the address, the cause and the flag to change.

The module imports the server (torch, FastAPI) only when the command runs, so that
``agilegs serve --help`` answers at once.
"""

from __future__ import annotations

import argparse
import logging
import re
import signal
import socket
import sys
import threading
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .server import Server

__all__ = ["SettingError", "add_arguments", "build_settings", "check_settings", "run",
           "zenoh_start_error"]

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``agilegs serve``: one per setting
    (:func:`agilegs.service.settings.add_flags`)."""
    from .settings import add_flags

    parser.epilog = ("Every flag has its AGILEGS_* environment variable (named in its help); a "
                     "flag given wins. The bearer token is read from AGILEGS_TOKEN only.")
    add_flags(parser)


class SettingError(ValueError):
    """A setting that this machine or the ROS 2 naming rules refuse; ``setting`` names the
    field (its flag is ``--`` + the name with dashes, its variable ``AGILEGS_`` + the name)."""

    def __init__(self, setting: str, message: str) -> None:
        super().__init__(f"{setting}: {message}")
        self.setting = setting
        self.message = message


def check_settings(settings: Any) -> None:
    """What the settings cannot check, as they import neither torch nor the client: the
    device exists on this machine, the ROS 2 namespaces are ROS names that do not repeat.
    Raises :class:`SettingError`."""
    device = str(settings.device)
    if device != "cpu":
        import torch

        if not torch.cuda.is_available():
            raise SettingError("device", f"{device!r}: CUDA is not available on this machine")
        index = int(device.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise SettingError("device", f"{device!r}: this machine has "
                                         f"{torch.cuda.device_count()} CUDA device(s)")
    if settings.ros2:
        from agilegs.client.ros2 import normalize_namespace

        try:
            names = [normalize_namespace(v) for v in settings.ros2]
        except ValueError as exc:
            raise SettingError("ros2", str(exc)) from None
        if len(set(names)) != len(names):
            raise SettingError("ros2", f"ROS 2 namespaces repeat: {names}")


def build_settings(args: argparse.Namespace) -> Any:
    """Settings from the environment, overridden by the flags given, and checked against
    this machine (:func:`check_settings`)."""
    from .settings import settings_from_flags

    settings = settings_from_flags(args)
    check_settings(settings)
    return settings


def bind_http(host: str, port: int) -> socket.socket:
    """The HTTP server's socket, bound (as uvicorn binds it); OSError if it cannot be."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # IPPROTO_TCP named: asyncio sets TCP_NODELAY only on sockets that name it, and without
    # it a response sent in two writes waits for the client's delayed ACK (about 40 ms)
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    sock.set_inheritable(True)
    return sock


def http_bind_error(exc: OSError, host: str, port: int) -> str:
    """One line saying why the HTTP address cannot be used, and the flags to change it."""
    cause = exc.strerror or str(exc)
    return (f"cannot listen on http://{host}:{port}: {cause[:1].lower()}{cause[1:]}; give "
            "another with --port (AGILEGS_PORT) or --host (AGILEGS_HOST), or serve Zenoh only "
            "with --no-http")


def zenoh_start_error(exc: BaseException, settings: Any) -> str | None:
    """One line saying why Zenoh could not start (the endpoint, the cause, the flag to
    change), or None when ``exc`` is not Zenoh's."""
    from .transports.zenoh.security import UsersFileError

    if isinstance(exc, UsersFileError):
        return str(exc)
    if type(exc).__module__.split(".")[0] != "zenoh":
        return None
    text = str(exc)
    listen = re.search(r"bound to (\S+?):? \[(?:[^\]]*?: )?([^\]]*?)(?: \(os error \d+\))?"
                       r"(?: at \S+)?\]", text)
    if listen:
        endpoint, cause = listen.group(1), listen.group(2).strip()
        return (f"cannot listen on the Zenoh endpoint {endpoint}: {cause[:1].lower()}"
                f"{cause[1:]}; give another with --zenoh-listen (AGILEGS_ZENOH_LISTEN)"
                + (", or serve HTTP only with --no-zenoh" if settings.http else ""))
    cause = re.sub(r" at /\S+", "", text.splitlines()[0] if text else type(exc).__name__)
    return (f"Zenoh could not start ({settings.zenoh_mode} mode, listening on "
            f"{','.join(settings.zenoh_listen) or 'nothing'}, connecting to "
            f"{','.join(settings.zenoh_connect) or 'nothing'}): {cause.rstrip('.')}; check "
            "--zenoh-listen, --zenoh-connect and --zenoh-mode"
            + (", or serve HTTP only with --no-zenoh" if settings.http else ""))


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from .server import Server
    from .store.state_dir import StateDirError
    from .transports.http.edge import raise_file_limit, tune_allocator

    try:
        settings = build_settings(args)
    except ValidationError as exc:  # one line per bad setting, naming its flag and variable
        for err in exc.errors():
            name = str(err["loc"][0]) if err["loc"] else "settings"
            sys.stderr.write(f"agilegs serve: --{name.replace('_', '-')} "
                             f"(AGILEGS_{name.upper()}): {err['msg']}\n")
        return 2
    except SettingError as exc:
        name = exc.setting
        sys.stderr.write(f"agilegs serve: --{name.replace('_', '-')} "
                         f"(AGILEGS_{name.upper()}): {exc.message}\n")
        return 2
    tune_allocator()
    server = Server(settings, freeze_gc=True)
    try:
        server.claim_state()
    except StateDirError as exc:  # read-only, cannot be created, or held by another server
        sys.stderr.write(f"agilegs serve: {exc}\n")
        server.close()
        return 2
    if not settings.http:
        return _start(server) or _serve_zenoh_only(server)
    try:
        sock = bind_http(settings.host, settings.port)
    except OSError as exc:
        sys.stderr.write(f"agilegs serve: {http_bind_error(exc, settings.host, settings.port)}"
                         "\n")
        server.close()
        return 2
    import uvicorn  # before the start, so that its objects are frozen with the server's

    from .transports.http.app import create_app

    app = create_app(server, start=False)
    failed = _start(server)
    if failed:
        sock.close()
        return failed
    log.info("agilegs serve: http://%s:%d (state in %s, zenoh %s)", settings.host, settings.port,
             settings.state_location(), "on" if settings.zenoh else "off")
    from .transports.http.edge import uvicorn_config

    raise_file_limit(settings.max_connections)
    config = uvicorn.Config(app, host=settings.host, port=settings.port,
                            log_level=settings.log_level.lower(), access_log=False,
                            timeout_graceful_shutdown=10, **uvicorn_config(settings))
    http = uvicorn.Server(config)
    exit_now = http.handle_exit

    def handle_exit(sig: int, frame: Any) -> None:
        # waiting decision polls and event streams answer now: uvicorn waits for open
        # responses before it stops
        server.registry.decisions.shutdown()
        exit_now(sig, frame)

    http.handle_exit = handle_exit  # type: ignore[method-assign]
    try:
        http.run(sockets=[sock])
    finally:
        server.close()  # the lifespan closed it unless uvicorn stopped before it ran
        sock.close()
    return 0


def _start(server: Server) -> int:
    """Start ``server`` (sessions loaded, Zenoh joined): 0, or 2 after one line on stderr
    when Zenoh cannot start."""
    try:
        server.start()
    except Exception as exc:
        server.close()
        line = zenoh_start_error(exc, server.settings)
        if line is None:
            raise
        sys.stderr.write(f"agilegs serve: {line}\n")
        return 2
    server.settings.warn_if_unsafe()  # once serving: a refused start stays one line
    return 0


def _serve_zenoh_only(server: Server) -> int:
    """Serve the started ``server`` over Zenoh until SIGTERM or SIGINT."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    log.info("agilegs serve: zenoh only, instance %r (state in %s)",
             server.cluster.instance_id, server.settings.state_location())
    try:
        stop.wait()
    finally:
        server.close()
    return 0
