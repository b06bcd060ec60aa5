"""Faults beyond a crash, through the HTTP API of a server in this process: every kind of
state file truncated or with a flipped byte, then a restart (the fault matrix); a full disk
during each kind of write.

Every case checks that the damaged session is either recovered to its last acknowledged
state or listed as damaged with the file and what is wrong (never absent, never served
wrong), that a repair brings back exactly the state acknowledged at the version it names,
and that the other session is untouched. ``pytest -s`` prints the matrix's figures.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, call, ring_poses
from inprocess import serve_in_process

from agilegs.client import Client, InsufficientStorageError, SessionDamagedError
from agilegs.schemas import ObservationIn
from agilegs.service.store.integrity import decode_manifest
from agilegs.service.store.records import MANIFEST
from agilegs.service.store.write import SessionStore

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}
POOL = ring_poses(8)
RNG = np.random.default_rng(7)
IMG = RNG.integers(0, 255, (32, 32, 3), dtype=np.uint8)
DEPTH = np.full((32, 32), 2.0, np.float32)


@dataclass
class Tally:
    """What the matrix saw."""

    cases: int = 0
    acknowledged: int = 0
    silently_lost: int = 0
    rolled_back: int = 0  # versions given up by a repair, each reported before it happened
    answers_500: int = 0
    resets: int = 0
    outcomes: dict[str, str] = field(default_factory=dict)


class Counting(httpx.BaseTransport):
    """Counts answers 500 and transport failures of the requests it passes on."""

    def __init__(self, inner: httpx.BaseTransport, tally: Tally) -> None:
        self.inner = inner
        self.tally = tally

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        try:
            resp = self.inner.handle_request(request)
        except httpx.TransportError:
            self.tally.resets += 1
            raise
        if resp.status_code >= 500 and resp.status_code != 507:
            self.tally.answers_500 += 1
        return resp


@contextmanager
def serving(state: Path, tally: Tally) -> Iterator[Client]:
    with serve_in_process(state, fsync=False) as srv:  # no power cut here: fsync adds nothing
        with Client(srv.url, transport=Counting(srv.transport, tally)) as c:
            yield c


def state_of(c: Client, sid: str) -> tuple:
    """What a session acknowledged (its version aside)."""
    info = c.get_session(sid)
    return (info.information.digest, info.gaussians.count,
            json.dumps(c.get_pool(sid).model_dump(exclude={"version"})),
            json.dumps(c.list_views(sid).model_dump(exclude={"version"})))


def frame(i: int) -> ObservationIn:
    return ObservationIn.from_numpy(POOL[i], image=IMG, depth=DEPTH)


LAST_WRITES: dict[str, Callable[[Client], Any]] = {
    "gaussians": lambda c: c.set_gaussians("a", {k: v * 1.01 for k, v in
                                                 c.get_gaussians("a").to_numpy().items()}),
    "information": lambda c: c.commit("a", pose=POOL[3]),
    "pool": lambda c: c.extend_pool("a", POOL[:2], ids=[100, 101]),
    "warm": lambda c: c.select("a", method="agile", commit=True),
    "frames": lambda c: c.add_observations("a", frame(5)),
}


def build(c: Client, last: str) -> dict[int, tuple]:
    """Session ``a``: five acknowledged writes, the last one ``LAST_WRITES[last]``; session
    ``other`` beside it. Returns ``a``'s acknowledged state per version."""
    c.create_session(SMALL_INTRINSICS, id="other", bounds=BOUNDS, init_gaussians=40,
                     pool=POOL, defaults={"shortlist_size": 3})
    c.commit("other", candidate_id=2)
    history: dict[int, tuple] = {}

    def ack(write: Callable[[], Any]) -> None:
        write()
        history[c.get_session("a").version] = state_of(c, "a")

    ack(lambda: c.create_session(SMALL_INTRINSICS, id="a", bounds=BOUNDS, init_gaussians=60,
                                 pool=POOL, defaults={"shortlist_size": 3}))
    ack(lambda: c.select("a", method="agile", commit=True))
    ack(lambda: c.add_observations("a", frame(4)))
    left = c.get_pool("a").ids()  # candidate 6, unless the selection committed it
    cid = 6 if 6 in left else left[-1]
    ack(lambda: c.commit("a", candidate_id=cid))
    ack(lambda: LAST_WRITES[last](c))
    return history


def target_file(folder: Path, kind: str) -> str:
    """The file of ``kind`` the current version of the session in ``folder`` names."""
    if kind == "manifest":
        return MANIFEST
    m = decode_manifest((folder / MANIFEST).read_bytes())
    if kind in ("image", "depth"):
        key = "image_file" if kind == "image" else "depth_file"
        return "views/" + [v[key] for v in m["views"] if v[key]][-1]
    return str(m["files"][kind])


