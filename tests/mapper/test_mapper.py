"""The incremental mapper: training lowers the loss, topology changes keep per-Gaussian state
aligned, views never reset the map, depth back-projection lands where the depth says."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import SCENES

from agilegs.config.mapper import MapperConfig
from agilegs.service.data.images import View
from agilegs.service.mapper.mapper import Mapper
from agilegs.service.mapper.points import backproject_depth, nearest_neighbour_scales
from agilegs.service.mapper.topology import TopologyChange, remap_per_gaussian
from agilegs.service.nbv import Camera, GaussianMap, Intrinsics, look_at, render
from agilegs.service.nbv.gaussians import SH_C0

SIZE = 32


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Tiny renders: one intra-op thread is ~10x faster than two on a loaded 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def gt_map(n: int = 300, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap(
        means=torch.rand(n, 3, generator=g) - 0.5,
        log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.05 + 0.03),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g) + 1.5,
        sh=torch.randn(n, 1, 3, generator=g) * 0.8,
    )


def ring_cameras(k: int = 6, radius: float = 1.6, size: int = SIZE) -> list[Camera]:
    intr = Intrinsics.from_fov(60.0, size, size)
    cams = []
    for i in range(k):
        a = 2 * math.pi * i / k
        eye = torch.tensor([radius * math.cos(a), 0.4 * (-1) ** i, radius * math.sin(a)])
        cams.append(Camera.from_intrinsics(look_at(eye, torch.zeros(3)), intr))
    return cams


def mean_loss(m: Mapper) -> float:
    return sum(m.loss_on_view(i)["loss"] for i in range(m.num_views)) / m.num_views


# a few dozen steps: learning rates above the 3DGS ones (tuned for 30k steps)
FAST = dict(
    lr_means=1.6e-3,
    lr_sh_dc=2.5e-2,
    scene_extent=1.0,
    densify=False,
    sh_degree_interval=None,
    opacity_reset_every=None,
)


def test_loss_goes_down_from_a_perturbed_map() -> None:
    gt = gt_map()
    cams = ring_cameras()
    g = torch.Generator().manual_seed(1)
    init = gt.clone()
    init.means += 0.02 * torch.randn(init.means.shape, generator=g)
    init.sh = 0.3 * torch.randn(init.sh.shape, generator=g)
    init.opacity_logits = torch.zeros_like(init.opacity_logits)
    init_copy = init.clone()
    m = Mapper(init, MapperConfig(**FAST))
    for c in cams:
        m.add_view(c, render(gt, c).rgb.detach())
    before = mean_loss(m)
    info = m.step(40)
    after = mean_loss(m)
    print(f"perturbed map: loss {before:.4f} -> {after:.4f}")
    assert after < 0.7 * before, (before, after)
    assert m.num_steps == 40 and info["num_steps"] == 40
    assert m.last_loss == pytest.approx(info["loss"])
    assert 0 <= info["view"] < len(cams) and info["num_views"] == len(cams)
    # the mapper trained its own copy: the map passed in is untouched
    for k, v in init_copy.tensors().items():
        assert torch.equal(getattr(init, k), v)


def test_loss_goes_down_from_points() -> None:
    gt = gt_map(seed=3)
    cams = ring_cameras()
    g = torch.Generator().manual_seed(2)
    m = Mapper(None, MapperConfig(**FAST, sh_degree=0))
    pts = gt.means + 0.01 * torch.randn(gt.means.shape, generator=g)
    m.init_from_points(pts, torch.rand(pts.shape, generator=g), opacity=0.5)
    assert m.num_gaussians == gt.num_gaussians and m.gmap.sh_degree == 0
    for c in cams:
        m.add_view(c, render(gt, c).rgb.detach())
    before = mean_loss(m)
    m.step(40)
    after = mean_loss(m)
    print(f"from points: loss {before:.4f} -> {after:.4f}")
    assert after < 0.7 * before


def test_step_is_seeded_and_deterministic() -> None:
    gt = gt_map(100)
    cams = ring_cameras(4)
    refs = [render(gt, c).rgb.detach() for c in cams]
    start = gt_map(100, seed=9)
    outs = []
    for _ in range(2):
        m = Mapper(start, MapperConfig(**FAST, seed=5))
        for c, r in zip(cams, refs, strict=True):
            m.add_view(c, r)
        seen = [m.step()["view"] for _ in range(6)]
        outs.append((seen, m.gmap))
    assert outs[0][0] == outs[1][0] and len(set(outs[0][0])) > 1
    for a, b in zip(outs[0][1].tensors().values(), outs[1][1].tensors().values(), strict=True):
        torch.testing.assert_close(a, b)


def _densify_setup(n: int = 200, **overrides):
    """A map with small (clone), large (split) and transparent (pruned) Gaussians, and
    learning rates so small that the parameters do not move between snapshot and densify."""
    g = torch.Generator().manual_seed(4)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 0.8
    scales = torch.where(torch.arange(n)[:, None] % 2 == 0, 0.02, 0.1).expand(n, 3).clone()
    opac = torch.full((n,), 2.0)
    opac[::7] = -8.0  # opacity 3e-4 < 0.005: pruned
    gmap = GaussianMap(
        means=means,
        log_scales=scales.log(),
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=opac,
        sh=torch.randn(n, 4, 3, generator=g) * 0.5,
    )
    tiny = 1e-12
    cfg = dict(
        lr_means=tiny,
        lr_means_final=tiny,
        lr_log_scales=tiny,
        lr_quats=tiny,
        lr_opacity=tiny,
        lr_sh_dc=tiny,
        lr_sh_rest=tiny,
        scene_extent=1.0,
        percent_dense=0.05,
        densify_from=3,
        densify_every=3,
        densify_grad_threshold=1e-12,
        prune_large_from=None,
        opacity_reset_every=None,
        sh_degree_interval=None,
    )
    cfg.update(overrides)
    m = Mapper(gmap, MapperConfig(**cfg))
    for c in ring_cameras(3):
        m.add_view(c, torch.rand(SIZE, SIZE, 3, generator=g))
    return m


def test_densify_prune_keeps_per_gaussian_state_aligned() -> None:
    m = _densify_setup()
    n0 = m.num_gaussians
    # per-Gaussian state the caller keeps: an id and a copy of each Gaussian's parameters
    state = {"id": torch.arange(n0, dtype=torch.float64), **m.gmap.tensors()}
    changes: list[TopologyChange] = []
    snap: dict[str, GaussianMap] = {}

    def on_change(ch: TopologyChange) -> None:
        nonlocal state
        changes.append(ch)
        assert ch.num_new == m.num_gaussians == ch.src.numel()
        state = remap_per_gaussian(state, ch.src, fill={"id": -1.0, "means": 0.0})
        snap["after"] = m.gmap

    m.on_topology_change.append(on_change)
    m.step(2)
    before = m.gmap
    info = m.step(1)
    assert len(changes) == 1
    ch = changes[0]
    assert ch.reason == "densify" and ch.num_old == n0
    assert info["cloned"] > 0 and info["split"] > 0 and info["pruned"] > 0
    assert ch.counts == {"cloned": info["cloned"], "split": info["split"], "pruned": info["pruned"]}
    after = snap["after"]
    src = ch.src
    assert (src >= 0).all()  # densify creates nothing from scratch
    # the tracked ids are the sources
    torch.testing.assert_close(state["id"], src.double())
    ident, ls = ch.identity, math.log(1.6)
    small = before.log_scales.exp().amax(1) <= 0.05
    # kept and cloned Gaussians are exact copies of their source (lr ~ 0 since the snapshot)
    copies = ident | small[src]
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        torch.testing.assert_close(
            getattr(after, k)[copies], getattr(before, k)[src[copies]], atol=1e-6, rtol=0
        )
        # the caller's copies followed their Gaussians
        torch.testing.assert_close(state[k][copies], getattr(after, k)[copies], atol=1e-6, rtol=0)
    # split children: scale / 1.6, same colour and rotation, positions near the parent
    child = ~copies
    per_parent = torch.bincount(src[child], minlength=n0)
    assert set(per_parent[per_parent > 0].tolist()) == {2}
    assert 0 < int(child.sum()) <= 2 * info["split"]
    torch.testing.assert_close(
        after.log_scales[child], before.log_scales[src[child]] - ls, atol=1e-6, rtol=0
    )
    torch.testing.assert_close(after.sh[child], before.sh[src[child]], atol=1e-6, rtol=0)
    d = (after.means[child] - before.means[src[child]]).norm(dim=1)
    assert (d > 0).all() and (d < 6 * 0.1 * math.sqrt(3)).all()
    # nothing transparent survives; every kept old Gaussian appears exactly once as itself
    assert (after.opacities >= 0.005).all()
    assert ch.kept.sum() == ident.sum()
    assert torch.equal(torch.sort(src[ident]).values, ch.kept.nonzero().squeeze(1))
    # split parents are not kept as themselves, transparent ones are gone
    assert not ch.kept[::7].any()
    # training goes on with the new set
    m.step(1)


def test_split_counts_and_cap() -> None:
    m = _densify_setup(max_gaussians=230)
    changes: list[TopologyChange] = []
    m.on_topology_change.append(changes.append)
    m.step(3)
    ch = changes[-1]
    # the cap bounds the densified set before pruning
    assert ch.counts["cloned"] + ch.counts["split"] <= 30
    assert m.num_gaussians <= 230
    # each split produced exactly two children with the same source
    child_src = ch.src[~ch.identity]
    counts = torch.bincount(child_src, minlength=ch.num_old)
    assert set(counts[counts > 0].tolist()) <= {1, 2}


def test_remap_per_gaussian() -> None:
    vals = {
        "h": torch.tensor([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0]]),
        "c": torch.tensor([5, 6, 7]),
    }
    src = torch.tensor([2, -1, 0, 0])
    out = remap_per_gaussian(vals, src, fill={"h": torch.tensor([0.5, 0.25]), "c": -1})
    torch.testing.assert_close(
        out["h"], torch.tensor([[3.0, 30.0], [0.5, 0.25], [1.0, 10.0], [1.0, 10.0]])
    )
    assert out["c"].tolist() == [7, -1, 5, 5]
    assert vals["h"][0, 0] == 1.0  # inputs untouched
    with pytest.raises(ValueError, match="src indexes outside"):
        remap_per_gaussian(vals, torch.tensor([3]))
    with pytest.raises(ValueError, match="src must be an integer"):
        remap_per_gaussian(vals, torch.tensor([0.0]))


def test_add_view_never_resets_the_map() -> None:
    gt = gt_map(150)
    cams = ring_cameras(4)
    m = Mapper(gt_map(150, seed=2), MapperConfig(**FAST))
    for c in cams[:2]:
        m.add_view(c, render(gt, c).rgb.detach())
    m.step(5)
    before = m.gmap
    params_before = m.params
    opt_state = {
        k: m._opt.state[p]["exp_avg"].clone() for k, p in params_before.items() if p.numel()
    }
    changes: list[TopologyChange] = []
    m.on_topology_change.append(changes.append)
    idx = m.add_view(cams[2], render(gt, cams[2]).rgb.detach())
    assert idx == 2 and m.num_views == 3 and m.num_steps == 5 and not changes
    after = m.gmap
    for a, b in zip(before.tensors().values(), after.tensors().values(), strict=True):
        assert torch.equal(a, b)
    for k, p in m.params.items():
        assert p is params_before[k]
        if k in opt_state:
            assert torch.equal(m._opt.state[p]["exp_avg"], opt_state[k])
    # a view with depth extends the map where it is not covered; old Gaussians untouched
    far = Camera.from_intrinsics(
        look_at(torch.tensor([0.0, 0.0, -1.6]), torch.tensor([0.0, 0.0, -3.0])), cams[0].intrinsics
    )
    depth = torch.full((SIZE, SIZE), 1.0)
    m.add_view(far, torch.full((SIZE, SIZE, 3), 0.25), depth)
    assert len(changes) == 1 and changes[0].reason == "extend"
    ch = changes[0]
    n0 = before.num_gaussians
    assert ch.num_old == n0 and ch.num_new == m.num_gaussians > n0
    assert torch.equal(ch.src[:n0], torch.arange(n0)) and (ch.src[n0:] == -1).all()
    assert ch.kept.all() and ch.identity[:n0].all() and not ch.identity[n0:].any()
    ext = m.gmap
    for k, v in before.tensors().items():
        assert torch.equal(getattr(ext, k)[:n0], v)
    # the new Gaussians sit on the observed plane z = -2.6 with the observed colour
    torch.testing.assert_close(ext.means[n0:, 2], torch.full((ch.num_new - n0,), -2.6))
    torch.testing.assert_close(
        ext.sh[n0:, 0], torch.full((ch.num_new - n0, 3), (0.25 - 0.5) / SH_C0)
    )
    # Adam moments carried for the kept Gaussians, zero for the new ones
    st = m._opt.state[m.params["means"]]["exp_avg"]
    torch.testing.assert_close(st[:n0], opt_state["means"])
    assert (st[n0:] == 0).all()
    m.step(2)
    assert m.num_steps == 7


def test_init_from_depth_puts_points_where_the_depth_says() -> None:
    g = torch.Generator().manual_seed(0)
    intr = Intrinsics(fx=30.0, fy=28.0, cx=15.0, cy=13.0, width=32, height=24)
    c2w = look_at(torch.tensor([0.5, -1.0, 2.0]), torch.tensor([0.0, 0.2, 0.0]))
    cam = Camera.from_intrinsics(c2w, intr)
    depth = 1.0 + 2.0 * torch.rand(24, 32, generator=g)
    depth[3, 4] = 0.0  # unknown
    depth[5, 6] = float("nan")
    image = torch.rand(24, 32, 3, generator=g)
    m = Mapper(None, MapperConfig(sh_degree=1))
    n = m.init_from_depth([View("v", cam, image, depth)], stride=1, max_points=10**6)
    assert n == 24 * 32 - 2
    gm = m.gmap
    assert gm.num_gaussians == n and gm.sh_degree == 1
    # project the Gaussians back: each lands on a pixel centre with the pixel's depth
    w2c = cam.w2c
    pc = gm.means @ w2c[:3, :3].T + w2c[:3, 3]
    u = intr.fx * pc[:, 0] / pc[:, 2] + intr.cx - 0.5
    v = intr.fy * pc[:, 1] / pc[:, 2] + intr.cy - 0.5
    ui, vi = u.round().long(), v.round().long()
    torch.testing.assert_close(u, ui.float(), atol=1e-3, rtol=0)
    torch.testing.assert_close(v, vi.float(), atol=1e-3, rtol=0)
    torch.testing.assert_close(pc[:, 2], depth[vi, ui], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(gm.sh[:, 0], (image[vi, ui] - 0.5) / SH_C0, atol=1e-5, rtol=0)
    assert len(set((vi * 32 + ui).tolist())) == n  # every valid pixel exactly once
    # opacity and nearest-neighbour scales
    torch.testing.assert_close(gm.opacities, torch.full((n,), 0.1))
    torch.testing.assert_close(gm.scales[:, 0], nearest_neighbour_scales(gm.means))
    assert (gm.scales > 0).all() and (gm.scales < 0.5).all()
    # stride and max_points subsample
    m2 = Mapper(None)
    assert m2.init_from_depth([View("v", cam, image, depth)], stride=4, max_points=10**6) == 48
    assert m2.init_from_depth([View("v", cam, image, depth)], stride=1, max_points=100) == 100


def test_backproject_and_nearest_neighbour_helpers() -> None:
    cam = Camera.from_intrinsics(torch.eye(4), Intrinsics(10.0, 10.0, 2.0, 2.0, 4, 4))
    depth = torch.full((4, 4), 2.0)
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[0, 1] = True
    pts, cols = backproject_depth(cam, depth, mask=mask)
    torch.testing.assert_close(
        pts, torch.tensor([[(1.5 - 2.0) / 10 * 2, (0.5 - 2.0) / 10 * 2, 2.0]])
    )
    torch.testing.assert_close(cols, torch.full((1, 3), 0.5))
    with pytest.raises(ValueError, match="depth must have shape"):
        backproject_depth(cam, torch.ones(3, 4))
    grid = torch.stack(torch.meshgrid(torch.arange(5.0), torch.arange(5.0), indexing="ij"), -1)
    pts = torch.cat([grid.reshape(-1, 2) * 0.1, torch.zeros(25, 1)], dim=1)
    s = nearest_neighbour_scales(pts)
    # an interior grid point has 4 neighbours at 0.1
    torch.testing.assert_close(s[12], torch.tensor(0.1))


def test_replace_gmap_carries_adam_moments() -> None:
    m = Mapper(gt_map(50), MapperConfig(**FAST))
    for c in ring_cameras(2):
        m.add_view(c, torch.rand(SIZE, SIZE, 3))
    m.step(3)
    old = m.gmap
    m_old = m._opt.state[m.params["quats"]]["exp_avg"].clone()
    perm = torch.randperm(50)
    src = torch.cat([perm[:40], torch.full((5,), -1)])
    new = GaussianMap(**{k: torch.cat([v[perm[:40]], v[:5]]) for k, v in old.items()})
    changes: list[TopologyChange] = []
    m.on_topology_change.append(changes.append)
    m.replace_gmap(new, src=src)
    assert changes[0].reason == "replace" and changes[0].num_new == 45
    m_new = m._opt.state[m.params["quats"]]["exp_avg"]
    torch.testing.assert_close(m_new[:40], m_old[perm[:40]])
    assert (m_new[40:] == 0).all()
    assert torch.equal(m.gmap.means, new.means)
    m.step(1)


def test_input_validation() -> None:
    m = Mapper(gt_map(20))
    cam = ring_cameras(1)[0]
    with pytest.raises(RuntimeError, match="no views"):
        m.step()
    with pytest.raises(ValueError, match=r"image must have shape \[32, 32, 3\]"):
        m.add_view(cam, torch.zeros(16, 16, 3))
    with pytest.raises(ValueError, match=r"image values must be in \[0, 1\]"):
        m.add_view(cam, torch.full((32, 32, 3), 2.0))
    with pytest.raises(ValueError, match="depth must have shape"):
        m.add_view(cam, torch.zeros(32, 32, 3), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="MapperConfig\nlambda_dssim"):
        MapperConfig(lambda_dssim=2.0)
    with pytest.raises(ValueError, match="MapperConfig\ndensify_every"):
        MapperConfig(densify_every=0)
    empty = Mapper(None)
    empty.add_view(cam, torch.zeros(32, 32, 3))
    with pytest.raises(RuntimeError, match="no Gaussians"):
        empty.step()
    with pytest.raises(ValueError, match="no view with a depth map"):
        empty.init_from_depth()
    # uint8 images are accepted
    assert m.add_view(cam, torch.zeros(32, 32, 3, dtype=torch.uint8)) == 0


def test_opacity_reset_and_sh_schedule() -> None:
    cfg = MapperConfig(
        **{**FAST, "opacity_reset_every": 2, "sh_degree_interval": 2, "densify": False}
    )
    m = Mapper(gt_map(60), cfg)
    m.replace_gmap(GaussianMap(**{**m.gmap.tensors(), "sh": torch.zeros(60, 4, 3)}))
    m.add_view(ring_cameras(1)[0], torch.rand(SIZE, SIZE, 3))
    assert m.active_sh_degree == 0
    info = m.step(2)
    assert info["opacity_resets"] == 1
    assert (m.gmap.opacities <= 0.01 + 1e-6).all()
    assert m.active_sh_degree == 1
    # the higher bands are untrained while inactive
    assert (m.gmap.sh[:, 1:] == 0).all()


def test_rgbd_views_of_a_real_scene_build_and_train_a_map() -> None:
    """Teapot splat: RGB-D views grow the map, training lowers the loss, Ĥ stays aligned."""
    from agilegs.service.nbv import init_information, load_scene
    from agilegs.service.nbv.candidates import capture_pool, scene_center_radius

    gt = load_scene(SCENES / "teapot", max_gaussians=2000)
    center, radius = scene_center_radius(gt.means)
    poses = capture_pool(center, 2.5 * radius, 8, seed=0)
    intr = Intrinsics.from_fov(50.0, SIZE, SIZE)
    cams = [Camera.from_intrinsics(p, intr) for p in poses[::2]]
    refs = []
    with torch.no_grad():
        for c in cams:
            out = render(gt, c)
            refs.append((out.rgb.clamp(0, 1), torch.where(out.alpha > 0.5, out.depth, 0.0)))
    cfg = MapperConfig(
        lr_means=1.6e-3,
        lr_sh_dc=2.5e-2,
        sh_degree=0,
        densify_from=10,
        densify_every=10,
        opacity_reset_every=None,
        init_stride=2,
        max_gaussians=600,
    )
    m = Mapper(None, cfg)
    h_acc: dict[str, torch.Tensor] = {}

    def follow(ch: TopologyChange) -> None:
        nonlocal h_acc
        # Ĥ: carried for kept, cloned and split Gaussians, the prior λ for new ones
        h_acc = remap_per_gaussian(h_acc, ch.src, fill=1e-6) if h_acc else h_acc

    m.on_topology_change.append(follow)
    counts = []
    for c, (rgb, depth) in zip(cams, refs, strict=True):
        m.add_view(c, rgb, depth)
        counts.append(m.num_gaussians)
        if not h_acc:
            h_acc = init_information(m.gmap, 1e-6)
    assert counts[0] > 0 and counts[-1] >= counts[0]
    before = mean_loss(m)
    info = m.step(30)
    after = mean_loss(m)
    print(f"teapot RGB-D: {counts} Gaussians, loss {before:.4f} -> {after:.4f}, {info}")
    assert after < 0.8 * before
    assert info["split"] + info["cloned"] > 0 and m.num_gaussians <= 600
    gm = m.gmap
    assert m.scene_extent is not None and m.scene_extent > radius
    for k, v in gm.tensors().items():
        assert h_acc[k].shape == v.shape


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_mapper_on_cuda() -> None:
    gt = gt_map(200).to("cuda")
    cams = [c.to("cuda") for c in ring_cameras(4)]
    cfg = MapperConfig(**{**FAST, "densify": True, "densify_from": 5, "densify_every": 5})
    m = Mapper(gt_map(200, seed=7), cfg, device="cuda")
    changes: list[TopologyChange] = []
    m.on_topology_change.append(changes.append)
    for c in cams:
        m.add_view(c, render(gt, c).rgb.detach(), render(gt, c).depth.detach())
    before = mean_loss(m)
    m.step(20)
    assert mean_loss(m) < before
    assert m.gmap.device.type == "cuda" and changes
    assert all(ch.src.device.type == "cuda" for ch in changes)
