"""Shared fixtures: free ports, a real ``agilegs serve`` subprocess (the e2e tests), an
in-process server behind an httpx transport (the service tests), camera rings.

The suite runs with one torch (OpenMP) thread per process, unless ``OMP_NUM_THREADS`` says
otherwise, and so do the processes it starts: it shares two cores with the servers it
starts, and two threads per process on two busy cores spend their time waiting for each other
(tests/nbv took 253 s with two threads and 30 s with one, on the shared machine).
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from inprocess import InProcess, serve_in_process
from pydantic import BaseModel

from agilegs.schemas import ObservationIn
from agilegs.service.launch import ServerProcess as _Launcher
from agilegs.service.launch import free_port
from agilegs.service.nbv import (
    Camera,
    GaussianMap,
    Intrinsics,
    accumulate_information,
    fisher_diag,
    init_information,
    look_at,
    render,
    se3_exp,
)
from agilegs.service.nbv.anchor.proxy import ProxyPsi
from agilegs.service.nbv.anchor.visibility import OpacityMaps
from agilegs.service.nbv.candidates import capture_pool, scene_center_radius
from agilegs.service.sessions.registry import SessionRegistry
from agilegs.service.settings import Settings
from agilegs.service.transports.requests import parse_request

os.environ.setdefault("OMP_NUM_THREADS", "1")  # the processes the tests start
torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))

__all__ = ["CI", "FULL", "ROOT", "SCENES", "SHARED_SCENES", "SMALL_INTRINSICS", "TINY_INTR",
           "TRAIN_FAST", "TRAIN_GT", "TRAIN_INTR", "TRAIN_POSES", "Fuzz", "InProcess",
           "ServerProcess", "call", "camera", "create", "free_port", "gaussian_blob", "make_core",
           "random_map", "ring_poses", "stateful_toml", "tiny_scene", "train_frame",
           "train_ground_truth", "train_reference", "wait_idle"]

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root."""
SCENES = ROOT / "lab" / "scenes"
"""The benchmark's ground-truth scenes, in the repository (not in the wheel)."""
SHARED_SCENES = SCENES
"""Another name of :data:`SCENES`."""


def call(registry: SessionRegistry, op: str, session: str | None, payload: Any) -> BaseModel:
    """Operation ``op`` on ``registry`` from decoded request data, validated as the gateway
    validates it (a 422 naming every bad field): the in-process tests' way in."""
    return registry.execute(op, session, parse_request(op, payload))


class ServerProcess(_Launcher):
    """The launcher with the tests' defaults: one torch thread, the mapper off unless a test
    asks for it (these tests check exact state), no warm-up (the suite compiles the kernels
    once)."""

    def __init__(self, state_dir: Path, *, env: dict[str, str] | None = None,
                 **kwargs: Any) -> None:
        super().__init__(state_dir, env={"AGILEGS_TORCH_THREADS": "1", "AGILEGS_MAPPER": "0",
                                         "AGILEGS_WARMUP": "0", **(env or {})}, **kwargs)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test under ``tests/e2e`` (subprocesses, clusters, the demo, deploy files) and
    every ``heavy`` one is ``slow``: ``pytest -m "not slow"`` is the fast lane."""
    for item in items:
        if "e2e" in Path(str(item.fspath)).parts or item.get_closest_marker("heavy"):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """One shared server (HTTP and Zenoh) for the tests that need no restart or token."""
    root = tmp_path_factory.mktemp("server")
    srv = ServerProcess(root / "state", env={"AGILEGS_MAX_BODY_BYTES": str(8 * 2**20)}).start()
    yield srv
    srv.stop()


@pytest.fixture
def api(tmp_path: Path) -> Iterator[InProcess]:
    """A fresh in-process server (HTTP only, the mapper off, bodies up to 8 MiB)."""
    with serve_in_process(tmp_path / "state", max_body_bytes=8 * 2**20) as srv:
        yield srv


@pytest.fixture
def api_factory(tmp_path: Path) -> Iterator[object]:
    """``api_factory(**settings)``: in-process servers of one's own, stopped at the end."""
    from contextlib import ExitStack

    with ExitStack() as stack:
        count = [0]

        def make(**settings: Any) -> InProcess:
            count[0] += 1
            return stack.enter_context(serve_in_process(tmp_path / f"state{count[0]}",
                                                        **settings))

        yield make


