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
``numba`` or ``torch``); else ``"auto"``. Asking for ``"numba"`` where the kernels cannot run
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

import logging
import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Literal, cast

import numpy as np
import torch
from torch import Tensor

from agilegs.service.nbv.camera import Camera
from agilegs.service.nbv.gaussians import FIELD_NAMES, GaussianMap
from agilegs.service.nbv.projection import Projected

log = logging.getLogger(__name__)

Backend = Literal["auto", "numba", "torch"]
BACKENDS: tuple[str, ...] = ("auto", "numba", "torch")
ENV_VAR = "AGILEGS_KERNELS"

_default: Backend | None = None
_LOCK = threading.RLock()
_kernels: Any = None
_import_error: str | None = None
_XY_CACHE: dict[tuple[int, str], np.ndarray] = {}

__all__ = [
    "BACKENDS",
    "ENV_VAR",
    "Backend",
    "default_backend",
    "kernel_composite",
    "kernel_fisher",
    "kernel_jacobians",
    "kernel_moments",
    "kernel_project",
    "kernels_available",
    "release_workspace",
    "resolve",
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
    env = os.environ.get(ENV_VAR, "").strip().lower()
    return _check_name(env, ENV_VAR) if env else "auto"


def _load() -> Any:
    global _kernels, _import_error
    if _kernels is None and _import_error is None:
        try:
            from agilegs.service.nbv import kernels as mod

            _kernels = mod
        except Exception as exc:  # numba missing or broken: the torch path serves
            _import_error = f"{type(exc).__name__}: {exc}"
            log.warning("compiled kernels unavailable, using the torch path (%s)", _import_error)
    return _kernels


def kernels_available() -> bool:
    """Whether the compiled kernels import (numba present and working)."""
    return _load() is not None


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
def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


_POOL: ThreadPoolExecutor | None = None


THREADS_ENV_VAR = "AGILEGS_KERNEL_THREADS"
_threads_default: int | None = None


def set_kernel_threads(n: int | None) -> None:
    """Run the kernels on ``n`` threads (None: back to ``AGILEGS_KERNEL_THREADS``, else
    torch's thread count)."""
    global _threads_default
    if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n < 1):
        raise ValueError(f"threads must be an integer >= 1, got {n!r}")
    _threads_default = n


