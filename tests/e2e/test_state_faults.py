"""Faults beyond a crash with real ``agilegs serve`` processes: two servers on one state
folder, a killed server's claim, a folder that cannot be used, an HTTP port or a Zenoh
endpoint already taken, a real full disk (a small tmpfs, as root) over HTTP and Zenoh, and
the offline ``agilegs store`` tools."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, ring_poses
from inprocess import serve_in_process
from readonly import read_only_folder, small_tmpfs

from agilegs.client import Client, InsufficientStorageError, SessionDamagedError, TransportError
from agilegs.schemas import ObservationIn

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}
POOL = ring_poses(8)


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AGILEGS_")}
    env.update(AGILEGS_TORCH_THREADS="1", AGILEGS_MAPPER="0")
    return env


def agilegs(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "agilegs.service.cli", *args], env=_env(),
                          capture_output=True, text=True, timeout=timeout)


def serve(state: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """``agilegs serve`` that is expected to refuse to start."""
    return agilegs("serve", "--host", "127.0.0.1", "--port", "0", "--no-zenoh",
                   "--state-dir", str(state), *extra, timeout=60)


def one_line(done: subprocess.CompletedProcess[str]) -> str:
    lines = [x for x in done.stderr.splitlines() if x.strip()]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert len(lines) == 1, done.stderr
    return lines[0]


@pytest.mark.heavy
def test_one_server_per_state_folder(server_factory: Any, tmp_path: Path) -> None:
    state = tmp_path / "state"
    first = server_factory(state, zenoh=False).start()
    with Client(first.url) as c:
        c.create_session(SMALL_INTRINSICS, id="a", bounds=BOUNDS, init_gaussians=30)
    line = one_line(serve(state))
    assert str(state) in line and "in use by agilegs serve" in line
    assert f"pid {first.proc.pid} " in line
    with Client(first.url) as c:  # the first one serves on, alone
        assert [s.id for s in c.list_sessions().sessions] == ["a"]
        # and the offline repair refuses to touch the folder under it
        done = agilegs("store", "repair", str(state))
        assert done.returncode == 2 and "in use by agilegs serve" in done.stderr
    first.kill()  # SIGKILL: its claim is left behind in the lock file ...
    second = server_factory(state, zenoh=False).start()  # ... and does not block a restart
    with Client(second.url) as c:
        assert c.get_session("a").version == 1


def test_a_folder_that_cannot_be_used_is_one_line_and_a_nonzero_exit(tmp_path: Path) -> None:
    a_file = tmp_path / "file"
    a_file.write_text("x")
    line = one_line(serve(a_file / "state"))
    assert "cannot create the state folder" in line
    with read_only_folder(tmp_path / "ro") as ro:
        line = one_line(serve(ro))
        assert "read-only" in line and str(ro) in line


def _error_line(done: subprocess.CompletedProcess[str]) -> str:
    """The one ``agilegs serve:`` line of a start that failed (log lines may precede it)."""
    lines = [x for x in done.stderr.splitlines() if x.startswith("agilegs serve:")]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert len(lines) == 1 and done.stderr.rstrip().endswith(lines[0]), done.stderr
    return lines[0]


def test_a_taken_port_or_endpoint_is_one_line_and_a_nonzero_exit(tmp_path: Path) -> None:
    from agilegs.service.store.state_dir import is_claimed

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with socket.socket() as other:  # a free port for the side that is not under test
            other.bind(("127.0.0.1", 0))
            free = other.getsockname()[1]
        line = _error_line(agilegs("serve", "--host", "127.0.0.1", "--port", str(free),
                                   "--zenoh-listen", f"tcp/127.0.0.1:{port}",
                                   "--state-dir", str(tmp_path / "z"), timeout=60))
        assert f"Zenoh endpoint tcp/127.0.0.1:{port}" in line, line
        assert "address already in use" in line and "--zenoh-listen" in line, line
        assert not is_claimed(tmp_path / "z")  # the state folder was let go
        line = _error_line(agilegs("serve", "--host", "127.0.0.1", "--port", str(port),
                                   "--no-zenoh", "--state-dir", str(tmp_path / "h"),
                                   timeout=60))
        assert f"http://127.0.0.1:{port}" in line and "address already in use" in line, line
        assert "--port" in line, line
        assert not is_claimed(tmp_path / "h")


def _fill(disk: Path) -> Path:
    """Fill ``disk`` to the last byte with one file; returns it."""
    filler = disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        for size in (65536, 4096, 1):
            while True:
                try:
                    os.write(fd, b"\0" * size)
                except OSError:
                    break
    finally:
        os.close(fd)
    return filler


@pytest.mark.heavy
def test_a_full_disk_is_507_over_http_and_zenoh(server_factory: Any, tmp_path: Path) -> None:
    from agilegs.client import ZenohClient

    with small_tmpfs(tmp_path / "disk", "4m") as disk:
        srv = server_factory(disk / "state", log_path=tmp_path / "serve.log").start()
        img = np.random.default_rng(0).integers(0, 255, (32, 32, 3), dtype=np.uint8)
        with Client(srv.url, timeout=30) as c, \
                ZenohClient([srv.zenoh_endpoint], timeout=30) as z:
            for sid in ("a", "b"):
                c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=200,
                                 pool=POOL, defaults={"shortlist_size": 3})
                c.select(sid, method="agile", commit=True)
            acked = {sid: (c.get_session(sid).version, c.get_session(sid).information.digest)
                     for sid in ("a", "b")}
            filler = _fill(disk)
            writes = [
                lambda cl: cl.create_session(SMALL_INTRINSICS, id="c", bounds=BOUNDS,
                                             init_gaussians=2000, pool=POOL),
                lambda cl: cl.commit("a", candidate_id=4),
                lambda cl: cl.select("b", method="agile", commit=True),
                lambda cl: cl.add_observations("a", ObservationIn.from_numpy(POOL[5],
                                                                             image=img)),
                lambda cl: cl.set_pool("b", POOL[:3]),
            ]
            refused, resets, bodies = 0, 0, {}
            for _ in range(3):
                for i, write in enumerate(writes):
                    for name, cl in (("http", c), ("zenoh", z)):
                        try:
                            write(cl)
                        except InsufficientStorageError as exc:
                            refused += 1
                            bodies.setdefault(i, {})[name] = (exc.status, exc.code, exc.message)
                        except TransportError:
                            resets += 1
                    # reads keep working on a full disk
                    assert [s.id for s in c.list_sessions().sessions] == ["a", "b"]
                    assert z.get_session("a").version == acked["a"][0]
                    c.select("b", method="agile")  # a selection without commit writes nothing
            assert resets == 0
            assert refused == 3 * len(writes) * 2
            for i, by in bodies.items():  # the same answer over both transports
                assert by["http"] == by["zenoh"], (i, by)
                assert by["http"][0] == 507 and by["http"][1] == "insufficient_storage"
            assert {sid: (c.get_session(sid).version, c.get_session(sid).information.digest)
                    for sid in ("a", "b")} == acked
            metrics = httpx_get(srv.url + "/metrics")
            counted = sum(float(x.rsplit(" ", 1)[1]) for x in metrics.splitlines()
                          if x.startswith("agilegs_writes_refused_total{"))
            assert counted == refused
            filler.unlink()  # space is back: the same writes succeed
            for write in writes:
                write(c)
            after = {sid: (c.get_session(sid).version, c.get_session(sid).information.digest)
                     for sid in ("a", "b", "c")}
        srv.stop()
        again = server_factory(disk / "state", log_path=tmp_path / "serve2.log").start()
        with Client(again.url) as c:
            assert {sid: (c.get_session(sid).version, c.get_session(sid).information.digest)
                    for sid in ("a", "b", "c")} == after
            assert {s.state for s in c.list_sessions().sessions} == {"ok"}
        again.stop()


def httpx_get(url: str) -> str:
    import httpx

    return httpx.get(url, timeout=10).text


@pytest.mark.heavy
def test_store_check_and_repair_from_the_command_line(server_factory: Any,
                                                      tmp_path: Path) -> None:
    state = tmp_path / "state"
    srv = server_factory(state, zenoh=False).start()
    with Client(srv.url) as c:
        c.create_session(SMALL_INTRINSICS, id="a", bounds=BOUNDS, init_gaussians=30, pool=POOL)
        c.commit("a", candidate_id=1)
        intact = c.get_session("a").information.digest
        c.commit("a", candidate_id=2)
        c.create_session(SMALL_INTRINSICS, id="b", bounds=BOUNDS, init_gaussians=30)
    srv.stop()
    manifest = state / "sessions" / "a" / "manifest.json"
    manifest.write_bytes(manifest.read_bytes()[:100])  # truncated, as a careless copy does

    done = agilegs("store", "check", str(state))
    assert done.returncode == 1, done.stdout + done.stderr
    assert "2 session(s), 1 damaged" in done.stdout and "manifest.json" in done.stdout

    # served (a server in this process: the tools' processes are what is under test here):
    # listed damaged, not absent
    with serve_in_process(state) as inproc, inproc.client() as c:
        listed = {s.id: s for s in c.list_sessions().sessions}
        assert listed["a"].state == "damaged" and listed["b"].state == "ok"
        with pytest.raises(SessionDamagedError, match="manifest.json"):
            c.get_session("a")

    done = agilegs("store", "repair", str(state))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "a: repaired" in done.stdout and "every session checks out" in done.stdout
    assert agilegs("store", "check", str(state)).returncode == 0
    with serve_in_process(state) as inproc, inproc.client() as c:
        assert c.get_session("a").information.digest == intact
