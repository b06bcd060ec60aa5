"""The session store in an object store: the same sessions, damage reports and repairs as the
state folder; fresh keys for every version; the conditional create and the fenced commit.

The object store is :class:`MemoryBlobs` here (the same conditional semantics as S3); a real
S3 API on loopback (moto's server) runs the same store in ``test_s3.py`` and ``tests/e2e``.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from conftest import call
from test_store import BOUNDS, POOL, SMALL_INTRINSICS, frame, snapshot

from agilegs.service import store_tool
from agilegs.service.errors import ServiceError
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.settings import Settings
from agilegs.service.store import objects
from agilegs.service.store.blobs import MemoryBlobs
from agilegs.service.store.integrity import Damage, decode_manifest
from agilegs.service.store.objects import Fenced, ObjectSessionStore, open_store
from agilegs.service.store.records import MANIFEST
from agilegs.service.store.write import SessionStore

Damager = Callable[[str, str, str], None]  # (session, file, how)


def flip_or_truncate(data: bytes, how: str) -> bytes:
    if how == "truncate":
        return data[: len(data) // 2]
    out = bytearray(data)
    out[len(out) // 2] ^= 0xFF
    return bytes(out)


class Backend:
    """A session store of one kind, and how to damage one of its files."""

    def __init__(self, kind: str, tmp: Path) -> None:
        self.kind = kind
        self.tmp = tmp
        self.blobs = MemoryBlobs()

    def store(self) -> SessionStore | ObjectSessionStore:
        if self.kind == "folder":
            return SessionStore(self.tmp / "state")
        return ObjectSessionStore(self.blobs)

    def core(self) -> SessionRegistry:
        c = SessionRegistry(Settings(state_dir=self.tmp / "state", zenoh=False, workers=2,
                                     mapper=False), store=self.store())
        c.load()
        return c

    def damage(self, sid: str, rel: str, how: str) -> None:
        if self.kind == "folder":
            path = self.tmp / "state" / "sessions" / sid / rel
            path.write_bytes(flip_or_truncate(path.read_bytes(), how))
        else:
            key = f"sessions/{sid}/{rel}"
            self.blobs.put(key, flip_or_truncate(self.blobs.get(key)[0], how))

    def manifest(self, sid: str) -> dict:
        if self.kind == "folder":
            return decode_manifest((self.tmp / "state" / "sessions" / sid / MANIFEST).read_bytes())
        return decode_manifest(self.blobs.get(f"sessions/{sid}/{MANIFEST}")[0])


def create(core: SessionRegistry, sid: str = "s") -> None:
    call(core, "create_session", None, {
        "id": sid, "intrinsics": SMALL_INTRINSICS, "bounds": BOUNDS, "init_gaussians": 50,
        "pool": {"poses": [{"matrix": p.tolist()} for p in POOL]},
        "defaults": {"shortlist_size": 3}, "seed": 7})


@pytest.fixture(params=["folder", "objects"])
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Backend:
    return Backend(request.param, tmp_path)


def timeless(snap: tuple) -> tuple:
    """A snapshot without its times (two runs differ in them alone)."""
    return tuple(re.sub(r'"(created_at|updated_at)":[0-9.e+]+', "", x) if isinstance(x, str)
                 else x for x in snap)


def history(b: Backend) -> list[tuple]:
    """A session built by the same calls on ``b``; its snapshot after each, and after a
    reload."""
    core = b.core()
    create(core)
    out = [timeless(snapshot(core))]
    call(core, "add_observations", "s", {"observations": [frame(1)]})
    out.append(timeless(snapshot(core)))
    call(core, "commit", "s", {"candidate_id": 2})
    out.append(timeless(snapshot(core)))
    core.close()
    again = b.core()
    out.append(timeless(snapshot(again)))
    again.close()
    return out


def test_both_backends_hold_the_same_sessions(tmp_path: Path) -> None:
    folder = history(Backend("folder", tmp_path / "a"))
    objects = history(Backend("objects", tmp_path / "b"))
    assert folder == objects
    assert folder[-1] == folder[-2]  # read back as acknowledged


def test_every_version_writes_fresh_keys_and_keeps_the_previous_one() -> None:
    b = Backend("objects", Path("/nonexistent"))
    core = b.core()
    create(core)
    call(core, "add_observations", "s", {"observations": [frame(1)]})
    call(core, "commit", "s", {"candidate_id": 2})
    m = b.manifest("s")
    assert all(name.count(".") == 3 for name in m["files"].values())  # role.<v>.<token>.pt
    image = m["views"][0]["image_file"]
    assert re.fullmatch(r"v00000000\.[0-9a-f]{10}\.rgb\.npy", image)
    # the objects of the version before the previous one are gone, no others
    keys = {k.split("/", 2)[2] for k in b.blobs.objects}
    prev = decode_manifest(b.blobs.get("sessions/s/manifest.prev.json")[0])
    named = set(m["files"].values()) | set(prev["files"].values()) | {
        f"views/{n}" for v in m["views"] for n in (v["image_file"], v["depth_file"]) if n}
    assert keys == named | {MANIFEST, "manifest.prev.json"}
    core.close()


@pytest.mark.parametrize("how", ["truncate", "flip"])
def test_damage_is_reported_and_repaired_alike(tmp_path: Path, how: str) -> None:
    results = {}
    for kind in ("folder", "objects"):
        b = Backend(kind, tmp_path / kind)
        core = b.core()
        create(core)
        create(core, "t")
        call(core, "commit", "s", {"candidate_id": 1})
        intact = snapshot(core)
        call(core, "commit", "s", {"candidate_id": 2})
        core.close()
        b.damage("s", MANIFEST, how)
        again = b.core()
        listed = {e.id: e for e in call(again, "list_sessions", None, None).sessions}
        assert listed["t"].state == "ok"
        damage = listed["s"].damage
        assert listed["s"].state == "damaged" and damage is not None
        with pytest.raises(ServiceError) as exc:
            call(again, "select", "s", {})
        assert exc.value.code == "session_damaged"
        done = call(again, "repair_session", "s", None)
        after = timeless(snapshot(again))
        call(again, "commit", "s", {"candidate_id": 3})
        again.close()
        assert after[1:] == timeless(intact)[1:]
        # the manifests differ in length alone (the objects' names hold a token)
        report = re.sub(r"\d+ bytes", "N bytes", str(damage.model_dump(exclude={"detected_at"})))
        results[kind] = (report, done.model_dump(), after)
    assert results["folder"] == results["objects"]


def test_a_damaged_frame_is_dropped_alike(tmp_path: Path) -> None:
    results = {}
    for kind in ("folder", "objects"):
        b = Backend(kind, tmp_path / kind)
        core = b.core()
        create(core)
        call(core, "add_observations", "s", {"observations": [frame(1)]})
        core.close()
        image = b.manifest("s")["views"][0]["image_file"]
        b.damage("s", f"views/{image}", "flip")
        store = b.store()
        got = store.inspect("s")
        assert isinstance(got, Damage) and got.drop_frames == (0,) and got.repairable
        assert got.reason() == f"views/{image}: checksum mismatch (its bytes changed since "\
                               "they were written)"
        done = store.repair("s")
        again = b.core()
        results[kind] = (done.rolled_back_to, done.dropped_frames, timeless(snapshot(again)))
        again.close()
    assert results["folder"] == results["objects"]


def test_store_check_and_repair_on_an_object_store(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str],
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    b = Backend("objects", tmp_path)
    core = b.core()
    create(core)
    create(core, "t")
    call(core, "commit", "s", {"candidate_id": 1})
    core.close()
    b.damage("s", MANIFEST, "truncate")
    monkeypatch.setattr(objects, "open_store", lambda *a, **k: ObjectSessionStore(b.blobs))
    assert store_tool.run_on("s3://bucket/x", "check") == 1
    out = capsys.readouterr().out
    assert "2 session(s), 1 damaged" in out and "manifest.json" in out and "roll back" in out
    assert store_tool.run_on("s3://bucket/x", "repair", dry_run=True) == 1
    assert "would roll back" in capsys.readouterr().out
    assert store_tool.run_on("s3://bucket/x", "repair") == 0
    assert "every session checks out" in capsys.readouterr().out
    assert store_tool.run_on("s3://bucket/x", "check") == 0


def test_one_of_two_instances_creating_one_id_wins() -> None:
    blobs = MemoryBlobs()
    stores = [ObjectSessionStore(blobs) for _ in range(8)]
    cores = [SessionRegistry(Settings(zenoh=False, workers=2, mapper=False), store=s)
             for s in stores]
    for c in cores:
        c.load()
    outcomes: list[str] = []
    gate = threading.Barrier(len(cores))

    def attempt(c: SessionRegistry) -> None:
        gate.wait()
        try:
            create(c, "same")
            outcomes.append("created")
        except ServiceError as exc:
            outcomes.append(f"{exc.status}")

    threads = [threading.Thread(target=attempt, args=(c,)) for c in cores]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(outcomes) == ["409"] * 7 + ["created"]
    # the losers left nothing behind: every object is named by the one manifest
    m = decode_manifest(blobs.get("sessions/same/manifest.json")[0])
    assert {k.split("/", 2)[2] for k in blobs.objects} == set(m["files"].values()) | {MANIFEST}
    for c in cores:
        c.close()


def on_store(blobs: MemoryBlobs) -> SessionRegistry:
    core = SessionRegistry(Settings(zenoh=False, workers=2, mapper=False),
                           store=ObjectSessionStore(blobs))
    core.load()
    return core


def taken_over() -> tuple[MemoryBlobs, SessionRegistry, SessionRegistry]:
    """A store, the instance that created session ``s``, and the one that took it over."""
    blobs = MemoryBlobs()
    old = on_store(blobs)
    create(old)
    return blobs, old, on_store(blobs)


def test_a_stale_owner_is_fenced_and_drops_the_session(caplog: pytest.LogCaptureFixture) -> None:
    blobs, old, new = taken_over()
    call(new, "commit", "s", {"candidate_id": 1})
    taken = snapshot(new)
    before = dict(blobs.objects)
    with pytest.raises(ServiceError) as exc:
        call(old, "commit", "s", {"candidate_id": 2})
    assert exc.value.code == "session_unavailable" and exc.value.status == 404
    assert "lost the lease" in caplog.text
    assert "s" not in old.sessions
    assert blobs.objects == before  # nothing of the stale write is left
    with pytest.raises(Fenced):  # and the store refuses it as well
        old.store.save(new.sessions["s"].record, ["warm"])
    assert snapshot(new) == taken
    old.close()
    new.close()


def test_a_stale_owner_deletes_nothing() -> None:
    blobs, old, new = taken_over()
    before = dict(blobs.objects)
    with pytest.raises(ServiceError) as exc:
        call(old, "delete_session", "s", None)
    assert (exc.value.status, exc.value.code) == (404, "session_unavailable")
    assert exc.value.retry_after is not None  # the owner deletes it, when asked again
    assert blobs.objects == before and "s" not in old.sessions
    assert call(new, "delete_session", "s", None).deleted
    assert not blobs.objects
    old.close()
    new.close()


def test_a_delete_cut_short_leaves_a_tombstone_that_reads_as_gone() -> None:
    blobs = MemoryBlobs()
    core = on_store(blobs)
    create(core)
    store = core.store
    assert isinstance(store, ObjectSessionStore)
    real_delete = blobs.delete
    blobs.delete = lambda keys: None  # type: ignore[method-assign]  # it dies after the tombstone
    store.delete("s")
    blobs.delete = real_delete  # type: ignore[method-assign]
    assert decode_manifest(blobs.get("sessions/s/manifest.json")[0])["deleted"] is True
    assert not store.exists("s")
    with pytest.raises(FileNotFoundError):
        store.take_over("s")
    core.close()
    again = SessionRegistry(Settings(zenoh=False, workers=2, mapper=False),
                            store=ObjectSessionStore(blobs))
    assert again.load() == 0  # not a damaged session: a deleted one
    create(again)  # the id is free again
    assert call(again, "get_session", "s", None).version == 1
    again.close()


def test_open_store_reads_the_url() -> None:
    assert isinstance(open_store("file:///tmp/x"), SessionStore)
    assert open_store("file:///tmp/x").root == Path("/tmp/x")  # type: ignore[union-attr]
    with pytest.raises(ValueError, match="s3://bucket/prefix"):
        open_store("gs://bucket/x")
    s = Settings(state_url="file:///tmp/y", zenoh=False)
    assert s.state_dir == Path("/tmp/y") and s.state_url is None


@pytest.fixture
def cores(backend: Backend) -> Iterator[SessionRegistry]:
    c = backend.core()
    yield c
    c.close()


def test_a_deleted_session_can_be_created_again(cores: SessionRegistry) -> None:
    create(cores)
    assert call(cores, "delete_session", "s", None).deleted
    create(cores)
    assert call(cores, "get_session", "s", None).version == 1
