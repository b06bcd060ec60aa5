"""Which implementation renders and computes the Fisher: compiled CPU kernels or pure torch.

Two backends compute the same maths:

- ``"numba"``: the compiled CPU kernels of :mod:`agilegs.service.nbv.kernels` (projection
  and its vector-Jacobian product, tile compositing and its backward, the one-pass Fisher with
  an analytic per-Gaussian projection Jacobian), wrapped here in autograd functions;
- ``"torch"``: the pure-torch reference (:mod:`agilegs.service.nbv.projection`,
  :mod:`agilegs.service.nbv.rasterize`, :mod:`agilegs.service.nbv.information`), twice
  differentiable, on any device.

``"auto"`` (the default) takes the kernels wherever they apply and the reference elsewhere:

- the kernels apply to CPU tensors of float32 or float64 when numba imports;
- a camera pose that requires grad keeps the projection (and the whole Fisher) in torch, so
  that the render is differentiable in the pose and the Fisher twice (the anchor's exact ψ);
  the compositing kernel still serves such a render (its backward returns the screen-space
  gradients that torch chains to the pose);
- ``render(..., backward="autograd")`` is the reference by definition.

The choice: the ``backend=`` argument of :func:`~agilegs.service.nbv.rasterize.render`,
:func:`~agilegs.service.nbv.information.fisher_diag` and their kin; else the module default
(:func:`set_default_backend`); else the environment variable ``AGILEGS_KERNELS`` (``auto``,
``numba`` or ``torch``; read through :func:`agilegs.service.settings.kernel_settings`); else
``"auto"``. Asking for ``"numba"`` where the kernels cannot run
raises :class:`ValueError` saying why.

Threads: each kernel runs in parts on as many Python threads (the kernels release the GIL):
:func:`set_kernel_threads`, else ``AGILEGS_KERNEL_THREADS``, else ``torch.get_num_threads()``
parts. One kernel call at a time per process (a lock: the calls share scratch buffers).
torch's own OpenMP threads busy-wait for a while after each parallel torch operation, and on
a machine with few cores they then compete with the kernels' threads: with torch on one
thread (``torch.set_num_threads(1)``) and the kernels on the cores, or with
``OMP_WAIT_POLICY=PASSIVE`` in the environment, they do not.
"""

from __future__ import annotations

import importlib
import logging
import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace
from typing import Any, Literal, cast

import numpy as np
import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera
from agilegs.service.nbv.gaussians import GaussianMap
from agilegs.service.settings import env_var, kernel_settings

log = logging.getLogger(__name__)

Backend = Literal["auto", "numba", "torch"]
BACKENDS: tuple[str, ...] = ("auto", "numba", "torch")
ENV_VAR = env_var("kernels")

_default: Backend | None = None
LOCK = threading.RLock()
_kernels: Any = None
_import_error: str | None = None
_XY_CACHE: dict[tuple[int, str], np.ndarray] = {}
_COMPILED: dict[str, tuple[str, ...]] = {
    "ascent": ("envelope_project_into", "projected_tangents", "se3_exp_into", "trial_pose"),
    "ascent_loop": ("CLOCK", "ascent_step"),
    "binning": ("bin_count", "bin_fill", "reduce_entries", "visible_order"),
    "common": ("CAM", "FWD", "MOMENTS", "REC"),
    "coverage": ("coverage_blocks", "coverage_terms"),
    "projection": ("PHI_INDEX", "fisher_chain", "jacobians", "project", "project_backward"),
    "proxy": ("proxy_psi",),
    "walks": ("composite_backward", "composite_forward", "fisher_tiles"),
}
"""The compiled modules of this package and the names the wrappers call
(:func:`kernel_module`)."""

__all__ = [
    "BACKENDS",
    "ENV_VAR",
    "LOCK",
    "WORKSPACE",
    "Backend",
    "Workspace",
    "as_numpy",
    "camera_vector",
    "default_backend",
    "kernel_module",
    "kernel_threads",
    "kernels_available",
    "load_kernels",
    "map_arrays",
    "parallel",
    "pixel_centres",
    "release_workspace",
    "resolve",
    "run_in_parts",
    "scalars",
    "set_default_backend",
    "set_kernel_threads",
]


