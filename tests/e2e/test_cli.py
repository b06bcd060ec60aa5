"""The command line wires every documented subcommand."""

from __future__ import annotations

import subprocess
import sys

import pytest

from agilegs.service.cli import build_parser


@pytest.mark.parametrize(
    "argv",
    [
        ["serve", "--help"],
        ["demo", "--help"],
        ["bench", "render", "--help"],
        ["bench", "latency", "--help"],
        ["bench", "run", "--help"],
        ["bench", "service", "--help"],
        ["bench", "proxy", "--help"],
    ],
)
def test_subcommand_help(argv: list[str]) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "usage: agilegs" in proc.stdout


def test_parser_has_no_import_errors() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name, p in sub.choices.items():  # type: ignore[attr-defined]
        assert p.get_default("_import_error") is None, name


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
