"""deploy/: checked as far as this machine can (a Docker client without an engine, no zenohd,
no systemd).

The Dockerfile is parsed (instructions, continuations, ARG defaults); its install commands
must be the deploy page's commands (docs/deploy.md); its ``CMD`` and the systemd ``ExecStart`` must be
accepted by the real ``agilegs serve`` parser and give valid settings; the image's command is
started for real (on 127.0.0.1) and its ``HEALTHCHECK`` must accept it; the compose file and
the environment file must give valid settings that join the router; the JSON5 files must
load with Zenoh's own configuration parser.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
import torch
from conftest import ROOT, free_port

from agilegs.service.cli import build_parser
from agilegs.service.serve import SettingError, build_settings
from agilegs.service.settings import Settings

DEPLOY = ROOT / "deploy"

_INSTRUCTIONS = {"FROM", "ARG", "ENV", "RUN", "WORKDIR", "COPY", "ADD", "USER", "VOLUME",
                 "EXPOSE", "HEALTHCHECK", "CMD", "ENTRYPOINT", "LABEL", "SHELL", "STOPSIGNAL",
                 "ONBUILD"}


# ============================================================================ parsers
def dockerfile(path: Path = DEPLOY / "Dockerfile") -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` in order: comments dropped, ``\\`` continuations joined."""
    out: list[tuple[str, str]] = []
    buf = ""
    for raw in path.read_text().splitlines():
        line = raw.rstrip()
        if line.lstrip().startswith("#") or (not buf and not line.strip()):
            continue  # Docker drops comment lines, inside continuations too
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        buf += line
        word, _, rest = buf.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
        buf = ""
    assert not buf, "a continuation line ends the file"
    return out


def expand(text: str, values: dict[str, str]) -> str:
    """``${NAME}`` / ``$NAME`` replaced by ``values`` (others left as they are)."""
    return re.sub(r"\$\{(\w+)\}|\$(\w+)",
                  lambda mt: values.get(mt.group(1) or mt.group(2), mt.group(0)), text)


def arg_defaults(instructions: list[tuple[str, str]]) -> dict[str, str]:
    out = {}
    for word, rest in instructions:
        if word == "ARG":
            name, _, default = rest.partition("=")
            out[name] = default
    return out


def shell_commands(script: str) -> list[list[str]]:
    """The simple commands of a one-line shell script (split at ``&&``, ``;``, ``|``)."""
    out = []
    script = re.sub(r"\$\([^)]*\)", "SUBST", script)  # $(...) stands for one word
    for part in re.split(r"&&|;|\|\|", script):
        words = shlex.split(part, comments=True)
        while words and re.match(r"^[A-Z_][A-Z0-9_]*=", words[0]):
            words = words[1:]  # VAR=value prefixes
        if words:
            out.append(words)
    return out


def readme_deploy_commands() -> list[list[str]]:
    """The commands of the code blocks of the deploy page (docs/deploy.md)."""
    text = (ROOT / "docs" / "deploy.md").read_text()
    commands = []
    for block in re.findall(r"```(?:bash|sh|console)?\n(.*?)```", text, re.S):
        script = re.sub(r"\\\n", " ", block)
        for line in script.splitlines():
            commands += shell_commands(line)
    return commands