def _check_name(backend: str, what: str) -> Backend:
    if backend not in BACKENDS:
        raise ValueError(f"{what} must be one of {BACKENDS}, got {backend!r}")
    return cast(Backend, backend)


def set_default_backend(backend: Backend | None) -> None:
    """Set the module default (None: back to ``AGILEGS_KERNELS`` or ``"auto"``)."""
    global _default
    _default = None if backend is None else _check_name(backend, "backend")


def default_backend() -> Backend:
    """The backend used where none is passed: the module default, else ``AGILEGS_KERNELS``,
    else ``"auto"``."""
    if _default is not None:
        return _default
    return kernel_settings().kernels


def load_kernels() -> Any:
    global _kernels, _import_error
    if _kernels is None and _import_error is None:
        try:
            mods = {m: importlib.import_module(f"{__package__}.{m}") for m in _COMPILED}
            _kernels = SimpleNamespace(**{name: getattr(mods[m], name)
                                          for m, names in _COMPILED.items() for name in names})
        except Exception as exc:  # numba missing or broken: the torch path serves
            _import_error = f"{type(exc).__name__}: {exc}"
            log.warning("compiled kernels unavailable, using the torch path (%s)", _import_error)
    return _kernels


def kernels_available() -> bool:
    """Whether the compiled kernels import (numba present and working)."""
    return load_kernels() is not None


def resolve(backend: Backend | None, tensors: Iterable[Tensor], *,
            pose_grad: bool = False) -> bool:
    """Whether to run the kernels for these inputs (see the module docstring).

    Args:
        backend: "auto", "numba", "torch" or None (the default backend).
        tensors: the inputs (device and dtype are checked).
        pose_grad: the computation must be differentiable in the camera pose.

    Raises:
        ValueError: ``backend="numba"`` where the kernels cannot run.
    """
    b = default_backend() if backend is None else _check_name(backend, "backend")
    if b == "torch":
        return False
    why = None
    for t in tensors:
        if t.device.type != "cpu":
            why = f"the kernels run on the CPU, got a tensor on {t.device}"
            break
        if t.dtype not in (torch.float32, torch.float64):
            why = f"the kernels take float32 or float64, got {t.dtype}"
            break
    if why is None and pose_grad:
        why = "the camera pose requires grad (the torch path differentiates in it)"
    if why is None and not kernels_available():
        why = f"the compiled kernels are unavailable ({_import_error})"
    if why is None:
        return True
    if b == "numba":
        raise ValueError(f"backend='numba': {why}")
    return False


# ----------------------------------------------------------------------------- helpers
def as_numpy(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


_POOL: ThreadPoolExecutor | None = None


_threads_default: int | None = None


def set_kernel_threads(n: int | None) -> None:
    """Run the kernels on ``n`` threads (None: back to ``AGILEGS_KERNEL_THREADS``, else
    torch's thread count)."""
    global _threads_default
    if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n < 1):
        raise ValueError(f"threads must be an integer >= 1, got {n!r}")
    _threads_default = n


def kernel_threads() -> int:
    """The number of parts (threads) a kernel runs in: :func:`set_kernel_threads`, else
    ``AGILEGS_KERNEL_THREADS``, else torch's thread count."""
    if _threads_default is not None:
        return _threads_default
    n = kernel_settings().kernel_threads
    return n if n is not None else max(1, torch.get_num_threads())


def parallel(fn: Callable[[int], Any], parts: int) -> None:
    """fn(0), ..., fn(parts - 1): the first on this thread, the others on the pool."""
    global _POOL
    if parts == 1:
        fn(0)
        return
    if _POOL is None or _POOL._max_workers < parts - 1:  # noqa: SLF001
        _POOL = ThreadPoolExecutor(max_workers=max(parts - 1, os.cpu_count() or 1),
                                   thread_name_prefix="agilegs-kernels")
    futures = [_POOL.submit(fn, p) for p in range(1, parts)]
    fn(0)
    for f in futures:
        f.result()


