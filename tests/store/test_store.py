"""The store's integrity: checksummed manifests and files, the previous version kept, a
refused write (no space) that leaves nothing behind, damage found and repaired."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, call, ring_poses

from agilegs.schemas import ObservationIn
from agilegs.service.errors import ServiceError
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.settings import Settings
from agilegs.service.store.integrity import (
    Damage,
    DamagedFile,
    ManifestError,
    checksum,
    decode_manifest,
    encode_manifest,
)
from agilegs.service.store.records import MANIFEST, PREVIOUS
from agilegs.service.store.write import SessionStore

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}
POOL = ring_poses(8)
IMG = np.random.default_rng(3).integers(0, 255, (32, 32, 3), dtype=np.uint8)
DEPTH = np.full((32, 32), 2.0, np.float32)


def make_core(path: Path) -> SessionRegistry:
    core = SessionRegistry(Settings(state_dir=path, zenoh=False, workers=2, mapper=False))
    core.load()
    return core


def create(core: SessionRegistry, sid: str = "s") -> None:
    call(core, "create_session", None, {
        "id": sid, "intrinsics": SMALL_INTRINSICS, "bounds": BOUNDS, "init_gaussians": 50,
        "pool": {"poses": [{"matrix": p.tolist()} for p in POOL]},
        "defaults": {"shortlist_size": 3}})


def frame(i: int) -> dict[str, Any]:
    return ObservationIn.from_numpy(POOL[i], image=IMG, depth=DEPTH).model_dump()


def snapshot(core: SessionRegistry, sid: str = "s") -> tuple:
    info = call(core, "get_session", sid, None)
    return (info.version, info.information.digest, info.gaussians.count,
            call(core, "get_pool", sid, None).model_dump_json(exclude={"version"}),
            call(core, "list_views", sid, None).model_dump_json(exclude={"version"}))


def folder_bytes(folder: Path) -> dict[str, str]:
    """Every file under ``folder``: relative path -> sha256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def core(tmp_path: Path) -> Iterator[SessionRegistry]:
    c = make_core(tmp_path / "state")
    create(c)
    yield c
    c.close()


