"""A session's state changes as functions of its record, without a server; and the same
acquisitions through a selection with commit or a selection followed by a commit."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import SMALL_INTRINSICS, call, ring_poses

from agilegs import schemas as m
from agilegs.schemas import ObservationIn
from agilegs.service.errors import ServiceError
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    fisher_diag,
    init_information,
)
from agilegs.service.sessions import transitions as tr
from agilegs.service.sessions.convert import parse_frame
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.sessions.selection import select_step
from agilegs.service.sessions.session import changed_roles
from agilegs.service.settings import Settings
from agilegs.service.store.integrity import decode_manifest
from agilegs.service.store.records import SessionRecord

POOL = ring_poses(16)
INTR = Intrinsics(**SMALL_INTRINSICS)
LIMITS = tr.Limits(max_pool_size=64, max_views=32, max_gaussians=10_000, max_shortlist=16,
                   max_image_pixels=1 << 20)


def blob(n: int = 150, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=g) - 0.5) * 0.8
    return GaussianMap.from_points(pts, torch.rand(n, 3, generator=g), scale=0.07, opacity=0.7)


def record(gmap: GaussianMap | None = None, **defaults: Any) -> SessionRecord:
    """A session's record as create_session makes it: a pool of 16 ring poses, no views."""
    gmap = gmap if gmap is not None else blob()
    rec = SessionRecord(
        id="s", created_at=0.0, updated_at=0.0, version=1, intrinsics=dict(SMALL_INTRINSICS),
        bounds=None, defaults=m.SelectDefaults(**defaults).model_dump(),
        information_config=m.InformationConfig().model_dump(by_alias=True), gmap=gmap,
        h_acc=init_information(gmap, 1e-3), pool_ids=np.zeros(0, dtype=np.int64),
        pool_poses=np.zeros((0, 4, 4)), next_candidate_id=0, views=(), next_view_id=0)
    return tr.set_pool(rec, POOL, None, LIMITS, "body", replace_pool=True, now=0.0)


def fisher(gmap: GaussianMap, pose: np.ndarray) -> dict[str, torch.Tensor]:
    with torch.no_grad():
        return fisher_diag(gmap, Camera(torch.from_numpy(pose).float(), INTR))


# ---------------------------------------------------------------------------- acquire
def test_acquire_appends_the_view_consumes_the_candidate_and_adds_its_fisher() -> None:
    rec = record()
    new, view = tr.acquire(rec, rec.pool_poses[3], candidate_id=3, now=5.0)
    assert (view.id, view.candidate_id, new.next_view_id) == (0, 3, 1)
    assert (new.version, new.updated_at, view.created_at) == (rec.version + 1, 5.0, 5.0)
    assert new.views == (view,) and 3 not in new.pool_ids and len(new.pool_ids) == 15
    want = accumulate_information(rec.h_acc, fisher(rec.gmap, POOL[3]))
    for k in want:
        assert torch.equal(new.h_acc[k], want[k])
    assert new.warm_state is rec.warm_state  # no selection: the warm state stays
    assert rec.views == () and len(rec.pool_ids) == 16  # the record given is untouched
    assert changed_roles(rec, new) == ["information", "pool"]
    kept, _ = tr.acquire(rec, rec.pool_poses[3], candidate_id=3, keep_in_pool=True)
    assert kept.pool_ids is rec.pool_ids and changed_roles(rec, kept) == ["information"]


def test_acquire_takes_a_given_fisher_a_warm_state_or_leaves_hhat() -> None:
    rec = record()
    given = {k: torch.full_like(v, 2.0) for k, v in rec.h_acc.items()}
    new, _ = tr.acquire(rec, POOL[0], h_view=given, next_state={"event": 4, "x": object()})
    assert all(torch.equal(new.h_acc[k], rec.h_acc[k] + 2.0) for k in given)
    assert new.warm_state == {"event": 4}  # what a torch.load(weights_only) reads back
    skipped, _ = tr.acquire(rec, POOL[0], update_information=False)
    assert skipped.h_acc is rec.h_acc and changed_roles(rec, skipped) == []
    with pytest.raises(ServiceError) as exc:
        tr.acquire(rec, POOL[0], candidate_id=99, field="body.x.candidate_id")
    assert (exc.value.status, exc.value.field) == (409, "body.x.candidate_id")


