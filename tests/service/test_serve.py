"""``agilegs serve``'s start errors: one line naming the address, the cause and the flag
(the processes themselves: tests/e2e/test_state_faults.py)."""

from __future__ import annotations

import errno
from pathlib import Path
from types import SimpleNamespace

import pytest

from agilegs.service.serve import http_bind_error, zenoh_start_error

ZError = type("ZError", (Exception,), {"__module__": "zenoh"})
SETTINGS = SimpleNamespace(http=True, zenoh_mode="peer", zenoh_listen=["tcp/127.0.0.1:7447"],
                           zenoh_connect=[])


def test_a_taken_zenoh_endpoint_names_it_its_cause_and_the_flag() -> None:
    exc = ZError("Can not create a new TCP listener bound to tcp/127.0.0.1:7447: "
                 "[127.0.0.1:7447: Address already in use (os error 98) at /src/tcp.rs:61.] "
                 "at /src/unicast.rs:338.")
    line = zenoh_start_error(exc, SETTINGS)
    assert line == (
        "cannot listen on the Zenoh endpoint tcp/127.0.0.1:7447: address already in use; give "
        "another with --zenoh-listen (AGILEGS_ZENOH_LISTEN), or serve HTTP only with --no-zenoh")
    server_md = (Path(__file__).resolve().parents[2] / "docs" / "server.md").read_text()
    assert f"agilegs serve: {line}\n" in server_md  # the page shows it as it is
    zenoh_only = SimpleNamespace(**{**vars(SETTINGS), "http": False})
    line = zenoh_start_error(exc, zenoh_only)
    assert line is not None and line.endswith("(AGILEGS_ZENOH_LISTEN)")


def test_any_other_zenoh_failure_is_one_line_without_source_locations() -> None:
    exc = ZError("Unable to connect to any of [tcp/10.0.0.1:7447]! at /src/runtime.rs:12.\n"
                 "more")
    line = zenoh_start_error(exc, SETTINGS)
    assert line is not None and "\n" not in line and "/src" not in line
    assert "Unable to connect to any of [tcp/10.0.0.1:7447]!" in line
    assert "--zenoh-connect" in line and "peer mode" in line


def test_what_is_not_zenohs_is_left_alone() -> None:
    assert zenoh_start_error(RuntimeError("boom"), SETTINGS) is None
    assert zenoh_start_error(OSError("no"), SETTINGS) is None


def test_a_taken_http_port_names_it_and_the_flags() -> None:
    exc = OSError(errno.EADDRINUSE, "Address already in use")
    assert http_bind_error(exc, "0.0.0.0", 8000) == (
        "cannot listen on http://0.0.0.0:8000: address already in use; give another with "
        "--port (AGILEGS_PORT) or --host (AGILEGS_HOST), or serve Zenoh only with --no-http")


def test_a_bad_setting_is_one_line_naming_its_flag_and_variable(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from agilegs.service import serve

    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    args = p.parse_args(["--port", "-5", "--state-dir", str(tmp_path / "s")])
    assert serve.run(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("agilegs serve: --port (AGILEGS_PORT): ")
    assert not (tmp_path / "s").exists()  # nothing was started or created


@pytest.mark.parametrize("content", [None, "", "\n"])
def test_the_tls_command_without_its_users_file_is_one_line_and_status_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str | None) -> None:
    """docs/server.md's TLS command, its users.txt missing (or empty)."""
    from conftest import free_port

    from agilegs.service.cli import main

    users = tmp_path / "users.txt"
    if content is not None:
        users.write_text(content)
    code = main(["serve", "--no-http", "--zenoh-listen", f"tls/127.0.0.1:{free_port()}",
                 "--zenoh-dev-certs", str(tmp_path / "certs"), "--zenoh-users-file", str(users),
                 "--state-dir", str(tmp_path / "state")])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith("agilegs serve:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert str(users) in lines[0] and "user:password" in lines[0]
    assert "create it" in lines[0]
