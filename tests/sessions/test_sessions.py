"""The session core in-process: state changes, Ĥ bookkeeping, persistence, bad input."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import SMALL_INTRINSICS, TRAIN_POSES, call, ring_poses

from agilegs.schemas import NDArray, ObservationIn, codec
from agilegs.service.errors import ServiceError
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    fisher_diag,
    init_information,
)
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.settings import Settings

BOUNDS = {"min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]}
POOL = ring_poses(24)


def make_core(path: Path, **settings: Any) -> SessionRegistry:
    settings.setdefault("mapper", False)  # exact-state checks: no background training
    core = SessionRegistry(Settings(state_dir=path, zenoh=False, workers=2, **settings))
    core.load()
    return core


def create(core: SessionRegistry, sid: str = "s", **extra: Any) -> None:
    body = {"id": sid, "intrinsics": SMALL_INTRINSICS, "bounds": BOUNDS, "init_gaussians": 200,
            "pool": {"poses": [{"matrix": p.tolist()} for p in POOL]}, **extra}
    call(core, "create_session", None, body)


def snapshot(core: SessionRegistry, sid: str = "s") -> tuple:
    info = call(core, "get_session", sid, None)
    pool = call(core, "get_pool", sid, None)
    views = call(core, "list_views", sid, None)
    return (info.version, info.information.digest, pool.model_dump_json(),
            views.model_dump_json(), info.gaussians.count)


def expected_information(gmap: GaussianMap, poses: list[np.ndarray], lam: float = 1e-3
                         ) -> dict[str, torch.Tensor]:
    k = Intrinsics(**SMALL_INTRINSICS)
    h = init_information(gmap, lam)
    for p in poses:
        h = accumulate_information(h, fisher_diag(gmap, Camera(torch.from_numpy(p).float(), k)))
    return h


@pytest.fixture
def core(tmp_path: Path) -> SessionRegistry:
    c = make_core(tmp_path / "state")
    create(c)
    yield c
    c.close()


def _bad_cases() -> list[tuple[str, Any, int, str]]:
    eye = np.eye(4).tolist()
    skew = np.eye(4)
    skew[0, 1] = 0.3
    nan = np.eye(4)
    nan[0, 3] = float("nan")
    img = NDArray.from_numpy(np.zeros((8, 8), np.float32))
    return [
        ("set_pool", {"poses": [{"matrix": eye}, {"matrix": skew.tolist()}]}, 422,
         "body.poses[1].matrix"),
        ("set_pool", {"poses": [{"matrix": nan.tolist()}]}, 422, "body.poses[0].matrix[0][3]"),
        ("set_pool", {"poses": [{"matrix": [[1, 0], [0, 1]]}]}, 422, "body.poses[0].matrix[0]"),
        ("set_pool", {"poses": "nope"}, 422, "body.poses"),
        ("set_pool", {"poses": [{"matrix": eye}] * 3, "ids": [1, 1, 2]}, 422, "body"),
        ("extend_pool", {"poses": [{"matrix": eye}], "ids": [0]}, 409, "body.ids[0]"),
        ("commit", {"candidate_id": 999}, 409, "body.candidate_id"),
        ("commit", {}, 422, "body"),
        ("select", {"shortlist_size": 0}, 422, "body.shortlist_size"),
        ("select", {"shortlist_size": 2000}, 422, "body.shortlist_size"),
        ("select", {"shortlist_size": 300}, 422, "body.shortlist_size"),  # > max_shortlist
        ("select", {"method": "oracle"}, 422, "body.method"),
        ("select", {"current_id": 12345}, 409, "body.current_id"),
        ("select", {"embodied_k": 3}, 409, "body.embodied_k"),  # no current view yet: the state
        ("select", {"config": {"warp": 9}}, 422, "body.config.warp"),
        ("select", {"config": {"anchor": {"iterations": "many"}}}, 422,
         "body.config.anchor.iterations"),
        ("select", {"config": {"scoring": {"gamma": -1.0}}}, 422, "body.config.scoring.gamma"),
        ("select", {"commit": True, "pool": {"poses": [{"matrix": skew.tolist()}]}}, 422,
         "body.pool.poses[0].matrix"),
        ("select", {"commit": True, "config": {"bogus": 1}, "pool": {"poses": [{"matrix": eye}]}},
         422, "body.config.bogus"),
        ("add_observations", {"observations": [{"view_id": 77}]}, 409,
         "body.observations[0].view_id"),
        ("add_observations", {"observations": [{"pose": {"matrix": eye}, "depth": img.model_dump()}]},
         422, "body.observations[0].depth"),
        ("add_observations", {"observations": [{"pose": {"matrix": eye}, "image": {
            "encoding": "png", "data": b"not a png"}}]}, 422, "body.observations[0].image.data"),
        ("add_observations", {"observations": [{"pose": {"matrix": eye}, "image": {
            "encoding": "raw", "dtype": "float32", "shape": [32, 32, 3],
            "data": np.full((32, 32, 3), np.nan, np.float32).tobytes()}}]}, 422,
         "body.observations[0].image.data"),
        ("set_gaussians", {"format": "ply", "data": b"ply\nformat garbage"}, 422,
         "body.data"),
        ("set_gaussians", {"format": "splat", "data": b"\0" * 31}, 422, "body.data"),
        ("set_gaussians", {"format": "arrays", "arrays": {
            k: NDArray.from_numpy(np.zeros(s, np.float32)).model_dump() for k, s in
            [("means", (2, 3)), ("log_scales", (2, 3)), ("quats", (2, 4)),
             ("opacity_logits", (3,)), ("sh", (2, 1, 3))]}}, 422, "body.arrays"),
        ("set_gaussians", {"format": "arrays", "arrays": {
            k: NDArray.from_numpy(np.full(s, np.inf, np.float32)).model_dump() for k, s in
            [("means", (2, 3)), ("log_scales", (2, 3)), ("quats", (2, 4)),
             ("opacity_logits", (2,)), ("sh", (2, 1, 3))]}}, 422, "body.arrays.means"),
    ]


@pytest.mark.parametrize("op, body, status, field", _bad_cases())
def test_bad_input_is_refused_naming_the_field_and_changes_nothing(
        core: SessionRegistry, op: str, body: Any, status: int, field: str) -> None:
    before = snapshot(core)
    with pytest.raises(ServiceError) as exc:
        call(core, op, "s", body)
    assert exc.value.status == status, exc.value
    assert exc.value.field == field, exc.value
    assert snapshot(core) == before


def test_unknown_session_and_bad_ids(core: SessionRegistry) -> None:
    with pytest.raises(ServiceError) as exc:
        call(core, "get_session", "missing", None)
    assert (exc.value.status, exc.value.field) == (404, "session")
    with pytest.raises(ServiceError) as exc:
        call(core, "select", "../etc", {})
    assert (exc.value.status, exc.value.field) == (422, "session")
    with pytest.raises(ServiceError) as exc:
        create(core)  # the id is taken
    assert (exc.value.status, exc.value.field) == (409, "body.id")


def test_empty_pool_and_empty_map_are_conflicts(core: SessionRegistry) -> None:
    call(core, "set_pool", "s", {"poses": []})
    with pytest.raises(ServiceError) as exc:
        call(core, "select", "s", {"method": "random"})
    assert (exc.value.status, exc.value.code, exc.value.field) == (409, "empty_pool", "pool")
    create(core, "empty", init_gaussians=0)
    with pytest.raises(ServiceError) as exc:
        call(core, "select", "empty", {"method": "random"})
    assert (exc.value.status, exc.value.code) == (409, "map_empty")


def test_spread_selects_and_commits_without_a_map(core: SessionRegistry) -> None:
    create(core, "empty", init_gaussians=0)
    first = call(core, "select", "empty", {"method": "spread", "commit": True})
    second = call(core, "select", "empty", {"method": "spread"})
    assert first.committed is not None and second.chosen.id != first.chosen.id
    assert second.chosen.id in second.eligible and first.chosen.id not in second.eligible


def test_select_carries_the_objective_and_the_targets(core: SessionRegistry) -> None:
    targets = [{"matrix": p.tolist()} for p in TRAIN_POSES[[1, 5]]]
    cfg = {"objective": "target", "target_views": 2}
    a = call(core, "select", "s", {"method": "full_eig", "config": cfg, "targets": targets})
    assert a.latency_ms["scoring.targets"] > 0 and a.chosen.id in a.eligible
    b = call(core, "select", "s", {"method": "full_eig", "config": cfg})  # the pool's
    assert b.latency_ms["scoring.targets"] > 0
    with pytest.raises(ServiceError) as exc:  # the eig objective takes no targets
        call(core, "select", "s", {"method": "full_eig", "targets": targets})
    assert (exc.value.status, exc.value.field) == (422, "body.targets")
    bad = [{"matrix": (2.0 * TRAIN_POSES[0]).tolist()}]
    with pytest.raises(ServiceError) as exc:
        call(core, "select", "s", {"method": "full_eig", "config": cfg, "targets": bad})
    assert exc.value.status == 422 and "targets" in str(exc.value.field)
    with pytest.raises(ServiceError) as exc:
        call(core, "select", "s", {"method": "full_eig", "config": cfg,
                                   "targets": targets * 600})
    assert exc.value.status == 422 and "targets" in str(exc.value.field)
    with pytest.raises(ServiceError) as exc:
        call(core, "select", "s", {"method": "full_eig", "config": {"objective": "best"}})
    assert exc.value.status == 422 and "objective" in str(exc.value.field)


def test_select_without_commit_changes_nothing_and_repeats(core: SessionRegistry) -> None:
    before = snapshot(core)
    a = call(core, "select", "s", {"method": "agile", "shortlist_size": 4})
    b = call(core, "select", "s", {"method": "agile", "shortlist_size": 4})
    assert snapshot(core) == before
    assert a.chosen.id == b.chosen.id and [x.id for x in a.shortlist] == [x.id for x in b.shortlist]
    assert len(a.shortlist) == 4 and a.anchor is not None
    assert set(a.latency_ms) >= {"anchor", "scoring", "leverage", "rerank", "total"}
    assert a.core_ms >= a.latency_ms["total"]


def test_commit_updates_information_exactly_and_consumes_the_candidate(core: SessionRegistry) -> None:
    gmap = core.sessions["s"].record.gmap
    r = call(core, "select", "s", {"method": "random", "commit": True})
    assert r.committed is not None and r.committed.candidate_id == r.chosen.id
    pool_ids = call(core, "get_pool", "s", None).ids()
    assert r.chosen.id not in pool_ids and len(pool_ids) == len(POOL) - 1
    v = call(core, "commit", "s", {"candidate_id": pool_ids[0], "keep_in_pool": True})
    assert pool_ids[0] in call(core, "get_pool", "s", None).ids()
    want = expected_information(gmap, [POOL[r.chosen.id], POOL[pool_ids[0]]])
    got = call(core, "get_information", "s", None).arrays()
    for k, t in want.items():
        np.testing.assert_allclose(got[k], t.numpy(), rtol=1e-5, atol=1e-9)
    assert v.id == r.committed.id + 1
    # the selector's warm-start state advanced with the commit, so random moves on
    warm = core.sessions["s"].record.warm_state
    assert warm is not None and warm["event"] == 1


def test_observations_store_frames_and_update_information(core: SessionRegistry) -> None:
    gmap = core.sessions["s"].record.gmap
    rng = np.random.default_rng(0)
    img = (rng.random((32, 32, 3)) * 255).astype(np.uint8)
    depth = rng.random((32, 32)).astype(np.float32)
    obs = [
        ObservationIn.from_numpy(POOL[3], image=img, image_encoding="png"),
        ObservationIn.from_numpy(candidate_id=5, image=img, depth=depth),
    ]
    body = codec.load(codec.dump({"observations": [o.model_dump() for o in obs]},
                                 codec.MSGPACK), codec.MSGPACK)
    out = call(core, "add_observations", "s", body)
    assert [v.has_image for v in out.views] == [True, True]
    assert out.views[1].candidate_id == 5 and out.views[1].has_depth
    assert 5 not in call(core, "get_pool", "s", None).ids()
    s = core.sessions["s"]
    np.testing.assert_array_equal(s.view_image(out.views[0].id), img)
    np.testing.assert_array_equal(s.view_image(out.views[1].id), img)
    np.testing.assert_array_equal(s.view_depth(out.views[1].id), depth)
    want = expected_information(gmap, [POOL[3], POOL[5]])
    got = call(core, "get_information", "s", None).arrays()
    np.testing.assert_allclose(got["means"], want["means"].numpy(), rtol=1e-5, atol=1e-9)
    # attaching a frame to a committed view adds no information twice
    v = call(core, "commit", "s", {"candidate_id": 7})
    before = call(core, "get_session", "s", None).information.digest
    call(core, "add_observations", "s", {"observations": [{"view_id": v.id, "image":
                                                          obs[0].image.model_dump()}]})
    assert call(core, "get_session", "s", None).information.digest == before
    with pytest.raises(ServiceError) as exc:  # a view takes one frame
        call(core, "add_observations", "s", {"observations": [{"view_id": v.id, "image":
                                                              obs[0].image.model_dump()}]})
    assert exc.value.status == 409


def test_mapper_hook_sees_new_views(core: SessionRegistry) -> None:
    seen: list[list[int]] = []

    class Mapper:
        def integrate(self, session: Any, views: list) -> None:
            seen.append([v.id for v in views])

    core.sessions["s"].mapper = Mapper()
    call(core, "add_observations", "s", {"observations": [{"pose": {"matrix": POOL[1].tolist()}}]})
    assert seen == [[0]]


def test_replacing_the_map_recomputes_information(core: SessionRegistry) -> None:
    call(core, "commit", "s", {"candidate_id": 2})
    g = GaussianMap.from_points(torch.rand(50, 3) - 0.5, torch.rand(50, 3), scale=0.05)
    arrays = {k: NDArray.from_numpy(v.numpy()).model_dump() for k, v in g.items()}
    info = call(core, "set_gaussians", "s", {"format": "arrays", "arrays": arrays})
    assert info.gaussians.count == 50
    want = expected_information(g, [POOL[2]])
    got = call(core, "get_information", "s", None).arrays()
    for k, t in want.items():
        np.testing.assert_allclose(got[k], t.numpy(), rtol=1e-5, atol=1e-9)


def test_splat_upload_and_rgbd_creation(core: SessionRegistry, tmp_path: Path) -> None:
    g = GaussianMap.from_points(torch.rand(40, 3) - 0.5, torch.rand(40, 3), scale=0.05)
    path = tmp_path / "m.splat"
    g.save(path)
    info = call(core, "set_gaussians", "s", {"format": "splat", "data": path.read_bytes()})
    assert info.gaussians.count == 40
    depth = np.full((32, 32), 2.0, np.float32)
    depth[:4] = 0  # missing values
    frames = [ObservationIn.from_numpy(POOL[i], depth=depth,
                                       image=np.full((32, 32, 3), 200, np.uint8)).model_dump()
              for i in (0, 6)]
    info = call(core, "create_session", None, {"id": "rgbd", "intrinsics": SMALL_INTRINSICS,
                                               "frames": frames, "init_gaussians": 150})
    assert info.gaussians.count == 150 and info.num_views == 2
    # RGB only and no bounds: no Gaussians until some are set
    info = call(core, "create_session", None, {"id": "rgb", "intrinsics": SMALL_INTRINSICS,
                                               "frames": [{"pose": {"matrix": POOL[0].tolist()}}]})
    assert info.gaussians.count == 0 and info.num_views == 1


def test_limits_are_settings(tmp_path: Path) -> None:
    c = make_core(tmp_path / "st", max_sessions=1, max_pool_size=5, max_image_pixels=100)
    with pytest.raises(ServiceError) as exc:
        create(c, "a")  # the 32x32 session camera exceeds max_image_pixels
    assert exc.value.status == 422 and exc.value.field == "body.intrinsics"
    assert exc.value.code == "limit_exceeded"
    c.settings.max_image_pixels = 4096
    with pytest.raises(ServiceError) as exc:
        create(c, "a")  # the 24-candidate pool exceeds max_pool_size
    assert exc.value.status == 422 and exc.value.field == "body.pool.poses"
    create(c, "a", pool=None)
    call(c, "set_pool", "a", {"poses": [{"matrix": np.eye(4).tolist()}] * 4})
    with pytest.raises(ServiceError) as exc:  # extending past the limit: a count reached
        call(c, "extend_pool", "a", {"poses": [{"matrix": np.eye(4).tolist()}] * 2})
    assert exc.value.status == 429 and exc.value.field == "body.poses"
    with pytest.raises(ServiceError) as exc:
        create(c, "b", pool=None)
    assert exc.value.status == 429
    c.close()


def test_everything_acknowledged_is_reloaded(core: SessionRegistry, tmp_path: Path) -> None:
    call(core, "select", "s", {"method": "agile", "commit": True})
    call(core, "extend_pool", "s", {"poses": [{"matrix": np.eye(4).tolist()}], "ids": [500]})
    call(core, "add_observations", "s", {"observations": [{
        "pose": {"position": [0, 0, -2], "orientation_xyzw": [0, 0, 0, 1]},
        "image": {"encoding": "raw", "dtype": "uint8", "shape": [32, 32, 3],
                  "data": bytes(32 * 32 * 3)}}]})
    before = snapshot(core)
    warm = core.sessions["s"].record.warm_state
    reloaded = make_core(tmp_path / "state")
    assert snapshot(reloaded) == before
    assert call(reloaded, "get_pool", "s", None).ids()[-1] == 500
    assert set(reloaded.sessions["s"].record.warm_state or {}) == set(warm or {})
    assert reloaded.sessions["s"].view_image(1).shape == (32, 32, 3)
    reloaded.close()


def test_interrupted_writes_are_cleaned_up(core: SessionRegistry, tmp_path: Path) -> None:
    folder = tmp_path / "state" / "sessions"
    (folder / ".creating-x-1234").mkdir()
    (folder / "s" / "information.999.pt").write_bytes(b"half written")
    (folder / "s" / ".manifest.json.tmp-abcd").write_bytes(b"{")
    (folder / "s" / "views").mkdir(exist_ok=True)
    (folder / "s" / "views" / "v00000099.rgb.png").write_bytes(b"orphan")
    before = snapshot(core)
    reloaded = make_core(tmp_path / "state")
    assert snapshot(reloaded) == before
    assert not (folder / ".creating-x-1234").exists()
    assert not (folder / "s" / "information.999.pt").exists()
    assert not (folder / "s" / ".manifest.json.tmp-abcd").exists()
    assert not (folder / "s" / "views" / "v00000099.rgb.png").exists()
    reloaded.close()


def test_delete_removes_the_session_everywhere(core: SessionRegistry, tmp_path: Path) -> None:
    assert call(core, "delete_session", "s", None).deleted
    assert not (tmp_path / "state" / "sessions" / "s").exists()
    with pytest.raises(ServiceError):
        call(core, "get_session", "s", None)
    assert make_core(tmp_path / "state").sessions == {}


def test_raw_images_round_trip_through_storage(core: SessionRegistry) -> None:
    img = np.random.default_rng(1).random((32, 32, 3)).astype(np.float32)
    o = ObservationIn.from_numpy(POOL[0], image=img)
    out = call(core, "add_observations", "s", {"observations": [o.model_dump()]})
    np.testing.assert_array_equal(core.sessions["s"].view_image(out.views[0].id), img)


def test_the_target_objective_adds_its_fisher_passes_to_the_estimate(core: SessionRegistry
                                                                      ) -> None:
    from agilegs.config.selection import SelectConfig
    from agilegs.service.sessions.selection import select_estimate

    rec = core.sessions["s"].record
    base = select_estimate(rec, "full_eig", SelectConfig())
    more = select_estimate(rec, "full_eig", SelectConfig(objective="target", target_views=8))
    most = select_estimate(rec, "full_eig", SelectConfig(objective="target", target_views=16))
    assert base.seconds < more.seconds < most.seconds
    assert select_estimate(rec, "agile", SelectConfig(objective="target")).seconds == \
        select_estimate(rec, "agile", SelectConfig()).seconds
