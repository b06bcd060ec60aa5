"""A client generated from ``/openapi.json`` by an off-the-shelf generator
(``openapi-python-client``, installed by the dev extra) drives a running server: it creates a
session, sets a pool, selects with commit and sends the committed view's frame, using only
the generated models (the poses, observations and images in their published forms)."""

from __future__ import annotations

import base64
import importlib
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, ServerProcess, ring_poses


def _generate(url: str, out: Path) -> None:
    spec = out / "openapi.json"
    spec.write_bytes(httpx.get(f"{url}/openapi.json", timeout=30).content)
    exe = (shutil.which("openapi-python-client")
           or str(Path(sys.executable).parent / "openapi-python-client"))
    proc = subprocess.run([exe, "generate", "--path", str(spec), "--meta", "none",
                           "--output-path", str(out / "agilegs_api")], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Unable to process schema" not in proc.stdout, proc.stdout


@pytest.mark.heavy
def test_a_generated_client_runs_the_robot_loop(tmp_path: Path) -> None:
    srv = ServerProcess(tmp_path / "state", zenoh=False).start()
    try:
        _generate(srv.url, tmp_path)
        sys.path.insert(0, str(tmp_path))
        try:
            api = importlib.import_module("agilegs_api")
            models = importlib.import_module("agilegs_api.models")
            create_session = importlib.import_module("agilegs_api.api.service.create_session")
            ops = {name: importlib.import_module(f"agilegs_api.api.sessions.{name}")
                   for name in ("set_pool", "select", "add_observations", "list_views")}
        finally:
            sys.path.remove(str(tmp_path))
        client = api.Client(base_url=srv.url, raise_on_unexpected_status=True, timeout=120)

        info = create_session.sync(client=client, body=models.SessionCreate(
            id="generated", intrinsics=models.Intrinsics(**SMALL_INTRINSICS),
            bounds=models.Bounds(min_=[-0.5] * 3, max_=[0.5] * 3), init_gaussians=200))
        assert isinstance(info, models.SessionInfo) and info.id == "generated", info

        pool = ops["set_pool"].sync("generated", client=client, body=models.PoolIn(
            poses=[models.PoseMatrix(matrix=p.tolist()) for p in ring_poses(8)]))
        assert isinstance(pool, models.PoolOut) and len(pool.candidates) == 8, pool

        decision = ops["select"].sync("generated", client=client, body=models.SelectRequest(
            method=models.SelectRequestMethodType0.AGILE_PLUS, commit=True))
        assert isinstance(decision, models.SelectResponse), decision
        assert decision.committed is not None
        assert decision.chosen.id in [c.id for c in pool.candidates]
        view_id = decision.committed.id

        h, w = SMALL_INTRINSICS["height"], SMALL_INTRINSICS["width"]
        pixels = np.full((h, w, 3), 128, np.uint8)
        image = models.ImageRaw(encoding="raw", dtype=models.ImageRawDtype.UINT8, shape=[h, w, 3],
                                data=base64.b64encode(pixels.tobytes()).decode())
        views = ops["add_observations"].sync("generated", client=client,
                                             body=models.ObservationsIn(observations=[
                                                 models.ObservationOfView(view_id=view_id,
                                                                          image=image)]))
        assert isinstance(views, models.ViewsOut) and views.views[0].has_image, views
        listed = ops["list_views"].sync("generated", client=client)
        assert [v.id for v in listed.views] == [view_id] and listed.views[0].has_image
    finally:
        srv.stop()
