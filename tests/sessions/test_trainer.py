"""The service's mapper: observations are trained into the session's map in the background."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import SMALL_INTRINSICS, call, create, make_core, wait_idle
from conftest import TRAIN_FAST as FAST
from conftest import TRAIN_INTR as INTR
from conftest import TRAIN_POSES as POSES
from conftest import train_frame as frame
from conftest import train_reference as reference
from inprocess import serve_in_process

from agilegs.schemas import NDArray, ObservationIn
from agilegs.service.errors import ServiceError
from agilegs.service.mapper.topology import remap_per_gaussian
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    accumulate_information,
    fisher_diag,
    init_information,
    render,
)
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.sessions.trainer import SessionTrainer, compose_src


def information_shapes_follow(info: Any) -> None:
    n = info.gaussians.count
    for name, f in info.information.fields.items():
        assert f.shape[0] == n, (name, f.shape, n)


@pytest.fixture
def core(tmp_path: Path) -> Any:
    c = make_core(tmp_path / "state")
    yield c
    c.close()


def test_observations_are_trained_into_the_map(core: SessionRegistry) -> None:
    info = create(core)
    assert info.mapper.state == "training" and info.mapper.pending_steps == 60
    assert info.mapper.views == 3 and info.mapper.steps_per_view == 20
    losses: list[float] = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        st = call(core, "get_session", "s", None)
        if st.mapper.last_loss is not None and (not losses or st.mapper.last_loss != losses[-1]):
            losses.append(st.mapper.last_loss)
        if st.mapper.state == "idle":
            break
        time.sleep(0.05)
    assert st.mapper.state == "idle", st.mapper
    assert st.mapper.steps == st.mapper.published_steps == 60 and st.mapper.pending_steps == 0
    assert len(losses) >= 2 and losses[-1] < losses[0]  # training lowers the loss
    # densification changed the Gaussian count and Ĥ followed it
    assert st.gaussians.count != 100 and st.mapper.num_gaussians == st.gaussians.count
    information_shapes_follow(st)
    assert st.version > info.version  # every publication is a persisted change
    g = call(core, "get_gaussians", "s", None)
    assert g.count == st.gaussians.count and g.mapper_steps == 60 and g.version == st.version
    assert g.to_numpy()["means"].shape == (g.count, 3)

    # a new view owes steps_per_view more steps, trained from the current map
    out = call(core, "add_observations", "s", {"observations": [frame(2)]})
    assert out.views[0].has_image and out.views[0].has_depth
    st2 = wait_idle(core)
    assert st2.mapper.steps == 80 and st2.mapper.views == 4 and st2.mapper.state == "idle"
    information_shapes_follow(st2)
    # the map renders the ground truth better than the initial map did
    assert psnr_of(core, "s") > psnr_of_map(initial_map(core, "s"))


def initial_map(core: SessionRegistry, sid: str) -> GaussianMap:
    from agilegs.service.sessions.convert import Frame as _Frame
    from agilegs.service.sessions.convert import gaussians_from_depth

    frames = []
    for i in (0, 4, 8):
        o = ObservationIn.model_validate(frame(i))
        frames.append(_Frame(index=i, obs=o, intrinsics=dict(SMALL_INTRINSICS),
                             image_rgb=o.image.to_numpy(), depth=o.depth.to_numpy().copy(),
                             pose=POSES[i]))
    return gaussians_from_depth(frames, 100, 0)


def psnr_of_map(g: GaussianMap) -> float:
    from agilegs.service.mapper.quality import psnr

    vals = []
    for i in (1, 5, 9):  # views the mapper never saw
        cam = Camera(torch.from_numpy(POSES[i]).float(), INTR)
        with torch.no_grad():
            vals.append(psnr(render(g, cam).rgb.clamp(0, 1), torch.from_numpy(reference(i)[0])))
    return float(np.mean(vals))


def psnr_of(core: SessionRegistry, sid: str) -> float:
    a = call(core, "get_gaussians", sid, None).to_numpy()
    return psnr_of_map(GaussianMap(**{k: torch.from_numpy(v.copy()) for k, v in a.items()}))


def test_information_is_carried_per_gaussian(core: SessionRegistry) -> None:
    create(core, mapper={"enabled": False})
    s = core.sessions["s"]
    rec = s.record
    n = len(rec.gmap)
    # kept 0..n-1 except 3, a clone of 5, two split children of 7, two brand new
    src = torch.tensor([i for i in range(n) if i != 3] + [5, 7, 7, -1, -1])
    g = rec.gmap.subset(src.clamp_min(0))
    with s.lock:
        s.replace_map(g, src=src, mapper_progress={"steps": 7, "last_loss": 0.5})
    h = s.record.h_acc
    want = remap_per_gaussian(rec.h_acc, src, 1e-3)
    for k in h:
        assert h[k].shape[0] == n + 4
        torch.testing.assert_close(h[k], want[k])
    assert (h["means"][-2:] == 1e-3).all() and (h["means"][-5] == rec.h_acc["means"][5]).all()
    assert s.record.mapper["steps"] == 7 and s.record.mapper["last_loss"] == 0.5

    # 'recompute': λ + Σ_v H_v on the new map from every acquired view
    call(core, "create_session", None, {"id": "r", "intrinsics": SMALL_INTRINSICS,
                                        "init_gaussians": 100, "frames": [frame(0)],
                                        "mapper": {"enabled": False},
                                        "information": {"mapper_update": "recompute"}})
    r = core.sessions["r"]
    g2 = r.record.gmap.subset(torch.arange(60))
    with r.lock:
        r.replace_map(g2, src=torch.arange(60))
    want2 = accumulate_information(init_information(g2, 1e-3),
                                   fisher_diag(g2, Camera(torch.from_numpy(POSES[0]).float(),
                                                          INTR)))
    for k, t in want2.items():
        torch.testing.assert_close(r.record.h_acc[k], t, rtol=1e-5, atol=1e-9)


def test_compose_src_follows_two_changes() -> None:
    first = torch.tensor([0, 2, 2, -1])  # kept 0, 2 twice, one new
    second = torch.tensor([1, 3, -1, 0])
    assert compose_src(first, second).tolist() == [2, -1, -1, 0]
    assert compose_src(torch.zeros(0, dtype=torch.long), torch.tensor([-1, -1])).tolist() == [
        -1, -1]


def test_select_and_commit_while_training(tmp_path: Path) -> None:
    core = make_core(tmp_path / "st", mapper_steps_per_view=40, mapper_burst=5)
    try:
        create(core)
        deadline = time.monotonic() + 30
        while call(core, "get_session", "s", None).mapper.steps == 0:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        results: list[Any] = []
        errors: list[BaseException] = []

        def pick() -> None:
            try:
                results.append(call(core, "select", "s", {"method": "agile", "commit": True,
                                                         "shortlist_size": 3}))
                results.append(call(core, "select", "s", {"method": "random"}))
            except BaseException as exc:  # pragma: no cover - reported below
                errors.append(exc)

        th = threading.Thread(target=pick)
        th.start()
        mid = call(core, "get_session", "s", None).mapper
        th.join(timeout=60)
        assert not errors and len(results) == 2
        assert mid.state == "training"
        d = results[0]
        assert d.committed is not None
        st = wait_idle(core)
        assert st.mapper.state == "idle" and st.mapper.steps == 120
        assert st.num_views == 4 and st.mapper.views == 3  # the committed view has no image
        information_shapes_follow(st)
        # the committed view's information survived the publications after it
        assert d.committed.id in [v.id for v in call(core, "list_views", "s", None).views]
    finally:
        core.close()


def test_a_pushed_map_wins_over_the_burst(core: SessionRegistry) -> None:
    create(core, mapper={"steps_per_view": 40, "config": {**FAST, "densify": False}})
    g = GaussianMap.from_points((torch.rand(50, 3) - 0.5) * 0.8, torch.rand(50, 3), scale=0.05)
    arrays = {k: NDArray.from_numpy(v.numpy()).model_dump() for k, v in g.items()}
    info = call(core, "set_gaussians", "s", {"format": "arrays", "arrays": arrays})
    assert info.gaussians.count == 50
    st = wait_idle(core)
    assert st.mapper.state == "idle"
    assert st.gaussians.count == 50  # trained from the pushed map, not the one it replaced
    information_shapes_follow(st)


def test_restart_resumes_from_the_persisted_map(tmp_path: Path) -> None:
    state = tmp_path / "state"
    c1 = make_core(state, mapper_steps_per_view=40, mapper_burst=5)
    create(c1)
    deadline = time.monotonic() + 30
    while call(c1, "get_session", "s", None).mapper.published_steps < 10:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    c1.close()  # stops after the current step; what was trained is published
    before = call(c1, "get_session", "s", None)
    g_before = call(c1, "get_gaussians", "s", None).to_numpy()
    assert 10 <= before.mapper.published_steps < 120
    assert before.mapper.steps == before.mapper.published_steps

    c2 = make_core(state, mapper=False)  # reload without training: nothing is lost
    again = call(c2, "get_session", "s", None)
    assert again.version == before.version and again.mapper.state == "off"
    assert again.mapper.steps == before.mapper.steps
    assert again.information.digest == before.information.digest
    g_again = call(c2, "get_gaussians", "s", None).to_numpy()
    for k in g_before:
        np.testing.assert_array_equal(g_again[k], g_before[k])
    c2.close()

    c3 = make_core(state, mapper_steps_per_view=40, mapper_burst=20)
    try:
        st = wait_idle(c3, timeout=120)  # the steps still owed are trained, then it idles
        assert st.mapper.state == "idle" and st.mapper.steps == 120
        assert st.mapper.published_steps == 120
        information_shapes_follow(st)
    finally:
        c3.close()


def test_mapper_off_and_failures_are_reported(tmp_path: Path) -> None:
    off = make_core(tmp_path / "off", mapper=False)
    info = create(off)
    assert info.mapper.state == "off" and info.mapper.pending_steps == 60
    time.sleep(0.3)
    assert call(off, "get_session", "s", None).version == info.version  # nothing trains
    off.close()

    core = make_core(tmp_path / "on")
    try:
        info = create(core, "quiet", mapper={"enabled": False})
        assert info.mapper.state == "off" and not info.mapper.enabled
        # an empty map and no depth: nothing to train, the error is in the state
        call(core, "create_session", None, {
            "id": "empty", "intrinsics": SMALL_INTRINSICS, "init_gaussians": 0,
            "bounds": {"min": [-1] * 3, "max": [1] * 3}, "mapper": {"config": FAST}})
        call(core, "add_observations", "empty", {"observations": [frame(1, depth=False)]})
        st = wait_idle(core, "empty")
        assert st.mapper.state == "error" and "no Gaussians" in (st.mapper.error or "")
        # a new RGB-D view retries: the map is initialised from its depth and trained
        call(core, "add_observations", "empty", {"observations": [frame(5)]})
        st = wait_idle(core, "empty")
        assert st.mapper.state == "idle" and st.gaussians.count > 0, st.mapper
        assert call(core, "get_session", "quiet", None).version == info.version
    finally:
        core.close()


def test_bad_mapper_options_are_refused(core: SessionRegistry) -> None:
    for config, field in (({"nope": 1}, "body.mapper.config.nope"),
                          ({"lambda_dssim": 2.0}, "body.mapper.config.lambda_dssim"),
                          ({"background": [0, 0]}, "body.mapper.config.background[2]")):
        with pytest.raises(ServiceError) as exc:
            create(core, mapper={"config": config})
        assert exc.value.status == 422 and exc.value.field == field, exc.value
    with pytest.raises(ServiceError) as exc:
        create(core, mapper={"steps_per_view": -1})
    assert exc.value.status == 422 and exc.value.field == "body.mapper.steps_per_view"
    assert "s" not in core.sessions


def test_session_trainer_is_the_observation_hook(core: SessionRegistry) -> None:
    call(core, "create_session", None, {"id": "s", "intrinsics": SMALL_INTRINSICS,
                                        "bounds": {"min": [-1] * 3, "max": [1] * 3},
                                        "init_gaussians": 10})
    assert isinstance(core.sessions["s"].mapper, SessionTrainer)
    assert core.trainer is not None and core.trainer.running


def test_served_mapper_trains_and_survives_a_restart(tmp_path: Path) -> None:
    settings = {"mapper": True, "mapper_steps_per_view": 15, "mapper_burst": 5, "fsync": False}
    state = tmp_path / "state"
    with serve_in_process(state, **settings) as srv, srv.client() as c:
        c.create_session(SMALL_INTRINSICS, id="live",
                         frames=[ObservationIn.model_validate(frame(i)) for i in (0, 6)],
                         init_gaussians=120, pool=POSES, mapper={"config": FAST})
        d = c.select("live", method="random", commit=True)
        c.add_observations("live", ObservationIn.model_validate(
            frame(0, view_id=d.committed.id)))
        deadline = time.monotonic() + 90
        while (st := c.get_session("live")).mapper.state != "idle":
            assert time.monotonic() < deadline, st.mapper
            time.sleep(0.1)
        assert st.mapper.steps == 45 and st.mapper.views == 3
        g = c.get_gaussians("live")
        assert g.count == st.gaussians.count and g.mapper_steps == 45
        information_shapes_follow(st)
    with serve_in_process(state, **settings) as srv, srv.client() as c:
        again = c.get_session("live")
        assert again.mapper.state == "idle" and again.mapper.steps == 45
        assert again.version == st.version
        g2 = c.get_gaussians("live").to_numpy()
        for k, v in g.to_numpy().items():
            np.testing.assert_array_equal(g2[k], v)


def test_deleting_a_session_under_training_leaves_the_worker_running(core: SessionRegistry,
                                                                     tmp_path: Path) -> None:
    create(core, "gone", mapper={"steps_per_view": 200, "config": FAST})
    deadline = time.monotonic() + 30
    while call(core, "get_session", "gone", None).mapper.steps == 0:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    call(core, "delete_session", "gone", None)
    assert not (tmp_path / "state" / "sessions" / "gone").exists()
    create(core, "next", views=(0, 6), mapper={"steps_per_view": 10, "config": FAST})
    st = wait_idle(core, "next")
    assert st.mapper.state == "idle" and st.mapper.steps == 20
    assert core.trainer is not None and core.trainer.running