# ---------------------------------------------------------------------------- checksums
def test_the_manifest_checksum_catches_any_changed_byte() -> None:
    body = {"format": 2, "id": "s", "version": 3, "views": [{"pose": [[1.5, -0.25]]}],
            "files": {"gaussians": "gaussians.3.pt"}, "note": "é"}
    data = encode_manifest(body)
    assert decode_manifest(data) == body
    for i in range(len(data)):  # every single flipped bit of a byte is caught
        bad = bytearray(data)
        bad[i] ^= 0x01
        with pytest.raises(ManifestError):
            decode_manifest(bytes(bad))
    for cut in (0, 1, len(data) // 2, len(data) - 1):
        with pytest.raises(ManifestError, match="empty|not valid JSON"):
            decode_manifest(data[:cut])
    with pytest.raises(ManifestError, match="unknown format"):
        decode_manifest(json.dumps({"format": 7}).encode())
    legacy = {"format": 1, "id": "s"}  # written before checksums: read unchecked
    assert decode_manifest(json.dumps(legacy).encode()) == legacy


def test_a_frame_read_back_is_checked(core: SessionRegistry, tmp_path: Path) -> None:
    out = call(core, "add_observations", "s", {"observations": [frame(1)]})
    vid = out.views[0].id
    s = core.sessions["s"]
    np.testing.assert_array_equal(s.view_image(vid), IMG)
    name = s.record.views[-1].image_file
    assert s.record.checksums[f"views/{name}"] == checksum(
        (tmp_path / "state" / "sessions" / "s" / "views" / name).read_bytes())
    path = tmp_path / "state" / "sessions" / "s" / "views" / name
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(DamagedFile, match="checksum mismatch"):
        s.view_image(vid)
    # the session left service: listed as damaged, its operations refused with the reason
    listed = {e.id: e for e in call(core, "list_sessions", None, None).sessions}
    assert listed["s"].state == "damaged" and listed["s"].damage is not None
    assert listed["s"].damage.files[0].file == f"views/{name}"
    assert listed["s"].damage.drop_frames == [vid] and listed["s"].damage.repairable
    with pytest.raises(ServiceError) as exc:
        call(core, "select", "s", {})
    assert exc.value.status == 409 and exc.value.code == "session_damaged"
    assert f"views/{name}" in exc.value.message
    done = call(core, "repair_session", "s", None)
    assert done.repaired and done.dropped_frames == [vid] and done.rolled_back_to is None
    view = call(core, "list_views", "s", None).views[-1]
    assert view.id == vid and not view.has_image and view.has_depth  # only the image was bad
    call(core, "select", "s", {"commit": True})


# ---------------------------------------------------------------------------- versions
def test_the_previous_version_and_its_files_are_kept(core: SessionRegistry,
                                                    tmp_path: Path) -> None:
    folder = tmp_path / "state" / "sessions" / "s"
    call(core, "commit", "s", {"candidate_id": 1})
    first = decode_manifest((folder / MANIFEST).read_bytes())
    call(core, "commit", "s", {"candidate_id": 2})
    cur = decode_manifest((folder / MANIFEST).read_bytes())
    prev = decode_manifest((folder / PREVIOUS).read_bytes())
    assert prev == first and prev["version"] == cur["version"] - 1
    for m in (cur, prev):  # both versions' files are there and check out
        for name in m["files"].values():
            assert checksum((folder / name).read_bytes()) == m["checksums"][name]
    call(core, "commit", "s", {"candidate_id": 3})
    # the version before the previous one is gone
    info_files = sorted(p.name for p in folder.glob("information.*.pt"))
    assert first["files"]["information"] not in info_files and len(info_files) == 2


def test_a_session_written_without_checksums_still_loads(core: SessionRegistry,
                                                         tmp_path: Path) -> None:
    folder = tmp_path / "state" / "sessions" / "s"
    call(core, "add_observations", "s", {"observations": [frame(2)]})
    before = snapshot(core)
    core.close()
    m = decode_manifest((folder / MANIFEST).read_bytes())
    m["format"] = 1
    del m["checksums"]
    (folder / MANIFEST).write_text(json.dumps(m))
    again = make_core(tmp_path / "state")
    assert snapshot(again) == before and not again.damaged
    call(again, "commit", "s", {"candidate_id": 0})  # written back with checksums
    m2 = decode_manifest((folder / MANIFEST).read_bytes())
    assert m2["format"] == 2 and set(m2["checksums"]) >= set(m2["files"].values())
    again.close()


# ---------------------------------------------------------------------------- repair
def _damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncate":
        path.write_bytes(data[: len(data) // 3])
    else:
        with open(path, "r+b") as f:
            f.seek(len(data) // 2)
            f.write(bytes([data[len(data) // 2] ^ 0x10]))


@pytest.mark.parametrize("how", ["truncate", "flip"])
def test_a_damaged_manifest_rolls_back_to_the_previous_version(core: SessionRegistry,
                                                               tmp_path: Path, how: str) -> None:
    call(core, "commit", "s", {"candidate_id": 1})
    intact = snapshot(core)
    call(core, "commit", "s", {"candidate_id": 2})
    lost_version = snapshot(core)[0]
    core.close()
    folder = tmp_path / "state" / "sessions" / "s"
    _damage(folder / MANIFEST, how)
    store = SessionStore(tmp_path / "state")
    got = store.inspect("s")
    assert isinstance(got, Damage) and got.files[0].file == MANIFEST
    assert got.version is None and got.rollback_to == intact[0] and got.repairable
    done = store.repair("s")
    assert done.rolled_back_to == intact[0] and done.record.version == lost_version + 1
    again = make_core(tmp_path / "state")
    assert snapshot(again)[1:] == intact[1:] and snapshot(again)[0] == lost_version + 1
    call(again, "commit", "s", {"candidate_id": 3})  # and it goes on from there
    again.close()
    assert not isinstance(SessionStore(tmp_path / "state").inspect("s"), Damage)


def test_a_file_both_versions_share_cannot_be_rolled_back(core: SessionRegistry,
                                                          tmp_path: Path) -> None:
    call(core, "commit", "s", {"candidate_id": 1})  # the Gaussians are not rewritten
    core.close()
    folder = tmp_path / "state" / "sessions" / "s"
    name = decode_manifest((folder / MANIFEST).read_bytes())["files"]["gaussians"]
    _damage(folder / name, "flip")
    got = SessionStore(tmp_path / "state").inspect("s")
    assert isinstance(got, Damage) and not got.repairable and got.files[0].file == name
    again = make_core(tmp_path / "state")
    with pytest.raises(ServiceError) as exc:
        call(again, "repair_session", "s", None)
    assert exc.value.code == "session_damaged" and "nothing intact" in exc.value.message
    assert call(again, "delete_session", "s", None).deleted
    assert not folder.exists()
    create(again, "s")  # the id is free again
    again.close()


def test_store_check_and_repair_offline(core: SessionRegistry, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    from agilegs.service import store_tool

    create(core, "t")
    call(core, "commit", "s", {"candidate_id": 1})
    core.close()
    state = tmp_path / "state"
    _damage(state / "sessions" / "s" / MANIFEST, "truncate")
    listing = {p.name: folder_bytes(p) for p in (state / "sessions").iterdir()}
    assert store_tool.check(state) == 1
    out = capsys.readouterr().out
    assert "2 session(s), 1 damaged" in out and "manifest.json" in out and "roll back" in out
    assert {p.name: folder_bytes(p) for p in (state / "sessions").iterdir()} == listing
    assert store_tool.check(state, as_json=True) == 1
    entries = {e["id"]: e for e in json.loads(capsys.readouterr().out)}
    assert entries["s"]["state"] == "damaged" and entries["t"]["state"] == "ok"
    assert store_tool.repair(state, dry_run=True) == 1
    assert "would roll back" in capsys.readouterr().out
    assert store_tool.repair(state) == 0
    assert "every session checks out" in capsys.readouterr().out
    assert store_tool.check(state) == 0
    assert os.path.exists(state / "sessions" / "t" / MANIFEST)
