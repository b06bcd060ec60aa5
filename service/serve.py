"""``agilegs serve``: run one server instance (:class:`~agilegs.service.server.Server`) over
HTTP, Zenoh or both, until SIGTERM or SIGINT.

Every flag has an ``AGILEGS_*`` environment variable (see :mod:`agilegs.service.settings`);
a flag given on the command line wins. The bearer token is read from ``AGILEGS_TOKEN`` only
(a command line is visible to every user of the machine).

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

__all__ = ["add_arguments", "build_settings", "run", "zenoh_start_error"]

log = logging.getLogger(__name__)


def _endpoints(text: str) -> list[str]:
    return [e.strip() for e in text.split(",") if e.strip()]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--host", help="HTTP bind address (AGILEGS_HOST, default 127.0.0.1)")
    a("--port", type=int, help="HTTP port (AGILEGS_PORT, default 8000)")
    a("--state-dir", help="persistent state folder (AGILEGS_STATE_DIR, default ./agilegs-state)")
    z = parser.add_mutually_exclusive_group()
    z.add_argument("--zenoh", dest="zenoh", action="store_const", const=True,
                   help="serve over Zenoh too (AGILEGS_ZENOH, the default)")
    z.add_argument("--no-zenoh", dest="zenoh", action="store_const", const=False,
                   help="HTTP only")
    h = parser.add_mutually_exclusive_group()
    h.add_argument("--http", dest="http", action="store_const", const=True,
                   help="serve over HTTP (AGILEGS_HTTP, the default)")
    h.add_argument("--no-http", dest="http", action="store_const", const=False,
                   help="Zenoh only")
    a("--zenoh-listen", action="append", type=_endpoints, metavar="ENDPOINTS",
      help="Zenoh listen endpoints, comma-separated or repeated "
           "(AGILEGS_ZENOH_LISTEN, default tcp/127.0.0.1:7447)")
    a("--zenoh-connect", action="append", type=_endpoints, metavar="ENDPOINTS",
      help="Zenoh peers / routers to connect to (AGILEGS_ZENOH_CONNECT)")
    a("--ros2", action="append", type=_endpoints, metavar="NAMESPACE",
      help="serve agilegs' ROS 2 topics and services under NAMESPACE over Zenoh, as "
           "zenoh-bridge-ros2dds carries them (e.g. /bot1/agilegs); comma-separated or "
           "repeated (AGILEGS_ROS2; see docs/ros2.md)")
    # several instances (see agilegs.service.transports.cluster)
    a("--zenoh-mode", choices=["peer", "client", "router"],
      help="Zenoh mode (AGILEGS_ZENOH_MODE, default peer; client: through a zenohd router)")
    a("--instance-id", help="this instance's id in a cluster "
                            "(AGILEGS_INSTANCE_ID, default <hostname>-<port>)")
    a("--forward-timeout", type=float, help="seconds an operation forwarded to the instance "
                                            "owning a session may take (AGILEGS_FORWARD_TIMEOUT)")
    a("--workers", type=int, help="worker threads for session work (AGILEGS_WORKERS, 16)")
    a("--torch-threads", type=int, help="torch intra-op threads, 0 = default "
                                        "(AGILEGS_TORCH_THREADS)")
    a("--max-body-bytes", type=int, help="largest request body (AGILEGS_MAX_BODY_BYTES)")
    a("--max-inflight-body-bytes", type=int,
      help="most bytes of request bodies in flight together (AGILEGS_MAX_INFLIGHT_BODY_BYTES)")
    a("--header-timeout", type=float,
      help="seconds to send a request's headers (AGILEGS_HEADER_TIMEOUT, 10)")
    a("--body-timeout", type=float,
      help="seconds to send a request's body (AGILEGS_BODY_TIMEOUT, 60)")
    a("--keep-alive-timeout", type=float,
      help="seconds an idle connection stays open (AGILEGS_KEEP_ALIVE_TIMEOUT, 5)")
    a("--max-connections", type=int,
      help="most HTTP connections at once (AGILEGS_MAX_CONNECTIONS, 2048)")
    a("--max-header-bytes", type=int,
      help="largest request head (AGILEGS_MAX_HEADER_BYTES, 16384)")
    a("--max-pool-size", type=int, help="most candidates per pool (AGILEGS_MAX_POOL_SIZE)")
    a("--max-image-pixels", type=int, help="most pixels per image (AGILEGS_MAX_IMAGE_PIXELS)")
    a("--max-sessions", type=int, help="most sessions (AGILEGS_MAX_SESSIONS)")
    a("--max-gaussians", type=int, help="most Gaussians per session (AGILEGS_MAX_GAUSSIANS)")
    a("--max-views", type=int, help="most views per session (AGILEGS_MAX_VIEWS)")
    a("--max-shortlist", type=int, help="largest shortlist size (AGILEGS_MAX_SHORTLIST)")
    a("--max-poll-wait", type=float,
      help="longest wait of a decisions poll or event stream, s (AGILEGS_MAX_POLL_WAIT, 25)")
    a("--decision-log", type=int,
      help="decisions held per session for get_decisions (AGILEGS_DECISION_LOG, 100)")
    f = parser.add_mutually_exclusive_group()
    f.add_argument("--fsync", dest="fsync", action="store_const", const=True,
                   help="fsync before acknowledging (AGILEGS_FSYNC, the default)")
    f.add_argument("--no-fsync", dest="fsync", action="store_const", const=False,
                   help="skip fsync (state survives a killed process, not a power cut)")
    m = parser.add_mutually_exclusive_group()
    m.add_argument("--mapper", dest="mapper", action="store_const", const=True,
                   help="train sessions' maps from the images they receive (AGILEGS_MAPPER, "
                        "the default)")
    m.add_argument("--no-mapper", dest="mapper", action="store_const", const=False,
                   help="keep maps as pushed: images are stored, not trained on")
    a("--mapper-steps-per-view", type=int,
      help="mapper training steps per view with an image (AGILEGS_MAPPER_STEPS_PER_VIEW, 100)")
    a("--mapper-burst", type=int,
      help="mapper steps between two publications of the map (AGILEGS_MAPPER_BURST, 20)")
    a("--log-level", help="log level (AGILEGS_LOG_LEVEL, default info)")
    # what one request may cost (see agilegs.service.transports.admission)
    a("--read-workers", type=int, help="threads running reads (AGILEGS_READ_WORKERS, 8)")
    a("--background-nice", type=int, help="lower OS priority of a session keeping compute "
                                          "queued (AGILEGS_BACKGROUND_NICE, 10)")
    a("--max-body-items", type=int,
      help="most values in a JSON / msgpack body (AGILEGS_MAX_BODY_ITEMS)")
    a("--max-request-decoded-bytes", type=int,
      help="most decoded image bytes per request (AGILEGS_MAX_REQUEST_DECODED_BYTES)")
    a("--max-inflight-decoded-bytes", type=int,
      help="most decoded image bytes in flight (AGILEGS_MAX_INFLIGHT_DECODED_BYTES)")
    a("--max-select-seconds", type=float,
      help="largest estimated select time, s (AGILEGS_MAX_SELECT_SECONDS, 120)")
    a("--max-select-bytes", type=int,
      help="largest estimated select peak memory (AGILEGS_MAX_SELECT_BYTES)")
    a("--max-session-queue", type=int,
      help="compute requests per session running or waiting (AGILEGS_MAX_SESSION_QUEUE, 4)")
    a("--max-queued", type=int,
      help="compute requests running or waiting in all (AGILEGS_MAX_QUEUED, 64)")
    a("--request-deadline", type=float,
      help="seconds a request may take (AGILEGS_REQUEST_DEADLINE, 300)")
    # Zenoh security (see agilegs.service.transports.zenoh.security)
    a("--zenoh-tls-certificate", help="PEM certificate of the tls/ listen endpoints "
                                      "(AGILEGS_ZENOH_TLS_CERTIFICATE)")
    a("--zenoh-tls-private-key", help="its PEM key (AGILEGS_ZENOH_TLS_PRIVATE_KEY)")
    a("--zenoh-tls-root-ca", help="PEM CA certificate (AGILEGS_ZENOH_TLS_ROOT_CA)")
    mt = parser.add_mutually_exclusive_group()
    mt.add_argument("--zenoh-mtls", dest="zenoh_mtls", action="store_const", const=True,
                    help="mutual TLS: peers need a certificate of the CA (AGILEGS_ZENOH_MTLS)")
    mt.add_argument("--no-zenoh-mtls", dest="zenoh_mtls", action="store_const", const=False,
                    help="no client certificates (the default)")
    a("--zenoh-users-file", help="user:password lines: Zenoh peers must authenticate as one "
                                 "(AGILEGS_ZENOH_USERS_FILE)")
    a("--zenoh-user", help="the Zenoh user this instance connects as (AGILEGS_ZENOH_USER; "
                           "its password: AGILEGS_ZENOH_PASSWORD)")
    a("--zenoh-insecure", dest="zenoh_insecure", action="store_const", const=True,
      help="INSECURE: with AGILEGS_TOKEN set, do not make or require Zenoh credentials: any "
           "peer that reaches the Zenoh endpoints reads every session's data "
           "(AGILEGS_ZENOH_INSECURE)")
    a("--zenoh-dev-certs", metavar="DIR",
      help="make a development CA, server and client certificate in DIR (once) and serve "
           "tls/ endpoints with them (AGILEGS_ZENOH_DEV_CERTS)")


_FIELDS = ("host", "port", "state_dir", "http", "zenoh", "zenoh_mode", "instance_id",
           "forward_timeout", "workers", "torch_threads", "max_body_bytes",
           "max_pool_size", "max_image_pixels", "max_sessions", "max_gaussians", "max_views",
           "max_shortlist", "max_poll_wait", "decision_log", "fsync", "mapper",
           "mapper_steps_per_view", "mapper_burst", "log_level", "read_workers", "background_nice",
           "max_body_items", "max_request_decoded_bytes", "max_inflight_decoded_bytes",
           "max_select_seconds", "max_select_bytes", "max_session_queue", "max_queued",
           "request_deadline", "zenoh_tls_certificate", "zenoh_tls_private_key",
           "zenoh_tls_root_ca", "zenoh_mtls", "zenoh_users_file", "zenoh_user",
           "zenoh_dev_certs", "zenoh_insecure", "max_inflight_body_bytes", "header_timeout",
           "body_timeout", "keep_alive_timeout", "max_connections", "max_header_bytes")


def build_settings(args: argparse.Namespace) -> Any:
    """Settings from the environment, overridden by the flags given."""
    from .settings import Settings

    overrides: dict[str, Any] = {}
    for name in _FIELDS:
        value = getattr(args, name, None)
        if value is not None:
            overrides[name] = value
    for name in ("zenoh_listen", "zenoh_connect", "ros2"):
        value = getattr(args, name, None)
        if value is not None:
            overrides[name] = [e for group in value for e in group]
    return Settings(**overrides)


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
    from .server import Server
    from .store.state_dir import StateDirError
    from .transports.http.edge import raise_file_limit, tune_allocator

    settings = build_settings(args)
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
             settings.state_dir, "on" if settings.zenoh else "off")
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
             server.cluster.instance_id, server.settings.state_dir)
    try:
        stop.wait()
    finally:
        server.close()
    return 0