def pixel_centres(n: int, dtype: np.dtype) -> np.ndarray:
    key = (n, str(dtype))
    arr = _XY_CACHE.get(key)
    if arr is None:
        arr = (np.arange(n, dtype=np.float64) + 0.5).astype(dtype)
        if len(_XY_CACHE) > 64:
            _XY_CACHE.clear()
        _XY_CACHE[key] = arr
    return arr


def camera_vector(camera: Camera, dtype: torch.dtype, near: float) -> np.ndarray:
    """The kernels' camera vector (see ``kernels.CAM``), the pose rounded to ``dtype`` as the
    torch projection rounds it."""
    w2c = camera.w2c.detach().to(dtype).to(torch.float64).cpu().numpy()
    pos = camera.c2w.detach()[:3, 3].to(dtype).to(torch.float64).cpu().numpy()
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    w, h = camera.width, camera.height
    return np.concatenate([
        w2c[:3, :3].reshape(-1), w2c[:3, 3], pos,
        np.array([fx, fy, cx, cy, w, h, near, (-cx - 0.15 * w) / fx, (w - cx + 0.15 * w) / fx,
                  (-cy - 0.15 * h) / fy, (h - cy + 0.15 * h) / fy], dtype=np.float64),
    ])


def map_arrays(gmap: GaussianMap) -> tuple[np.ndarray, ...]:
    return tuple(as_numpy(t) for t in (gmap.means, gmap.log_scales, gmap.quats,
                                       gmap.opacity_logits, gmap.sh))


def scalars(np_dtype: np.dtype) -> tuple[Any, Any, Any]:
    t = np_dtype.type
    return t(0.5), t(1.0 / 255.0), t(0.99)


# ----------------------------------------------------------------------------- workspace
class Workspace:
    """Scratch buffers reused from one kernel call to the next (only under ``LOCK``, and
    never handed out of the call): fresh allocations of tens of MB cost page faults that
    rival the kernels' own work. Buffers above ``limit`` bytes are not kept."""

    def __init__(self, limit: int = 1 << 30) -> None:
        self.limit = limit
        self._bufs: dict[str, np.ndarray] = {}

    def take(self, name: str, shape: tuple[int, ...], dtype: Any, *, zero: bool = False
             ) -> np.ndarray:
        dt = np.dtype(dtype)
        nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
        buf = self._bufs.get(name)
        if buf is None or buf.nbytes < nbytes + 64:  # room for the alignment below
            if nbytes > self.limit:
                self._bufs.pop(name, None)
                return np.zeros(shape, dt) if zero else np.empty(shape, dt)
            buf = np.empty(nbytes + nbytes // 4 + 128, np.uint8)
            self._bufs[name] = buf
        skip = (-buf.ctypes.data) % 64  # cache-line aligned rows
        out = buf[skip:skip + nbytes].view(dt).reshape(shape)
        if zero:
            out.fill(0)
        return out

    def clear(self) -> None:
        self._bufs.clear()

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self._bufs.values())


WORKSPACE = Workspace()


def release_workspace() -> int:
    """Free the kernels' cached scratch buffers; returns the bytes released."""
    with LOCK:
        n = WORKSPACE.nbytes
        WORKSPACE.clear()
    return n


def run_in_parts(fn: Callable[[int, int], Any], items: int) -> None:
    """``fn(start, stop)`` over ``items`` items split into contiguous ranges, one per kernel
    thread (:func:`set_kernel_threads`); the ranges run at once on Python threads (the
    kernels release the GIL)."""
    parts = max(1, min(kernel_threads(), items))
    bounds = [items * p // parts for p in range(parts + 1)]
    parallel(lambda p: fn(bounds[p], bounds[p + 1]), parts)


def kernel_module() -> Any:
    """The compiled kernels: the functions and constants of :data:`_COMPILED` as attributes
    (None when numba does not import)."""
    return load_kernels()
