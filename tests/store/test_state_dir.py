"""One server per state folder: the exclusive claim, its holder named when refused, a killed
holder's claim released by the kernel; a folder that cannot be used refused in one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from inprocess import serve_in_process
from readonly import read_only_folder

from agilegs.service.server import Server
from agilegs.service.settings import Settings
from agilegs.service.store.state_dir import (
    LOCK_FILE,
    StateDirError,
    claim_state_dir,
    is_claimed,
    read_holder,
)


def test_a_second_claim_is_refused_naming_the_holder(tmp_path: Path) -> None:
    state = tmp_path / "new" / "state"  # missing: created
    first = claim_state_dir(state, command="agilegs serve", instance="lab-8000")
    assert state.is_dir() and is_claimed(state)
    holder = read_holder(state)
    assert holder is not None and holder["pid"] == os.getpid()
    assert holder["instance"] == "lab-8000" and holder["command"] == "agilegs serve"
    with pytest.raises(StateDirError) as exc:
        claim_state_dir(state, command="agilegs serve")
    msg = str(exc.value)
    assert "\n" not in msg and str(state) in msg and "in use by agilegs serve" in msg
    assert f"pid {os.getpid()}" in msg and "instance lab-8000" in msg
    first.release()
    assert not is_claimed(state)
    with claim_state_dir(state, command="agilegs store repair") as again:
        assert again.held and read_holder(state)["command"] == "agilegs store repair"
    assert not is_claimed(state)


HOLD = textwrap.dedent("""
    import sys, time
    from agilegs.service.store.state_dir import claim_state_dir
    lock = claim_state_dir(sys.argv[1], command="agilegs serve", instance="killed-1")
    print("held", flush=True)
    time.sleep(600)
""")


def test_a_killed_holder_does_not_block_the_next_claim(tmp_path: Path) -> None:
    state = tmp_path / "state"
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(state)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
        with pytest.raises(StateDirError, match=f"pid {proc.pid} .*instance killed-1"):
            claim_state_dir(state, command="agilegs serve")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
        if proc.stdout is not None:
            proc.stdout.close()
    assert read_holder(state)["pid"] == proc.pid  # the stale record is still there
    with claim_state_dir(state, command="agilegs serve") as lock:  # but nothing holds it
        assert lock.held and read_holder(state)["pid"] == os.getpid()


def test_a_folder_that_cannot_be_used_is_one_line(tmp_path: Path) -> None:
    a_file = tmp_path / "file"
    a_file.write_text("not a folder")
    with pytest.raises(StateDirError, match="cannot create the state folder") as exc:
        claim_state_dir(a_file / "state", command="agilegs serve")
    assert "\n" not in str(exc.value)
    with pytest.raises(StateDirError, match="is not a folder"):
        claim_state_dir(a_file, command="agilegs serve")
    with read_only_folder(tmp_path / "ro") as ro:
        with pytest.raises(StateDirError, match="read-only") as exc:
            claim_state_dir(ro, command="agilegs serve")
        assert "\n" not in str(exc.value)
        with pytest.raises(StateDirError, match="read-only"):
            claim_state_dir(ro / "state", command="agilegs serve")


def test_a_server_holds_its_folder_while_it_runs(tmp_path: Path) -> None:
    state = tmp_path / "state"
    with serve_in_process(state) as srv:
        assert is_claimed(state) and (state / LOCK_FILE).exists()
        assert read_holder(state)["instance"] == srv.server.cluster.instance_id
        second = Server(Settings(state_dir=state, zenoh=False, mapper=False))
        with pytest.raises(StateDirError, match="in use by agilegs serve"):
            second.start()
        second.close()
        srv.client().health()  # the first one serves on
    assert not is_claimed(state)  # released on shutdown
    with serve_in_process(state) as srv:
        assert srv.client().health().status == "ok"