def _threads() -> int:
    """The number of parts (threads) a kernel runs in: :func:`set_kernel_threads`, else
    ``AGILEGS_KERNEL_THREADS``, else torch's thread count."""
    if _threads_default is not None:
        return _threads_default
    env = os.environ.get(THREADS_ENV_VAR, "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n < 1:
            raise ValueError(f"{THREADS_ENV_VAR} must be an integer >= 1, got {env!r}")
        return n
    return max(1, torch.get_num_threads())


def _parallel(fn: Callable[[int], Any], parts: int) -> None:
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


def _centres(n: int, dtype: np.dtype) -> np.ndarray:
    key = (n, str(dtype))
    arr = _XY_CACHE.get(key)
    if arr is None:
        arr = (np.arange(n, dtype=np.float64) + 0.5).astype(dtype)
        if len(_XY_CACHE) > 64:
            _XY_CACHE.clear()
        _XY_CACHE[key] = arr
    return arr


def _camera_vector(camera: Camera, dtype: torch.dtype, near: float) -> np.ndarray:
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


def _params(gmap: GaussianMap) -> tuple[np.ndarray, ...]:
    return (_np(gmap.means), _np(gmap.log_scales), _np(gmap.quats), _np(gmap.opacity_logits),
            _np(gmap.sh))


def _scalars(np_dtype: np.dtype) -> tuple[Any, Any, Any]:
    t = np_dtype.type
    return t(0.5), t(1.0 / 255.0), t(0.99)


# ----------------------------------------------------------------------------- projection
class _ProjectFn(torch.autograd.Function):
    """The kernels' projection with its analytic vector-Jacobian product."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means: Tensor, log_scales: Tensor, quats: Tensor, logits: Tensor, sh: Tensor,
        cam: np.ndarray,
    ) -> tuple[Tensor, ...]:
        k = _load()
        arrs = tuple(_np(t) for t in (means, log_scales, quats, logits, sh))
        n = means.shape[0]
        dt = means.dtype
        m2 = torch.empty(n, 2, dtype=dt)
        con = torch.empty(n, 3, dtype=dt)
        z = torch.empty(n, dtype=dt)
        radii = torch.empty(n, dtype=torch.int64)
        col = torch.empty(n, 3, dtype=dt)
        op = torch.empty(n, dtype=dt)
        cov = torch.empty(n, 3, dtype=dt)
        if n:
            outs = (m2.numpy(), con.numpy(), z.numpy(), radii.numpy(), col.numpy(), op.numpy(),
                    cov.numpy())
            with _LOCK:
                nth = _threads()
                _parallel(lambda part: k.project(*arrs, cam, part, nth, *outs), nth)
        ctx.arrs = arrs
        ctx.cam = cam
        ctx.mark_non_differentiable(radii, cov)
        return m2, con, z, col, op, radii, cov

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(  # type: ignore[override]
        ctx: Any, g_m2: Tensor | None, g_con: Tensor | None, g_z: Tensor | None,
        g_col: Tensor | None, g_op: Tensor | None, _g_radii: Any, _g_cov: Any,
    ) -> tuple[Tensor | None, ...]:
        k = _load()
        means, log_scales, quats, logits, sh = ctx.arrs
        n = means.shape[0]
        dt = torch.float32 if means.dtype == np.float32 else torch.float64
        gs = torch.zeros(n, 10, dtype=dt)
        if g_m2 is not None:
            gs[:, 0:2] = g_m2
        if g_con is not None:
            gs[:, 2:5] = g_con
        if g_op is not None:
            gs[:, 5] = g_op
        if g_col is not None:
            gs[:, 6:9] = g_col
        if g_z is not None:
            gs[:, 9] = g_z
        outs = [torch.zeros(a.shape, dtype=dt) for a in ctx.arrs]
        if n:
            gsn = gs.numpy()
            outn = [o.numpy() for o in outs]
            with _LOCK:
                nth = _threads()
                _parallel(lambda part: k.project_backward(*ctx.arrs, ctx.cam, part, nth, gsn,
                                                          *outn), nth)
        return (*outs, None)


def kernel_project(gmap: GaussianMap, camera: Camera, *, near: float = 0.01) -> Projected:
    """:func:`~agilegs.service.nbv.projection.project_map` by the kernels (differentiable in
    the Gaussians; not in the pose)."""
    cam = _camera_vector(camera, gmap.dtype, near)
    m2, con, z, col, op, radii, cov = _ProjectFn.apply(
        gmap.means, gmap.log_scales, gmap.quats, gmap.opacity_logits, gmap.sh, cam)
    return Projected(means2d=m2, conics=con, depths=z, radii=radii, colors=col, opacities=op,
                     cov2d=cov)


# ----------------------------------------------------------------------------- workspace
class _Workspace:
    """Scratch buffers reused from one kernel call to the next (only under ``_LOCK``, and
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
        if buf is None or buf.nbytes < nbytes:
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


_WORKSPACE = _Workspace()


def release_workspace() -> int:
    """Free the kernels' cached scratch buffers; returns the bytes released."""
    with _LOCK:
        n = _WORKSPACE.nbytes
        _WORKSPACE.clear()
    return n


# ----------------------------------------------------------------------------- binning
class _Tiles:
    """The depth-sorted visible Gaussians binned to tiles as records (numpy; see
    ``kernels.bin_count`` and ``kernels.bin_fill``). With ``scratch`` the arrays live in the
    workspace (valid until the next kernel call: only inside one locked call)."""

    def __init__(self, m2: np.ndarray, con: np.ndarray, op: np.ndarray, col: np.ndarray,
                 z: np.ndarray, radii: np.ndarray, cov: np.ndarray, width: int, height: int,
                 tile: int, *, scratch: bool = False) -> None:
        k = _load()
        dt = m2.dtype
        n = m2.shape[0]
        nc = col.shape[1]

        def buf(name: str, shape: tuple[int, ...], dtype: Any, zero: bool = False
                ) -> np.ndarray:
            if scratch:
                return _WORKSPACE.take("tiles." + name, shape, dtype, zero=zero)
            return np.zeros(shape, dtype) if zero else np.empty(shape, dtype)

        tiles_x = (width + tile - 1) // tile
        n_tiles = tiles_x * ((height + tile - 1) // tile)
        own = buf("own", (n, k.REC + nc + 5), dt)
        counts = np.zeros(n_tiles + 1, np.int64)
        areas = np.zeros(n_tiles + 1, np.int64)
        nvis = k.bin_count(m2, con, op, z, col, radii, radii.astype(dt), cov, width, height,
                           tile, dt.type(tile), own, counts, areas)
        bits = (z.view(np.uint32).astype(np.uint64) if dt == np.float32
                else z.view(np.uint64))
        self.order = np.empty(nvis, np.int64)
        k.visible_order(radii, bits, dt.itemsize, nvis, self.order)
        self.offsets = np.cumsum(counts)
        self.slots = np.cumsum(areas)
        m = int(self.offsets[-1])
        self.rec = buf("rec", (m, k.REC + nc), dt)
        self.rbox = buf("rbox", (m, 4), np.int32)
        self.rg = buf("rg", (m,), np.int32)
        self.ent_off = buf("ent_off", (nvis + 1,), np.int64)
        self.ent = buf("ent", (m,), np.int32)
        k.bin_fill(self.order, own, self.offsets, width, tile,
                   buf("sorted_own", (nvis, own.shape[1]), dt), self.rec, self.rbox, self.rg,
                   self.ent_off, self.ent)
        self.xs = _centres(width, dt)
        self.ys = _centres(height, dt)
        self.width, self.height, self.tile = width, height, tile
        self.channels = nc
        self.n = n

    @property
    def num_visible(self) -> int:
        return int(self.order.shape[0])

    def common(self) -> tuple[Any, ...]:
        return (self.offsets, self.rec, self.rbox, self.xs, self.ys, self.width, self.height,
                self.tile, *_scalars(self.rec.dtype))

    def pair_buffers(self, record: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Slots for every tile's composited pairs (list position, tile pixel, α before the
        clamp), or empty ones when nothing is recorded."""
        size = int(self.slots[-1]) if record else 0
        return (np.empty(size, np.int32), np.empty(size, np.int32),
                np.empty(size, self.rec.dtype))

    def reduce(self, k: Any, per_entry: np.ndarray, out: np.ndarray, nth: int, *,
               compact: bool = False) -> np.ndarray:
        """Sum every visible Gaussian's entries' rows of per_entry into out: row g of out
        [N, K] (the other rows are left as they are), or with ``compact`` row v of out
        [V, K] in depth order."""
        if self.num_visible:
            visit = np.arange(self.num_visible)
            target = visit if compact else self.order
            _parallel(lambda part: k.reduce_entries(visit, target, self.ent_off, self.ent,
                                                    per_entry, part, nth, out), nth)
        return out


# ----------------------------------------------------------------------------- compositing
class _CompositeFn(torch.autograd.Function):
    """Tile compositing by the kernels, with their backward."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
        depths: Tensor, bg: Tensor, radii: Tensor, cov2d: Tensor, width: int, height: int,
        tile: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        k = _load()
        dt = colors.dtype
        hw = width * height
        nc = colors.shape[1]
        with _LOCK:
            nth = _threads()
            tiles = _Tiles(_np(means2d), _np(conics), _np(opacities), _np(colors),
                           _np(depths), _np(radii).astype(np.int64), _np(cov2d), width, height,
                           tile)
            acc = np.empty((hw, nc), dtype=tiles.rec.dtype)
            tf = np.empty(hw, dtype=np.float64)
            dacc = np.empty(hw, dtype=tiles.rec.dtype)
            record = any(ctx.needs_input_grad)
            pairs = tiles.pair_buffers(record)
            npairs = np.zeros(tiles.offsets.shape[0] - 1, dtype=np.int64)
            common = tiles.common()
            _parallel(lambda part: k.composite_forward(*common, part, nth, tiles.slots, record,
                                                       *pairs, npairs, acc, tf, dacc), nth)
        t_final = torch.from_numpy(tf).to(dt)
        color = torch.from_numpy(acc) + t_final[:, None] * bg.detach()
        ctx.tiles = tiles
        ctx.tf = tf
        ctx.pairs = (*pairs, npairs)
        ctx.n = means2d.shape[0]
        ctx.save_for_backward(bg)
        return (color.reshape(height, width, nc), (1.0 - t_final).reshape(height, width),
                torch.from_numpy(dacc).reshape(height, width))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(  # type: ignore[override]
        ctx: Any, g_color: Tensor, g_alpha: Tensor, g_depth: Tensor
    ) -> tuple[Tensor | None, ...]:
        k = _load()
        (bg,) = ctx.saved_tensors
        tiles: _Tiles = ctx.tiles
        dt = bg.dtype
        nc = tiles.channels
        hw = tiles.width * tiles.height
        g_c = g_color.reshape(hw, nc).to(dt).contiguous()
        g_a = g_alpha.reshape(hw).to(dt).contiguous()
        g_d = g_depth.reshape(hw).to(dt).contiguous()
        with _LOCK:
            nth = _threads()
            per_entry = np.zeros((tiles.rec.shape[0], 7 + nc), dtype=np.float64)
            common = tiles.common()
            args = (tiles.slots, *ctx.pairs, ctx.tf, _np(bg), g_c.numpy(), g_a.numpy(),
                    g_d.numpy(), per_entry)
            _parallel(lambda part: k.composite_backward(*common, part, nth, *args), nth)
            red = tiles.reduce(k, per_entry, np.zeros((ctx.n, 7 + nc), np.float64), nth)
        full = torch.from_numpy(red).to(dt)
        tf = torch.from_numpy(ctx.tf).to(dt)
        gbg = (tf[:, None] * g_c).sum(0)
        return (full[:, 0:2], full[:, 2:5], full[:, 5], full[:, 7:], full[:, 6], gbg,
                None, None, None, None, None)


def kernel_composite(proj: Projected, colors: Tensor, bg: Tensor, width: int, height: int,
                     tile_size: int) -> tuple[Tensor, Tensor, Tensor]:
    """Composite a projection by the kernels: colour [H, W, C] (background included),
    accumulated alpha [H, W], Σ w z [H, W]; differentiable in the screen attributes,
    ``colors`` [N, C] and ``bg`` [C]."""
    return _CompositeFn.apply(proj.means2d, proj.conics, proj.opacities, colors, proj.depths,
                              bg, proj.radii, proj.cov2d, int(width), int(height),
                              int(tile_size))


# ----------------------------------------------------------------------------- the Fisher
def _project_np(k: Any, arrs: tuple[np.ndarray, ...], cam: np.ndarray, nth: int,
                scratch: bool = False) -> tuple[np.ndarray, ...]:
    n = arrs[0].shape[0]
    dt = arrs[0].dtype

    def buf(name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        return (_WORKSPACE.take("proj." + name, shape, dtype) if scratch
                else np.empty(shape, dtype))

    out = (buf("m2", (n, 2), dt), buf("con", (n, 3), dt), buf("z", (n,), dt),
           buf("radii", (n,), np.int64), buf("col", (n, 3), dt), buf("op", (n,), dt),
           buf("cov", (n, 3), dt))
    if n:
        _parallel(lambda part: k.project(*arrs, cam, part, nth, *out), nth)
    return out


def _moments_np(k: Any, arrs: tuple[np.ndarray, ...], cam: np.ndarray, camera: Camera,
                bg: np.ndarray, tile: int, pixels: bool, nth: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Project, bin and accumulate the Fisher's moments (in the workspace: valid inside the
    locked call only). Returns the visible Gaussians in depth order [V] and every Gaussian's
    moments [N, MOMENTS] (float64; the rows of Gaussians that are not visible undefined)."""
    m2, con, z, radii, col, op, cov = _project_np(k, arrs, cam, nth, scratch=True)
    tiles = _Tiles(m2, con, op, col, z, radii, cov, camera.width, camera.height, tile,
                   scratch=True)
    per_entry = _WORKSPACE.take("fisher.entries", (tiles.rec.shape[0], k.MOMENTS),
                                tiles.rec.dtype, zero=True)
    mom = _WORKSPACE.take("fisher.moments", (arrs[0].shape[0], k.MOMENTS), np.float64)
    if tiles.num_visible:
        common = tiles.common()
        _parallel(lambda part: k.fisher_tiles(*common, part, nth, tiles.slots, bg, pixels,
                                              per_entry), nth)
        tiles.reduce(k, per_entry, mom, nth)
    return tiles.order, mom


def _background(background: Tensor | None, dtype: torch.dtype) -> np.ndarray:
    if background is None:
        return np.zeros(3, dtype=np.float64)
    return torch.as_tensor(background).detach().to(dtype).reshape(3).to(
        torch.float64).cpu().numpy()


def kernel_moments(gmap: GaussianMap, camera: Camera, *, background: Tensor | None = None,
                   tile_size: int = 8, near: float = 0.01, residuals: str = "channels"
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """The Fisher's per-Gaussian moments by the kernels (float64; zero for Gaussians without a
    composited pair): Φ = Σ f4 φφᵀ [N, 6, 6], C2 = Σ f2 ⊗ φ [N, 3, 6] and Σ w² [N] (see
    ``kernels.fisher_tiles``)."""
    k = _load()
    arrs = _params(gmap)
    n = gmap.num_gaussians
    cam = _camera_vector(camera, gmap.dtype, near)
    full = torch.zeros(n, k.MOMENTS, dtype=torch.float64)
    with _LOCK:
        order, mom = _moments_np(k, arrs, cam, camera, _background(background, gmap.dtype),
                                 tile_size, residuals == "pixels", _threads())
        idx = torch.from_numpy(order)
        full[idx] = torch.from_numpy(mom)[idx]
    phi = full[:, torch.from_numpy(k.PHI_INDEX).reshape(-1)].reshape(n, 6, 6)
    return phi, full[:, 15:33].reshape(n, 3, 6), full[:, 33]


def kernel_fisher(gmap: GaussianMap, camera: Camera, fields: Iterable[str], *,
                  background: Tensor | None = None, tile_size: int = 8, near: float = 0.01,
                  residuals: str = "channels") -> dict[str, Tensor]:
    """diag(Jᵀ M J) per parameter block by the kernels, in one pass (projection, binning, the
    tiles' moments, the analytic per-Gaussian Jacobian and the sandwich).

    Args:
        gmap: the Gaussians (N); camera: the view (its pose is not differentiated).
        fields: the blocks wanted (names of :data:`FIELD_NAMES`).
        residuals: "channels" (the exact Fisher of the RGB) or "pixels" (the channel sum one
            residual per pixel, α's derivatives through its clamp; FisherRF's).

    Returns:
        {field: the diagonal, the field's shape, the map's dtype}.
    """
    k = _load()
    want_names = tuple(fields)
    arrs = _params(gmap)
    dt = gmap.dtype
    want = np.array([f in want_names for f in FIELD_NAMES], dtype=np.bool_)
    cam = _camera_vector(camera, dt, near)
    outs = {f: torch.zeros(getattr(gmap, f).shape, dtype=dt) for f in FIELD_NAMES}
    with _LOCK:
        nth = _threads()
        order, mom = _moments_np(k, arrs, cam, camera, _background(background, dt), tile_size,
                                 residuals == "pixels", nth)
        if order.shape[0]:
            hs = [outs[f].numpy() for f in FIELD_NAMES]
            pixels = residuals == "pixels"
            _parallel(lambda part: k.fisher_chain(order, mom, *arrs, cam, part, nth, pixels,
                                                  want, *hs), nth)
    return {f: outs[f] for f in want_names}


def kernel_jacobians(gmap: GaussianMap, camera: Camera, fields: Iterable[str], *,
                     near: float = 0.01) -> dict[str, Tensor]:
    """∂s_i/∂θ_i of the 9 screen attributes by the kernels' analytic Jacobian: {field:
    [N, 9, P_f]} (the layout of :func:`~agilegs.service.nbv.information.projection_jacobians`)."""
    k = _load()
    arrs = _params(gmap)
    n = gmap.num_gaussians
    nk = gmap.sh.shape[1]
    dt = gmap.dtype
    cam = _camera_vector(camera, dt, near)
    jac = np.zeros((n, 10, 11), dtype=np.float64)
    basis = np.zeros((n, max(nk, 1)), dtype=np.float64)
    mask = np.zeros((n, 3), dtype=np.float64)
    if n:
        with _LOCK:
            nth = _threads()
            _parallel(lambda part: k.jacobians(*arrs, cam, part, nth, jac, basis, mask), nth)
    j = torch.from_numpy(jac).to(dt)
    out: dict[str, Tensor] = {}
    cols = {"means": (0, 3), "log_scales": (3, 6), "quats": (6, 10), "opacity_logits": (10, 11)}
    for f in fields:
        if f == "sh":
            sh_j = torch.zeros(n, 9, nk, 3, dtype=dt)
            b = torch.from_numpy(basis[:, :nk]).to(dt)
            mk = torch.from_numpy(mask).to(dt)
            for ch in range(3):
                sh_j[:, 6 + ch, :, ch] = b * mk[:, ch:ch + 1]
            out[f] = sh_j.reshape(n, 9, nk * 3)
        else:
            lo, hi = cols[f]
            out[f] = j[:, :9, lo:hi].contiguous()
    return out
