"""The views out: ``get_frames`` gives the acquired images and depth back as they came, and
``agilegs export`` writes a session as a nerfstudio ``transforms.json`` dataset and a COLMAP
text model that this project's loaders (and pycolmap) read back with the same poses and
pixels."""

from __future__ import annotations

import io
import json
import uuid
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_INTRINSICS, InProcess, ring_poses

from agilegs.client import NotFoundError
from agilegs.schemas import ObservationIn
from agilegs.service import export
from agilegs.service.cli import main

BOUNDS = {"min": [-0.5] * 3, "max": [0.5] * 3}


def _png(a: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


@pytest.fixture
def acquired(api: InProcess) -> tuple[str, dict[int, np.ndarray], dict[int, np.ndarray],
                                      dict[int, np.ndarray]]:
    """A session with four views: a png frame with depth, a raw uint8 frame, a png frame
    without depth, and a committed candidate without a frame; (session, the images by view
    id, their depth, every view's pose)."""
    rng = np.random.default_rng(0)
    poses = ring_poses(6)
    images = [rng.integers(0, 256, (32, 32, 3), dtype=np.uint8) for _ in range(3)]
    depth = rng.uniform(0.5, 3.0, (32, 32)).astype(np.float32)
    depth[0, :4] = 0  # missing values
    sid = f"x-{uuid.uuid4().hex[:8]}"
    with api.client() as c:
        c.create_session(SMALL_INTRINSICS, id=sid, bounds=BOUNDS, init_gaussians=300, frames=[
            ObservationIn.from_numpy(poses[0], image=images[0], depth=depth,
                                     image_encoding="png"),
            ObservationIn.from_numpy(poses[1], image=images[1]),
            ObservationIn.from_numpy(poses[2], image=images[2], image_encoding="png")])
        c.set_pool(sid, poses[3:])
        c.commit(sid, 1)
        views = c.list_views(sid).views
    ids = [v.id for v in views]
    return (sid, dict(zip(ids[:3], images)), {ids[0]: depth},
            {v.id: v.pose.to_matrix() for v in views})


def test_get_frames_gives_the_frames_back_as_they_came(api: InProcess, acquired) -> None:
    sid, images, depths, poses = acquired
    first = min(images)
    with api.client() as c:
        got = c.get_frames(sid)
        assert [f.view.id for f in got.frames] == sorted(poses)
        for f in got.frames:
            if f.view.id in images:
                np.testing.assert_array_equal(f.image.to_numpy(), images[f.view.id])
            else:
                assert f.image is None and f.depth is None
        assert got.frames[0].image.encoding == "png"
        assert got.frames[0].image.data == _png(images[first])  # the file as it came
        np.testing.assert_array_equal(got.frames[0].depth.to_numpy(), depths[first])
        one = c.get_frames(sid, first, depth=False)
        assert [f.view.id for f in one.frames] == [first] and one.frames[0].depth is None
        with pytest.raises(NotFoundError) as exc:
            c.get_frames(sid, 999)
        assert exc.value.field == "view_id"
    with api.http() as h:
        r = h.get(f"/v1/sessions/{sid}/frames", params={"view_id": "x"})
        assert r.status_code == 422 and r.json()["error"]["field"] == "query.view_id"


def _check_views(views: list, images: dict, depths: dict, poses: dict) -> None:
    """Loaded views: every acquired view with an image, the same pose to 1e-6, the same
    pixels bit for bit, the depth to the PNG's thousandths."""
    by_id = {int(Path(v.name).stem): v for v in views}
    assert sorted(by_id) == sorted(images)
    for vid, v in by_id.items():
        np.testing.assert_allclose(v.camera.c2w.double().numpy(), poses[vid], atol=1e-6,
                                   rtol=0)
        assert (v.camera.fx, v.camera.width) == (SMALL_INTRINSICS["fx"], 32)
        if v.image is not None:
            pixels = (v.image.double().numpy() * 255).round().astype(np.uint8)
            np.testing.assert_array_equal(pixels, images[vid])


def test_export_from_the_server_reads_back_through_the_loaders(api: InProcess, acquired,
                                                              tmp_path: Path) -> None:
    from agilegs.service.data.colmap import load_colmap
    from agilegs.service.data.transforms import load_transforms

    sid, images, depths, poses = acquired
    with api.client() as c:
        frames, gaussians = export.from_server(c, sid)
    done = export.write_dataset(tmp_path / "ds", frames, gaussians)
    assert (done.images, done.skipped, done.points) == (3, 1, 300)
    for vid, img in images.items():  # the png files are the bytes that came
        if (tmp_path / "ds" / "images" / f"{vid:05d}.png").read_bytes() == _png(img):
            continue
        assert vid == sorted(images)[1]  # the raw frame, encoded losslessly
    cap = load_transforms(tmp_path / "ds" / "transforms.json")
    _check_views(cap.views, images, depths, poses)
    first = min(images)
    loaded = {int(Path(v.name).stem): v for v in cap.views}
    np.testing.assert_allclose(loaded[first].depth.numpy(), depths[first], atol=5e-4, rtol=0)
    views, points, colours = load_colmap(tmp_path / "ds" / "sparse" / "0",
                                         tmp_path / "ds" / "images")
    _check_views(views, images, depths, poses)
    np.testing.assert_array_equal(points.numpy(), gaussians.arrays.means.to_numpy())
    assert colours.shape == (300, 3)


def test_export_offline_from_the_state_folder_equals_the_server_s(api: InProcess, acquired,
                                                                 tmp_path: Path,
                                                                 capsys) -> None:
    sid = acquired[0]
    state = Path(api.server.settings.state_dir)
    assert main(["export", sid, str(tmp_path / "off"), "--state-dir", str(state)]) == 0
    assert "3 views" in capsys.readouterr().out
    with api.client() as c:
        export.write_dataset(tmp_path / "on", *export.from_server(c, sid))
    for rel in ("transforms.json", "sparse/0/cameras.txt", "sparse/0/images.txt",
                "sparse/0/points3D.txt", "images/00000.png", "depth/00000.png"):
        assert (tmp_path / "off" / rel).read_bytes() == (tmp_path / "on" / rel).read_bytes(), rel
    doc = json.loads((tmp_path / "off" / "transforms.json").read_text())
    assert doc["camera_model"] == "PINHOLE" and len(doc["frames"]) == 3


def test_export_reaches_the_benchmark_scene_loader(api: InProcess, acquired,
                                                   tmp_path: Path) -> None:
    from agilegs.lab.bench.scenes import detect_scene_kind

    sid = acquired[0]
    with api.client() as c:
        frames, gaussians = export.from_server(c, sid)
    export.write_dataset(tmp_path / "ns", frames, gaussians, ["nerfstudio"])
    export.write_dataset(tmp_path / "cm", frames, gaussians, ["colmap"])
    assert detect_scene_kind(tmp_path / "ns") == "transforms"
    assert detect_scene_kind(tmp_path / "cm") == "colmap"


def test_pycolmap_reads_the_model(api: InProcess, acquired, tmp_path: Path) -> None:
    pycolmap = pytest.importorskip("pycolmap")
    sid, images, _, poses = acquired
    with api.client() as c:
        export.write_dataset(tmp_path / "ds", *export.from_server(c, sid), ["colmap"])
    rec = pycolmap.Reconstruction(str(tmp_path / "ds" / "sparse" / "0"))
    assert len(rec.images) == 3 and len(rec.cameras) == 1 and len(rec.points3D) == 300
    for image in rec.images.values():
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        np.testing.assert_allclose(np.linalg.inv(w2c), poses[int(Path(image.name).stem)],
                                   atol=1e-6, rtol=0)


def test_export_refuses_a_missing_session_in_one_line(tmp_path: Path, capsys) -> None:
    assert main(["export", "nope", str(tmp_path / "out"), "--state-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no session 'nope'" in err


def test_export_to_a_ply_file_writes_the_map(api: InProcess, acquired, tmp_path: Path,
                                             capsys) -> None:
    from agilegs.service.nbv import GaussianMap

    sid = acquired[0]
    state = Path(api.server.settings.state_dir)
    assert main(["export", sid, str(tmp_path / "off.ply"), "--state-dir", str(state)]) == 0
    assert "300 Gaussians" in capsys.readouterr().out
    with api.client() as c:
        c.save_gaussians(sid, tmp_path / "on.ply")
        arrays = c.get_gaussians(sid).to_numpy()
    assert (tmp_path / "off.ply").read_bytes() == (tmp_path / "on.ply").read_bytes()
    back = GaussianMap.load(tmp_path / "off.ply")
    for name, t in back.items():
        np.testing.assert_array_equal(t.numpy(), arrays[name])


def test_export_from_no_server_is_one_line(tmp_path: Path, capsys) -> None:
    from conftest import free_port

    url = f"http://127.0.0.1:{free_port()}"
    assert main(["export", "s", str(tmp_path / "out"), "--server", url]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("agilegs export: ")
