"""agilegs: the next-best-view service for active 3D Gaussian Splatting.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``. Building the parser imports no command module but the one the command
line names, and only for its options: a module that imports torch defines its options in a
light module instead (:data:`OPTIONS`), so ``agilegs --help``, ``agilegs COMMAND --help``
and a mistyped command answer without importing torch, FastAPI or matplotlib. The command's
own module is imported when it runs; on a client-only install (no torch) that prints what to
install instead of a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from functools import cache
from importlib.metadata import entry_points

# (command path, module, help)
COMMANDS: list[tuple[tuple[str, ...], str, str]] = [
    (("serve",), "agilegs.service.serve", "run the NBV server (HTTP and Zenoh)"),
    (("store", "check"), "agilegs.service.store_tool",
     "check a state folder's sessions against their checksums (offline)"),
    (("store", "repair"), "agilegs.service.store_tool",
     "roll damaged sessions of a state folder back to their last intact version (offline)"),
    (("export",), "agilegs.service.export",
     "write a session's views as a nerfstudio / COLMAP dataset (from a server or a state folder)"),
    (("view",), "agilegs.service.viewer.cli",
     "a live browser view of a session, or the replay of a benchmark run (agilegs[viewer])"),
]
"""The server's own commands; more come from the ``agilegs.commands`` entry points."""

GROUPS: dict[str, str] = {
    "store": "check or repair a server's state folder, offline",
}
"""The help of each command that groups subcommands."""

OPTIONS: dict[str, str] = {}
"""``module:function`` that adds the options of a command whose module imports torch (the
others' ``add_arguments`` is used)."""

ENTRY_POINTS = "agilegs.commands"
"""The entry-point group of more commands (the lab's: ``agilegs bench ...``, ``agilegs demo``):
each names a light module with ``COMMANDS`` and, optionally, ``GROUPS`` and ``OPTIONS`` shaped
as this module's."""

# third-party modules of the `service` extra: a client-only install lacks them
_SERVER_EXTRAS = {
    "torch",
    "uvicorn",
    "fastapi",
    "fastapi_offline",
    "zenoh",
    "pydantic_settings",
    "prometheus_client",
    "plyfile",
    "PIL",
    "starlette",
}

# third-party modules of the `lab` extra (the benchmark's and the demo's)
_LAB_EXTRAS = {"matplotlib", "rich", "skimage"}

_INSTALL = "Install them with: pip install torch==2.13.0 && pip install 'agilegs[service,lab]'\n"


@cache
def _tables() -> tuple[list[tuple[tuple[str, ...], str, str]], dict[str, str], dict[str, str]]:
    """The commands, groups and options: this module's and those of the entry points."""
    commands, groups, options = list(COMMANDS), dict(GROUPS), dict(OPTIONS)
    for ep in sorted(entry_points(group=ENTRY_POINTS), key=lambda e: e.name):
        try:
            mod = ep.load()
        except ImportError as exc:  # a broken plugin must not take the server's commands down
            logging.getLogger(__name__).warning("agilegs: commands of %s not loaded: %s",
                                                ep.value, exc)
            continue
        commands += getattr(mod, "COMMANDS", [])
        groups.update(getattr(mod, "GROUPS", {}))
        options.update(getattr(mod, "OPTIONS", {}))
    return commands, groups, options


def options_function(module: str) -> str:
    """Where the options of the command run by ``module`` are defined (``module:function``)."""
    return _tables()[2].get(module, f"{module}:add_arguments")


def _add_options(sub: argparse.ArgumentParser, module: str) -> None:
    where, _, function = options_function(module).partition(":")
    try:  # the options may import the command's extra too (serve's come from its settings)
        mod = importlib.import_module(where)
        getattr(mod, function)(sub)
    except ImportError as exc:  # e.g. the viewer's extra, or torch, missing
        sub.set_defaults(_import_error=str(exc))


def _positionals(argv: Sequence[str]) -> list[str]:
    return [a for a in argv if not a.startswith("-")]


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``agilegs`` parser. With ``argv``, only the command it names gets its options
    (enough to parse it, and fast); without, every command does."""
    words = _positionals(argv) if argv is not None else None
    parser = argparse.ArgumentParser(
        prog="agilegs", description=(__doc__ or "").splitlines()[0],
        epilog="Run agilegs COMMAND --help for a command's options. Documentation: README.md "
               "and docs/ of the repository.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    top = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands, group_help, _ = _tables()
    groups: dict[str, argparse._SubParsersAction] = {}
    for path, module, help_text in commands:
        if len(path) == 1:
            sub = top.add_parser(path[0], help=help_text, description=help_text)
        else:
            if path[0] not in groups:
                text = group_help.get(path[0], f"{path[0]} subcommands")
                g = top.add_parser(path[0], help=text, description=text)
                groups[path[0]] = g.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")
            sub = groups[path[0]].add_parser(path[1], help=help_text, description=help_text)
        sub.set_defaults(_module=module)
        if words is None or words[:len(path)] == list(path):
            _add_options(sub, module)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv)
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
        sys.stderr.write(f"agilegs: this command needs the server extras ({err}).\n{_INSTALL}")
        return 2
    try:
        mod = importlib.import_module(args._module)
        return int(mod.run(args) or 0)
    except ModuleNotFoundError as exc:
        top = exc.name.split(".")[0] if exc.name else ""
        if top in _LAB_EXTRAS:
            sys.stderr.write(f"agilegs: this command needs the lab extras (missing "
                             f"{exc.name!r}).\n{_INSTALL}")
            return 2
        if top in _SERVER_EXTRAS:
            sys.stderr.write(f"agilegs: this command needs the server extras (missing "
                             f"{exc.name!r}).\n{_INSTALL}")
            return 2
        raise


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