def folder_bytes(folder: Path) -> dict[str, str]:
    """Every file under ``folder``: relative path -> sha256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncate":
        path.write_bytes(data[: len(data) // 2])
    else:  # one byte changed in place, the way a failing disk or a stray write leaves it
        with open(path, "r+b") as f:
            f.seek(len(data) // 2)
            f.write(bytes([data[len(data) // 2] ^ 0x04]))


# (kind of file damaged, the last write before the damage, what the restart must show)
#   rollback: damaged, repair restores the version before the last write
#   drop: damaged, repair drops the frame of the last view (the current version stays)
#   recovered: served as acknowledged (a damaged warm-start state is only a cold start)
#   lost: damaged, the file is shared by both kept versions: nothing to roll back to
CASES = [
    ("manifest", "information", "rollback"),
    ("manifest", "frames", "rollback"),
    ("gaussians", "gaussians", "rollback"),
    ("information", "information", "rollback"),
    ("pool", "pool", "rollback"),
    ("warm", "warm", "recovered"),
    ("image", "frames", "drop"),
    ("depth", "frames", "drop"),
    ("image", "information", "drop"),  # an older view's image: still only that frame
    ("gaussians", "pool", "lost"),
    ("information", "pool", "lost"),
    ("pool", "information", "lost"),
]


def test_fault_matrix(tmp_path: Path) -> None:
    """Every case of :data:`CASES`, truncated and with a flipped byte; prints the figures."""
    tally = Tally()
    built = {}
    for last in sorted({c[1] for c in CASES}):  # one state folder per last write, built once
        state = tmp_path / f"built-{last}"
        with serving(state, tally) as c:
            history = build(c, last)
            other = state_of(c, "other"), c.get_session("other").version
        built[last] = (state, history, other)
    for kind, last, expect in CASES:
        for how in ("truncate", "flip"):
            what = "truncated" if how == "truncate" else "a byte flipped"
            case = f"{kind}: {what}, after the {last} write"
            try:
                run_case(tmp_path / f"{kind}-{last}-{how}", built[last], kind, expect, how,
                         tally)
            except AssertionError as exc:
                raise AssertionError(f"case {case}: {exc}") from exc
            tally.cases += 1
            tally.outcomes[case] = expect
    unrecoverable = sum(1 for o in tally.outcomes.values() if o == "lost")
    print(f"\nfault matrix: {tally.cases} cases, {tally.acknowledged} acknowledged writes, "
          f"{tally.silently_lost} silently lost, {tally.rolled_back} repairs rolled back one "
          f"version (reported first), {unrecoverable} unrecoverable (reported, then deleted), "
          f"{tally.answers_500} answers 500, {tally.resets} resets")
    for case, outcome in tally.outcomes.items():
        print(f"  {case:<44} {outcome}")
    assert tally.cases == 2 * len(CASES)
    assert tally.silently_lost == 0 and tally.answers_500 == 0 and tally.resets == 0


def run_case(state: Path, built: tuple[Path, dict, tuple], kind: str, expect: str, how: str,
             tally: Tally) -> None:
    src, history, (other_state, other_version) = built
    shutil.copytree(src, state)
    last_version = max(history)
    tally.acknowledged += len(history)
    folder = state / "sessions" / "a"
    name = target_file(folder, kind)
    damage(folder / name, how)

    with serving(state, tally) as c:
        listed = {e.id: e for e in c.list_sessions().sessions}
        if "a" not in listed:
            tally.silently_lost += 1
        assert set(listed) == {"a", "other"}  # never silently absent
        a = listed["a"]
        if expect == "recovered":
            if a.state != "ok" or state_of(c, "a") != history[last_version]:
                tally.silently_lost += 1
            assert a.state == "ok" and a.version == last_version
            assert state_of(c, "a") == history[last_version]
            c.select("a", method="agile")  # a cold start, from the checked state
        else:
            if a.state != "damaged":
                tally.silently_lost += 1
            assert a.state == "damaged" and a.damage is not None
            assert [p.file for p in a.damage.files] == [name], a.damage
            assert a.damage.files[0].problem  # what is wrong, in words
            # never served: every operation names the damage
            for read in (c.get_session, c.get_pool, c.list_views, c.get_information):
                with pytest.raises(SessionDamagedError, match=name):
                    read("a")
            with pytest.raises(SessionDamagedError):
                c.select("a", method="random", commit=True)
            with pytest.raises(SessionDamagedError):
                c.create_session(SMALL_INTRINSICS, id="a", bounds=BOUNDS)
            _repair(c, a, expect, name, history, last_version, tally)
        # the other session is untouched
        assert state_of(c, "other") == other_state
        assert c.get_session("other").version == other_version
        c.commit("other", candidate_id=3)


def _repair(c: Client, a: Any, expect: str, name: str, history: dict[int, tuple],
            last_version: int, tally: Tally) -> None:
    if expect == "lost":
        assert not a.damage.repairable and a.damage.rollback_to is None
        with pytest.raises(SessionDamagedError, match="nothing intact"):
            c.repair_session("a")
        assert c.delete_session("a").deleted
        assert "a" not in {e.id for e in c.list_sessions().sessions}
        c.create_session(SMALL_INTRINSICS, id="a", bounds=BOUNDS)  # the id is free again
        return
    assert a.damage.repairable
    done = c.repair_session("a")
    assert done.repaired and done.version > last_version
    after = state_of(c, "a")
    if expect == "rollback":
        assert a.damage.rollback_to == last_version - 1 == done.rolled_back_to
        assert after == history[last_version - 1]  # exactly what was acknowledged then
        tally.rolled_back += 1
    else:  # drop: the current version, without the damaged frame file
        vid = int(name.split("/v")[1].split(".")[0])
        assert a.damage.drop_frames == [vid] == done.dropped_frames
        assert done.rolled_back_to is None
        digest, count, pool, _ = history[last_version]
        assert after[:3] == (digest, count, pool)
        view = {v.id: v for v in c.list_views("a").views}[vid]
        assert view.has_image == ("rgb" not in name) and view.has_depth == ("depth" not in name)
    c.select("a", method="random", commit=True)  # serving again
    assert c.repair_session("a").repaired is False  # nothing left to repair


# ---------------------------------------------------------------------------- a full disk
WRITES = {  # the file name a write makes -> an operation that makes it
    "gaussians.": lambda c: c.set_gaussians("a", c.get_gaussians("a").to_numpy()),
    "information.": lambda c: c.commit("a", pose=POOL[1]),
    "pool.": lambda c: c.set_pool("a", POOL[:4]),
    "warm.": lambda c: c.select("a", method="agile", commit=True),
    ".rgb.": lambda c: c.add_observations("a", frame(2)),
    ".depth.": lambda c: c.add_observations("a", ObservationIn.from_numpy(POOL[2],
                                                                          depth=DEPTH)),
    MANIFEST: lambda c: c.extend_pool("a", POOL[:1], ids=[55]),
    "link": lambda c: c.commit("a", candidate_id=5),  # the previous manifest's hard link
    "upload-": lambda c: c.set_gaussians("a", str(UPLOAD)),
    "creating": lambda c: c.create_session(SMALL_INTRINSICS, id="b", bounds=BOUNDS),
}
UPLOAD = Path(__file__).resolve().parents[2] / "lab" / "scenes" / "spot" / "spot_10k.splat"


@pytest.mark.parametrize("match", list(WRITES), ids=[w.strip(".-") for w in WRITES])
def test_a_full_disk_is_a_507_and_changes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                  match: str) -> None:
    state = tmp_path / "state"
    with serve_in_process(state) as srv, srv.client() as c:
        c.create_session(SMALL_INTRINSICS, id="a", bounds=BOUNDS, init_gaussians=60, pool=POOL,
                         defaults={"shortlist_size": 3})
        c.create_session(SMALL_INTRINSICS, id="other", bounds=BOUNDS, init_gaussians=30)
        before = {sid: (state_of(c, sid), c.get_session(sid).version) for sid in ("a", "other")}
        files = folder_bytes(state / "sessions")
        with monkeypatch.context() as mp:
            _fill_disk(mp, match)
            with pytest.raises(InsufficientStorageError) as exc:
                WRITES[match](c)
            assert exc.value.status == 507 and exc.value.code == "insufficient_storage"
            assert "full" in exc.value.message
            # reads keep working, and nothing changed, in memory or on disk
            assert folder_bytes(state / "sessions") == files
            assert {sid: (state_of(c, sid), c.get_session(sid).version)
                    for sid in ("a", "other")} == before
            assert [s.id for s in c.list_sessions().sessions] == ["a", "other"]
            c.select("a", method="agile")
        metrics = srv.http().get("/metrics").text
        line = next(x for x in metrics.splitlines()
                    if x.startswith("agilegs_writes_refused_total{"))
        assert 'source="http"' in line and line.endswith(" 1.0")
        WRITES[match](c)  # space is back: the same write succeeds
        assert not list(state.rglob("*.tmp-*")) and not list((state / "tmp").iterdir())
        leftovers = [p for p in (state / "sessions").iterdir() if p.name.startswith(".")]
        assert leftovers == []
        assert c.get_session("other").version == before["other"][1]
        after = {sid: state_of(c, sid) for sid in ("a", "other")}
    with serve_in_process(state) as srv, srv.client() as c:  # and all of it is persisted
        assert {sid: state_of(c, sid) for sid in ("a", "other")} == after
        assert {s.state for s in c.list_sessions().sessions} == {"ok"}


def _fill_disk(mp: pytest.MonkeyPatch, match: str) -> None:
    """Every write of a file whose name contains ``match`` fails as on a full disk."""
    import builtins

    real_open = builtins.open

    def refusing_open(file: Any, mode: str = "r", *args: Any, **kw: Any) -> Any:
        if "w" in mode and match in str(file):
            raise OSError(errno.ENOSPC, "No space left on device", str(file))
        return real_open(file, mode, *args, **kw)

    real_mkdir = Path.mkdir

    def refusing_mkdir(self: Path, *args: Any, **kw: Any) -> None:
        if match in self.name:
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        real_mkdir(self, *args, **kw)

    if match == "link":
        def refusing_link(*args: Any, **kw: Any) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

        mp.setattr(os, "link", refusing_link)
        return
    mp.setattr(builtins, "open", refusing_open)
    mp.setattr(Path, "mkdir", refusing_mkdir)
    if match == "upload-":  # the upload is written with Path.write_bytes
        real_write_bytes = Path.write_bytes

        def refusing_write_bytes(self: Path, data: Any) -> int:
            if match in self.name:
                raise OSError(errno.ENOSPC, "No space left on device", str(self))
            return real_write_bytes(self, data)

        mp.setattr(Path, "write_bytes", refusing_write_bytes)


def test_a_full_disk_during_a_map_publication_is_retried(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from agilegs.service.sessions.registry import SessionRegistry
    from agilegs.service.sessions.trainer import Trainer
    from agilegs.service.settings import Settings

    core = SessionRegistry(Settings(state_dir=tmp_path / "state", zenoh=False, workers=2,
                                    mapper=False, mapper_steps_per_view=4, mapper_burst=4))
    refused: list[str] = []
    core.on_refused_write = lambda source, op: refused.append(f"{source}/{op}")
    core.load()
    call(core, "create_session", None, {
        "id": "s", "intrinsics": SMALL_INTRINSICS, "init_gaussians": 60, "bounds": BOUNDS,
        "frames": [frame(0).model_dump()]})
    # the mapper's worker, its bursts driven from here
    trainer = Trainer(lambda: list(core.sessions.values()), core.settings,
                      on_refused_write=core._refused_publication)
    st = trainer.attach(core.sessions["s"])
    version = core.sessions["s"].record.version
    with monkeypatch.context() as mp:
        real = SessionStore.save

        def full(self: SessionStore, *args: Any, **kw: Any) -> Any:
            raise OSError(errno.ENOSPC, "No space left on device")

        mp.setattr(SessionStore, "save", full)
        assert trainer.burst(st) == 0
        status = call(core, "get_session", "s", None).mapper
        assert status.state == "error" and "full" in (status.error or "")
        assert refused == ["mapper/publish"] and st.steps == 4 and st.dirty  # kept
        assert not st.has_work()  # waits before the next try
        mp.setattr(SessionStore, "save", real)
    st.full_until = 0.0  # the wait is over
    assert st.has_work()
    trainer.burst(st)
    info = call(core, "get_session", "s", None)
    assert info.version == version + 1 and info.mapper.published_steps == 4
    assert info.mapper.state == "idle"
    core.close()


def test_with_the_mapper_on_a_repaired_session_trains_again(tmp_path: Path) -> None:
    import time

    state = tmp_path / "state"
    settings = {"mapper": True, "mapper_steps_per_view": 4, "mapper_burst": 4}
    opts = {"config": {"densify_from": 10_000}}

    def idle(c: Client, sid: str) -> Any:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            info = c.get_session(sid)
            if info.mapper is not None and info.mapper.state == "idle":
                return info
            time.sleep(0.05)
        raise AssertionError(f"the mapper of {sid} did not finish: {info.mapper}")

    with serve_in_process(state, **settings) as srv, srv.client() as c:
        c.create_session(SMALL_INTRINSICS, id="a", init_gaussians=60, frames=[frame(0)],
                         pool=POOL, mapper=opts)
        c.create_session(SMALL_INTRINSICS, id="other", init_gaussians=30, bounds=BOUNDS)
        idle(c, "a")
        c.add_observations("a", frame(1))
        before = idle(c, "a")
        other = c.get_session("other").version
    damage(state / "sessions" / "a" / MANIFEST, "truncate")
    with serve_in_process(state, **settings) as srv, srv.client() as c:
        listed = {s.id: s for s in c.list_sessions().sessions}
        assert listed["a"].state == "damaged" and listed["other"].state == "ok"
        done = c.repair_session("a")
        assert done.rolled_back_to is not None and done.rolled_back_to < before.version
        after = idle(c, "a")  # the mapper trains what the restored version owes
        assert after.mapper.steps == after.mapper.published_steps == 4 * after.num_views
        assert c.get_session("other").version == other
