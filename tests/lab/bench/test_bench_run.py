"""``agilegs bench run``: the progressive protocol end to end (tiny profile), its outputs, the
skip-on-rerun, and the scene sources (splat, transforms.json, COLMAP text)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from agilegs.lab.bench import report
from agilegs.lab.bench.profiles import PROFILES
from agilegs.lab.bench.protocol import (
    initial_view_indices,
    run_progressive,
    trajectory_stats,
)
from agilegs.lab.bench.scene_model import SceneOptions, evenly_spaced, orbit_cameras
from agilegs.lab.bench.scenes import detect_scene_kind, load_bench_scene
from agilegs.lab.bench.variants import Variant, build_variants, display_name
from agilegs.lab.scenes import bundled_scene
from agilegs.service.cli import main
from agilegs.service.data.colmap import rotmat_to_qvec
from agilegs.service.nbv import Camera, Intrinsics, load_scene, render

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RUN_KEYS = {
    "psnr", "ssim", "lpips", "events", "sequence", "selected", "initial", "curve",
    "latency_ms", "path_length", "mean_index_jump", "trajectory", "seed", "method",
    "train_s", "select_s", "information_s", "eval_s", "wall_s", "redundancy",
}
EVENT_KEYS = {  # what the report, the plots and the replay (agilegs view --run) read
    "event", "step", "views_before", "choice", "shortlist", "eligible", "latency_ms",
    "select_wall_ms", "select_cpu_ms", "information_ms", "upkeep_ms", "num_gaussians",
    "scores", "anchor", "anchor_psi", "best_candidate_psi", "probes", "probe_won", "eig_mass",
}


def test_tiny_run_writes_outputs_and_rerun_skips(tmp_path: Path) -> None:
    out = tmp_path / "bench"
    argv = ["bench", "run", "--scene", str(bundled_scene("spot")), "--methods",
            "random,agile_plus", "--profile", "tiny", "--seeds", "0", "--out", str(out),
            "--budgets", "2"]
    assert main(argv) == 0

    res = json.loads((out / "results.json").read_text())
    assert res["settings"]["kernel_warmup_s"] > 0  # the compile, apart from the selections
    prof = PROFILES["tiny"]
    scene = res["scenes"]["spot_10k"]
    assert scene["pool"] == prof.scene.pool_size and scene["kind"] == "splat"
    for method in ("random", "agile_plus"):
        run = scene["runs"][method]["0"]
        assert RUN_KEYS <= set(run), RUN_KEYS - set(run)
        assert run["method"] == method and run["seed"] == 0
        assert math.isfinite(run["psnr"]) and run["psnr"] > 8.0
        assert 0.0 < run["ssim"] <= 1.0
        # the budget is reached: initial views plus one selection per event, all distinct
        assert len(run["sequence"]) == prof.view_budget
        assert len(set(run["sequence"])) == len(run["sequence"])
        assert run["sequence"][: prof.initial_views] == run["initial"]
        assert len(run["events"]) == prof.view_budget - prof.initial_views
        for ev in run["events"]:
            assert set(ev) == EVENT_KEYS, set(ev) ^ EVENT_KEYS
            assert ev["latency_ms"]["total"] > 0.0 and ev["select_cpu_ms"] >= 0.0
            assert 0 <= ev["choice"] < scene["pool"]
            # AGILE-GS+'s probes are the shortlist's last and were scored with it
            if method == "agile_plus":
                assert ev["probes"] >= 1 and isinstance(ev["probe_won"], bool)
                scored = {int(v) for v, _ in ev["scores"]}
                assert set(ev["shortlist"][-ev["probes"]:]) <= scored
            else:
                assert ev["probes"] is None and ev["probe_won"] is None
        assert run["curve"][-1]["views"] == prof.view_budget
        assert all(set(c) == {"views", "step", "psnr"} for c in run["curve"])
        assert run["path_length"] > 0.0 and run["mean_index_jump"] > 0.0
        summ = scene["summary"][method]
        assert summ["psnr_mean"] == pytest.approx(run["psnr"])
    # agile_plus reranks a shortlist by EIG: it has a shortlist and pays a rerank
    ev = scene["runs"]["agile_plus"]["0"]["events"][0]
    assert 0 < len(ev["shortlist"]) <= prof.shortlist_size
    assert ev["choice"] in ev["shortlist"]
    assert ev["latency_ms"]["rerank"] > 0.0 and ev["information_ms"] > 0.0
    assert 0.0 < ev["latency_ms"]["anchor.ascent"] <= ev["latency_ms"]["anchor"]
    assert ev["select_cpu_ms"] > 0.0
    assert res["summary"]["agile_plus"]["cpu_ms_mean"] > res["summary"]["random"]["cpu_ms_mean"]
    # the budget ablation: AGILE-GS+ with N = 2 reranks at most 2 views
    for ev in scene["runs"]["agile_plus@n2"]["0"]["events"]:
        assert 0 < len(ev["shortlist"]) <= 2 and ev["choice"] in ev["shortlist"]
    assert res["invocation"]["skipped"] == []
    assert len(res["invocation"]["executed"]) == 3

    table = (out / "table.md").read_text()
    assert "| Random |" in table and "| AGILE-GS+ |" in table
    assert "spot_10k PSNR↑" in table and "Avg. selection time (s)" in table
    assert "## Ablation: AGILE-GS+ shortlist budget N" in table
    assert "## Where the anchor's time goes" in table
    split = table.split("## Where the anchor's time goes")[1]
    assert "| AGILE-GS+ |" in split and "| Random |" not in split.split("##")[0]
    budget_rows = table.split("## Ablation: AGILE-GS+ shortlist budget N")[1]
    assert "| 2 |" in budget_rows and f"| {prof.shortlist_size} |" in budget_rows
    # paired differences between the main methods (the budget variant is not one of them)
    pair = res["paired_psnr"]["agile_plus"]["random"]
    assert pair["n"] == 1 and pair["se"] is None
    assert pair["mean"] == pytest.approx(
        scene["runs"]["agile_plus"]["0"]["psnr"] - scene["runs"]["random"]["0"]["psnr"])
    assert set(res["paired_psnr"]) == {"random", "agile_plus"}
    assert "## Paired PSNR differences" in table
    # the same per scene and per scene type
    assert res["paired_psnr_by_scene"]["spot_10k"]["agile_plus"]["random"]["mean"] == \
        pytest.approx(pair["mean"])
    assert res["paired_psnr_by_type"]["object"]["agile_plus"]["random"]["n"] == 1
    assert "per scene type and per scene" in table and "| spot_10k (object) |" in table
    # latency per event: the selection alone and with the method's information upkeep
    s_ap = res["summary"]["agile_plus"]
    assert s_ap["event_ms_mean"] > s_ap["selection_ms_mean"] > 0

    pngs = ["psnr_vs_views.png", "latency.png", "trajectories_spot_10k.png"]
    for name in pngs:
        data = (out / name).read_bytes()
        assert data[:8] == PNG_MAGIC, name
        with Image.open(out / name) as im:
            im.verify()

    runs = sorted((out / "runs").rglob("seed*.json"))
    assert len(runs) == 3
    before = {p: p.stat().st_mtime_ns for p in runs}
    assert main(argv) == 0
    res2 = json.loads((out / "results.json").read_text())
    assert res2["invocation"]["executed"] == []
    assert {(s["variant"], s["seed"]) for s in res2["invocation"]["skipped"]} == {
        ("random", 0), ("agile_plus", 0), ("agile_plus@n2", 0)}
    assert {p: p.stat().st_mtime_ns for p in runs} == before
    # the skipped runs' results are still reported
    assert res2["scenes"]["spot_10k"]["runs"]["random"]["0"]["psnr"] == pytest.approx(
        res["scenes"]["spot_10k"]["runs"]["random"]["0"]["psnr"])
    # report only: the finished runs are reported, a run not there yet is listed as missing
    argv3 = [a if a != "random,agile_plus" else "random,agile_plus,agile" for a in argv]
    assert main([*argv3, "--seeds", "0,1", "--report-only", "--no-plots"]) == 0
    res3 = json.loads((out / "results.json").read_text())
    assert res3["invocation"]["executed"] == []
    assert {(s["variant"], s["seed"]) for s in res3["invocation"]["missing"]} == {
        ("agile", 0), ("random", 1), ("agile_plus", 1), ("agile", 1), ("agile_plus@n2", 1)}
    assert set(res3["scenes"]["spot_10k"]["runs"]) == {"random", "agile_plus", "agile_plus@n2"}
    assert res3["paired_psnr"]["agile_plus"]["random"]["mean"] == pytest.approx(pair["mean"])
    assert sorted((out / "runs").rglob("seed*.json")) == runs


def test_paired_differences() -> None:
    runs = {
        "a": {"x": {"0": {"psnr": 30.0}, "1": {"psnr": 31.0}}, "y": {"0": {"psnr": 29.0},
                                                                    "1": {"psnr": 31.5}}},
        "b": {"x": {"0": {"psnr": 20.0}, "1": {"psnr": 22.0}, "2": {"psnr": 25.0}},
              "y": {"0": {"psnr": 19.0}, "1": {"psnr": None}}},
    }
    out = report.paired_differences(runs, ["x", "y"])
    # pairs (a,0): +1, (a,1): -0.5, (b,0): +1; (b,1) has no y value, (b,2) no y run
    xy = out["x"]["y"]
    assert xy["n"] == 3 and xy["wins"] == 2
    assert xy["mean"] == pytest.approx(0.5)
    assert xy["se"] == pytest.approx(float(np.std([1.0, -0.5, 1.0], ddof=1)) / math.sqrt(3))
    yx = out["y"]["x"]
    assert yx["mean"] == pytest.approx(-0.5) and yx["wins"] == 1 and yx["n"] == 3
    none = report.paired_differences({"a": {"x": {"0": {"psnr": 1.0}}}}, ["x", "z"])
    assert none["x"]["z"] == {"mean": None, "se": None, "wins": 0, "n": 0}


def test_same_seed_same_initialisation_and_embodied_restriction() -> None:
    prof = PROFILES["tiny"]
    scene = load_bench_scene(bundled_scene("teapot"), prof.scene)
    a = run_progressive(scene, Variant("random", "random", shortlist_size=4), 3, prof,
                        embodied_k=2)
    b = run_progressive(scene, Variant("random", "random", shortlist_size=4), 3, prof,
                        embodied_k=2)
    assert a["sequence"] == b["sequence"]  # seeded: reproducible
    assert a["psnr"] == pytest.approx(b["psnr"], abs=1e-4)
    pos = scene.pool_poses[:, :3, 3]
    seq = [a["initial"][-1]] + a["selected"]
    for ev, cur in zip(a["events"], seq[:-1]):
        assert ev["eligible"] == 2  # only the K = 2 nearest remaining candidates
        assert ev["choice"] != cur
    stats = trajectory_stats(pos[seq], seq)
    assert stats["path_length"] == pytest.approx(a["path_length"])


def test_trajectory_stats_and_initial_views() -> None:
    pos = torch.tensor([[0.0, 0, 0], [3.0, 4, 0], [3.0, 4, 1]])
    st = trajectory_stats(pos, [5, 9, 2])
    assert st["path_length"] == pytest.approx(6.0)
    assert st["mean_index_jump"] == pytest.approx((4 + 7) / 2)
    assert trajectory_stats(pos[:1], [1]) == {"path_length": 0.0, "mean_index_jump": 0.0}
    a = initial_view_indices(180, 4, 0)
    assert a == initial_view_indices(180, 4, 0) and len(set(a)) == 4
    assert a != initial_view_indices(180, 4, 1)
    assert all(0 <= i < 180 for i in a)
    assert sorted(initial_view_indices(5, 5, 2)) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="exceed the pool"):
        initial_view_indices(3, 4, 0)
    assert evenly_spaced(10, 3) == [1, 5, 8] and evenly_spaced(3, 5) == [0, 1, 2]


def test_variants_and_errors() -> None:
    v = build_variants(["random", "agile"], 10, ["leverage", "knearest"], [5, 10])
    keys = [x.key for x in v]
    assert keys == ["random", "agile", "agile@knearest", "agile_plus@n5", "agile_plus"]
    assert {x.key: x.shortlist_size for x in v}["agile_plus@n5"] == 5
    v = build_variants(["agile_plus"], 10, ["topnorm"], shortlist_method="agile_plus")
    assert [(x.key, x.method, x.shortlist) for x in v] == [
        ("agile_plus", "agile_plus", "leverage"), ("agile_plus@topnorm", "agile_plus", "topnorm")]
    with pytest.raises(ValueError, match="unknown method"):
        build_variants(["nope"], 10)
    with pytest.raises(ValueError, match="unknown strategy"):
        build_variants([], 10, ["best"])
    assert display_name("agile_plus@n20") == "AGILE-GS+ (N=20)"


def test_splat_scene_tests_are_held_out(tmp_path: Path) -> None:
    opt = SceneOptions(width=24, height=24, max_gaussians=200, pool_size=12, test_count=4)
    scene = load_bench_scene(bundled_scene("spot"), opt)
    assert scene.pool_images.shape == (12, 24, 24, 3)
    assert scene.pool_depths is not None and bool((scene.pool_depths > 0).any())
    assert scene.test_images.shape == (4, 24, 24, 3)
    # no test camera coincides with a pool camera
    d = torch.cdist(scene.test_poses[:, :3, 3], scene.pool_poses[:, :3, 3])
    assert float(d.min()) > 1e-3
    with pytest.raises(FileNotFoundError):
        detect_scene_kind(tmp_path / "missing.splat")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no .splat"):
        detect_scene_kind(tmp_path / "empty")


def _posed_frames(n: int, size: int) -> tuple[list[torch.Tensor], list[np.ndarray], Intrinsics]:
    gt = load_scene(bundled_scene("spot"), max_gaussians=300)
    poses = orbit_cameras(torch.zeros(3), 2.0, (20.0,), n)
    intr = Intrinsics.from_fov(50.0, size, size)
    imgs = []
    with torch.no_grad():
        for p in poses:
            rgb = render(gt, Camera(c2w=p, intrinsics=intr),
                         background=torch.ones(3)).rgb.clamp(0, 1)
            imgs.append((rgb.numpy() * 255).round().astype(np.uint8))
    return list(poses), imgs, intr


def test_transforms_json_scene(tmp_path: Path) -> None:
    poses, imgs, intr = _posed_frames(10, 16)
    frames = []
    for i, (p, im) in enumerate(zip(poses, imgs)):
        Image.fromarray(im).save(tmp_path / f"r_{i}.png")
        gl = p.clone().double()
        gl[:3, 1:3] = -gl[:3, 1:3]  # OpenCV -> OpenGL camera axes
        frames.append({"file_path": f"./r_{i}", "transform_matrix": gl.tolist()})
    fov = 2 * math.atan(0.5 * intr.width / intr.fx)
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"camera_angle_x": fov, "frames": frames}))
    assert detect_scene_kind(tmp_path) == "transforms"
    opt = SceneOptions(width=16, random_init_points=200)
    scene = load_bench_scene(tmp_path, opt)
    assert scene.kind == "transforms"
    assert scene.test_poses.shape[0] == 2  # frames 0 and 8
    assert scene.pool_size == 8
    torch.testing.assert_close(scene.test_poses[1], poses[8], atol=1e-5, rtol=0)
    assert scene.init_points is not None and scene.init_points.shape == (200, 3)
    # the cameras look at the origin: the random points surround it
    assert float(scene.init_points.mean(0).norm()) < 0.3
    assert float((scene.center).norm()) < 1e-3
    # a whole tiny run on it (no depth: the map starts from the random points)
    prof = PROFILES["tiny"]
    rec = run_progressive(scene, Variant("cover", "cover"), 0, prof)
    assert len(rec["sequence"]) == prof.view_budget and math.isfinite(rec["psnr"])


def test_transforms_json_scene_with_depth(tmp_path: Path) -> None:
    poses, imgs, intr = _posed_frames(9, 16)
    frames = []
    for i, (p, im) in enumerate(zip(poses, imgs)):
        Image.fromarray(im).save(tmp_path / f"r_{i}.png")
        # a constant 2.5 m in uint16 millimetres, as a depth camera writes it
        Image.fromarray(np.full((16, 16), 2500, dtype=np.uint16)).save(tmp_path / f"d_{i}.png")
        gl = p.clone().double()
        gl[:3, 1:3] = -gl[:3, 1:3]
        frames.append({"file_path": f"./r_{i}", "depth_file_path": f"d_{i}.png",
                       "transform_matrix": gl.tolist()})
    fov = 2 * math.atan(0.5 * intr.width / intr.fx)
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"camera_angle_x": fov, "frames": frames}))
    scene = load_bench_scene(tmp_path, SceneOptions(width=16))
    assert scene.pool_depths is not None and scene.pool_depths.shape == (7, 16, 16)
    torch.testing.assert_close(scene.pool_depths, torch.full((7, 16, 16), 2.5))
    assert scene.init_points is None  # the mapper back-projects the depth maps instead
    assert scene.info["type"] == "posed" and scene.info["init"] == "depth"
    # the splat scenes are objects, or captures when their meta.json says so
    assert load_bench_scene(bundled_scene("spot"), PROFILES["tiny"].scene).info["type"] == \
        "object"


def test_colmap_text_scene(tmp_path: Path) -> None:
    poses, imgs, intr = _posed_frames(9, 16)
    (tmp_path / "images").mkdir()
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(
        f"1 PINHOLE {intr.width} {intr.height} {intr.fx} {intr.fy} {intr.cx} {intr.cy}\n")
    lines = []
    for i, (p, im) in enumerate(zip(poses, imgs)):
        Image.fromarray(im).save(tmp_path / "images" / f"f{i:02d}.png")
        r = p[:3, :3].double().numpy().T  # world-to-camera rotation
        t = -r @ p[:3, 3].double().numpy()
        q = rotmat_to_qvec(r)
        lines.append(f"{i + 1} {' '.join(map(str, q))} {' '.join(map(str, t))} 1 f{i:02d}.png")
        lines.append("")
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    pts = ["1 0.1 0.0 0.0 255 0 0 0.5", "2 -0.1 0.1 0.0 0 255 0 0.5",
           "3 0.0 -0.1 0.1 0 0 255 0.5", "4 0.0 0.0 -0.1 9 9 9 0.5"]
    (model / "points3D.txt").write_text("\n".join(pts) + "\n")
    assert detect_scene_kind(tmp_path) == "colmap"
    scene = load_bench_scene(tmp_path, SceneOptions(width=16))
    assert scene.kind == "colmap"
    assert scene.test_poses.shape[0] == 2 and scene.pool_size == 7  # f00, f08 held out
    torch.testing.assert_close(scene.pool_poses[0], poses[1], atol=1e-4, rtol=0)
    assert scene.init_points is not None and scene.init_points.shape == (4, 3)
    torch.testing.assert_close(scene.init_colors[0], torch.tensor([1.0, 0.0, 0.0]))
    assert scene.pool_images.shape == (7, 16, 16, 3)
    ref = torch.from_numpy(imgs[1]).float() / 255
    torch.testing.assert_close(scene.pool_images[0], ref, atol=1e-6, rtol=0)
