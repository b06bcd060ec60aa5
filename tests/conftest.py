"""Shared fixtures: free ports, a real ``agilegs serve`` subprocess (the e2e tests), an
in-process server behind an httpx transport (the service tests), camera rings.

The suite runs with one torch (OpenMP) thread per process, unless ``OMP_NUM_THREADS`` says
otherwise, and so do the processes it starts: it shares two cores with the servers it
starts, and two threads per process on two busy cores spend their time waiting for each other
(tests/nbv took 253 s with two threads and 30 s with one, on the shared machine).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from inprocess import InProcess, serve_in_process

from agilegs.service.launch import ServerProcess as _Launcher
from agilegs.service.launch import free_port

os.environ.setdefault("OMP_NUM_THREADS", "1")  # the processes the tests start
torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))

__all__ = ["ROOT", "SCENES", "SHARED_SCENES", "SMALL_INTRINSICS", "InProcess", "ServerProcess", "free_port",
           "gaussian_blob", "ring_poses"]

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root."""
SCENES = ROOT / "lab" / "scenes"
"""The benchmark's ground-truth scenes, in the repository (not in the wheel)."""
SHARED_SCENES = SCENES
"""Another name of :data:`SCENES`."""


class ServerProcess(_Launcher):
    """The launcher with the tests' defaults: one torch thread, the mapper off unless a test
    asks for it (these tests check exact state)."""

    def __init__(self, state_dir: Path, *, env: dict[str, str] | None = None,
                 **kwargs: Any) -> None:
        super().__init__(state_dir, env={"AGILEGS_TORCH_THREADS": "1", "AGILEGS_MAPPER": "0",
                                         **(env or {})}, **kwargs)


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