def test_commit_takes_the_pending_selection_and_its_fisher_where_it_applies() -> None:
    rec = record()
    cheap = {k: torch.full_like(v, 3.0) for k, v in rec.h_acc.items()}
    pending = tr.PendingSelection(next_state={"event": 1}, candidate_id=5, pose=POOL[5],
                                  gmap=rec.gmap, information=cheap)
    new, _ = tr.commit_view(rec, LIMITS, candidate_id=5, pending=pending)
    assert new.warm_state == {"event": 1}
    assert torch.equal(new.h_acc["means"], rec.h_acc["means"] + 3.0)  # reused, not recomputed
    # another candidate: the warm state moves on, its Fisher is computed
    other, _ = tr.commit_view(rec, LIMITS, candidate_id=6, pending=pending)
    assert other.warm_state == {"event": 1}
    want = accumulate_information(rec.h_acc, fisher(rec.gmap, POOL[6]))
    assert torch.equal(other.h_acc["means"], want["means"])
    # a map changed since the selection: computed on the new map
    moved = replace(rec, gmap=blob(seed=1))
    on_new, _ = tr.commit_view(moved, LIMITS, pose=POOL[5], pending=pending)
    assert not torch.equal(on_new.h_acc["means"], rec.h_acc["means"] + 3.0)
    with pytest.raises(ServiceError) as exc:
        tr.commit_view(rec, replace(LIMITS, max_views=0), candidate_id=5)
    assert exc.value.status == 429


# ---------------------------------------------------------------------------- pool, frames, map
def test_a_pool_that_is_the_session_s_leaves_the_record() -> None:
    rec = record()
    assert tr.with_pool(rec, POOL.copy(), None, LIMITS, "body.pool") is rec
    assert tr.with_pool(rec, POOL.copy(), list(range(16)), LIMITS, "body.pool") is rec
    moved = tr.with_pool(rec, POOL[::-1].copy(), None, LIMITS, "body.pool")
    assert moved.version == rec.version + 1 and moved.pool_ids.tolist() == list(range(16, 32))
    with pytest.raises(ServiceError) as exc:
        tr.set_pool(rec, POOL[:1], [4], LIMITS, "body", replace_pool=False)
    assert (exc.value.status, exc.value.field) == (409, "body.ids[0]")
    with pytest.raises(ServiceError) as exc:
        tr.set_pool(rec, POOL, None, replace(LIMITS, max_pool_size=20), "body",
                    replace_pool=False)
    assert exc.value.status == 429


def test_a_batch_of_frames_is_one_version_and_acquires_each_new_view() -> None:
    rec = record()
    img = (np.random.default_rng(0).random((32, 32, 3)) * 255).astype(np.uint8)
    obs = [ObservationIn.from_numpy(POOL[2], image=img, image_encoding="png"),
           ObservationIn.from_numpy(candidate_id=7, depth=np.ones((32, 32), np.float32))]
    frames = [parse_frame(o, i, "body.observations", rec.intrinsics,
                          max_image_pixels=1 << 20) for i, o in enumerate(obs)]
    new, blobs, touched = tr.integrate_frames(rec, frames, "body.observations", LIMITS)
    assert new.version == rec.version + 1 and [v.id for v in touched] == [0, 1]
    assert sorted(blobs) == ["v00000000.rgb.png", "v00000001.depth.npy"]
    assert 7 not in new.pool_ids and new.views[1].candidate_id == 7
    want = accumulate_information(accumulate_information(rec.h_acc, fisher(rec.gmap, POOL[2])),
                                  fisher(rec.gmap, POOL[7]))
    for k in want:
        assert torch.equal(new.h_acc[k], want[k])
    new, bare = tr.acquire(new, POOL[9])  # a commit: a view without a frame
    attach = [parse_frame(ObservationIn.from_numpy(view_id=bare.id, image=img), 0, "body.obs",
                          rec.intrinsics, max_image_pixels=1 << 20)]
    again, _, _ = tr.integrate_frames(new, attach, "body.obs", LIMITS)
    assert again.h_acc is new.h_acc and again.views[2].image_file is not None
    with pytest.raises(ServiceError) as exc:
        tr.integrate_frames(again, attach, "body.obs", LIMITS)
    assert (exc.value.status, exc.value.field) == (409, "body.obs[0].view_id")


