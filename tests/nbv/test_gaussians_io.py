"""Gaussian map file IO: Inria PLY, antimatter15 .splat, the benchmark's scenes, bad files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SCENES
from plyfile import PlyData, PlyElement

from agilegs.service.nbv import GaussianMap, load_scene
from agilegs.service.nbv.gaussians import SH_C0

TEAPOT = SCENES / "teapot" / "teapot_10k.splat"
PLANT = SCENES / "plant" / "plant.splat"


def random_map(n: int, degree: int, seed: int = 0, dtype: torch.dtype = torch.float32):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return GaussianMap(
        means=torch.randn(n, 3, generator=g, dtype=dtype),
        log_scales=torch.randn(n, 3, generator=g, dtype=dtype) - 4.0,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),  # not unit: PLY keeps them raw
        opacity_logits=torch.randn(n, generator=g, dtype=dtype) * 3,
        sh=torch.randn(n, k, 3, generator=g, dtype=dtype) * 0.5,
    )


def assert_maps_equal(a: GaussianMap, b: GaussianMap) -> None:
    for (name, x), (_, y) in zip(a.items(), b.items(), strict=True):
        assert x.dtype == y.dtype, name
        assert x.shape == y.shape, name
        # bit-exact, not just close
        assert torch.equal(x.view(torch.int32), y.view(torch.int32)), name


# ------------------------------------------------------------------------------- PLY
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip_is_bit_exact(tmp_path: Path, degree: int) -> None:
    m = random_map(257, degree)
    # awkward float32 values survive too
    m.means[0] = torch.tensor([-0.0, 1e-45, 3.4028235e38])
    m.sh[1, 0, 0] = 1.1754942e-38  # subnormal
    path = tmp_path / "map.ply"
    m.save(path)
    back = GaussianMap.load(path)
    assert back.sh_degree == degree
    assert back.num_gaussians == 257
    assert_maps_equal(back, m)
    # plain, writable, contiguous CPU tensors (not views into the parsed file)
    assert all(t.is_contiguous() and t.device.type == "cpu" for t in back.tensors().values())
    back.opacity_logits.mul_(1.0)  # in place: fails on a read-only view
    # saving the loaded map gives the same bytes
    path2 = tmp_path / "again.ply"
    back.save(path2)
    assert path.read_bytes() == path2.read_bytes()


def test_ply_layout_matches_reference_3dgs(tmp_path: Path) -> None:
    """Property names and order, float32, and channel-major f_rest as the Inria code writes."""
    m = random_map(5, 3, seed=1)
    path = tmp_path / "ref.ply"
    m.save(path)
    ply = PlyData.read(str(path))
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    expected = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert names == expected
    assert all(v.data.dtype[n] == np.dtype("<f4") for n in names)
    # reference: features_rest [N, 15, 3] -> transpose(1, 2) -> flatten
    ref_rest = m.sh[:, 1:, :].transpose(1, 2).reshape(5, -1).numpy()
    got_rest = np.stack([v.data[f"f_rest_{i}"] for i in range(45)], axis=1)
    assert np.array_equal(got_rest, ref_rest)
    # f_rest_0..14 are the red channel coefficients 1..15
    assert np.array_equal(got_rest[:, :15], m.sh[:, 1:, 0].numpy())
    assert np.array_equal(v.data["rot_0"], m.quats[:, 0].numpy())  # w first
    assert np.array_equal(v.data["opacity"], m.opacity_logits.numpy())  # raw logits
    assert np.array_equal(v.data["scale_2"], m.log_scales[:, 2].numpy())  # log scales


def _write_ply(path: Path, columns: dict[str, np.ndarray], text: bool = False) -> None:
    arr = np.empty(
        len(next(iter(columns.values()))), dtype=[(k, v.dtype) for k, v in columns.items()]
    )
    for k, v in columns.items():
        arr[k] = v
    PlyData([PlyElement.describe(arr, "vertex")], text=text).write(str(path))


def _inria_columns(m: GaussianMap, dtype: str = "<f4") -> dict[str, np.ndarray]:
    n = m.num_gaussians
    rest = m.sh[:, 1:, :].transpose(1, 2).reshape(n, -1)
    cols: dict[str, np.ndarray] = {}
    for i, c in enumerate("xyz"):
        cols[c] = m.means[:, i].numpy().astype(dtype)
    for i in range(3):
        cols[f"f_dc_{i}"] = m.sh[:, 0, i].numpy().astype(dtype)
    for i in range(rest.shape[1]):
        cols[f"f_rest_{i}"] = rest[:, i].numpy().astype(dtype)
    cols["opacity"] = m.opacity_logits.numpy().astype(dtype)
    for i in range(3):
        cols[f"scale_{i}"] = m.log_scales[:, i].numpy().astype(dtype)
    for i in range(4):
        cols[f"rot_{i}"] = m.quats[:, i].numpy().astype(dtype)
    return cols


def test_ply_accepts_float64_extra_properties_and_other_orders(tmp_path: Path) -> None:
    m = random_map(40, 1, seed=2)
    cols = _inria_columns(m, dtype="<f8")
    # extra properties (and no normals), shuffled order, f_rest out of order
    cols = dict(reversed(list(cols.items())))
    cols["red"] = np.full(40, 7, dtype=np.uint8)
    cols["filter_3D"] = np.zeros(40, dtype="<f4")
    path = tmp_path / "f64.ply"
    _write_ply(path, cols)
    back = GaussianMap.load(path)
    assert back.dtype == torch.float32
    assert back.sh_degree == 1
    # float64 properties whose values are float32-representable load exactly
    assert_maps_equal(back, m)

    # big-endian and ASCII files
    _write_ply(tmp_path / "be.ply", {k: v.astype(">f4") for k, v in _inria_columns(m).items()})
    assert_maps_equal(GaussianMap.load(tmp_path / "be.ply"), m)
    _write_ply(tmp_path / "ascii.ply", _inria_columns(m), text=True)
    torch.testing.assert_close(GaussianMap.load(tmp_path / "ascii.ply").sh, m.sh)


def test_ply_float64_map_saves_as_float32(tmp_path: Path) -> None:
    m = random_map(10, 0, dtype=torch.float64)
    m.save(tmp_path / "m.ply")
    back = GaussianMap.load(tmp_path / "m.ply")
    assert back.dtype == torch.float32
    torch.testing.assert_close(back.to(dtype=torch.float64).means, m.means, rtol=1e-7, atol=0)


def test_save_detaches_and_accepts_grad_tensors(tmp_path: Path) -> None:
    m = random_map(10, 0).requires_grad_(True)
    m.save(tmp_path / "g.ply")
    m.save(tmp_path / "g.splat")
    assert GaussianMap.load(tmp_path / "g.ply").num_gaussians == 10


# ------------------------------------------------------------------------------- .splat
def test_splat_round_trip_within_quantisation_and_idempotent(tmp_path: Path) -> None:
    m = random_map(500, 2, seed=3)
    m.quats = m.quats / m.quats.norm(dim=-1, keepdim=True)
    p1 = tmp_path / "one.splat"
    m.save(p1)
    assert p1.stat().st_size == 500 * 32
    once = GaussianMap.load(p1)
    assert once.sh_degree == 0  # higher bands are dropped

    # positions and scales are stored as float32: exact / to float32 rounding of exp/log
    assert torch.equal(once.means, m.means)
    torch.testing.assert_close(once.log_scales, m.log_scales, atol=1e-6, rtol=0)
    # colour: 1/255 steps of rgb = 0.5 + C0 dc (clamped to [0, 1])
    rgb_in = (0.5 + SH_C0 * m.sh[:, 0]).clamp(0, 1)
    rgb_out = 0.5 + SH_C0 * once.sh[:, 0]
    assert float((rgb_in - rgb_out).abs().max()) <= 0.5 / 255 + 1e-6
    # opacity: 1/255 steps, clipped away from 0 and 1
    assert float((m.opacities - once.opacities).abs().max()) <= 0.5 / 255 + 1e-4
    # quaternions: unit length, same rotation within the 1/128 quantisation
    torch.testing.assert_close(once.quats.norm(dim=-1), torch.ones(500), atol=1e-6, rtol=0)
    cos = (once.quats * m.quats).sum(-1).abs()
    assert float(cos.min()) > math.cos(2.5 / 128)

    # a second round changes nothing, bit for bit, and the bytes are stable
    p2 = tmp_path / "two.splat"
    once.save(p2)
    twice = GaussianMap.load(p2)
    assert_maps_equal(twice, once)
    p3 = tmp_path / "three.splat"
    twice.save(p3)
    assert p2.read_bytes() == p3.read_bytes()


def test_splat_record_layout(tmp_path: Path) -> None:
    m = GaussianMap.from_points(
        torch.tensor([[1.0, -2.0, 3.0]]), torch.tensor([[1.0, 0.0, 0.5]]), scale=0.25, opacity=0.5
    )
    m.save(tmp_path / "one.splat")
    raw = (tmp_path / "one.splat").read_bytes()
    assert len(raw) == 32
    assert np.frombuffer(raw[0:12], "<f4").tolist() == [1.0, -2.0, 3.0]
    assert np.frombuffer(raw[12:24], "<f4").tolist() == [0.25, 0.25, 0.25]
    assert list(raw[24:28]) == [255, 0, 128, 128]  # 0.5 * 255 = 127.5 rounds to even 128
    assert list(raw[28:32]) == [255, 128, 128, 128]  # identity, w = 1 -> 256 clipped


def test_splat_edge_values(tmp_path: Path) -> None:
    """Alpha 0 / 255, zero quaternion bytes and zero scales load as finite values."""
    rec = np.zeros(3, dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("q", "u1", 4)])
    rec["s"] = [[0.01, 0.02, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5]]
    rec["c"] = [[0, 0, 0, 0], [255, 255, 255, 255], [10, 20, 30, 128]]
    rec["q"] = [[128, 128, 128, 128], [0, 128, 128, 128], [200, 100, 150, 60]]
    path = tmp_path / "edge.splat"
    path.write_bytes(rec.tobytes())
    m = GaussianMap.load(path)
    for name, t in m.items():
        assert torch.isfinite(t).all(), name
    assert m.quats[0].tolist() == [1.0, 0.0, 0.0, 0.0]  # zero quaternion -> identity
    assert m.quats[1].tolist() == [-1.0, 0.0, 0.0, 0.0]
    assert 0 < float(m.opacities[0]) < 1e-3 and 1 - 1e-3 < float(m.opacities[1]) < 1
    m.save(tmp_path / "edge2.splat")
    back = np.frombuffer((tmp_path / "edge2.splat").read_bytes(), dtype=rec.dtype)
    assert back["c"].tolist() == rec["c"].tolist()
    assert back["q"][:2].tolist() == [[255, 128, 128, 128], [0, 128, 128, 128]]


# ------------------------------------------------------------------------------- scenes
def test_teapot_scene_loads() -> None:
    m = GaussianMap.load(TEAPOT)
    assert m.num_gaussians == 10000
    assert m.sh_degree == 0 and m.dtype == torch.float32
    for name, t in m.items():
        assert torch.isfinite(t).all(), name
    torch.testing.assert_close(m.quats.norm(dim=-1), torch.ones(10000), atol=1e-6, rtol=0)
    # README: centred on the origin, longest side exactly 1
    ext = m.means.amax(0) - m.means.amin(0)
    assert 0.9 < float(ext.max()) < 1.1
    assert float(m.means.mean(0).abs().max()) < 0.2
    assert float(m.scales.max()) < 0.1


def test_plant_scene_loads_and_subsamples() -> None:
    m = load_scene(PLANT)
    assert m.num_gaussians == 113648
    for name, t in m.items():
        assert torch.isfinite(t).all(), name
    sub = load_scene(PLANT, max_gaussians=5000, seed=3)
    assert sub.num_gaussians == 5000
    again = load_scene(PLANT, max_gaussians=5000, seed=3)
    assert_maps_equal(sub, again)  # deterministic
    other = load_scene(PLANT, max_gaussians=5000, seed=4)
    assert not torch.equal(sub.means, other.means)
    # the subset is a subset, in file order
    idx = torch.randperm(113648, generator=torch.Generator().manual_seed(3))[:5000].sort().values
    assert torch.equal(sub.means, m.means[idx])


def test_every_benchmark_scene_loads() -> None:
    files = sorted(SCENES.glob("*/*.splat"))
    assert files
    for f in files:
        m = GaussianMap.load(f)
        assert m.num_gaussians == f.stat().st_size // 32
        assert all(torch.isfinite(t).all() for t in m.tensors().values()), f


def test_load_scene_folder_and_limits(tmp_path: Path) -> None:
    assert load_scene(SCENES / "teapot").num_gaussians == 10000
    assert load_scene(TEAPOT, max_gaussians=20000).num_gaussians == 10000  # no-op if smaller
    two = tmp_path / "two"  # two levels of detail: which one is meant?
    two.mkdir()
    for name in ("a_10k.splat", "a_5k.splat"):
        (two / name).write_bytes(TEAPOT.read_bytes()[: 32 * 5000])
    with pytest.raises(ValueError, match="exactly one"):
        load_scene(two)
    with pytest.raises(ValueError, match="max_gaussians"):
        load_scene(TEAPOT, max_gaussians=0)


# ------------------------------------------------------------------------------- bad files
def test_truncated_ply(tmp_path: Path) -> None:
    random_map(20, 1).save(tmp_path / "ok.ply")
    raw = (tmp_path / "ok.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(raw[:-7])
    with pytest.raises(ValueError, match="truncated"):
        GaussianMap.load(tmp_path / "cut.ply")
    (tmp_path / "header.ply").write_bytes(raw[:40])  # inside the header
    with pytest.raises(ValueError, match="truncated"):
        GaussianMap.load(tmp_path / "header.ply")


def test_not_a_ply(tmp_path: Path) -> None:
    (tmp_path / "junk.ply").write_bytes(b"this is not a ply file\n")
    with pytest.raises(ValueError, match="malformed PLY"):
        GaussianMap.load(tmp_path / "junk.ply")


def test_splat_of_wrong_size(tmp_path: Path) -> None:
    random_map(4, 0).save(tmp_path / "ok.splat")
    (tmp_path / "bad.splat").write_bytes((tmp_path / "ok.splat").read_bytes()[:-5])
    with pytest.raises(ValueError, match="not a multiple of the 32-byte"):
        GaussianMap.load(tmp_path / "bad.splat")


def test_nan_in_ply(tmp_path: Path) -> None:
    m = random_map(6, 0)
    cols = _inria_columns(m)
    cols["opacity"][3] = np.nan
    _write_ply(tmp_path / "nan.ply", cols)
    with pytest.raises(ValueError, match="'opacity' has 1 NaN or infinite"):
        GaussianMap.load(tmp_path / "nan.ply")
    cols = _inria_columns(m)
    cols["scale_1"][0] = np.inf
    _write_ply(tmp_path / "inf.ply", cols)
    with pytest.raises(ValueError, match="'scale_1' has 1 NaN or infinite"):
        GaussianMap.load(tmp_path / "inf.ply")
    # float64 values beyond the float32 range are infinite after the cast
    cols64 = _inria_columns(m, dtype="<f8")
    cols64["x"][2] = 1e300
    _write_ply(tmp_path / "big.ply", cols64)
    with pytest.raises(ValueError, match="'x' has 1 NaN or infinite"):
        GaussianMap.load(tmp_path / "big.ply")


def test_nan_in_splat(tmp_path: Path) -> None:
    rec = np.zeros(2, dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("q", "u1", 4)])
    rec["s"] = 0.1
    rec["p"][1, 0] = np.nan
    (tmp_path / "nan.splat").write_bytes(rec.tobytes())
    with pytest.raises(ValueError, match="position has 1 NaN"):
        GaussianMap.load(tmp_path / "nan.splat")
    rec["p"][1, 0] = 0
    rec["s"][0, 0] = -1
    (tmp_path / "neg.splat").write_bytes(rec.tobytes())
    with pytest.raises(ValueError, match="scale has 1 negative"):
        GaussianMap.load(tmp_path / "neg.splat")


def test_missing_property(tmp_path: Path) -> None:
    cols = _inria_columns(random_map(6, 0))
    del cols["rot_3"], cols["opacity"]
    _write_ply(tmp_path / "missing.ply", cols)
    with pytest.raises(ValueError, match=r"missing required properties \['opacity', 'rot_3'\]"):
        GaussianMap.load(tmp_path / "missing.ply")


def test_bad_f_rest_count(tmp_path: Path) -> None:
    cols = _inria_columns(random_map(6, 1))
    del cols["f_rest_8"]
    _write_ply(tmp_path / "rest.ply", cols)
    with pytest.raises(ValueError, match="8 f_rest"):
        GaussianMap.load(tmp_path / "rest.ply")


def test_no_vertex_element(tmp_path: Path) -> None:
    arr = np.zeros(3, dtype=[("a", "<f4")])
    PlyData([PlyElement.describe(arr, "face")]).write(str(tmp_path / "face.ply"))
    with pytest.raises(ValueError, match="no 'vertex' element"):
        GaussianMap.load(tmp_path / "face.ply")


def test_unknown_suffix(tmp_path: Path) -> None:
    (tmp_path / "map.npz").write_bytes(b"x" * 32)
    with pytest.raises(ValueError, match=r"unknown file suffix '\.npz'"):
        GaussianMap.load(tmp_path / "map.npz")
    with pytest.raises(ValueError, match="unknown file suffix ''"):
        random_map(2, 0).save(tmp_path / "noext")
    assert not (tmp_path / "noext").exists()


@pytest.mark.parametrize("suffix", [".ply", ".splat"])
def test_empty_file(tmp_path: Path, suffix: str) -> None:
    (tmp_path / f"empty{suffix}").write_bytes(b"")
    with pytest.raises(ValueError, match="file is empty"):
        GaussianMap.load(tmp_path / f"empty{suffix}")


def test_zero_vertex_ply(tmp_path: Path) -> None:
    _write_ply(
        tmp_path / "zero.ply", {k: v[:0] for k, v in _inria_columns(random_map(2, 0)).items()}
    )
    with pytest.raises(ValueError, match="no Gaussians"):
        GaussianMap.load(tmp_path / "zero.ply")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        GaussianMap.load(tmp_path / "nope.ply")


@pytest.mark.parametrize("suffix", [".ply", ".splat"])
def test_save_rejects_bad_maps(tmp_path: Path, suffix: str) -> None:
    m = random_map(3, 0)
    m.means[1, 1] = float("nan")
    with pytest.raises(ValueError, match="means has 1 NaN"):
        m.save(tmp_path / f"nan{suffix}")
    empty = random_map(0, 0)
    with pytest.raises(ValueError, match="empty map"):
        empty.save(tmp_path / f"empty{suffix}")
    assert list(tmp_path.iterdir()) == []  # nothing (not even a temporary) left behind
