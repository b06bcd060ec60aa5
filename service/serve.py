"""``agilegs serve``: run one server instance (:class:`~agilegs.service.server.Server`) over
HTTP, Zenoh or both, until SIGTERM or SIGINT.

Every flag has an ``AGILEGS_*`` environment variable (see :mod:`agilegs.service.settings`);
a flag given on the command line wins. The bearer token is read from ``AGILEGS_TOKEN`` only
(a command line is visible to every user of the machine).

The state folder is claimed before anything else (:mod:`agilegs.service.state_dir`): a folder
that cannot be created, is read-only, or is held by another server ends the command with one
line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from .http_app import create_app
from .server import Server
from .settings import Settings
from .state_dir import StateDirError

__all__ = ["add_arguments", "build_settings", "run"]

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
    # several instances (see agilegs.service.cluster)
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


_FIELDS = ("host", "port", "state_dir", "http", "zenoh", "zenoh_mode", "instance_id",
           "forward_timeout", "workers", "torch_threads", "max_body_bytes",
           "max_pool_size", "max_image_pixels", "max_sessions", "max_gaussians", "max_views",
           "max_shortlist", "max_poll_wait", "decision_log", "fsync", "mapper",
           "mapper_steps_per_view", "mapper_burst", "log_level")


def build_settings(args: argparse.Namespace) -> Any:
    """Settings from the environment, overridden by the flags given."""
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


def run(args: argparse.Namespace) -> int:
    settings = build_settings(args)
    settings.warn_if_unsafe()
    server = Server(settings, freeze_gc=True)
    try:
        server.claim_state()
    except StateDirError as exc:  # read-only, cannot be created, or held by another server
        sys.stderr.write(f"agilegs serve: {exc}\n")
        server.close()
        return 2
    if not settings.http:
        return _serve_zenoh_only(server)
    import uvicorn

    app = create_app(settings, server)
    log.info("agilegs serve: http://%s:%d (state in %s, zenoh %s)", settings.host, settings.port,
             settings.state_dir, "on" if settings.zenoh else "off")
    config = uvicorn.Config(app, host=settings.host, port=settings.port,
                            log_level=settings.log_level.lower(), access_log=False,
                            timeout_graceful_shutdown=10)
    http = uvicorn.Server(config)
    exit_now = http.handle_exit

    def handle_exit(sig: int, frame: Any) -> None:
        # waiting decision polls and event streams answer now: uvicorn waits for open
        # responses before it stops
        server.registry.decisions.shutdown()
        exit_now(sig, frame)

    http.handle_exit = handle_exit  # type: ignore[method-assign]
    http.run()
    return 0


def _serve_zenoh_only(server: Server) -> int:
    """Serve over Zenoh until SIGTERM or SIGINT."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    server.start()
    log.info("agilegs serve: zenoh only, instance %r (state in %s)",
             server.cluster.instance_id, server.settings.state_dir)
    try:
        stop.wait()
    finally:
        server.close()
    return 0