@pytest.fixture
def server_factory(tmp_path: Path) -> Iterator[type[ServerProcess] | object]:
    """Build servers of one's own (``server_factory(zenoh=False, env={...})``); all are
    stopped at the end of the test."""
    started: list[ServerProcess] = []

    def make(state_dir: Path | None = None, **kwargs: object) -> ServerProcess:
        srv = ServerProcess(state_dir or tmp_path / f"state{len(started)}", **kwargs)  # type: ignore[arg-type]
        started.append(srv)
        return srv

    yield make
    for srv in started:
        srv.stop()


def ring_poses(n: int, radius: float = 2.0, height: float = -0.3) -> np.ndarray:
    """``n`` camera-to-world poses [n, 4, 4] (OpenCV axes) on a ring, looking at the origin
    (world up is -y)."""
    out = []
    for a in np.linspace(0.0, 2 * np.pi, n, endpoint=False):
        eye = np.array([radius * np.cos(a), height, radius * np.sin(a)])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(np.array([0.0, 1.0, 0.0]), z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
        out.append(m)
    return np.stack(out)


@pytest.fixture
def ring() -> object:
    """``ring(n)``: camera poses on a ring around the origin (see :func:`ring_poses`)."""
    return ring_poses


def gaussian_blob(n: int, color: tuple[float, float, float] = (0.1, 0.8, 0.2),
                  radius: float = 0.3, seed: int = 0) -> dict[str, np.ndarray]:
    """``n`` opaque Gaussians of one colour (RGB in [0, 1]) in a ball of about ``radius``
    around the origin: the five arrays (``create_session(gaussians=...)``)."""
    rng = np.random.default_rng(seed)
    dc = (np.asarray(color) - 0.5) / 0.28209479177387814  # colour = 0.5 + C0 * DC
    return {
        "means": (rng.normal(size=(n, 3)) * radius / 2).astype(np.float32),
        "log_scales": np.full((n, 3), np.log(0.04), np.float32),
        "quats": np.tile(np.array([1.0, 0, 0, 0], np.float32), (n, 1)),
        "opacity_logits": np.full(n, 2.0, np.float32),
        "sh": np.tile(dc.astype(np.float32), (n, 1, 1)),
    }


SMALL_INTRINSICS = {"fx": 28.0, "fy": 28.0, "cx": 16.0, "cy": 16.0, "width": 32, "height": 32}


@pytest.fixture
def small_intrinsics() -> dict[str, float]:
    """32x32 pinhole intrinsics (keeps server tests fast)."""
    return dict(SMALL_INTRINSICS)


# ---- from nbv/test_anchor.py ----
TINY_INTR = Intrinsics.from_fov(55.0, 32, 32)


def tiny_scene(n: int = 250, seed: int = 0, dtype: torch.dtype = torch.float64):
    """A blob of Gaussians, a 24-camera capture pool and Hhat from 3 of its views."""
    g = torch.Generator().manual_seed(seed)
    pts = 0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    pts[:, 0] *= 1.5  # elongated so that views differ
    cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
    gmap = GaussianMap.from_points(pts, cols, scale=0.05, opacity=0.7).to(dtype=dtype)
    pool = capture_pool([0.0, 0.0, 0.0], 2.0, 24, seed=seed, dtype=dtype)
    acq = pool[[0, 8, 9]]
    h = init_information(gmap, 1e-6)
    with torch.no_grad():
        for p in acq:
            h = accumulate_information(h, fisher_diag(gmap, Camera(c2w=p, intrinsics=TINY_INTR)))
    return gmap, pool, acq, h



# ---- from nbv/test_kernels.py ----
def random_map(n: int, *, seed: int = 0, deg: int = 1, dtype: torch.dtype = torch.float64,
               scale: tuple[float, float] = (0.04, 0.14), opaque: int = 6) -> GaussianMap:
    """n Gaussians in a unit cube; the first ``opaque`` nearly opaque (α clamped at 0.99 and
    transmittance stops), some behind the camera or off screen."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = scale
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5
    means[-2] = torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64)  # behind the camera
    means[-1] = torch.tensor([5.0, 0.0, 0.0], dtype=torch.float64)  # off screen
    logits = torch.randn(n, generator=g, dtype=torch.float64)
    logits[:opaque] += 6.0
    return GaussianMap(
        means=means,
        log_scales=torch.log(torch.rand(n, 3, generator=g, dtype=torch.float64) * (hi - lo) + lo),
        quats=torch.randn(n, 4, generator=g, dtype=torch.float64),
        opacity_logits=logits,
        sh=torch.randn(n, (deg + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.4,
    ).to(dtype=dtype)


def camera(w: int = 21, h: int = 18, dtype: torch.dtype = torch.float64,
           eye: tuple[float, float, float] = (0.3, -0.4, -2.0)) -> Camera:
    c2w = look_at(torch.tensor(eye, dtype=dtype), torch.zeros(3, dtype=dtype))
    return Camera.from_c2w(c2w, fx=0.9 * w, fy=0.95 * w, cx=w / 2 + 0.3, cy=h / 2 - 0.2,
                           width=w, height=h)



# ---- from sessions/test_trainer.py ----
TRAIN_POSES = ring_poses(12, radius=2.0, height=-0.4)


TRAIN_INTR = Intrinsics(**SMALL_INTRINSICS)


TRAIN_FAST = {"sh_degree": 0, "densify_from": 10, "densify_every": 10, "densify_until": 40,
        "max_gaussians": 400}


def train_ground_truth() -> GaussianMap:
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(250, 3, generator=g) - 0.5) * 0.8
    return GaussianMap.from_points(pts, torch.rand(250, 3, generator=g), scale=0.07, opacity=0.8)


TRAIN_GT = train_ground_truth()


@functools.cache
def train_reference(i: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth RGB [32, 32, 3] and depth [32, 32] (0: background) from ring pose ``i``."""
    with torch.no_grad():
        out = render(TRAIN_GT, Camera(torch.from_numpy(TRAIN_POSES[i]).float(), TRAIN_INTR))
    d = torch.where(out.alpha > 0.5, out.depth, torch.zeros_like(out.depth))
    return out.rgb.clamp(0, 1).numpy(), d.numpy()


def train_frame(i: int, *, depth: bool = True, **where: Any) -> dict[str, Any]:
    """An RGB(-D) observation of the ground truth from ring pose ``i`` (wire dict)."""
    rgb, d = train_reference(i)
    pose = None if where else TRAIN_POSES[i]
    o = ObservationIn.from_numpy(pose, image=rgb, depth=d if depth else None, **where)
    return o.model_dump()


def make_core(path: Path, **settings: Any) -> SessionRegistry:
    base: dict[str, Any] = {"state_dir": path, "zenoh": False, "workers": 2, "fsync": False,
                            "mapper_steps_per_view": 20, "mapper_burst": 10}
    core = SessionRegistry(Settings(**{**base, **settings}))
    core.load()
    return core


def create(core: SessionRegistry, sid: str = "s", views: tuple[int, ...] = (0, 4, 8),
           **extra: Any) -> Any:
    body = {"id": sid, "intrinsics": SMALL_INTRINSICS, "init_gaussians": 100,
            "frames": [train_frame(i) for i in views],
            "pool": {"poses": [{"matrix": p.tolist()} for p in TRAIN_POSES]},
            "mapper": {"config": TRAIN_FAST}, **extra}
    return call(core, "create_session", None, body)


def wait_idle(core: SessionRegistry, sid: str = "s", timeout: float = 60.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = call(core, "get_session", sid, None)
        if info.mapper.state in ("idle", "error", "off"):
            return info
        time.sleep(0.05)
    raise AssertionError(f"the mapper did not finish in {timeout} s: {info.mapper}")



# ---- from e2e/test_schemathesis.py ----
@dataclass(frozen=True)
class Fuzz:
    """One schemathesis run's size: its phases, cases per operation, the stateful phase's
    scenarios and steps, the fewest cases it must generate, its time limit (s)."""

    phases: str
    max_examples: int
    scenarios: int
    steps: int
    min_cases: int
    timeout: float


CI = Fuzz("examples,fuzzing,stateful", max_examples=15, scenarios=60, steps=12, min_cases=400,
          timeout=240)


FULL = Fuzz("examples,coverage,fuzzing,stateful", max_examples=10, scenarios=80, steps=12,
            min_cases=500, timeout=1500)


def stateful_toml(size: Fuzz) -> str:
    """The schemathesis config file that sizes the stateful phase."""
    return (f"[phases.stateful]\nmax-steps = {size.steps}\n\n"
            f"[phases.stateful.generation]\nmax-examples = {size.scenarios}\n")




# ---- from nbv/kernels/test_gpu_proxy.py ----
def proxy_scene(dtype: torch.dtype = torch.float64, *, n: int = 80, samples: int = 50,
                poses: int = 4) -> tuple[torch.Tensor, list[tuple[str, ProxyPsi]]]:
    """Small proxies ψ of every form the anchor builds (linear, log, directional with slots
    of every direction factor; with deep opacity maps and without; with extra samples
    appended) over anisotropic, rotated Gaussians, and poses [poses, 4, 4] about them: pool
    poses moved by small random twists, the last turned half away, the one before it (with
    three poses or more) inside the cloud."""
    g = torch.Generator().manual_seed(0)
    f64 = torch.float64
    pts = 0.3 * torch.randn(n, 3, generator=g, dtype=f64)
    gm = GaussianMap.from_points(pts, torch.rand(n, 3, generator=g, dtype=f64), scale=0.05,
                                 opacity=0.7)
    gm = GaussianMap(means=gm.means, log_scales=gm.log_scales
                     + 0.5 * torch.randn(n, 3, generator=g, dtype=f64),
                     quats=torch.randn(n, 4, generator=g, dtype=f64),
                     opacity_logits=gm.opacity_logits, sh=gm.sh).to(dtype=dtype)
    intr = Intrinsics.from_fov(55.0, 40, 32)
    centre, r98 = scene_center_radius(gm.means)
    pool = capture_pool(centre, 2.6 * r98, poses, seed=0).to(f64)
    xi = 0.1 * torch.randn(poses, 6, generator=g, dtype=f64)
    xi[-1, 3:] = torch.tensor([0.0, 1.2, 0.0], dtype=f64)
    moved = pool @ se3_exp(xi)
    if poses > 2:  # one inside the cloud: samples behind it and at its near plane
        moved[-2, :3, 3] = centre.to(f64) + 0.05
    moved = moved.to(dtype)
    grid = OpacityMaps.build(gm, intr, centre, r98, cells=5, bins=6, max_occluders=60,
                             generator=g)
    c = (torch.rand(n, generator=g, dtype=f64) + 0.1).to(dtype)
    rate = (2.0 * torch.rand(n, 9, generator=g, dtype=f64)).to(dtype)
    kinds = torch.tensor([0, 1, 2, 3, 4, 5, 6, 0, 3])
    kw: dict[str, Any] = dict(near=0.05 * float(r98), edge=2.0, generator=g)
    out: list[tuple[str, ProxyPsi]] = []
    for tag, vis in (("grid", grid), ("none", None)):
        out += [
            (f"linear/{tag}", ProxyPsi.build(gm, c, intr, num_samples=samples, grid=vis, **kw)),
            (f"log/{tag}", ProxyPsi.build(gm, c, intr, num_samples=samples, grid=vis,
                                          rate=rate[:, 0], slots=3, **kw)),
            (f"directional/{tag}", ProxyPsi.build(gm, c, intr, num_samples=samples, grid=vis,
                                                  rate=rate, slot_kinds=kinds, **kw)),
        ]
    last = out[2][1]
    extra = last.means[:4] + 0.05
    out.append(("directional/extended", last.extended(
        extra, 1e-3 * torch.eye(3, dtype=dtype).expand(4, 3, 3), torch.ones(4, dtype=dtype),
        last.rate[:4])))
    return moved, out
