"""The ``agilegs`` command line.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; this file only wires them together, importing each lazily so that a
client-only install (no torch) still prints a clear message instead of a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

# (command path, module, help)
COMMANDS: list[tuple[tuple[str, ...], str, str]] = [
    (("serve",), "agilegs.service.serve", "run the NBV server (HTTP and Zenoh)"),
    (("demo",), "agilegs.service.demo", "closed-loop demo on the bundled scene"),
    (("store", "check"), "agilegs.service.store_tool",
     "check a state folder's sessions against their checksums (offline)"),
    (("store", "repair"), "agilegs.service.store_tool",
     "roll damaged sessions of a state folder back to their last intact version (offline)"),
    (("view",), "agilegs.service.viewer.cli",
     "a live browser view of a session, or the replay of a benchmark run (agilegs[viewer])"),
    (("bench", "render"), "agilegs.service.bench.render_bench", "rasterizer and Fisher timings"),
    (("bench", "latency"), "agilegs.service.bench.latency", "selection latency of every method"),
    (("bench", "run"), "agilegs.service.bench.run_cli", "the paper's progressive protocol"),
    (("bench", "service"), "agilegs.service.bench.service_bench", "transport overhead"),
    (("bench", "value"), "agilegs.service.bench.value",
     "what each candidate is worth, and which scores predict it"),
    (("bench", "proxy"), "agilegs.service.bench.proxy_check",
     "how the anchor's choices follow the exact EIG on trained maps"),
]


# third-party modules of the `service` extra: a client-only install lacks them
_SERVER_EXTRAS = {
    "torch",
    "uvicorn",
    "fastapi",
    "zenoh",
    "pydantic_settings",
    "prometheus_client",
    "plyfile",
    "PIL",
    "matplotlib",
    "rich",
    "skimage",
    "starlette",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agilegs", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    top = parser.add_subparsers(dest="command", metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction] = {}
    for path, module, help_text in COMMANDS:
        if len(path) == 1:
            sub = top.add_parser(path[0], help=help_text)
        else:
            if path[0] not in groups:
                g = top.add_parser(path[0], help=f"{path[0]} subcommands")
                groups[path[0]] = g.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")
            sub = groups[path[0]].add_parser(path[1], help=help_text)
        sub.set_defaults(_module=module)
        try:
            mod = importlib.import_module(module)
        except ImportError as exc:  # e.g. torch missing in a client-only install
            sub.set_defaults(_import_error=str(exc))
            continue
        mod.add_arguments(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "_module", None):
        parser.print_help()
        return 2
    err = getattr(args, "_import_error", None)
    if err:
        sys.stderr.write(
            f"agilegs: this command needs the server extras ({err}).\n"
            "Install them with: pip install torch==2.13.0 && pip install 'agilegs[service]'\n"
        )
        return 2
    mod = importlib.import_module(args._module)
    try:
        return int(mod.run(args) or 0)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] in _SERVER_EXTRAS:
            sys.stderr.write(
                f"agilegs: this command needs the server extras (missing {exc.name!r}).\n"
                "Install them with: pip install torch==2.13.0 && pip install 'agilegs[service]'\n"
            )
            return 2
        raise


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
