"""``agilegs view``: a live browser view of a session, or the replay of a benchmark run.

::

    agilegs view http://127.0.0.1:8000 --session scene        # over HTTP (long polls)
    agilegs view --zenoh tcp/127.0.0.1:7447 --session scene   # over Zenoh (the publication)
    agilegs view --run bench-out/                              # replay an `agilegs bench run`

The page is served on ``http://127.0.0.1:8080`` (``--host`` / ``--port``) until Ctrl-C;
``--screenshot PNG`` writes a headless-Chromium screenshot of it once drawn, and exits.
Needs viser (``pip install "agilegs[viewer]"``); no torch.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from .extra import ViewerMissing, require_viser

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("url", nargs="?", default="http://127.0.0.1:8000",
      help="the server (default http://127.0.0.1:8000)")
    a("--session", help="the session to follow (it may not exist yet)")
    a("--token", help="the server's bearer token (default: AGILEGS_TOKEN)")
    a("--zenoh-credentials", metavar="CLIENT_JSON",
      help="with --zenoh: the server's <state-dir>/zenoh/client.json (its Zenoh user and "
           "password; a server with a token admits no Zenoh peer without them)")
    a("--zenoh", metavar="ENDPOINT",
      help="reach the server over Zenoh (e.g. tcp/127.0.0.1:7447) instead of HTTP")
    a("--run", metavar="DIR", help="replay the output folder of `agilegs bench run`")
    a("--host", default="127.0.0.1",
      help="address the page is served on (default 127.0.0.1; 0.0.0.0 to share it)")
    a("--port", type=int, default=8080, help="port of the page (default 8080)")
    a("--poll", type=float, default=1.0,
      help="seconds each long poll waits for a decision (default 1)")
    a("--screenshot", metavar="PNG", help="write a screenshot of the page (headless "
                                          "chromium) once it is drawn, then exit")
    a("--timeout", type=float, default=60.0,
      help="with --screenshot: seconds to wait for the session and the drawing (default 60)")
    a("--duration", type=float, default=None,
      help="serve the page this many seconds, then exit (default: until Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    logging.getLogger("websockets").setLevel(logging.WARNING)  # viser's connection chatter
    logging.getLogger("httpx").setLevel(logging.WARNING)  # a line per request (polls) otherwise
    try:
        require_viser()
    except ViewerMissing as exc:
        sys.stderr.write(f"agilegs view: {exc}\n")
        return 2
    if args.poll <= 0 or args.poll > 60:
        sys.stderr.write("agilegs view: --poll must be in (0, 60] seconds\n")
        return 2
    if args.run:
        return _replay(args)
    if not args.session:
        sys.stderr.write("agilegs view: give --session ID (or --run DIR to replay a "
                         "benchmark run)\n")
        return 2
    return _live(args)


def _replay(args: argparse.Namespace) -> int:
    from .replay import RunReplay

    try:
        viewer = RunReplay(args.run, host=args.host, port=args.port)
    except ValueError as exc:
        sys.stderr.write(f"agilegs view --run: {exc}\n")
        return 2
    try:
        return _serve(viewer, args, ready=lambda: True, problem=lambda: None)
    finally:
        viewer.close()


def _live(args: argparse.Namespace) -> int:
    from agilegs.client import Client, TransportError
    from agilegs.service.settings import Credentials

    from .live import SessionViewer

    token = args.token or Credentials().token_value()
    client: Any
    if args.zenoh:
        try:
            from agilegs.client import ZenohClient

            client = ZenohClient([args.zenoh], token=token, wait=0,
                                 timeout=max(30.0, args.poll + 30.0),
                                 credentials=getattr(args, "zenoh_credentials", None))
        except TransportError as exc:
            sys.stderr.write(f"agilegs view: {exc}\n")
            return 2
        where, decisions = f"zenoh {args.zenoh}", "zenoh"
    else:
        client = Client(args.url, token=token, timeout=max(30.0, args.poll + 30.0))
        where, decisions = args.url, "poll"
    try:
        viewer = SessionViewer(client, args.session, host=args.host, port=args.port,
                               where=where, decisions=decisions)  # type: ignore[arg-type]
    except BaseException:
        client.close()
        raise
    try:
        viewer.start(poll=args.poll)
        return _serve(viewer, args, ready=lambda: viewer.loaded,
                      problem=lambda: viewer.problem)
    finally:
        viewer.close()
        client.close()


def _serve(viewer: Any, args: argparse.Namespace, *, ready: Any, problem: Any) -> int:
    """Serve until Ctrl-C, ``--duration``, or the screenshot is written."""
    sys.stdout.write(f"agilegs view: open {viewer.url}\n")
    sys.stdout.flush()
    if args.screenshot:
        from .browser import capture, write_png

        got = viewer_wait(ready, problem, args.timeout)
        if got is not None:
            sys.stderr.write(f"agilegs view: {got}\n")
            return 1
        try:
            png = capture(viewer.url, timeout=max(args.timeout, 30.0))
        except RuntimeError as exc:
            sys.stderr.write(f"agilegs view: {exc}\n")
            return 1
        write_png(args.screenshot, png)
        sys.stdout.write(f"agilegs view: wrote {args.screenshot}\n")
        return 0
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    stop.wait(args.duration)
    return 0


def viewer_wait(ready: Any, problem: Any, timeout: float) -> str | None:
    """Wait until ``ready()``; the viewer's problem (a string) if it is not ready in time."""
    done = threading.Event()
    for _ in range(int(timeout / 0.1)):
        if ready():
            return None
        done.wait(0.1)
    return str(problem() or f"the session did not load within {timeout:.0f} s")