def test_a_pushed_map_recomputes_hhat_from_the_views() -> None:
    rec, _ = tr.acquire(record(), POOL[1], candidate_id=1)
    g = blob(80, seed=2)
    new = tr.replace_map(rec, g, LIMITS)
    want = accumulate_information(init_information(g, 1e-3), fisher(g, POOL[1]))
    for k in want:
        torch.testing.assert_close(new.h_acc[k], want[k], rtol=1e-6, atol=0)
    assert changed_roles(rec, new) == ["gaussians", "information"]
    with pytest.raises(ServiceError) as exc:
        tr.replace_map(rec, g, replace(LIMITS, max_gaussians=10))
    assert (exc.value.code, exc.value.field) == ("limit_exceeded", "body")


# ---------------------------------------------------------------------------- select
@pytest.mark.parametrize("method", ["agile", "agile_plus", "random"])
def test_select_then_commit_is_select_with_commit(method: str) -> None:
    """The pure steps: the same records, event counters, anchors and Hhat either way."""
    a = b = record(shortlist_size=4)
    for _ in range(3):
        sa = select_step(a, m.SelectRequest(method=method, commit=True), LIMITS)
        sb = select_step(b, m.SelectRequest(method=method), LIMITS)
        assert sb.record is b and sb.pending is not None and sa.pending is None
        assert sa.chosen_id == sb.chosen_id
        b, _ = tr.commit_view(b, LIMITS, candidate_id=sb.chosen_id, pending=sb.pending)
        a = sa.record
        assert a.warm_state is not None and b.warm_state is not None
        assert a.warm_state.keys() == b.warm_state.keys()
        for k, v in a.warm_state.items():
            assert torch.equal(v, b.warm_state[k]) if isinstance(v, torch.Tensor) else (
                v == b.warm_state[k]), k
        for k in a.h_acc:
            assert torch.equal(a.h_acc[k], b.h_acc[k]), k
        assert a.pool_ids.tolist() == b.pool_ids.tolist() and a.version == b.version


def test_the_chosen_fisher_kept_from_scoring_is_what_a_fresh_pass_gives() -> None:
    rec = record(shortlist_size=4)
    out = select_step(rec, m.SelectRequest(method="agile_plus", commit=True), LIMITS)
    fresh, _ = tr.acquire(rec, out.chosen_pose, candidate_id=out.chosen_id)
    for k in fresh.h_acc:
        assert torch.equal(out.record.h_acc[k], fresh.h_acc[k]), k
    # another background than the session's: not reused (and still exact)
    bg = select_step(rec, m.SelectRequest(method="agile_plus", commit=True,
                                          config={"fisher_background": [1.0, 1.0, 1.0]}),
                     LIMITS)
    assert bg.pending is None
    again, _ = tr.acquire(rec, bg.chosen_pose, candidate_id=bg.chosen_id)
    for k in again.h_acc:
        assert torch.equal(bg.record.h_acc[k], again.h_acc[k]), k


# ---------------------------------------------------------------------------- through a server
def make_core(path: Path) -> SessionRegistry:
    core = SessionRegistry(Settings(state_dir=path, zenoh=False, workers=2, mapper=False))
    core.load()
    call(core, "create_session", None, {
        "id": "s", "intrinsics": SMALL_INTRINSICS, "init_gaussians": 200,
        "bounds": {"min": [-0.5] * 3, "max": [0.5] * 3},
        "pool": {"poses": [{"matrix": p.tolist()} for p in ring_poses(40)]},
        "defaults": {"shortlist_size": 5}})
    return core


def files_of(core: SessionRegistry) -> dict[str, Any]:
    """The session's folder: every file's bytes (sha256), the manifest without times."""
    folder = core.store.session_dir("s")
    out: dict[str, Any] = {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
                           for p in sorted(folder.rglob("*")) if p.is_file()
                           and not p.name.startswith("manifest")}
    man = decode_manifest((folder / "manifest.json").read_bytes())
    for key in ("created_at", "updated_at"):
        man.pop(key)
    for v in man["views"]:
        v.pop("created_at")
    out["manifest.json"] = json.dumps(man, sort_keys=True)
    return out


