"""The browser viewer through viser's Python API, on in-process servers: what the live view
draws after each change of a session, its messages when the session or the server goes
away, the replay of a ``bench run`` folder, the conversions and the command line."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, InProcess, gaussian_blob, ring_poses

from agilegs.client import Client
from agilegs.lab.scenes import bundled_scene
from agilegs.service.cli import main
from agilegs.service.launch import free_port
from agilegs.service.viewer.canvas import ANCHOR, CHOSEN
from agilegs.service.viewer.live import SessionViewer
from agilegs.service.viewer.replay import RunReplay, load_runs
from agilegs.service.viewer.scene import (
    GREY,
    colormap,
    pose_wxyz_position,
    score_colors,
    splat_parameters,
    up_direction,
)

GREEN = (0.1, 0.8, 0.2)
blob = gaussian_blob


def viewer_for(api: InProcess, session: str = "s", **kwargs: Any) -> SessionViewer:
    return SessionViewer(kwargs.pop("client", None) or api.client(), session, port=free_port(),
                         where="the test server", **kwargs)


def make(c: Client, sid: str = "s", n: int = 80, pool: int = 8) -> None:
    c.create_session(SMALL_INTRINSICS, id=sid, gaussians=blob(n), pool=ring_poses(pool),
                     defaults={"method": "agile", "shortlist_size": 3})


def position(handle: Any) -> np.ndarray:
    return np.asarray(handle.position, dtype=np.float64)


# ============================================================================ conversions
def test_poses_scores_and_splats_convert_as_viser_expects() -> None:
    from viser import transforms as tf

    for pose in ring_poses(7):
        wxyz, pos = pose_wxyz_position(pose)
        np.testing.assert_allclose(tf.SO3(wxyz).as_matrix(), pose[:3, :3], atol=1e-9)
        np.testing.assert_allclose(pos, pose[:3, 3])
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # trace -1: the other branch
    np.testing.assert_allclose(tf.SO3(pose_wxyz_position(flip)[0]).as_matrix(), flip[:3, :3],
                               atol=1e-9)
    # scores: the lowest dark, the highest yellow, no score grey
    cols = score_colors({1: 0.0, 2: 5.0, 3: 10.0, 4: None})
    assert cols[1] == tuple(colormap(np.array(0.0))) and cols[3] == tuple(colormap(np.array(1.0)))
    assert cols[4] == GREY and cols[2] not in (cols[1], cols[3])
    assert cols[3] == (253, 231, 37)
    # splats: covariance R diag(s²) Rᵀ, colour from the DC band, opacity = sigmoid
    g = blob(3)
    g["quats"][1] = [math.cos(0.4), 0.0, 0.0, math.sin(0.4)]  # 0.8 rad about z
    g["log_scales"][1] = np.log([0.1, 0.02, 0.05])
    centers, cov, rgb, opacity = splat_parameters(g)
    r = tf.SO3.from_z_radians(0.8).as_matrix()
    np.testing.assert_allclose(cov[1], r @ np.diag([0.01, 0.0004, 0.0025]) @ r.T, atol=1e-6)
    np.testing.assert_allclose(rgb, np.tile(GREEN, (3, 1)), atol=1e-6)
    np.testing.assert_allclose(opacity[:, 0], 1 / (1 + math.exp(-2.0)), atol=1e-6)
    np.testing.assert_allclose(up_direction(ring_poses(6)), [0, -1, 0], atol=1e-9)


# ============================================================================ live
def test_after_a_select_with_commit_the_scene_holds_it_all(api: InProcess) -> None:
    with api.client() as c, viewer_for(api) as v:
        make(c)
        assert v.step()
        assert v.canvas.splats is not None and v.canvas.splats.buffer.shape == (80, 8)
        assert sorted(v.canvas.pool) == list(range(8)) and v.canvas.chosen is None
        assert all(h.color == GREY for h in v.canvas.pool.values())
        d = c.select("s", commit=True)
        assert v.step(wait=2)
        pool = c.get_pool("s")
        assert sorted(v.canvas.pool) == sorted(pool.ids()) and d.chosen.id not in v.canvas.pool
        for cand in pool.candidates:  # one frustum per candidate, where it is
            np.testing.assert_allclose(position(v.canvas.pool[cand.id]),
                                       cand.pose.to_matrix()[:3, 3], atol=1e-6)
        expect = score_colors({s.id: s.score for s in d.scores})
        shortlist = {s.id for s in d.shortlist}
        assert len(d.scores) >= 2 and len(shortlist) == 3
        for cid, h in v.canvas.pool.items():
            assert h.color == expect.get(cid, GREY), cid
            assert (h.variant == "filled") == (cid in shortlist), cid
            assert h.scale == pytest.approx(v.canvas.size * (1.5 if cid in shortlist else 1.0))
        assert v.canvas.chosen.color == CHOSEN
        np.testing.assert_allclose(position(v.canvas.chosen), d.chosen.pose.to_matrix()[:3, 3],
                                   atol=1e-6)
        assert d.anchor is not None and v.canvas.anchor.color == ANCHOR
        np.testing.assert_allclose(position(v.canvas.anchor), d.anchor.to_matrix()[:3, 3],
                                   atol=1e-6)
        assert v.canvas.anchor_line is not None
        # the path: the acquired view, then a second one and the line between them
        assert len(v.canvas.views) == 1 and v.canvas.path_line is None
        np.testing.assert_allclose(position(v.canvas.views[0]), d.chosen.pose.to_matrix()[:3, 3],
                                   atol=1e-6)
        d2 = c.select("s", commit=True, seed=5)
        assert v.step(wait=2)
        assert len(v.canvas.views) == 2 and v.canvas.path_line is not None
        np.testing.assert_allclose(v.canvas.path_line.points[0], np.stack([
            d.chosen.pose.to_matrix()[:3, 3], d2.chosen.pose.to_matrix()[:3, 3]]), atol=1e-4)
        # the panel: the method, the latency breakdown, the counts
        text = v.decision_md.content
        assert f"chose candidate **{d2.chosen.id}**" in text and "acquired as view 1" in text
        for stage in ("anchor", "scoring", "total", "server"):
            assert f"| {stage}" in text
        assert "views **2** · pool **6**" in v.session_md.content
        assert v.latency_chart.data[1].tolist() == [d.latency_ms["total"], d2.latency_ms["total"]]
        assert "following live · 2 decision(s)" in v.status_md.content


def test_map_pool_and_psnr_updates_are_followed(api: InProcess) -> None:
    with api.client() as c, viewer_for(api) as v:
        make(c)
        assert v.step()
        before = v.canvas.splats
        c.set_gaussians("s", blob(30, color=(0.9, 0.1, 0.1), seed=3))
        assert v.step(wait=0.2)
        assert v.canvas.splats is not before and v.canvas.splats.buffer.shape == (30, 8)
        v.controls["map"].value = "points"  # the panel's toggle
        assert v.canvas.splats is None and v.canvas.points.points.shape == (30, 3)
        np.testing.assert_allclose(v.canvas.points.colors, np.tile([230, 26, 26], (30, 1)), atol=1)
        v.controls["map"].value = "splats + points"
        assert v.canvas.splats is not None and v.canvas.points is not None
        poses = ring_poses(5, radius=3.0)
        c.set_pool("s", poses, ids=[10, 11, 12, 13, 14])
        assert v.step(wait=0.2)
        assert sorted(v.canvas.pool) == [10, 11, 12, 13, 14]
        np.testing.assert_allclose(position(v.canvas.pool[12]), poses[2][:3, 3], atol=1e-6)
        v.controls["pool"].value = False
        assert not any(h.visible for h in v.canvas.pool.values())
        v.report_psnr(3, 18.5)
        v.report_psnr(4, 19.25)
        assert v.psnr_chart.data[0].tolist() == [3.0, 4.0]
        assert v.psnr_chart.data[1].tolist() == [18.5, 19.25]


def test_a_large_pool_is_drawn_in_part_and_said_so(api: InProcess) -> None:
    with api.client() as c, viewer_for(api, max_frustums=5) as v:
        make(c, pool=12)
        assert v.step()
        assert sorted(v.canvas.pool) == [0, 1, 2, 3, 4] and v.canvas.pool_hidden == 7
        assert "pool **12** (7 not drawn)" in v.session_md.content


def test_a_deleted_session_is_said_in_the_panel_and_followed_again(api: InProcess) -> None:
    with api.client() as c, viewer_for(api) as v:
        make(c)
        c.select("s")
        assert v.step()
        c.delete_session("s")
        assert not v.step(wait=2)
        assert "was deleted" in v.status_md.content and "`s`" in v.status_md.content
        assert not v.step()  # the next rounds: the session does not exist
        assert "no session `s`" in v.status_md.content
        assert v.canvas.chosen is not None  # the last state stays on the page
        make(c, n=20, pool=4)  # created again: followed from scratch
        assert v.step()
        assert v.problem is None and sorted(v.canvas.pool) == [0, 1, 2, 3]
        assert v.canvas.splats.buffer.shape == (20, 8) and v.canvas.chosen is None


class Switch(httpx.BaseTransport):
    """Forwards to a transport until ``down`` is set, then fails as a dead server does."""

    def __init__(self, inner: httpx.BaseTransport) -> None:
        self.inner = inner
        self.down = False

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if self.down:
            raise httpx.ConnectError("connection refused", request=request)
        return self.inner.handle_request(request)


def test_a_server_that_goes_away_is_said_in_the_panel(api: InProcess) -> None:
    switch = Switch(api.transport)
    client = Client(api.url, transport=switch)
    with api.client() as c, viewer_for(api, client=client) as v:
        make(c)
        assert v.step()
        switch.down = True
        assert not v.step(wait=0.5)
        assert "does not answer" in v.status_md.content and "retrying" in v.status_md.content
        switch.down = False
        c.select("s")
        assert v.step()
        assert v.problem is None and v.canvas.chosen is not None


def test_a_refused_token_is_said_in_the_panel(api_factory: Any) -> None:
    api = api_factory(token="tok")
    with api.client(token="tok") as c, viewer_for(api) as v:
        make(c)
        assert not v.step()
        assert "401" in v.status_md.content and "--token" in v.status_md.content
    with viewer_for(api, client=api.client(token="tok")) as v:
        assert v.step() and sorted(v.canvas.pool) == list(range(8))


def test_the_background_loop_follows_decisions(api: InProcess) -> None:
    with api.client() as c, viewer_for(api) as v:
        make(c)
        v.start(poll=0.3)
        assert v.wait_until(lambda x: x.loaded, 20)
        d = c.select("s", commit=True)
        assert v.wait_until(lambda x: len(x.decisions) == 1 and len(x.canvas.views) == 1, 20)
        np.testing.assert_allclose(position(v.canvas.chosen), d.chosen.pose.to_matrix()[:3, 3],
                                   atol=1e-6)


# ============================================================================ replay
@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bench")
    assert main(["bench", "run", "--scene", str(bundled_scene("spot")), "--methods",
                 "random,agile_plus", "--profile", "tiny", "--seeds", "0", "--out", str(out),
                 "--no-plots"]) == 0
    return out


def test_the_replay_steps_through_a_run(run_dir: Path) -> None:
    runs = load_runs(run_dir)
    assert [(r.variant, r.seed) for r in runs] == [("agile_plus", 0), ("random", 0)]
    with RunReplay(run_dir, port=free_port()) as rp:
        rec = rp.record
        assert rec.variant == "agile_plus"
        poses = rec.pool_poses
        assert poses is not None and poses.shape[1:] == (4, 4)
        initial = rec.data["initial"]
        # event 0: the initial views as the path, the rest as the pool, no decision
        assert len(rp.canvas.views) == len(initial) and rp.canvas.chosen is None
        assert sorted(rp.canvas.pool) == [i for i in range(len(poses)) if i not in initial]
        n = len(rec.events)
        assert n >= 2
        for k in range(1, n + 1):
            rp.show_event(k)
            ev = rec.events[k - 1]
            np.testing.assert_allclose(position(rp.canvas.chosen), poses[ev["choice"]][:3, 3],
                                       atol=1e-6)
            # acquired at this event: out of the pool, the path's newest view
            assert ev["choice"] not in rp.canvas.pool
            assert len(rp.canvas.views) == len(initial) + k
            np.testing.assert_allclose(position(rp.canvas.views[-1]),
                                       poses[ev["choice"]][:3, 3], atol=1e-6)
            np.testing.assert_allclose(position(rp.canvas.anchor), np.asarray(ev["anchor"])[:3, 3],
                                       atol=1e-6)
            expect = score_colors({int(i): float(s) for i, s in ev["scores"]})
            for cid, h in rp.canvas.pool.items():
                assert h.color == expect.get(cid, GREY)
                assert (h.variant == "filled") == (cid in ev["shortlist"])
            assert f"event {k} of {n}" in rp.event_md.content
            red = rec.data["redundancy"]["events"][k - 1]
            assert f"pick → nearest acquired view {red['pick_angle_deg']:.1f}°" in (
                rp.event_md.content)
            assert f"anchor → nearest acquired view {red['anchor_angle_deg']:.1f}°" in (
                rp.event_md.content)
        gap = rec.data["redundancy"]["final_gap_deg"]
        assert f"the pool's final gap {gap:.1f}°" in rp.run_md.content
        curve = rec.data["curve"]
        assert rp.psnr_chart.data[1].tolist() == [c["psnr"] for c in curve]
        assert np.nansum(rp.psnr_chart.data[2]) == pytest.approx(curve[-1]["psnr"])
        rp.show_event(n + 5)  # clamped
        assert rp.event == n
        rp.select("spot_10k", "random", 0)
        rp.show_event(1)
        assert rp.canvas.anchor is None and rp.canvas.chosen is not None
        assert rp.variant_dd.value == "random" and "random" in rp.run_md.content


def test_an_older_record_is_replayed_from_its_camera_centres(run_dir: Path, tmp_path: Path
                                                             ) -> None:
    old = tmp_path / "old"
    shutil.copytree(run_dir / "runs", old / "runs")
    for path in (old / "runs").rglob("seed*.json"):
        data = json.loads(path.read_text())
        for key in ("pool_poses", "intrinsics"):
            data.pop(key)
        for ev in data["events"]:
            ev.pop("scores")
            ev.pop("anchor")
        path.write_text(json.dumps(data))
    with RunReplay(old, port=free_port()) as rp:
        assert rp.canvas.pool == {} and rp.trajectory is not None
        rp.show_event(2)
        assert rp.trajectory[0].points.shape == (3, 3) and "no pool poses" in rp.run_md.content


# ============================================================================ the command
def test_the_command_without_the_extra_or_a_session_says_what_to_do(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        tmp_path: Path) -> None:
    assert main(["view"]) == 2
    assert "--session" in capsys.readouterr().err
    assert main(["view", "--run", str(tmp_path)]) == 2
    assert "no run records" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "viser", None)  # as if viser were not installed
    assert main(["view", "--session", "s"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and 'pip install "agilegs[viewer]"' in err
    assert main(["demo", "--quick", "--view"]) == 2
    assert 'pip install "agilegs[viewer]"' in capsys.readouterr().out
