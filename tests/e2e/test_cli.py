"""The command line wires every documented subcommand, answers ``--help`` and typos without
importing torch, FastAPI or matplotlib, and documents every option."""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys

import pytest

from agilegs.service.cli import COMMANDS, OPTIONS, build_parser, options_function

HEAVY = ("torch", "fastapi", "matplotlib")
"""Modules that ``--help`` and a typo must not import (seconds each on a busy machine)."""

#: every command's --help, the groups', the top level's, and mistyped commands
HELP = [["--help"], ["bench", "--help"], ["store", "--help"]] + [
    [*path, "--help"] for path, _module, _help in COMMANDS]
TYPOS = [["serv"], ["bench", "lantency"], ["store", "chek", "x"], ["demo", "--no-such-flag"]]

_PROBE = """
import json, sys
from agilegs.service.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps({"code": code, "loaded": [m for m in %r if m in sys.modules]}))
"""


def _probe(argv: list[str]) -> tuple[dict[str, object], subprocess.CompletedProcess[str]]:
    proc = subprocess.run([sys.executable, "-c", _PROBE % (HEAVY,), *argv],
                          capture_output=True, text=True, timeout=60)
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc


@pytest.mark.parametrize("argv", HELP, ids=" ".join)
def test_help_answers_without_torch_fastapi_or_matplotlib(argv: list[str]) -> None:
    got, proc = _probe(argv)
    assert got == {"code": 0, "loaded": []}, (got, proc.stderr[-2000:])
    assert "usage: agilegs" in proc.stdout


@pytest.mark.parametrize("argv", TYPOS, ids=" ".join)
def test_a_typo_is_one_usage_error_without_torch(argv: list[str]) -> None:
    got, proc = _probe(argv)
    assert got == {"code": 2, "loaded": []}, (got, proc.stderr[-2000:])
    assert "error:" in proc.stderr and "Traceback" not in proc.stderr


def test_the_console_script_answers_help() -> None:
    proc = subprocess.run([sys.executable, "-m", "agilegs.service.cli", "bench", "run", "--help"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "--scene" in proc.stdout, proc.stderr


def _parsers(parser: argparse.ArgumentParser, path: str = "agilegs"
             ) -> list[tuple[str, argparse.ArgumentParser]]:
    out = [(path, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += _parsers(sub, f"{path} {name}")
    return out


def test_every_option_has_help_and_the_help_has_no_markup() -> None:
    parser = build_parser()
    missing = [f"{path} {'/'.join(a.option_strings) or a.dest}"
               for path, p in _parsers(parser) for a in p._actions
               if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
               and not (a.help or "").strip()]
    assert missing == []
    top = parser.format_help()
    assert "`" not in top and "::" not in top, top
    for path, p in _parsers(parser):
        assert p.get_default("_import_error") is None, path


def test_the_light_options_are_the_commands_own() -> None:
    """A command whose module imports torch defines its options in a light module, and the
    module exposes the same function as ``add_arguments``."""
    from agilegs.config.selection import METHODS
    from agilegs.lab.bench.options import PROFILE_NAMES
    from agilegs.lab.bench.profiles import PROFILES
    from agilegs.service.nbv.methods.base import method_names

    for module, where in OPTIONS.items():
        light, _, function = where.partition(":")
        assert options_function(module) == where
        assert importlib.import_module(module).add_arguments is getattr(
            importlib.import_module(light), function), module
    assert sorted(PROFILE_NAMES) == sorted(PROFILES)
    assert METHODS == method_names()  # bench run's default --methods, in registry order


@pytest.mark.heavy  # five child processes, each importing torch (a benchmark's own check)
def test_bench_render_runs_small() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "bench", "render", "--sizes", "32",
         "--gaussians", "200", "--repeats", "1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "fisher" in proc.stdout and "32²" in proc.stdout


def test_serve_mapper_flags(monkeypatch: pytest.MonkeyPatch) -> None:
    from agilegs.service.serve import build_settings

    monkeypatch.setenv("AGILEGS_MAPPER_BURST", "7")
    args = build_parser().parse_args(
        ["serve", "--no-mapper", "--mapper-steps-per-view", "25", "--no-zenoh"]
    )
    s = build_settings(args)
    assert (s.mapper, s.mapper_steps_per_view, s.mapper_burst, s.zenoh) == (False, 25, 7, False)
    defaults = build_settings(build_parser().parse_args(["serve"]))
    assert defaults.mapper is True and defaults.mapper_steps_per_view == 100
    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", "--mapper", "--no-mapper"])


def test_a_command_line_builds_only_its_own_options() -> None:
    """``build_parser(argv)`` fills in the command that ``argv`` names, and parses it as the
    full parser does."""
    argv = ["bench", "latency", "--pool", "12", "--methods", "base"]
    assert vars(build_parser(argv).parse_args(argv)) == vars(build_parser().parse_args(argv))
    lean = build_parser(["serve"])
    with pytest.raises(SystemExit):  # bench latency has no options in a parser built for serve
        lean.parse_args(argv)
