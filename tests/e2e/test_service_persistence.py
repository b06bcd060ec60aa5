"""SIGKILL and restart on the same state folder loses nothing acknowledged."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from conftest import SMALL_INTRINSICS, ring_poses

from agilegs.client import AgileGSError, Client
from agilegs.schemas import ObservationIn

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


def state_of(c: Client, sid: str) -> tuple:
    info = c.get_session(sid)
    return (info.version, info.information.digest, info.gaussians.count,
            c.get_pool(sid).candidates, c.list_views(sid).views)


def test_sigkill_and_restart_loses_nothing_acknowledged(server_factory: Any, tmp_path: Path
                                                        ) -> None:
    state = tmp_path / "state"
    srv = server_factory(state, zenoh=False).start()
    poses = ring_poses(16)
    img = np.random.default_rng(0).integers(0, 255, (32, 32, 3), dtype=np.uint8)
    with Client(srv.url) as c:
        c.create_session(SMALL_INTRINSICS, id="keep", bounds=BOUNDS, init_gaussians=120,
                         pool=poses, defaults={"shortlist_size": 3})
        c.select("keep", method="agile", commit=True)
        c.add_observations("keep", ObservationIn.from_numpy(poses[5], image=img,
                                                            depth=np.ones((32, 32))))
        c.extend_pool("keep", poses[:2], ids=[100, 101])
        c.create_session(SMALL_INTRINSICS, id="gone", bounds=BOUNDS, init_gaussians=10)
        c.delete_session("gone")
        before = state_of(c, "keep")

        # acknowledged commits keep arriving while the server is killed
        acked: list[int] = []
        stop = threading.Event()

        def writer() -> None:
            with Client(srv.url, timeout=5) as w:
                while not stop.is_set():
                    try:
                        acked.append(w.commit("keep", pose=poses[len(acked) % 4]).id)
                    except AgileGSError:
                        return
                    time.sleep(0.02)

        th = threading.Thread(target=writer)
        th.start()
        time.sleep(1.0)
        srv.kill()
        stop.set()
        th.join(timeout=30)
    assert len(acked) >= 3

    srv2 = server_factory(state, zenoh=False).start()
    with Client(srv2.url) as c:
        assert [s.id for s in c.list_sessions().sessions] == ["keep"]
        views = c.list_views("keep").views
        ids = [v.id for v in views]
        for vid in acked:  # every acknowledged commit is back
            assert vid in ids
        after = c.get_session("keep")
        assert after.version >= before[0] + len(acked)
        # what was there before the writes is untouched
        assert c.get_pool("keep").candidates == before[3]
        assert views[: len(before[4])] == before[4]
        assert views[1].has_image and views[1].has_depth
        # Ĥ is back and consistent with every view that is back: λ + Σ_v H_v
        h = c.get_information("keep").arrays()
        want = expected_information([v.pose.to_matrix() for v in views])
        for k, t in want.items():
            np.testing.assert_allclose(h[k], t.numpy(), rtol=1e-4, atol=1e-9)
        c.select("keep", method="agile", commit=True)


def expected_information(poses: list[np.ndarray]) -> dict:
    import torch

    from agilegs.schemas import Bounds
    from agilegs.service.nbv import (
        Camera,
        Intrinsics,
        accumulate_information,
        fisher_diag,
        init_information,
    )
    from agilegs.service.sessions.convert import random_gaussians

    gmap = random_gaussians(Bounds(**BOUNDS), 120, 0)  # the session's map (same seed)
    h = init_information(gmap, 1e-3)
    k = Intrinsics(**SMALL_INTRINSICS)
    per_pose: dict[bytes, dict] = {}  # the writer repeats poses: one Fisher pass per pose
    for p in poses:
        key = p.tobytes()
        if key not in per_pose:
            per_pose[key] = fisher_diag(gmap, Camera(torch.from_numpy(p).float(), k))
        h = accumulate_information(h, per_pose[key])
    return h