def systemd_unit(path: Path) -> dict[str, list[tuple[str, str]]]:
    """``{section: [(key, value), ...]}`` of a unit file (continuations joined)."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    buf = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not buf and (not line or line[0] in "#;"):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        line, buf = buf + line, ""
        if line.startswith("["):
            assert line.endswith("]"), line
            current = line[1:-1]
            sections[current] = []
            continue
        assert current is not None, f"{line!r} before any section"
        key, sep, value = line.partition("=")
        assert sep, f"not key=value: {line!r}"
        sections[current].append((key.strip(), value.strip()))
    return sections


def env_file(path: Path) -> dict[str, str]:
    out = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            key, sep, value = line.partition("=")
            assert sep and re.match(r"^[A-Z_][A-Z0-9_]*$", key), line
            out[key] = value
    return out


def settings_from_env(env: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> Settings:
    for key in list(os.environ):
        if key.startswith("AGILEGS_"):
            monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    unknown = {k for k in env if k.startswith("AGILEGS_")
               and k[len("AGILEGS_"):].lower() not in Settings.model_fields}
    assert not unknown, f"no such setting: {unknown}"
    return Settings()


def serve_args(argv: list[str]) -> Any:
    """The parsed ``agilegs serve`` arguments (SystemExit on an unknown or bad flag)."""
    assert argv[:2] == ["agilegs", "serve"], argv
    return build_parser().parse_args(argv[1:])


def image_command() -> list[str]:
    cmds = [rest for word, rest in dockerfile() if word == "CMD"]
    assert len(cmds) == 1
    argv = json.loads(cmds[0])  # exec form: no shell in between
    assert isinstance(argv, list) and all(isinstance(a, str) for a in argv)
    return argv


# ============================================================================ Dockerfile
def test_dockerfile_parses_and_builds_cpu_or_cuda_from_arguments() -> None:
    ins = dockerfile()
    assert ins and {w for w, _ in ins} <= _INSTRUCTIONS
    words = [w for w, _ in ins]
    first_from = words.index("FROM")
    assert set(words[:first_from]) <= {"ARG"} and words.count("FROM") == 1
    args = arg_defaults(ins)
    assert ins[first_from][1] == "${BASE}" and args["BASE"] == "python:3.11-slim"
    assert args["TORCH_INDEX"] == "https://download.pytorch.org/whl/cpu"
    # the torch pin is the project's
    pin = re.search(r'"torch>=[\d.]+,<=([\d.]+)"', (ROOT / "pyproject.toml").read_text())
    assert pin and args["TORCH"] == pin.group(1)
    # what it copies exists, and is what the package needs
    copied = [shlex.split(rest)[:-1] for w, rest in ins if w == "COPY"]
    sources = {s for group in copied for s in group}
    assert sources == {"pyproject.toml", "README.md", "config", "schemas", "client", "service",
                       "lab"}
    assert all((ROOT / s).exists() for s in sources)
    # the CMD's ports and state folder are the ones exposed and kept in a volume
    exposed = {p for w, rest in ins if w == "EXPOSE" for p in rest.split()}
    volumes = [json.loads(rest) for w, rest in ins if w == "VOLUME"]
    s = build_settings(serve_args(image_command()))
    assert str(s.port) in exposed and volumes == [[str(s.state_dir)]]
    assert {e.rsplit(":", 1)[1] for e in s.zenoh_listen} <= exposed
    assert s.host == "0.0.0.0" and s.zenoh_mode == "peer"
    for path in ("Dockerfile", "compose.yaml", "zenoh-router.json5", "robot-client.json5",
                 "agilegs.env", "agilegs.service"):
        assert "CHANGE" in (DEPLOY / path).read_text(), f"{path}: mark what users change"


def test_the_image_installs_with_the_readme_commands() -> None:
    ins = dockerfile()
    args = arg_defaults(ins)
    installs = [c for w, rest in ins if w == "RUN"
                for c in shell_commands(expand(rest, args)) if c[:2] == ["pip", "install"]]
    assert installs == [
        ["pip", "install", "torch==2.13.0", "--index-url", "https://download.pytorch.org/whl/cpu"],
        ["pip", "install", ".[service]"],
    ]
    readme = readme_deploy_commands()
    for command in installs:
        assert command in readme, f"docs/deploy.md lacks: {shlex.join(command)}"
    assert image_command() in readme, "docs/deploy.md lacks the image's serve command"
    for command in readme:  # every serve command the page shows is valid
        if command[:2] == ["agilegs", "serve"]:
            args = serve_args(command)
            if str(args.device).startswith("cuda") and not torch.cuda.is_available():
                # a GPU workstation's command: here, refused naming the setting
                with pytest.raises(SettingError, match=r"^device: .*CUDA is not available"):
                    build_settings(args)
            else:
                build_settings(args)


def test_the_readme_docker_commands_fit_the_image() -> None:
    ins = dockerfile()
    args = arg_defaults(ins)
    exposed = {p for w, rest in ins if w == "EXPOSE" for p in rest.split()}
    volume = json.loads(next(rest for w, rest in ins if w == "VOLUME"))[0]
    builds = runs = 0
    for c in readme_deploy_commands():
        if c[:2] == ["docker", "build"]:
            builds += 1
            assert (ROOT / c[c.index("-f") + 1]).is_file() and c[-1] == "."
            build_args = [c[i + 1].split("=", 1)[0] for i, w in enumerate(c) if w == "--build-arg"]
            assert set(build_args) <= set(args), build_args
        elif c[:2] == ["docker", "run"]:
            runs += 1
            ports = [c[i + 1].split(":")[1] for i, w in enumerate(c) if w == "-p"]
            mounts = [c[i + 1].split(":")[1] for i, w in enumerate(c) if w == "-v"]
            assert set(ports) == exposed and mounts == [volume]
        elif c[:3] == ["docker", "compose", "-f"]:
            assert (ROOT / c[3]).is_file()
    assert builds >= 2 and runs >= 2  # CPU and CUDA


def test_the_image_command_serves_and_its_healthcheck_accepts_it(tmp_path: Path) -> None:
    """The CMD run for real with the installed console script (host, ports and state folder
    swapped for loopback, free ports and a temporary folder), then the HEALTHCHECK."""
    argv = image_command()
    port, zport = free_port(), free_port()
    swap = {"--host": "127.0.0.1", "--port": str(port), "--state-dir": str(tmp_path / "state"),
            "--zenoh-listen": f"tcp/127.0.0.1:{zport}"}
    cmd = [str(Path(sys.executable).with_name("agilegs"))] + [
        swap.get(argv[i - 1], a) if i > 0 else a for i, a in enumerate(argv)][1:]
    assert Path(cmd[0]).exists()
    health = [rest for w, rest in dockerfile() if w == "HEALTHCHECK"]
    assert len(health) == 1
    check = shlex.split(health[0].split(" CMD ", 1)[1])
    assert check[:2] == ["python3", "-c"]
    probe = [sys.executable, "-c", check[2].replace("127.0.0.1:8000", f"127.0.0.1:{port}")]

    env = {k: v for k, v in os.environ.items() if not k.startswith("AGILEGS_")}
    env.update(AGILEGS_TOKEN="deploy-test-token", AGILEGS_TORCH_THREADS="1")
    log = open(tmp_path / "serve.log", "wb")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()[-2000:]
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 401:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "the image's command did not serve"
            time.sleep(0.1)
        ok = subprocess.run(probe, env=env, capture_output=True, timeout=30)
        assert ok.returncode == 0, ok.stderr.decode()
        no_token = {k: v for k, v in env.items() if k != "AGILEGS_TOKEN"}
        refused = subprocess.run(probe, env=no_token, capture_output=True, timeout=30)
        assert refused.returncode != 0 and b"401" in refused.stderr
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


# ============================================================================ Zenoh configs
def _zenoh_config(name: str) -> Any:
    import zenoh

    return zenoh.Config.from_file(str(DEPLOY / name))  # Zenoh's own parser: unknown keys fail


def test_router_and_robot_configs_load_with_zenoh() -> None:
    router = _zenoh_config("zenoh-router.json5")
    assert json.loads(router.get_json("mode")) == "router"
    assert json.loads(router.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]
    robot = _zenoh_config("robot-client.json5")
    assert json.loads(robot.get_json("mode")) == "client"
    connect = json.loads(robot.get_json("connect/endpoints"))
    assert connect and all(re.match(r"^tcp/[\w.\-\[\]:]+:7447$", e) for e in connect)


def test_zenoh_rejects_what_the_config_check_relies_on(tmp_path: Path) -> None:
    import zenoh

    bad = tmp_path / "bad.json5"
    bad.write_text('{ mode: "router", listne: { endpoints: [] } }')
    with pytest.raises(zenoh.ZError):
        zenoh.Config.from_file(str(bad))


# ============================================================================ compose
def test_compose_wires_the_router_the_object_store_and_two_instances(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import yaml

    doc = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    services = doc["services"]
    assert set(services) == {"zenoh-router", "minio", "minio-bucket", "agilegs-1", "agilegs-2"}
    router = services["zenoh-router"]
    assert router["image"].startswith("eclipse/zenoh:")
    mount = router["volumes"][0].split(":")
    assert (DEPLOY / mount[0]).resolve() == DEPLOY / "zenoh-router.json5"
    assert router["command"] == ["-c", mount[1]]
    assert "7447:7447" in router["ports"]
    minio = services["minio"]
    assert minio["image"].startswith("minio/minio:") and minio["command"][0] == "server"
    assert "mc mb --ignore-existing m/agilegs" in services["minio-bucket"]["entrypoint"][-1]

    image_settings = build_settings(serve_args(image_command()))
    ids, ports = set(), set()
    for name in ("agilegs-1", "agilegs-2"):
        svc = services[name]
        build = svc["build"]
        context = (DEPLOY / build["context"]).resolve()
        assert context == ROOT and (context / build["dockerfile"]).is_file()
        assert set(build["args"]) <= set(arg_defaults(dockerfile()))
        env = {k: re.sub(r"\$\{(AGILEGS_TOKEN|MINIO_ROOT_PASSWORD):\?[^}]*\}", "compose-secret",
                         str(v)) for k, v in svc["environment"].items()}
        assert svc["environment"]["AGILEGS_TOKEN"].startswith("${AGILEGS_TOKEN:?")  # required
        s = settings_from_env(env, monkeypatch)
        assert s.zenoh_mode == "client" and s.zenoh_connect == ["tcp/zenoh-router:7447"]
        assert s.instance_id and s.token is not None
        assert s.state_url == "s3://agilegs/state" and s.state_endpoint == "http://minio:9000"
        assert env["AWS_ACCESS_KEY_ID"] == minio["environment"]["MINIO_ROOT_USER"]
        assert svc["environment"]["AWS_SECRET_ACCESS_KEY"] == (
            minio["environment"]["MINIO_ROOT_PASSWORD"])
        assert svc["depends_on"]["minio-bucket"]["condition"] == (
            "service_completed_successfully")
        assert "zenoh-router" in svc["depends_on"]
        ids.add(s.instance_id)
        ports.update(p.split(":")[0] for p in svc["ports"])
        assert all(p.endswith(f":{image_settings.port}") for p in svc["ports"])
        volume = svc["volumes"][0].split(":")
        assert volume[1] == str(image_settings.state_dir) and volume[0] in doc["volumes"]
    assert len(ids) == 2 and len(ports) == 2  # one id and one host port each


def test_the_environment_file_joins_the_router(monkeypatch: pytest.MonkeyPatch) -> None:
    s = settings_from_env(env_file(DEPLOY / "agilegs.env"), monkeypatch)
    assert s.zenoh_mode == "client" and s.instance_id == "gpu-1"
    assert len(s.zenoh_connect) == 1 and s.zenoh_connect[0].endswith(":7447")


# ============================================================================ systemd
_UNIT_KEYS = {
    "Unit": {"Description", "Documentation", "Wants", "After", "Requires"},
    "Service": {"Type", "User", "Group", "StateDirectory", "WorkingDirectory",
                "EnvironmentFile", "Environment", "ExecStart", "TimeoutStopSec", "Restart",
                "RestartSec", "NoNewPrivileges", "ProtectSystem", "ProtectHome", "PrivateTmp",
                "ReadWritePaths"},
    "Install": {"WantedBy"},
}


def test_systemd_unit_runs_a_valid_serve_command() -> None:
    unit = systemd_unit(DEPLOY / "agilegs.service")
    assert set(unit) == set(_UNIT_KEYS)
    for section, items in unit.items():
        unknown = {k for k, _ in items} - _UNIT_KEYS[section]
        assert not unknown, f"[{section}] unexpected keys {unknown}"
    service = dict(unit["Service"])
    argv = shlex.split(service["ExecStart"])
    assert argv[0] == "/opt/agilegs/bin/agilegs"
    assert argv[1:] == image_command()[1:]  # the image, the unit and the deploy page run one command
    s = build_settings(serve_args(["agilegs", *argv[1:]]))
    assert str(s.state_dir).startswith(f"/var/lib/{service['StateDirectory']}/")
    assert service["WorkingDirectory"] == f"/var/lib/{service['StateDirectory']}"
    assert service["EnvironmentFile"].lstrip("-") == "/etc/agilegs/agilegs.env"
    assert service["Type"] == "exec" and service["Restart"] == "on-failure"
    assert dict(unit["Install"])["WantedBy"] == "multi-user.target"
    # the install commands in its header are the deploy page's
    header = [line[1:].strip() for line in (DEPLOY / "agilegs.service").read_text().splitlines()
              if line.startswith("#")]
    pips = [c for line in header if "/pip install" in line for c in shell_commands(line)
            if len(c) > 1 and c[0].endswith("/pip") and c[1] == "install"]
    assert [["pip", *c[1:]] for c in pips][0] in readme_deploy_commands()
