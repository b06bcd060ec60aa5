"""The object-store backend on a real S3 API (moto's server on loopback): the blob store's
conditional writes as S3 answers them, and the session store on it giving what the state
folder gives."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import call
from s3api import S3Api, s3_api
from test_objects import Backend, create, history

from agilegs.service.errors import ServiceError
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.settings import Settings
from agilegs.service.store.blobs import PreconditionFailed, S3Blobs, open_blobs
from agilegs.service.store.integrity import Damage
from agilegs.service.store.objects import ObjectSessionStore, open_store
from agilegs.service.store.records import MANIFEST

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def api() -> Iterator[S3Api]:
    with s3_api() as running:
        yield running


@pytest.fixture
def s3env(api: S3Api, monkeypatch: pytest.MonkeyPatch) -> S3Api:
    for k, v in api.env.items():
        monkeypatch.setenv(k, v)
    return api


def test_the_conditional_writes_as_s3_answers_them(s3env: S3Api) -> None:
    b = open_blobs(s3env.url("blobs"))
    assert isinstance(b, S3Blobs) and b.where == f"s3://{s3env.bucket}/blobs"
    first = b.put_if_absent("a/m.json", b"1")
    with pytest.raises(PreconditionFailed):
        b.put_if_absent("a/m.json", b"2")
    assert first is not None
    second = b.put_if_match("a/m.json", b"3", first)
    with pytest.raises(PreconditionFailed):  # written since: the ETag is stale
        b.put_if_match("a/m.json", b"4", first)
    assert b.get("a/m.json") == (b"3", second)
    b.put("a/x/y", b"5")
    b.put("ab/z", b"6")
    assert [i.key for i in b.list("a/")] == ["a/m.json", "a/x/y"]
    assert b.children("") == ["a", "ab"] and b.children("a/") == ["x"]
    b.delete(["a/m.json", "a/none"])
    with pytest.raises(FileNotFoundError):
        b.get("a/m.json")


def test_sessions_on_s3_are_those_of_the_folder(s3env: S3Api, tmp_path: Path) -> None:
    class OnS3(Backend):
        def store(self) -> ObjectSessionStore:
            got = open_store(s3env.url("same"))
            assert isinstance(got, ObjectSessionStore)
            return got

    assert history(OnS3("objects", tmp_path)) == history(Backend("folder", tmp_path / "f"))


def test_damage_on_s3_is_found_and_repaired(s3env: S3Api, tmp_path: Path) -> None:
    url = s3env.url("damage")
    core = SessionRegistry(Settings(state_dir=tmp_path, state_url=url, zenoh=False,
                                    workers=2, mapper=False))
    core.load()
    create(core)
    call(core, "commit", "s", {"candidate_id": 1})
    call(core, "commit", "s", {"candidate_id": 2})
    core.close()
    blobs = open_blobs(url)
    key = f"sessions/s/{MANIFEST}"
    blobs.put(key, blobs.get(key)[0][:100])
    store = open_store(url)
    got = store.inspect("s")
    assert isinstance(got, Damage) and got.rollback_to == 2
    assert got.reason().startswith("manifest.json: not valid JSON (100 bytes")
    assert store.repair("s").rolled_back_to == 2
    again = SessionRegistry(Settings(state_dir=tmp_path, state_url=url, zenoh=False,
                                     workers=2, mapper=False))
    again.load()
    assert call(again, "get_session", "s", None).version == 4
    with pytest.raises(ServiceError) as exc:  # the id is taken in the store
        create(again)
    assert exc.value.status == 409
    again.close()
