"""``agilegs serve``'s flags come from the settings' fields: the flags of the hand-written
parser the server had before all parse as they did, each setting has its flag (or is kept to
the environment), its help shows its description, default and variable in its group; the
kernels' and the viewer's environment variables are read through the settings."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import pytest

from agilegs.service.settings import (
    GROUPS,
    Credentials,
    Settings,
    add_flags,
    env_var,
    kernel_settings,
    settings_from_flags,
)

# the flags of the server's parser as it was written by hand (every one must still parse)
OLD_FLAGS = (
    "--background-nice", "--body-timeout", "--decision-log", "--forward-timeout", "--fsync",
    "--header-timeout", "--host", "--http", "--instance-id", "--keep-alive-timeout",
    "--log-level", "--mapper", "--mapper-burst", "--mapper-steps-per-view", "--max-body-bytes",
    "--max-body-items", "--max-connections", "--max-gaussians", "--max-header-bytes",
    "--max-image-pixels", "--max-inflight-body-bytes", "--max-inflight-decoded-bytes",
    "--max-poll-wait", "--max-pool-size", "--max-queued", "--max-request-decoded-bytes",
    "--max-select-bytes", "--max-select-seconds", "--max-session-queue", "--max-sessions",
    "--max-shortlist", "--max-views", "--no-fsync", "--no-http", "--no-mapper", "--no-zenoh",
    "--no-zenoh-mtls", "--port", "--read-workers", "--request-deadline", "--ros2",
    "--state-dir", "--torch-threads", "--workers", "--zenoh", "--zenoh-connect",
    "--zenoh-dev-certs", "--zenoh-insecure", "--zenoh-listen", "--zenoh-mode", "--zenoh-mtls",
    "--zenoh-tls-certificate", "--zenoh-tls-private-key", "--zenoh-tls-root-ca",
    "--zenoh-user", "--zenoh-users-file",
)
# what a flag needs beside it to make valid settings (--zenoh-user: AGILEGS_ZENOH_PASSWORD)
COMPANIONS = {
    "--zenoh-tls-certificate": ["--zenoh-tls-private-key", "k.pem"],
    "--zenoh-tls-private-key": ["--zenoh-tls-certificate", "c.pem"],
    "--zenoh-mtls": ["--zenoh-tls-root-ca", "ca.pem", "--zenoh-tls-certificate", "c.pem",
                     "--zenoh-tls-private-key", "k.pem"],
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_flags(parser)
    return parser


def _field(option: str) -> str:
    return option.removeprefix("--").removeprefix("no-").replace("-", "_")


def _sample(option: str) -> tuple[list[str], Any]:
    """A command line giving ``option`` a valid value, and the value the setting takes."""
    name = _field(option)
    field = Settings.model_fields[name]
    default = field.get_default(call_default_factory=True)
    if isinstance(default, bool):
        return [option], not option.startswith("--no-")
    if name == "ros2":
        return [option, "/bot1/agilegs,/bot2/agilegs"], ["/bot1/agilegs", "/bot2/agilegs"]
    if isinstance(default, list):
        return [option, "tcp/10.0.0.1:7447,tcp/10.0.0.2:7447", option, "udp/10.0.0.3:7447"], [
            "tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447", "udp/10.0.0.3:7447"]
    if name == "zenoh_mode":
        return [option, "router"], "router"
    if isinstance(default, int):
        return [option, str(default + 1)], default + 1
    if isinstance(default, float):
        return [option, str(default + 0.5)], default + 0.5
    if name == "instance_id":
        return [option, "node-1"], "node-1"
    if name in ("state_dir",) or name.endswith(("_certificate", "_key", "_ca", "_file", "_certs")):
        return [option, "some/where"], Path("some/where")
    return [option, "debug"], "debug"


@pytest.mark.parametrize("option", OLD_FLAGS)
def test_every_old_flag_parses_to_its_setting(option: str,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    if option == "--zenoh-user":
        monkeypatch.setenv("AGILEGS_ZENOH_PASSWORD", "secret")
    argv, value = _sample(option)
    if isinstance(value, bool):  # the flag wins over the variable saying the opposite
        monkeypatch.setenv(env_var(_field(option)), str(not value).lower())
    else:
        assert value != Settings.model_fields[_field(option)].get_default(
            call_default_factory=True)
    settings = settings_from_flags(_parser().parse_args(argv + COMPANIONS.get(option, [])))
    assert getattr(settings, _field(option)) == value


def test_no_flag_given_is_the_environment_then_the_defaults(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AGILEGS_MAPPER_BURST", "7")
    monkeypatch.setenv("AGILEGS_ZENOH_LISTEN", "tcp/127.0.0.1:9000")
    s = settings_from_flags(_parser().parse_args(["--mapper-burst", "9"]))
    assert (s.mapper_burst, s.zenoh_listen, s.port, s.fsync) == (9, ["tcp/127.0.0.1:9000"],
                                                                 8000, True)
    assert settings_from_flags(_parser().parse_args([])) == Settings()


def test_each_setting_has_its_flag_but_the_secrets() -> None:
    options = {o for a in _parser()._actions for o in a.option_strings} - {"-h", "--help"}
    env_only = {"token", "zenoh_password"}
    want = {f"--{n.replace('_', '-')}" for n in Settings.model_fields if n not in env_only}
    yes_no = {f"--no-{n.replace('_', '-')}" for n, f in Settings.model_fields.items()
              if isinstance(f.default, bool)}
    assert options == want | yes_no
    assert set(OLD_FLAGS) <= options


def test_the_help_shows_description_default_and_variable_in_groups() -> None:
    parser = _parser()
    titles = [g.title for g in parser._action_groups][2:]
    assert titles == list(GROUPS)
    assert "AGILEGS_FORWARD_TIMEOUT" in parser.format_help()  # it renders
    text = " | ".join(a.help for a in parser._actions if a.help)
    for name, field in Settings.model_fields.items():
        if name in ("token", "zenoh_password"):
            continue
        action = next(a for a in parser._actions if a.dest == name and a.help
                      and not a.help.startswith("the opposite"))
        assert action.help is not None
        help_text = action.help.replace("%%", "%")
        assert help_text.startswith(field.description or "?"), name
        assert help_text.endswith(f"{env_var(name)})"), name
        assert "default" in help_text, name
    assert "(default 8000; AGILEGS_PORT)" in text
    assert "(default on; AGILEGS_FSYNC)" in text
    assert "(default tcp/127.0.0.1:7447;" in text
    with pytest.raises(SystemExit):
        parser.parse_args(["--mapper", "--no-mapper"])


def test_the_kernels_environment_goes_through_the_settings(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("AGILEGS_KERNELS", raising=False)
    monkeypatch.delenv("AGILEGS_KERNEL_THREADS", raising=False)
    assert (kernel_settings().kernels, kernel_settings().kernel_threads) == ("auto", None)
    monkeypatch.setenv("AGILEGS_KERNELS", " Torch ")
    monkeypatch.setenv("AGILEGS_KERNEL_THREADS", "3")
    assert (kernel_settings().kernels, kernel_settings().kernel_threads) == ("torch", 3)
    monkeypatch.setenv("AGILEGS_KERNELS", "")
    assert kernel_settings().kernels == "auto"
    monkeypatch.delenv("AGILEGS_GPU_ANCHOR", raising=False)
    assert kernel_settings().gpu_anchor
    monkeypatch.setenv("AGILEGS_GPU_ANCHOR", "0")
    assert not kernel_settings().gpu_anchor
    monkeypatch.setenv("AGILEGS_GPU_ANCHOR", " ")
    assert kernel_settings().gpu_anchor
    for var, bad in (("AGILEGS_KERNELS", "fast"), ("AGILEGS_KERNEL_THREADS", "0"),
                     ("AGILEGS_KERNEL_THREADS", "two"), ("AGILEGS_GPU_ANCHOR", "maybe")):
        monkeypatch.setenv(var, bad)
        with pytest.raises(ValueError, match=f"{var}: .*got '{bad}'"):
            kernel_settings()
        monkeypatch.delenv(var)


def test_the_token_is_one_setting_for_the_server_and_the_viewer(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AGILEGS_TOKEN", "t0ken")
    assert Credentials().token_value() == "t0ken" == Settings().token_value()
    monkeypatch.setenv("AGILEGS_TOKEN", "")
    assert Credentials().token_value() is None