@pytest.mark.parametrize("method", ["agile", "agile_plus"])
def test_the_same_acquisitions_either_way_give_the_same_selections_state_and_files(
        tmp_path: Path, method: str) -> None:
    one, two = make_core(tmp_path / "one"), make_core(tmp_path / "two")
    try:
        for _ in range(4):
            a = call(one, "select", "s", {"method": method, "commit": True})
            b = call(two, "select", "s", {"method": method})
            call(two, "commit", "s", {"candidate_id": b.chosen.id})
            assert a.chosen.id == b.chosen.id
            assert [c.id for c in a.shortlist] == [c.id for c in b.shortlist]
        ra, rb = one.sessions["s"].record, two.sessions["s"].record
        assert ra.warm_state is not None and rb.warm_state is not None
        assert ra.warm_state["event"] == rb.warm_state["event"] == 4
        assert torch.equal(ra.warm_state["anchor_c2w"], rb.warm_state["anchor_c2w"])
        nxt_a = call(one, "select", "s", {"method": method})
        nxt_b = call(two, "select", "s", {"method": method})
        assert (nxt_a.chosen.id, nxt_a.version) == (nxt_b.chosen.id, nxt_b.version)
        assert call(one, "get_session", "s", None).information.digest == call(two,
            "get_session", "s", None).information.digest
        assert files_of(one) == files_of(two)
    finally:
        one.close()
        two.close()


def test_a_selection_without_commit_is_taken_by_an_observation(tmp_path: Path) -> None:
    one, two = make_core(tmp_path / "one"), make_core(tmp_path / "two")
    try:
        a = call(one, "select", "s", {"method": "agile", "commit": True})
        b = call(two, "select", "s", {"method": "agile"})
        call(two, "add_observations", "s", {"observations": [
            {"candidate_id": b.chosen.id}]})
        assert two.sessions["s"].record.warm_state["event"] == 1
        assert call(one, "select", "s", {"method": "agile"}).chosen.id == call(two,
            "select", "s", {"method": "agile"}).chosen.id
        assert a.chosen.id == b.chosen.id
        # the commit after that selection takes its warm state; the next one, with no
        # selection since the last acquisition, leaves it
        s = two.sessions["s"]
        call(two, "commit", "s", {"candidate_id": int(s.record.pool_ids[0])})
        assert s.record.warm_state["event"] == 2
        call(two, "commit", "s", {"candidate_id": int(s.record.pool_ids[0])})
        assert s.record.warm_state["event"] == 2
    finally:
        one.close()
        two.close()


def test_decoded_frames_are_kept_for_the_mapper_only(tmp_path: Path) -> None:
    core = make_core(tmp_path / "state")
    try:
        s = core.sessions["s"]
        img = (np.random.default_rng(1).random((32, 32, 3)) * 255).astype(np.uint8)
        body = {"observations": [ObservationIn.from_numpy(ring_poses(40)[3], image=img,
                                                          image_encoding="png").model_dump()]}
        call(core, "add_observations", "s", body)
        assert s.take_frame(0) is None  # no mapper: nothing kept

        class Hook:
            def integrate(self, session: Any, views: list) -> None:
                pass

        s.mapper = Hook()  # type: ignore[assignment]
        call(core, "add_observations", "s", body)
        got = s.take_frame(1)
        assert got is not None and got[1] is None
        np.testing.assert_array_equal(got[0], img)
        np.testing.assert_array_equal(s.view_image(1), img)  # what the store gives back
        assert s.take_frame(1) is None  # taken once
    finally:
        core.close()


def test_a_reply_s_pose_stays_within_the_wire_s_bound() -> None:
    """An anchor computed in float32 from a candidate at the bound rounds past it: the reply
    clips it (and a pose within the bound is returned as it is)."""
    from agilegs.config.geometry import MAX_COORD
    from agilegs.service.sessions.convert import pose_out

    at_bound = np.eye(4)
    at_bound[:3, 3] = [0.0025, MAX_COORD, -MAX_COORD]
    rounded = torch.from_numpy(at_bound).float()
    rounded[1, 3] = MAX_COORD + 0.125
    out = pose_out(rounded).to_matrix()
    assert out[1, 3] == MAX_COORD and out[2, 3] == -MAX_COORD
    m.Pose.model_validate(pose_out(rounded).model_dump())  # what the schema accepts
    assert np.array_equal(pose_out(at_bound).to_matrix(), at_bound)
